"""``ohmni sim``: serve the simulated robot on a pseudo-terminal."""

from __future__ import annotations

import asyncio
import os
import signal
import stat
import sys
import threading
from collections import deque
from typing import TYPE_CHECKING, Annotated, Final
from urllib.parse import parse_qsl, urlsplit

import typer

from ohmni_tb.cli.common import run
from ohmni_tb.errors import ConfigError, InvalidArgumentError, OhmniError

if TYPE_CHECKING:
    from ohmni_tb.sim.line import LineFaults, LineStats, SimLine
    from ohmni_tb.sim.robot import SimRobot

__all__ = ["MAX_CONSOLE_LINE", "sim"]

#: The longest operator command line taken on stdin, in bytes; a longer one is refused.
MAX_CONSOLE_LINE: Final = 1024
#: Console output waiting for a slow reader of stderr; beyond it lines are dropped.
_CONSOLE_BACKLOG: Final = 64 * 1024
#: How long the last words ("simulator stopped") may wait for stderr at the end.
_CONSOLE_CLOSE_S: Final = 1.0
#: Signals that stop the simulator cleanly (exit code 0).
_STOP_SIGNALS: Final = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

_HELP_COMMANDS = """commands on stdin: dock | undock | power (cycle) | unplug | plug |
  silent SID | talk SID | stall SID [off] | slip SID [off] | drop RATE | corrupt RATE |
  status | quit"""


def sim(
    pty: Annotated[
        bool, typer.Option("--pty", help="Serve on a new pseudo-terminal (required).")
    ] = False,
    url: Annotated[
        str,
        typer.Option(
            "--url",
            help="Simulator options as a sim:// URL, e.g. 'sim://?neck=worm&docked=1' "
            "(see ohmni_tb.sim.url for every option).",
            metavar="URL",
        ),
    ] = "sim://",
) -> None:
    """Serve the simulated robot on a pseudo-terminal.

    Prints the device path alone on the first line of stdout; open it at 115200 8N1 from
    any serial program (or `ohmni status --port PATH`). Reads simple commands on stdin
    to dock, cut the cable or silence a device. Ctrl-C, SIGTERM, SIGHUP, `quit` or the end
    of stdin (Ctrl-D) stop it.

    Example: ohmni sim --pty --url 'sim://?neck=worm&docked=1'
    """
    if not pty:
        raise typer.BadParameter("the simulator serves on a pseudo-terminal: run `ohmni sim --pty`")
    parts = urlsplit(url)
    if parts.scheme != "sim":
        raise typer.BadParameter(f"--url must start with sim://, not {url!r}")
    options = dict(parse_qsl(parts.query, keep_blank_values=True))
    run(lambda: _serve(options))


class _Stop:
    """Why the simulator stops: the first reason given wins."""

    def __init__(self) -> None:
        self.event = asyncio.Event()
        self.reason = ""

    def __call__(self, reason: str) -> None:
        if not self.event.is_set():
            self.reason = reason
            self.event.set()


async def _serve(options: dict[str, str]) -> None:
    # The simulator (numpy) loads when it serves: `ohmni sim --help` starts without it.
    from ohmni_tb.sim.pty import open_pty_pair  # noqa: PLC0415
    from ohmni_tb.sim.url import build_line  # noqa: PLC0415

    line, robot = build_line(options)
    if options:
        raise ConfigError(f"unknown simulator option(s): {sorted(options)}")
    transport = open_pty_pair(baudrate=line.baudrate)
    robot.attach_clock(line.now_s)
    stop = _Stop()
    loop = asyncio.get_running_loop()
    for signum in _STOP_SIGNALS:
        loop.add_signal_handler(signum, stop, signal.Signals(signum).name)
    out = _ConsoleOut()
    print(transport.path, flush=True)
    out.say(f"simulated Ohmni on {transport.path} @ {line.baudrate} 8N1")
    out.say(_HELP_COMMANDS)
    try:
        async with asyncio.TaskGroup() as tg:
            server = tg.create_task(line.serve(transport))
            console = tg.create_task(_console(line, robot, stop, out))
            await stop.event.wait()
            server.cancel()
            console.cancel()
    finally:
        for signum in _STOP_SIGNALS:
            loop.remove_signal_handler(signum)
        await transport.aclose()
        out.say(f"simulator stopped ({stop.reason or 'error'})")
        out.close(_CONSOLE_CLOSE_S)


