"""What every ``ohmni`` command shares: the port option, output, error reporting."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import socket
import sys
import traceback
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Annotated, Any, Final, NoReturn, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from ohmni_tb import eventloop
from ohmni_tb._checks import ws_address
from ohmni_tb.errors import OhmniError, StopNotConfirmedError

if TYPE_CHECKING:
    from rich.table import Table

    from ohmni_tb.bus import Bus, BusStats
    from ohmni_tb.config import RobotConfig
    from ohmni_tb.robot import Robot
    from ohmni_tb.safety import StopReport
    from ohmni_tb.transport import Transport

__all__ = [
    "DAEMON_URL_ENV",
    "DirectOption",
    "JsonOption",
    "PortOption",
    "RobotWarnings",
    "TimeoutOption",
    "YesOption",
    "confirm_motion",
    "confirm_stop",
    "console",
    "daemon_for",
    "drive_source",
    "emit_json",
    "error_line",
    "is_simulated",
    "load_config",
    "open_bus",
    "open_robot",
    "parse_int",
    "plain_table",
    "quiet_stdout",
    "resolve_port",
    "run",
    "set_debug",
    "set_verbosity",
    "stats_rows",
    "write_line",
]

T = TypeVar("T")

#: Where the commands look for ``ohmni serve`` (``off``: never).
DAEMON_URL_ENV: Final = "OHMNI_DAEMON_URL"
#: ohmni_tb.client.DEFAULT_URL, without importing the client.
_DEFAULT_DAEMON_URL = "ws://127.0.0.1:8766"
#: How long the check that the daemon listens may take (loopback: microseconds).
_PROBE_S = 0.3

DirectOption = Annotated[
    bool,
    typer.Option(
        "--direct",
        help="Open the port even when ohmni serve runs (by default the command goes "
        "through the daemon, which holds the port).",
    ),
]
PortOption = Annotated[
    str | None,
    typer.Option(
        "--port",
        "-p",
        help="Serial device or URL: /dev/ttyUSB0, serial:///dev/ttyUSB0?baudrate=115200, "
        "sim:// (built-in simulator), auto (the bus adapter by its USB id). Default: "
        "$OHMNI_PORT, else the config file's port, else auto.",
        show_default=False,
        metavar="PORT",
    ),
]
YesOption = Annotated[
    bool,
    typer.Option("--yes", "-y", help="Move a real robot without asking first."),
]
JsonOption = Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")]
TimeoutOption = Annotated[
    float,
    typer.Option(
        "--timeout",
        help="Reply timeout per attempt, in seconds, 0.001..10.",
        min=0.001,
        max=10.0,
        metavar="S",
    ),
]

console = Console()
_err = Console(stderr=True)
_options: dict[str, Any] = {"debug": False, "verbosity": 0}


def error_line(message: str) -> None:
    """Print ``message`` as the command's one red ``error:`` line on stderr (one line
    whatever the terminal's width; the text is ours, not markup)."""
    _err.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)


def set_debug(on: bool) -> None:
    """``ohmni --debug``: errors print their traceback; the library logs at DEBUG."""
    set_verbosity(2 if on else 0, tracebacks=on)


#: ``ohmni -q`` / ``-v`` / ``-vv``: the lowest level of the library's log shown on stderr.
_LEVELS = {-1: logging.ERROR, 0: logging.WARNING, 1: logging.INFO, 2: logging.DEBUG}


def set_verbosity(level: int, *, tracebacks: bool = False) -> None:
    """How much the library logs on stderr: ``-1`` errors only (``-q``), ``0`` warnings
    (the default), ``1`` info (``-v``), ``2`` and more debug (``-vv``, ``--debug``);
    ``tracebacks``: an error prints its traceback (``--debug``)."""
    level = max(-1, min(2, level))
    _options["debug"] = tracebacks
    _options["verbosity"] = level
    logger = logging.getLogger("ohmni_tb")
    previous = _options.pop("handler", None)
    if isinstance(previous, logging.Handler):
        logger.removeHandler(previous)
    if level > 0:
        # Each line with its time and logger; on stderr as it is now (a test's capture).
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
        logger.addHandler(handler)
        _options["handler"] = handler
        logger.setLevel(_LEVELS[level])
    else:
        logger.setLevel(logging.NOTSET)


