"""``ohmni serve``: run the Robot and share it with local clients over WebSocket."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import stat
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlsplit

import typer

from ohmni_tb._checks import host_port
from ohmni_tb.cli.common import PortOption, open_robot, resolve_port, run, write_line
from ohmni_tb.errors import ConfigError, RobotClosedError
from ohmni_tb.eventloop import set_realtime

__all__ = ["parse_foxglove", "serve"]

_log = logging.getLogger("ohmni_tb.daemon")
#: ``--listen``'s default: the daemon's loopback address (ohmni_tb.daemon.server).
_DEFAULT_LISTEN = "127.0.0.1:8766"
#: SCHED_FIFO's highest priority on Linux.
_MAX_RT_PRIORITY = 99


def serve(
    ctx: typer.Context,
    port: PortOption = None,
    listen: Annotated[
        str,
        typer.Option(
            "--listen",
            help="HOST:PORT to serve on. Loopback (127.0.0.1, [::1], localhost) needs no "
            "token; any other address needs the token file. Port 0 picks a free one.",
            metavar="HOST:PORT",
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
            metavar="FILE",
        ),
    ] = None,
    allow_origin: Annotated[
        list[str] | None,
        typer.Option(
            "--allow-origin",
            help="A browser origin allowed to connect (repeat for more), e.g. "
            "http://localhost:8080. Browsers from other origins are refused.",
            metavar="ORIGIN",
        ),
    ] = None,
    web: Annotated[
        bool,
        typer.Option(
            "--web/--no-web",
            help="Serve the web console at http://HOST:PORT/ on the daemon's own port: status, "
            "live plots, a joystick and the neck, from a phone or a laptop, under the "
            "daemon's rules (the token beyond loopback, one driver). Its URL is the last "
            "line of stdout at start. --no-web: WebSocket clients only.",
        ),
    ] = True,
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
            "/tb_cmd_vel: the pure velocity command; /cmd_vel_accel or /cmd_vel: "
            "acceleration-limited), the Parameters panel sets PID gains and stream rates, "
            "and the reset_odom and neck_move services answer — for a client that first "
            'called /tb_control/unlock with {"token": ...} (the daemon\'s token; on loopback '
            "without one, the default token file's), through the daemon's control lease like "
            "any client and under the Robot's watchdog. Beyond loopback only with a token.",
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
    max_clients: Annotated[
        int,
        typer.Option(
            "--max-clients",
            metavar="N",
            min=1,
            max=10000,
            help="Serve at most N connections at once; the next is refused with HTTP 503 "
            "(lowered when ulimit -n leaves too few files). Readers share one budget of "
            "work, so the control tick keeps its rate however many connect.",
        ),
    ] = 64,
    foreground: Annotated[
        bool,
        typer.Option(
            "--foreground",
            help="Log every connection, lease change, refusal and departure to stderr, one "
            "structured line each (it always runs in the foreground).",
        ),
    ] = False,
    mqtt: Annotated[
        str | None,
        typer.Option(
            "--mqtt",
            metavar="URL",
            help="Also publish the robot to this MQTT broker and take commands from it: "
            "mqtt://HOST[:PORT] or mqtts://HOST[:PORT] (default: the mqtt_url setting). "
            "Credentials and TLS files come from the settings (OHMNI_MQTT_USERNAME …). "
            "Needs the mqtt extra (docs/fleet.md).",
            show_default=False,
        ),
    ] = None,
    robot_id: Annotated[
        str | None,
        typer.Option(
            "--robot-id",
            metavar="ID",
            help="The robot's name on the broker: topics ohmni/ID/... (default: the "
            "robot_id setting, else the host name).",
            show_default=False,
        ),
    ] = None,
    mqtt_discovery: Annotated[
        bool | None,
        typer.Option(
            "--mqtt-discovery/--no-mqtt-discovery",
            help="Announce the robot to Home Assistant over MQTT (default: the "
            "mqtt_discovery setting).",
            show_default=False,
        ),
    ] = None,
    supervisor_fd: Annotated[
        int | None,
        typer.Option(
            "--supervisor-fd",
            hidden=True,
            min=0,
            max=2**31 - 1,  # a descriptor is a C int
            help="Run as the worker of the supervisor whose pipe is this descriptor "
            "(ohmni_tb.daemon.supervisor starts it so).",
        ),
    ] = None,
) -> None:
    """Serve the robot to many local clients over WebSocket: one driver, many readers.

    Opens the port like every command, then prints the address (ws://HOST:PORT) alone on
    the first line of stdout, and the web console's page (http://HOST:PORT/) on the last
    (docs/web.md). Clients subscribe to the Robot's streams, call its services
    and, holding the control lease, command it (Robot.open("ws://HOST:PORT") in Python;
    docs/daemon.md). Ctrl-C or SIGTERM closes the clients, stops the wheels and exits
    with 0. The robot runs in a worker process: when it dies, this one stops the wheels
    and starts it again (docs/daemon.md).

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
    # Every option is checked before anything is asked of a daemon or a port.
    fleet = _mqtt_settings(mqtt, robot_id, mqtt_discovery)
    if handoff is not None or reclaim:
        _hand_off(host, tcp_port, handoff, reclaim=reclaim, token_file=token_file)
        return
    if foreground:
        _log_to_stderr()
    if foxglove_control and foxglove is None:
        raise typer.BadParameter(
            "--foxglove-control needs --foxglove [HOST:]PORT", param_hint="--foxglove-control"
        )
    token = _token(host, token_file, say=supervisor_fd is None)
    view = (
        parse_foxglove(foxglove, control=foxglove_control, token=token, say=supervisor_fd is None)
        if foxglove is not None
        else None
    )
    url = resolve_port(port)
    origins = tuple(allow_origin or ())
    stop = asyncio.Event()
    if supervisor_fd is not None:
        _check_pipe(supervisor_fd)
    elif os.name == "posix":
        _supervise(ctx, url, listen, foxglove, rt_priority=rt_priority, stop=stop, web=web)
        return
    run(
        lambda: _serve(
            url,
            host,
            tcp_port,
            read_only=read_only,
            token=token,
            origins=origins,
            max_clients=max_clients,
            foxglove=view,
            foxglove_control=foxglove_control,
            rt_priority=rt_priority,
            stop=stop,
            supervisor_fd=supervisor_fd,
            mqtt=fleet,
            web=web,
        ),
        stop_requested=stop,
    )


async def _serve(
    url: str,
    host: str,
    tcp_port: int,
    *,
    read_only: bool,
    token: str | None,
    origins: tuple[str, ...],
    max_clients: int = 64,
    foxglove: tuple[str, int] | None = None,
    foxglove_control: bool = False,
    rt_priority: int | None = None,
    stop: asyncio.Event | None = None,
    supervisor_fd: int | None = None,
    mqtt: dict[str, Any] | None = None,
    web: bool = True,
) -> None:
    # The server and the Robot load when serving: `ohmni serve --help` starts without them.
    from ohmni_tb.daemon.server import RobotServer, check_listen  # noqa: PLC0415
    from ohmni_tb.daemon.supervisor import until_stopped  # noqa: PLC0415

    check_listen(host, token)  # before the port opens: a refused address moves nothing
    if rt_priority is not None:
        # This thread runs the event loop: the class is a thread's (and its later threads').
        set_realtime(rt_priority)
        _log.info("running under SCHED_FIFO at priority %d", rt_priority)
    async with (
        open_robot(url, **(mqtt or {})) as robot,
        RobotServer(
            robot,
            host=host,
            port=tcp_port,
            read_only=read_only,
            token=token,
            origins=origins,
            max_clients=max_clients,
            serves=url,
            web=web,
        ) as server,
        contextlib.AsyncExitStack() as stack,
    ):
        write_line(server.url)
        if foxglove is not None:
            from ohmni_tb.client import RobotClient  # noqa: PLC0415
            from ohmni_tb.daemon.auth import load_or_create_token  # noqa: PLC0415
            from ohmni_tb.foxglove import FoxgloveBridge  # noqa: PLC0415  # the extra
            from ohmni_tb.foxglove.control import RobotControl  # noqa: PLC0415
            from ohmni_tb.foxglove.teleop import FoxgloveTeleop  # noqa: PLC0415

            teleop = None
            control = None
            unlock = None
            if foxglove_control:
                # The app is one more client of the daemon: the same lease as any other,
                # for its Twists, its parameter changes and its service calls, as the
                # command source of an operator elsewhere (remote: a person at the robot
                # overrides it, it overrides a script); connected again when the daemon
                # closes the connection.
                operator = await stack.enter_async_context(
                    RobotClient.connect(server.url, token=token, reconnect=True, source="remote")
                )
                teleop = await stack.enter_async_context(FoxgloveTeleop(operator))
                control = RobotControl(operator, writable=True, before_change=teleop.hold)
                # The SDK shows no client's Origin: every client unlocks with a token, the
                # daemon's, or on a loopback daemon without one the default token file's.
                unlock = token if token is not None else load_or_create_token()
            bridge = await stack.enter_async_context(
                FoxgloveBridge(
                    robot,
                    host=foxglove[0],
                    port=foxglove[1],
                    teleop=teleop,
                    control=control,
                    token=unlock,
                )
            )
            write_line(bridge.url)
            _log.info("serving the Foxglove app on %s", bridge.url)
        if robot.config.mqtt_url:
            from ohmni_tb.mqtt import MqttBridge  # noqa: PLC0415  # the extra

            # A client of the daemon like any other: its commands take the lease.
            await stack.enter_async_context(MqttBridge(robot, server))
        if server.web_url is not None:
            # Last, on a line of its own: the lines before it keep their places.
            write_line(server.web_url)
            _log.info("serving the web console on %s", server.web_url)
        # What is loaded and open now lives as long as the daemon: keep it out of the
        # cycle collector's full passes, which otherwise walk ~55,000 objects and pause
        # the loop 30–45 ms (two control periods) now and then. (A link reopened later
        # leaves its old transport's few objects to the collector no more: a few KiB.)
        gc.freeze()
        why = await until_stopped(stop or asyncio.Event(), supervisor_fd)
        if why == "gone":
            _log.warning("the supervisor is gone: stopping the wheels and closing")
        # The brake goes out now, not after the clients are closed.
        with contextlib.suppress(RobotClosedError):  # closed already: it stopped the wheels
            robot.stop()


def parse_foxglove(
    text: str, *, control: bool = False, token: str | None = None, say: bool = True
) -> tuple[str, int]:
    """``--foxglove [HOST:]PORT``; the extra must be installed. With ``control``
    (``--foxglove-control``) beyond loopback only when the daemon has a ``token``. ``say``:
    tell where the token that unlocks control is, and, beyond loopback, what anyone there
    can do (the supervisor does; its worker does not again)."""
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

    unlock = '/tb_control/unlock {"token": ...}'
    if control:
        if token is None and not is_loopback(host):
            raise typer.BadParameter(
                f"--foxglove-control on {host}, beyond loopback, needs the daemon's token: "
                "give --token-file PATH (Foxglove clients unlock control with it), or keep "
                "--foxglove on 127.0.0.1 and reach it with ssh -L",
                param_hint="--foxglove-control",
            )
        where = _unlock_token(token)
        if say:
            typer.echo(
                f"Foxglove clients watch; to drive, set parameters or call services, a client "
                f"first calls {unlock} with {where}",
                err=True,
            )
    if say and not is_loopback(host):
        can = (
            f"drive, set parameters and call services only with the token ({unlock})"
            if control
            else "change nothing"
        )
        typer.echo(
            f"warning: the Foxglove view on {host} has no authentication of its own: anyone "
            f"who reaches it can watch every stream and read the parameters, and {can} "
            "(prefer loopback and ssh -L)",
            err=True,
        )
    return host, port


def _mqtt_settings(url: str | None, robot_id: str | None, discovery: bool | None) -> dict[str, Any]:
    """The MQTT settings given as options, checked before the port opens (a bad one moves
    nothing); and, when the robot goes on a broker, that the mqtt extra is there and the
    streams of ``mqtt_rates`` exist."""
    import importlib.util  # noqa: PLC0415

    from ohmni_tb.config import RobotConfig  # noqa: PLC0415

    given: dict[str, Any] = {}
    for name, hint, value in (
        ("mqtt_url", "--mqtt", url),
        ("robot_id", "--robot-id", robot_id),
        ("mqtt_discovery", "--mqtt-discovery", discovery),
    ):
        if value is None:
            continue
        try:
            RobotConfig.check_setting(name, value)
        except ConfigError as exc:
            raise typer.BadParameter(str(exc), param_hint=hint) from None
        given[name] = value
    try:
        config = RobotConfig.load(**given)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc)) from None
    if not config.mqtt_url:
        return given
    if importlib.util.find_spec("aiomqtt") is None:
        raise typer.BadParameter(
            "needs the mqtt extra: pip install 'ohmni_tb[mqtt]'", param_hint="--mqtt"
        )
    from ohmni_tb.robot.samples import STREAM_NAMES  # noqa: PLC0415

    unknown = sorted(set(config.mqtt_streams()) - set(STREAM_NAMES))
    if unknown:
        raise typer.BadParameter(
            f"mqtt_rates={config.mqtt_rates!r} names no stream {', '.join(unknown)}: the "
            f"streams are {', '.join(STREAM_NAMES)}"
        )
    return given