class _ConsoleOut:
    """The console's lines to stderr, written by a thread so they never stall the loop.

    Console output is best effort: once the path is out, the pty is what matters. A
    reader of stderr that falls behind (or a pipe nobody reads) leaves lines waiting, up
    to :data:`_CONSOLE_BACKLOG` bytes; beyond that new lines are dropped and counted, and
    a note says how many once the reader catches up. A stderr that fails (a launcher
    that closed it, a terminal gone) silences the console without ending the session.
    """

    def __init__(self) -> None:
        try:
            fd: int | None = sys.stderr.fileno()
        except (AttributeError, ValueError, OSError):
            fd = None  # no stderr at all: nothing is said
        self._fd = fd
        self._lines: deque[bytes] = deque()
        self._queued = 0
        self._closing = False
        self.dropped = 0
        self._noted = 0
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        if fd is not None:
            # A daemon: a write stuck on a full pipe must not keep the process alive.
            self._thread = threading.Thread(target=self._run, name="sim-console", daemon=True)
            self._thread.start()

    def say(self, text: str) -> None:
        """Queue one line; never blocks."""
        data = (text + "\n").encode(errors="backslashreplace")
        with self._cond:
            if self._fd is None:
                return
            if self._queued + len(data) > _CONSOLE_BACKLOG:
                self.dropped += 1
                return
            self._lines.append(data)
            self._queued += len(data)
            self._cond.notify()

    def close(self, timeout_s: float) -> None:
        """Let the queued lines out, waiting at most ``timeout_s`` for a slow reader."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _run(self) -> None:
        fd = self._fd
        assert fd is not None  # the thread is started only with a stderr
        while True:
            with self._cond:
                while not self._lines and not self._closing:
                    self._cond.wait()
                if not self._lines:
                    return
                batch = b"".join(self._lines)
                self._lines.clear()
                self._queued = 0
                if self.dropped > self._noted:
                    note = f"[{self.dropped - self._noted} console lines dropped: stderr was full]"
                    batch = note.encode() + b"\n" + batch
                    self._noted = self.dropped
            try:
                view = memoryview(batch)
                while view:
                    view = view[os.write(fd, view) :]
            except OSError:
                with self._cond:
                    self._fd = None  # stderr is gone: say nothing more
                    self._lines.clear()
                return


async def _console(line: SimLine, robot: SimRobot, stop: _Stop, out: _ConsoleOut) -> None:
    """Read operator commands from stdin, if there is a console there.

    With no console (stdin closed, ``/dev/null``, a plain file) the simulator serves
    until a signal. A console that ends (Ctrl-D, a launcher that closed the pipe or went
    away, a terminal gone) stops the simulator, as ``quit`` does.
    """
    try:
        fd = sys.stdin.fileno()
        mode = os.fstat(fd).st_mode
    except (AttributeError, ValueError, OSError):
        return  # no stdin at all: serve without a console
    # The loop can watch a pipe, a socket or a terminal; /dev/null or a plain file is
    # accepted by connect_read_pipe but fails to register later, inside the loop, with
    # a traceback on stderr. Serve without a console then, as for a closed stdin.
    if not (stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode) or os.isatty(fd)):
        return
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    try:
        await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    except (ValueError, OSError):
        return  # no usable stdin (closed, or a plain file): serve without a console
    held = bytearray()
    skipping = False  # inside a line too long to be a command, until its newline
    while True:
        try:
            chunk = await reader.read(4096)
        except OSError:
            chunk = b""  # a terminal gone (EIO) ends the console like an EOF
        if not chunk:
            if held and not skipping:
                _run_command(bytes(held), line, robot, stop, out)
            stop("stdin closed")
            return
        held += chunk
        while True:
            end = held.find(b"\n")
            if end < 0:
                if len(held) > MAX_CONSOLE_LINE:
                    if not skipping:
                        out.say(_too_long())
                    skipping = True
                    held.clear()
                break
            raw = bytes(held[:end])
            del held[: end + 1]
            if skipping:
                skipping = False  # the tail of the long line: not a command
            elif len(raw) > MAX_CONSOLE_LINE:
                out.say(_too_long())
            else:
                _run_command(raw, line, robot, stop, out)


def _too_long() -> str:
    return f"console line longer than {MAX_CONSOLE_LINE} bytes ignored (commands are short)"


def _run_command(raw: bytes, line: SimLine, robot: SimRobot, stop: _Stop, out: _ConsoleOut) -> None:
    words = raw.decode(errors="replace").split()
    try:
        reply = _command(words, line, robot, stop)
    except OhmniError as exc:
        reply = f"{words[0]}: {exc}"
    if reply:
        out.say(reply)


def _command(words: list[str], line: SimLine, robot: SimRobot, stop: _Stop) -> str:
    if not words:
        return ""
    verb, args = words[0].lower(), words[1:]
    faults = line.faults
    try:
        if verb == "dock":
            robot.set_docked(True)
        elif verb == "undock":
            robot.set_docked(False)
        elif verb == "power":
            line.power_cycle()
        elif verb == "unplug":
            faults.unplugged = True
        elif verb == "plug":
            faults.unplugged = False
        elif verb == "silent":
            faults.silent.add(int(args[0], 0))
        elif verb == "talk":
            faults.silent.discard(int(args[0], 0))
        elif verb in ("stall", "slip"):
            return _wheel_fault(verb, args, robot)
        elif verb in ("drop", "corrupt"):
            rate = float(args[0])
            if not 0.0 <= rate <= 1.0:
                return f"{verb} rate {rate} is out of range: allowed 0..1"
            if verb == "drop":
                faults.drop_rate = rate
            else:
                faults.corrupt_rate = rate
        elif verb == "status":
            pose = robot.pose
            s = robot.core.status()
            return (
                f"pose x={pose.x:.3f} m y={pose.y:.3f} m yaw={pose.yaw:.3f} rad; "
                f"pack {s.pack_mv} mV {s.charging_current_ma} mA "
                f"{'docked' if s.docked else 'undocked'}; line {_line_text(line.stats)}; "
                f"faults {_faults_text(faults, robot)}"
            )
        elif verb in ("quit", "exit"):
            stop(verb)
        else:
            return f"unknown command {verb!r}; {_HELP_COMMANDS}"
    except (IndexError, ValueError):
        return f"{verb}: missing or bad argument"
    return "ok"


def _line_text(stats: LineStats) -> str:
    """The line's counters in words: bytes, packets, replies, and only the troubles seen."""
    text = (
        f"{stats.bytes_to_devices} B to the devices, {stats.bytes_to_host} B to the host, "
        f"{stats.packets} packets, {stats.replies} replies, busy {stats.busy_s:.2f} s"
    )
    troubles = {
        "collisions": stats.collisions,
        "host collisions": stats.host_collisions,
        "expired frames": stats.expired,
        "dropped bytes": stats.dropped_bytes,
        "corrupted bytes": stats.corrupted_bytes,
        "host waits": stats.host_waits,
    }
    return text + "".join(f", {count} {name}" for name, count in troubles.items() if count)