def resolve_port(port: str | None) -> str:
    """The port a command opens: ``--port``, else ``$OHMNI_PORT``, else the config file's
    ``port``, else ``auto`` (the bus adapter, found when the port opens).

    Raises:
        ConfigError: The config file is invalid.
    """
    if port:
        return port
    from_env = os.environ.get("OHMNI_PORT")
    if from_env:
        return from_env
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # pydantic: only when needed

    return RobotConfig.load().port


def is_simulated(port: str) -> bool:
    """Whether ``port`` is the built-in simulator (motion needs no consent there)."""
    return port.lower().startswith("sim:")


def confirm_motion(port: str, what: str, *, yes: bool) -> None:
    """Ask once before a command moves a real robot; ``--yes``, ``sim://`` or a daemon
    (``ws://``) whose hello says it serves the simulator skip it.

    Raises:
        typer.Exit: Code 1 when the answer is no, or when nobody can answer (stdin is
            not a terminal and ``--yes`` was not given).
    """
    if yes or is_simulated(port) or _daemon_simulated(port):
        return
    if not sys.stdin.isatty():
        _err.print(
            f"[red]error:[/red] {escape(what)} on {escape(port)} moves the robot: "
            "pass --yes to allow it (stdin is not a terminal to ask)",
            soft_wrap=True,
        )
        raise typer.Exit(1)
    if not typer.confirm(f"{what} on {port} moves the robot. Is the way clear?", default=False):
        _err.print("nothing moved")
        raise typer.Exit(1)


def _daemon_simulated(port: str) -> bool:
    """Whether ``port`` is a daemon's URL and the daemon serves the built-in simulator."""
    if not port.lower().startswith(("ws://", "wss://")):
        return False
    from ohmni_tb.cli.remote import serves_simulator  # noqa: PLC0415  # the client: when used

    return run(lambda: serves_simulator(port))


@asynccontextmanager
async def open_robot(
    port: str,
    *,
    via: str | None = None,
    control: bool = False,
    source: str | None = None,
    **overrides: Any,
) -> AsyncIterator[Robot]:
    """``Robot.open`` with the settings from the environment and config file — or, with
    ``via`` (a daemon's URL from :func:`daemon_for`), the daemon's robot.

    Args:
        port: The port to open (resolved: :func:`resolve_port`).
        via: Use the daemon at this URL instead of opening ``port``.
        control: The command moves the robot: through the daemon it is refused at once,
            naming the holder, when another client holds the control lease of its command
            source (its first command takes the lease otherwise).
        source: The command source of the robot's drive commands (default: the Robot's,
            ``autonomy``).
        overrides: RobotConfig settings for a Robot this opens (not the daemon's).

    Raises:
        LeaseError: ``control``, and another client of the daemon drives the robot.
        TransportError: No device of the robot answered on the port it opened.
    """
    if via is not None:
        from ohmni_tb.errors import LeaseError  # noqa: PLC0415
        from ohmni_tb.robot import RemoteRobot  # noqa: PLC0415  # the client: when used

        async with RemoteRobot.open(via, source=source) as remote:
            holder = remote.lease_holder
            if control and holder is not None:
                raise LeaseError(
                    f"another client of the daemon at {via} drives the robot ({holder}): "
                    "this command needs the control lease"
                    + ("" if source is None else f" of command source {source}"),
                    holder=holder,
                )
            _err.print(
                f"[dim]via the daemon at {escape(via)} (--direct: open the port)[/dim]",
                soft_wrap=True,
            )
            yield remote
        return
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # the Robot only when used
    from ohmni_tb.robot import Robot  # noqa: PLC0415

    async with Robot.open(port, config=RobotConfig.load(), source=source, **overrides) as robot:
        if not robot.state.present:
            from ohmni_tb.errors import TransportError  # noqa: PLC0415

            raise TransportError(
                f"nothing answered on {port}: no board of the robot replied (is it the "
                "robot's bus? `ohmni ports` lists the serial ports, `ohmni probe --port "
                f"{port}` asks every id)"
            )
        yield robot