def _unlock_token(token: str | None) -> str:
    """Where the token that unlocks Foxglove control is: the daemon's, or the default
    token file's (made on first use) on a loopback daemon without one."""
    if token is not None:
        return "the daemon's token"
    from ohmni_tb.daemon.auth import default_token_path, load_or_create_token  # noqa: PLC0415

    path = default_token_path()
    try:
        load_or_create_token(path)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--foxglove-control") from None
    return f"the token in {path}"


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


def _token(host: str, token_file: Path | None, *, say: bool = True) -> str | None:
    """The token clients must present: from ``--token-file``, or the default file beyond
    loopback (made on first use); none on loopback without ``--token-file``. ``say``:
    tell where it is (the supervisor does; its worker does not again)."""
    from ohmni_tb.daemon.auth import default_token_path, load_or_create_token  # noqa: PLC0415
    from ohmni_tb.daemon.server import is_loopback  # noqa: PLC0415

    if token_file is None and is_loopback(host):
        return None
    path = token_file if token_file is not None else default_token_path()
    try:
        token = load_or_create_token(path)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--token-file") from None
    if say:
        typer.echo(
            f"clients need the token in {path} (Robot.open(url, token=...) or $OHMNI_DAEMON_TOKEN)",
            err=True,
        )
    return token