def _wheel_fault(verb: str, args: list[str], robot: SimRobot) -> str:
    """``stall SID [off]`` / ``slip SID [off]``: drive board SID's wheel blocked, or
    without traction, or (``off``) back to normal.

    Raises:
        IndexError: No SID.
        ValueError: SID is not a number.
    """
    sid = int(args[0], 0)
    if args[1:] not in ([], ["off"]):
        return f"{verb}: say `{verb} SID` or `{verb} SID off`, not {' '.join(args)!r}"
    on = not args[1:]
    set_fault = robot.stall if verb == "stall" else robot.slip
    try:
        set_fault(sid, on)
    except InvalidArgumentError as exc:
        return f"{verb}: {exc}"
    return "ok"


def _faults_text(faults: LineFaults, robot: SimRobot) -> str:
    """The injected faults in words, or ``none``."""
    parts = []
    boards = (robot.left, robot.right)
    for name, wheels in (("stall", robot.blocked_wheels), ("slip", robot.slipping_wheels)):
        sids = [str(board.sid) for board, on in zip(boards, wheels, strict=True) if on]
        if sids:
            parts.append(f"{name} {','.join(sids)}")
    if faults.drop_rate:
        parts.append(f"drop {faults.drop_rate:g}")
    if faults.corrupt_rate:
        parts.append(f"corrupt {faults.corrupt_rate:g}")
    if faults.silent:
        parts.append("silent " + ",".join(map(str, sorted(faults.silent))))
    if faults.unplugged:
        parts.append("unplugged")
    return ", ".join(parts) or "none"