def drive_source(via: str | None) -> str:
    """The command source a person's commands go as: ``local`` on the robot's own
    computer (the port opened here, or a daemon on loopback), ``remote`` elsewhere."""
    if via is None:
        return "local"
    address = ws_address(via)
    host = "" if address is None else address[0].strip("[]")
    if host == "localhost":
        return "local"
    import ipaddress  # noqa: PLC0415  # only for a daemon's URL

    try:
        return "local" if ipaddress.ip_address(host).is_loopback else "remote"
    except ValueError:
        return "remote"  # a host name: another computer, as far as can be told


def daemon_for(port_option: str | None, direct: bool) -> str | None:
    """The daemon's URL when the command should go through it, else ``None`` (open the port).

    Not with ``--direct``, nor with ``--port`` (the command names what to open), nor with
    ``$OHMNI_DAEMON_URL=off``, nor when nothing listens at ``$OHMNI_DAEMON_URL`` (default
    ``ws://127.0.0.1:8766``): a plain TCP connect decides, so a command without a daemon
    loads no WebSocket code.
    """
    if direct or port_option is not None:
        return None
    url = os.environ.get(DAEMON_URL_ENV) or _DEFAULT_DAEMON_URL
    if url.lower() == "off":
        return None
    try:
        with socket.create_connection(_daemon_address(url), timeout=_PROBE_S):
            return url
    except OSError:
        return None
    except UnicodeError:  # a host name the resolver cannot encode (a label over 63 bytes)
        _bad_daemon_url(url)


def _daemon_address(url: str) -> tuple[str, int]:
    """The host and port of ``$OHMNI_DAEMON_URL``; a malformed one ends the command
    (:func:`_bad_daemon_url`)."""
    address = ws_address(url)
    if address is None:
        _bad_daemon_url(url)
    return address


def _bad_daemon_url(url: str) -> NoReturn:
    """Exit code 1, as for the other settings, after one line naming the variable, its
    value and what it takes."""
    error_line(
        f"{DAEMON_URL_ENV}={_shown(url)} is not a daemon URL: expected ws://HOST:PORT or "
        "wss://HOST:PORT (port 1..65535), or off"
    )
    raise typer.Exit(1)


def run(
    main: Callable[[], Coroutine[Any, Any, T]],
    *,
    on_interrupt: Callable[[], None] | None = None,
    stop_requested: asyncio.Event | None = None,
) -> T:
    """Run a coroutine for a command; our errors become one red line and exit code 1.

    Ctrl-C (SIGINT), SIGTERM and SIGHUP cancel the command's task, so its cleanup runs:
    the Robot stops the wheels and confirms it (the host's watchdog dies with the
    process, and the drive boards keep their last command). Another signal meanwhile
    does not cut that short (asyncio's own Ctrl-C handler would raise KeyboardInterrupt
    in the middle of the event loop, abandoning the stop). The exit code is then 128 +
    the signal's number (130 for Ctrl-C), after ``on_interrupt`` (a command's summary).

    A command whose normal end is a signal (``ohmni serve``) passes ``stop_requested``:
    the first signal sets it instead of cancelling, and the command ends itself through
    its normal exit — exit code 0 when that succeeds, 1 with its error when not (a stop
    the wheel counts did not confirm).
    """
    signals = _Signals(stop_requested)
    logger = logging.getLogger("ohmni_tb")
    shown = _WarningLines(logger)
    if _options["verbosity"] < 0:
        shown.setLevel(logging.ERROR)
    if _options["verbosity"] <= 0:  # -v and more: the log lines go to the root handler
        logger.addHandler(shown)
    try:
        # Timers to the tenth of a millisecond: the bus's schedule needs them.
        return eventloop.run(_guarded(main, signals))
    except OhmniError as exc:
        if _options["debug"]:
            traceback.print_exc()
        # One line whatever the terminal's width; the text is ours, not markup.
        error_line(str(exc))
        raise typer.Exit(1) from exc
    except (KeyboardInterrupt, asyncio.CancelledError) as exc:
        if isinstance(exc, asyncio.CancelledError) and signals.first is None:
            raise
        if on_interrupt is not None:
            with contextlib.suppress(OSError):  # SIGHUP: the terminal may be gone
                on_interrupt()
        raise typer.Exit(128 + (signals.first or signal.SIGINT)) from None
    finally:
        logger.removeHandler(shown)