def _supervise(
    ctx: typer.Context,
    url: str,
    listen: str,
    foxglove: str | None,
    *,
    rt_priority: int | None,
    stop: asyncio.Event,
    web: bool = True,
) -> None:
    """Serve through a worker process (ohmni_tb.daemon.supervisor); exit with its code."""
    from ohmni_tb.daemon.supervisor import supervise  # noqa: PLC0415

    root = ["--debug"] if ctx.find_root().params.get("debug") else []
    # Every other option given, as given: the worker checks them again and serves with
    # them. The port (resolved) and the addresses are set below.
    given: list[str] = []
    for param in ctx.command.params:
        name = param.name or ""
        source = ctx.get_parameter_source(name)
        if (
            param.param_type_name != "option"
            or name in ("port", "listen", "foxglove", "supervisor_fd")
            or source is None
            or source.name == "DEFAULT"
        ):
            continue
        value = ctx.params[name]
        flag = param.opts[0]
        if getattr(param, "is_flag", False):
            given += [flag] if value else param.secondary_opts[:1]
        elif param.multiple:
            for item in value:
                given += [flag, str(item)]
        elif value is not None:
            given += [flag, str(value)]

    def command(fd: int, shown: Sequence[str]) -> list[str]:
        # A restarted worker serves where the first one did (a port 0 chose one).
        where, view = listen, foxglove
        if shown:
            where = _with_port(listen, urlsplit(shown[0]).port)
        if view is not None and len(shown) > 1:
            view = _with_port(view, urlsplit(shown[1]).port)
        extra = [] if view is None else ["--foxglove", view]
        return [
            sys.executable, "-m", "ohmni_tb", *root, "serve", "--supervisor-fd", str(fd),
            "--port", url, "--listen", where, *extra, *given,
        ]  # fmt: skip

    async def main() -> int:
        if rt_priority is not None:
            # The supervisor stops the wheels when the worker dies: as promptly as it serves.
            set_realtime(rt_priority)
        return await supervise(
            command,
            port=url,
            stop=stop,
            ready_lines=1 + (foxglove is not None) + web,
            write=write_line,
        )

    code = run(main, stop_requested=stop)
    if code:
        raise typer.Exit(code)


def _check_pipe(fd: int) -> None:
    """``--supervisor-fd`` must be the worker's end of the supervisor's socket pair."""
    try:
        is_pipe = stat.S_ISSOCK(os.fstat(fd).st_mode)
    except OSError:
        is_pipe = False
    if not is_pipe:
        raise typer.BadParameter(
            f"{fd} is not an open pipe (ohmni serve passes it to its own worker)",
            param_hint="--supervisor-fd",
        )


def _with_port(address: str, port: int | None) -> str:
    """``HOST:PORT`` (or ``PORT``) with another port."""
    return address if port is None else f"{address.rpartition(':')[0]}:{port}"


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
