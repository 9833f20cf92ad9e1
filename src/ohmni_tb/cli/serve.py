"""``ohmni serve``: run the Robot and share it with local clients over WebSocket."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from ohmni_tb._checks import host_port
from ohmni_tb.cli.common import PortOption, open_robot, resolve_port, run, write_line
from ohmni_tb.errors import ConfigError
from ohmni_tb.eventloop import set_realtime

if TYPE_CHECKING:
    from ohmni_tb.client import RobotClient

__all__ = ["parse_foxglove", "serve"]

_log = logging.getLogger("ohmni_tb.daemon")
#: The Foxglove Teleop panel gives the control lease back this long after its last Twist.
_TELEOP_IDLE_S = 1.0
#: ``--listen``'s default: the daemon's loopback address (ohmni_tb.daemon.server).
_DEFAULT_LISTEN = "127.0.0.1:8766"
#: SCHED_FIFO's highest priority on Linux.
_MAX_RT_PRIORITY = 99


def serve(
    port: PortOption = None,
    listen: Annotated[
        str,
        typer.Option(
            "--listen",
            help="HOST:PORT to serve on. Loopback (127.0.0.1, [::1], localhost) needs no "
            "token; any other address needs the token file. Port 0 picks a free one.",
        ),
    ] = _DEFAULT_LISTEN,
    read_only: Annotated[
        bool,
        typer.Option(
            "--read-only", help="Refuse every command but stop and estop: clients only watch."
        ),
    ] = False,
    token_file: Annotated[
        Path | None,
        typer.Option(
            "--token-file",
            help="Require the token in this file (created, mode 0600, when missing). "
            "Default beyond loopback: ~/.config/ohmni/daemon-token; on loopback: no token.",
            dir_okay=False,
        ),
    ] = None,
    allow_origin: Annotated[
        list[str] | None,
        typer.Option(
            "--allow-origin",
            help="A browser origin allowed to connect (repeat for more), e.g. "
            "http://localhost:8080. Browsers from other origins are refused.",
        ),
    ] = None,
    foxglove: Annotated[
        str | None,
        typer.Option(
            "--foxglove",
            metavar="[HOST:]PORT",
            help="Also serve every stream to the Foxglove app (its WebSocket protocol; "
            "default host 127.0.0.1, the app's default port is 8765; 0 picks a free one). "
            "Its URL is the second line of stdout. Needs the foxglove extra. The protocol "
            "has no authentication: keep it on loopback (ssh -L to reach it).",
            show_default=False,
        ),
    ] = None,
    foxglove_control: Annotated[
        bool,
        typer.Option(
            "--foxglove-control",
            help="With --foxglove: the Foxglove Teleop panel drives the robot (Twist on "
            "/tb_cmd_vel or /cmd_vel), the Parameters panel sets PID gains and stream rates, "
            "and the reset_odom and neck_move services answer — through the daemon's control "
            "lease like any client and under the Robot's watchdog.",
        ),
    ] = False,
    handoff: Annotated[
        float | None,
        typer.Option(
            "--handoff",
            metavar="SECONDS",
            help="Do not serve: tell the daemon running at --listen to hand the serial port "
            "to another program (tb-node, a flashing tool) for SECONDS (0.1..3600), after "
            "stopping the wheels; it takes the port back by itself then.",
            show_default=False,
        ),
    ] = None,
    reclaim: Annotated[
        bool,
        typer.Option(
            "--reclaim",
            help="Do not serve: tell the daemon running at --listen to take the port back now.",
        ),
    ] = False,
    rt_priority: Annotated[
        int | None,
        typer.Option(
            "--rt-priority",
            metavar="N",
            help="Run the daemon under real-time scheduling (SCHED_FIFO) at priority N "
            "(1..99; 10 suggested), so the control tick is on time however busy the other "
            "programs keep the cores. Needs root, CAP_SYS_NICE or RLIMIT_RTPRIO >= N "
            "(docs/hardware.md). Linux only.",
            show_default=False,
        ),
    ] = None,
    foreground: Annotated[
        bool,
        typer.Option(
            "--foreground",
            help="Log every connection, lease change, refusal and departure to stderr, one "
            "structured line each (it always runs in the foreground).",
        ),
    ] = False,
) -> None:
    """Serve the robot to many local clients over WebSocket: one driver, many readers.

    Opens the port like every command, then prints the address (ws://HOST:PORT) alone on
    the first line of stdout. Clients subscribe to the Robot's streams, call its services
    and, holding the control lease, command it (ohmni_tb.client.RobotClient;
    docs/daemon.md). Ctrl-C or SIGTERM closes the clients, stops the wheels and exits.

    With --handoff SECONDS or --reclaim it does not serve: it asks the daemon already
    running at --listen to hand the serial port to another program, or take it back.

    Example: ohmni serve --port sim:// --listen 127.0.0.1:8766 ; ohmni serve --handoff 60
    """
    host, tcp_port = _parse_listen(listen)
    if rt_priority is not None and not 1 <= rt_priority <= _MAX_RT_PRIORITY:
        # 0 would mean "time-shared", which is what leaving the option out already says.
        raise typer.BadParameter(
            f"{rt_priority} is not in 1..{_MAX_RT_PRIORITY}", param_hint="--rt-priority"
        )
    if handoff is not None or reclaim:
        _hand_off(host, tcp_port, handoff, reclaim=reclaim, token_file=token_file)
        return
    if foreground:
        _log_to_stderr()
    if foxglove_control and foxglove is None:
        raise typer.BadParameter(
            "--foxglove-control needs --foxglove [HOST:]PORT", param_hint="--foxglove-control"
        )
    view = parse_foxglove(foxglove) if foxglove is not None else None
    token = _token(host, token_file)
    url = resolve_port(port)
    origins = tuple(allow_origin or ())
    run(
        lambda: _serve(
            url,
            host,
            tcp_port,
            read_only=read_only,
            token=token,
            origins=origins,
            foxglove=view,
            foxglove_control=foxglove_control,
            rt_priority=rt_priority,
        )
    )


async def _serve(
    url: str,
    host: str,
    tcp_port: int,
    *,
    read_only: bool,
    token: str | None,
    origins: tuple[str, ...],
    foxglove: tuple[str, int] | None = None,
    foxglove_control: bool = False,
    rt_priority: int | None = None,
) -> None:
    # The server and the Robot load when serving: `ohmni serve --help` starts without them.
    from ohmni_tb.daemon.server import RobotServer, check_listen  # noqa: PLC0415

    check_listen(host, token)  # before the port opens: a refused address moves nothing
    if rt_priority is not None:
        # This thread runs the event loop: the class is a thread's (and its later threads').
        set_realtime(rt_priority)
        _log.info("running under SCHED_FIFO at priority %d", rt_priority)
    async with (
        open_robot(url) as robot,
        RobotServer(
            robot, host=host, port=tcp_port, read_only=read_only, token=token, origins=origins
        ) as server,
        contextlib.AsyncExitStack() as stack,
    ):
        write_line(server.url)
        if foxglove is not None:
            from ohmni_tb.client import RobotClient  # noqa: PLC0415
            from ohmni_tb.foxglove import FoxgloveBridge  # noqa: PLC0415  # the extra
            from ohmni_tb.foxglove.control import RobotControl  # noqa: PLC0415

            teleop = None
            control = None
            if foxglove_control:
                # The panel is one more client of the daemon: the same lease as any other,
                # for its Twists, its parameter changes and its service calls.
                operator = await stack.enter_async_context(
                    RobotClient.connect(server.url, token=token)
                )
                teleop = _FoxgloveTeleop(operator)
                stack.push_async_callback(teleop.aclose)
                control = RobotControl(operator, writable=True, before_change=teleop.hold)
            bridge = await stack.enter_async_context(
                FoxgloveBridge(
                    robot,
                    host=foxglove[0],
                    port=foxglove[1],
                    teleop=teleop,
                    control=control,
                )
            )
            write_line(bridge.url)
            _log.info("serving the Foxglove app on %s", bridge.url)
        # What is loaded and open now lives as long as the daemon: keep it out of the
        # cycle collector's full passes, which otherwise walk ~55,000 objects and pause
        # the loop 30–45 ms (two control periods) now and then. (A link reopened later
        # leaves its old transport's few objects to the collector no more: a few KiB.)
        gc.freeze()
        await asyncio.Event().wait()  # until a signal cancels it


class _FoxgloveTeleop:
    """Twists from the Foxglove Teleop panel, driven through the daemon's control lease.

    The first Twist takes the lease when nobody holds it (never steals: while another
    client drives, the panel's Twists are refused and logged); it is given back, which
    stops the robot, :data:`_TELEOP_IDLE_S` after the last Twist. The Robot's watchdog
    stops the wheels sooner when the panel goes quiet.
    """

    def __init__(self, client: RobotClient) -> None:
        self._client = client
        self._acquiring: asyncio.Task[None] | None = None
        self._idle: asyncio.TimerHandle | None = None
        self._refused_by: str | None = None
        self._releasing: asyncio.Task[None] | None = None

    def __call__(self, linear_mps: float, angular_radps: float) -> None:
        if self._client.has_lease:
            self._drive(linear_mps, angular_radps)
        elif self._acquiring is None or self._acquiring.done():
            self._acquiring = asyncio.get_running_loop().create_task(
                self._acquire_then(linear_mps, angular_radps)
            )

    async def _acquire_then(self, linear_mps: float, angular_radps: float) -> None:
        from ohmni_tb.errors import OhmniError  # noqa: PLC0415

        try:
            await self._client.acquire()
        except OhmniError as exc:
            holder = getattr(exc, "holder", None)
            if holder != self._refused_by:  # once per holder, not once per Twist
                _log.warning("foxglove teleop refused: %s", exc)
                self._refused_by = holder
            return
        self._refused_by = None
        _log.info("foxglove teleop took the control lease")
        self._drive(linear_mps, angular_radps)

    async def hold(self) -> None:
        """Hold the lease for a parameter change or a service call: take it when nobody
        holds it (never steals), and give it back a second after the last use.

        Raises:
            LeaseError: Another client holds it (the message names it).
        """
        if not self._client.has_lease:
            await self._client.acquire()
            _log.info("foxglove took the control lease")
        self._rearm()

    def _rearm(self) -> None:
        if self._idle is not None:
            self._idle.cancel()
        self._idle = asyncio.get_running_loop().call_later(_TELEOP_IDLE_S, self._give_back)

    def _drive(self, linear_mps: float, angular_radps: float) -> None:
        from ohmni_tb.errors import OhmniError  # noqa: PLC0415

        try:
            self._client.drive(linear_mps, angular_radps)
        except OhmniError as exc:
            _log.warning("foxglove teleop: %s", exc)
        self._rearm()

    def _give_back(self) -> None:
        self._idle = None
        self._releasing = asyncio.get_running_loop().create_task(self._client.release())

    async def aclose(self) -> None:
        if self._idle is not None:
            self._idle.cancel()
        if self._acquiring is not None:
            self._acquiring.cancel()


def parse_foxglove(text: str) -> tuple[str, int]:
    """``--foxglove [HOST:]PORT``; the extra must be installed."""
    import importlib.util  # noqa: PLC0415

    address = host_port(text, default_host="127.0.0.1")
    if address is None:
        raise typer.BadParameter(
            f"--foxglove must be [HOST:]PORT with a port 0..65535, not {text!r}",
            param_hint="--foxglove",
        )
    host, port = address
    if importlib.util.find_spec("foxglove") is None:
        raise typer.BadParameter(
            "needs the foxglove extra: pip install 'ohmni_tb[foxglove]'", param_hint="--foxglove"
        )
    from ohmni_tb.daemon.server import is_loopback  # noqa: PLC0415

    if not is_loopback(host):
        typer.echo(
            f"warning: the Foxglove view on {host} has no authentication: anyone who reaches "
            "it can watch the robot (prefer loopback and ssh -L)",
            err=True,
        )
    return host, port


def _hand_off(
    host: str, tcp_port: int, seconds: float | None, *, reclaim: bool, token_file: Path | None
) -> None:
    """``--handoff`` / ``--reclaim``: ask the running daemon, holding its lease meanwhile."""
    import math  # noqa: PLC0415

    if seconds is not None and reclaim:
        raise typer.BadParameter("--handoff and --reclaim ask opposite things: give one")
    if seconds is not None and not (math.isfinite(seconds) and 0.1 <= seconds <= 3600):
        raise typer.BadParameter(
            f"--handoff={seconds!r} is out of range: allowed 0.1..3600 s", param_hint="--handoff"
        )
    token = None
    if token_file is not None:
        from ohmni_tb.daemon.auth import read_token  # noqa: PLC0415

        try:
            token = read_token(token_file)
        except (OSError, ConfigError) as exc:
            raise typer.BadParameter(str(exc), param_hint="--token-file") from None
    local = "127.0.0.1" if host in ("0.0.0.0", "") else "::1" if host == "::" else host
    url = f"ws://[{local}]:{tcp_port}" if ":" in local else f"ws://{local}:{tcp_port}"

    async def ask() -> None:
        from ohmni_tb.client import RobotClient  # noqa: PLC0415

        async with RobotClient.connect(url, token=token) as client, client.lease():
            if reclaim:
                await client.reclaim_port()
            else:
                await client.release_port(seconds)

    run(ask)
    if reclaim:
        write_line(f"the daemon at {url} takes the port back (robot_state says when it has it)")
    else:
        write_line(
            f"the daemon at {url} released the port for {seconds:g} s; it takes it back then "
            "(now: ohmni serve --reclaim)"
        )


def _token(host: str, token_file: Path | None) -> str | None:
    """The token clients must present: from ``--token-file``, or the default file beyond
    loopback (made on first use); none on loopback without ``--token-file``."""
    from ohmni_tb.daemon.auth import default_token_path, load_or_create_token  # noqa: PLC0415
    from ohmni_tb.daemon.server import is_loopback  # noqa: PLC0415

    if token_file is None and is_loopback(host):
        return None
    path = token_file if token_file is not None else default_token_path()
    try:
        token = load_or_create_token(path)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--token-file") from None
    typer.echo(
        f"clients need the token in {path} (RobotClient.connect(token=...) or $OHMNI_DAEMON_TOKEN)",
        err=True,
    )
    return token


def _parse_listen(listen: str) -> tuple[str, int]:
    address = host_port(listen)
    if address is None:
        raise typer.BadParameter(
            f"--listen must be HOST:PORT with a port 0..65535, not {listen!r}",
            param_hint="--listen",
        )
    return address


class _Structured(logging.Formatter):
    """``2025-01-01T12:00:00.123Z level=info logger=ohmni_tb.daemon msg="..."``."""

    def format(self, record: logging.LogRecord) -> str:
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        message = record.getMessage().replace('"', '\\"')
        line = (
            f"{stamp}.{int(record.msecs):03d}Z level={record.levelname.lower()} "
            f'logger={record.name} msg="{message}"'
        )
        if record.exc_info:
            line += " " + self.formatException(record.exc_info).replace("\n", " | ")
        return line


def _log_to_stderr() -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Structured())
    logger = logging.getLogger("ohmni_tb")
    logger.addHandler(handler)
    logger.setLevel(min(logger.getEffectiveLevel(), logging.INFO))