def run_watch(main: Callable[[], Coroutine[Any, Any, T]], *, watch: bool) -> T | None:
    """:func:`run` for a command with ``--watch``: a watch ended by Ctrl-C before its
    first frame is a normal end too (``None``, exit code 0): what it opened has closed."""
    try:
        return run(main)
    except typer.Exit as exc:
        if watch and exc.exit_code == 128 + signal.SIGINT:
            return None
        raise


class _WarningLines(logging.Handler):
    """The library's warnings during a command, one yellow line each on stderr (its errors
    one red ``error:`` line each; Python's last-resort handler would print them bare). A
    command that installs its own handler on the logger (``drive``, ``demo``) takes them
    over."""

    def __init__(self, logger: logging.Logger) -> None:
        super().__init__(logging.WARNING)
        self._logger = logger

    def emit(self, record: logging.LogRecord) -> None:
        if any(h is not self for h in self._logger.handlers):
            return
        with contextlib.suppress(OSError):  # SIGHUP: the terminal may be gone
            if record.levelno >= logging.ERROR:
                error_line(record.getMessage())
                return
            _err.print(f"[yellow]warning: {escape(record.getMessage())}[/yellow]", soft_wrap=True)


#: Signals that end a command through its cleanup (see :func:`run`).
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class _Signals:
    """The stop signals a command received: the first cancels its task (or sets the
    command's ``stop_requested``)."""

    def __init__(self, stop_requested: asyncio.Event | None = None) -> None:
        self.first: int | None = None
        self.count = 0
        self._stop_requested = stop_requested

    def received(self, signum: int, task: asyncio.Task[Any] | None) -> None:
        self.count += 1
        if self.count == 1:
            if self._stop_requested is not None:
                # The command ends itself: not an interruption (no 128 + N).
                self._stop_requested.set()
                return
            self.first = signum
            if task is not None:
                task.cancel()
        elif self.count == 2:
            with contextlib.suppress(OSError):
                _err.print(
                    "interrupted again: finishing the cleanup first (stopping the wheels, "
                    "confirming the stop); Ctrl-\\ kills without it",
                    soft_wrap=True,
                )


async def _guarded(main: Callable[[], Coroutine[Any, Any, T]], signals: _Signals) -> T:
    """``main()`` with the stop signals handled in the loop (see :func:`run`)."""
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    installed = []
    try:
        for signum in _STOP_SIGNALS:
            try:
                loop.add_signal_handler(signum, signals.received, signum, task)
            except (NotImplementedError, RuntimeError, ValueError):  # no POSIX, no main thread
                break
            installed.append(signum)
        return await main()
    finally:
        for signum in installed:
            loop.remove_signal_handler(signum)


async def open_transport(url: str) -> Transport:
    """:func:`ohmni_tb.transport.open_transport`, imported when a command opens a port."""
    from ohmni_tb.transport import open_transport as open_url  # noqa: PLC0415

    return await open_url(url)


async def open_bus(port: str | None, timeout_s: float | None = None) -> Bus:
    """Open the port (:func:`resolve_port`) and start a bus on it; the caller closes it
    (``async with``)."""
    # Imported here: `ohmni CMD --help` starts without the bus and asyncio's machinery.
    from ohmni_tb.bus import DEFAULT_TIMEOUT_S, Bus  # noqa: PLC0415

    transport = await open_transport(resolve_port(port))
    bus = Bus(transport, timeout_s=DEFAULT_TIMEOUT_S if timeout_s is None else timeout_s)
    bus.start()
    return bus


def parse_int(
    text: str, name: str, low: int | None = None, high: int | None = None, *, of: str = ""
) -> int:
    """Parse decimal or 0x-hex ASCII text, in ``low..high`` when they are given.

    Other digits (``٣``, ``３``) are refused: an id is typed, not localised. ``of`` says
    whose range it is (``" for servo 3"``) in the error.

    Raises:
        typer.BadParameter: Names the argument, the text and the allowed range.
    """
    try:
        if not text.isascii():
            raise ValueError(text)
        value = int(text, 0)
    except ValueError:  # also a number of more than 4300 digits
        raise typer.BadParameter(
            f"{name} must be an integer (decimal or 0x..), not {_shown(text)}"
        ) from None
    if low is not None and high is not None and not low <= value <= high:
        # A huge hex number has too many decimal digits to print: show what was typed.
        shown = str(value) if value.bit_length() <= 64 else _shown(text)
        raise typer.BadParameter(f"{name}={shown} is out of range{of}: allowed {low}..{high}")
    return value


def _shown(text: str) -> str:
    """Typed text for an error line, quoted, and cut short when it is long."""
    return repr(text) if len(text) <= 40 else f"{text[:20]!r}… ({len(text)} characters)"


def emit_json(value: Any) -> None:
    """Print one JSON document on stdout."""
    sys.stdout.write(json.dumps(value, indent=2, default=str) + "\n")


def stats_rows(stats: BusStats) -> list[dict[str, Any]]:
    """One row per device of the bus statistics, for tables and JSON."""
    return [
        {
            "sid": dev.sid,
            "requests": dev.requests,
            "replies": dev.replies,
            "timeouts": dev.timeouts,
            "retries": dev.retries,
            "unmatched": dev.unmatched,
            "late": dev.late,
            "breaker": dev.breaker.value,
            "latency_p50_ms": None
            if dev.latency_p50_s is None
            else round(dev.latency_p50_s * 1e3, 3),
            "latency_p99_ms": None
            if dev.latency_p99_s is None
            else round(dev.latency_p99_s * 1e3, 3),
        }
        for dev in stats.devices.values()
    ]


async def confirm_stop(robot: Robot, timeout_s: float) -> StopReport:
    """Wait until the ``wheel_encoder`` stream shows both wheels standing still: the rule
    of :func:`ohmni_tb.safety.stop_wheels`, applied by its
    :class:`~ohmni_tb.safety.SettleWindow` to the Robot's own 50 Hz counts (every control
    tick carries the zero wheel command meanwhile).

    Raises:
        StopNotConfirmedError: Not within ``timeout_s``: the robot may still be moving.
    """
    from ohmni_tb.errors import StopNotConfirmedError  # noqa: PLC0415
    from ohmni_tb.safety import (  # noqa: PLC0415
        DEFAULT_SETTLE_S,
        DEFAULT_TOLERANCE_TICKS,
        SettleWindow,
        StopReport,
    )

    loop = asyncio.get_running_loop()
    started = loop.time()
    missed_before = robot.stats().streams["wheel_encoder"].missed
    windows = (SettleWindow(), SettleWindow())
    reads = 0
    last: tuple[int, int] | None = None

    def report(*, confirmed: bool) -> StopReport:
        missed = robot.stats().streams["wheel_encoder"].missed - missed_before
        elapsed = loop.time() - started
        return StopReport(
            confirmed, round(elapsed * robot.config.wheel_hz), reads, missed, elapsed, last
        )

    try:
        async with asyncio.timeout(timeout_s), robot.subscribe("wheel_encoder") as sub:
            async for sample in sub:
                reads += 1
                last = (sample.left_raw, sample.right_raw)
                for window, count in zip(windows, last, strict=True):
                    window.add(count, sample.stamp_s, DEFAULT_TOLERANCE_TICKS)
                if all(window.settled(DEFAULT_SETTLE_S) for window in windows):
                    return report(confirmed=True)
    except TimeoutError:
        pass
    reason = (
        "no wheel counts arrived"
        if reads == 0
        else f"the wheel counts did not hold still ({reads} wheel_encoder samples)"
    )
    raise StopNotConfirmedError(sid=0, report=report(confirmed=False), reason=reason)


def load_config() -> RobotConfig:
    """The settings (environment, config file) for a command; an invalid one is exit 1,
    one line (through :func:`run`)."""
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # pydantic: only when run

    async def load() -> RobotConfig:
        return RobotConfig.load()

    return run(load)


def plain_table(title: str | None = None) -> Table:
    """A table of the commands' plain look: a rule under the header, no frame, the title
    (if any) bold on the left."""
    from rich import box  # noqa: PLC0415
    from rich.table import Table  # noqa: PLC0415

    return Table(
        title=title,
        title_justify="left",
        title_style="bold",
        box=box.SIMPLE_HEAD,
        padding=(0, 1),
        pad_edge=False,
    )


@contextlib.contextmanager
def watching(*, as_json: bool) -> Iterator[Any]:
    """Where a ``--watch`` redraws: rich's ``Live`` on the console, or ``None`` with
    ``--json`` (the caller writes a JSON line a frame, :func:`write_line`).

    Ctrl-C (the interrupt itself, or ``asyncio.run`` cancelling the task) ends the watch
    normally, so what was opened closes as on a clean exit (a Robot reports a wheel stop
    it could not confirm). A file's last frame ends with a newline, which ``Live`` leaves
    out.
    """
    if as_json:
        display: contextlib.AbstractContextManager[Any] = contextlib.nullcontext()
    else:
        from rich.live import Live  # noqa: PLC0415  # only to watch

        display = Live(console=console, auto_refresh=False)
    try:
        with display as live:
            yield live
    except (KeyboardInterrupt, asyncio.CancelledError):
        task = asyncio.current_task()
        if task is not None:
            while task.cancelling():
                task.uncancel()
    if not as_json and not console.is_terminal:
        console.line()


def write_line(text: str) -> bool:
    """Print one line on stdout now (flushed: a pipe's reader sees it at once); ``False``
    when the reader has gone (``ohmni odom | head -3``), after pointing stdout at nothing
    so the interpreter's last flush does not fail too."""
    try:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
    except BrokenPipeError:
        quiet_stdout()
        return False
    return True


def quiet_stdout() -> None:
    """Point stdout at /dev/null (its reader has gone): the exit flush then says nothing."""
    with contextlib.suppress(OSError, ValueError, AttributeError):  # a test runner's stdout
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, sys.stdout.fileno())
        finally:
            os.close(devnull)


class RobotWarnings(logging.Handler):
    """The Robot's warnings while a command that drives runs (``drive``, ``demo``): a
    stop it could not confirm on closing is kept in ``stop`` (the command raises or
    reports it once, not also as a log line); the rest are shown as they come. Added
    to the ``ohmni_tb`` logger, it takes the warnings over from :func:`run`'s."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.stop: StopNotConfirmedError | None = None
        self.unconfirmed = False  # the stop on closing failed another way (a link error)
        self.opened = False  # the Robot opened (and so closes with a confirmed stop)
        self.show: Callable[[str], None] = self._print

    @staticmethod
    def _print(text: str) -> None:
        _err.print(f"[yellow]robot: {escape(text)}[/yellow]", soft_wrap=True)

    def emit(self, record: logging.LogRecord) -> None:
        args = record.args if isinstance(record.args, tuple) else ()
        for arg in args:
            if isinstance(arg, StopNotConfirmedError):
                self.stop = arg
                return
        message = record.getMessage()
        if message.startswith("closing: stop not confirmed"):
            self.unconfirmed = True
        self.show(message)
