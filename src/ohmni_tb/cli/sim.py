"""``ohmni sim``: serve the simulated robot on a pseudo-terminal."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import stat
import sys
from typing import Annotated
from urllib.parse import parse_qsl, urlsplit

import typer

from ohmni_tb.cli.common import run
from ohmni_tb.errors import ConfigError
from ohmni_tb.sim.line import SimLine
from ohmni_tb.sim.pty import open_pty_pair
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.url import build_line

__all__ = ["sim"]

_HELP_COMMANDS = """commands on stdin: dock | undock | power (cycle) | unplug | plug |
  silent SID | talk SID | drop RATE | corrupt RATE | status | quit"""


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
        ),
    ] = "sim://",
) -> None:
    """Serve the simulated robot on a pseudo-terminal.

    Prints the device path alone on the first line of stdout; open it at 115200 8N1 from
    any serial program (or `ohmni --port PATH ...`). Reads simple commands on stdin to
    dock, cut the cable or silence a device. Ctrl-C stops it.
    """
    if not pty:
        raise typer.BadParameter("the simulator serves on a pseudo-terminal: run `ohmni sim --pty`")
    parts = urlsplit(url)
    if parts.scheme != "sim":
        raise typer.BadParameter(f"--url must start with sim://, not {url!r}")
    options = dict(parse_qsl(parts.query, keep_blank_values=True))
    run(lambda: _serve(options))


async def _serve(options: dict[str, str]) -> None:
    line, robot = build_line(options)
    if options:
        raise ConfigError(f"unknown simulator option(s): {sorted(options)}")
    transport = open_pty_pair(baudrate=line.baudrate)
    robot.attach_clock(line.now_s)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    print(transport.path, flush=True)
    _say(f"simulated Ohmni on {transport.path} @ {line.baudrate} 8N1")
    _say(_HELP_COMMANDS)
    try:
        async with asyncio.TaskGroup() as tg:
            server = tg.create_task(line.serve(transport))
            console = tg.create_task(_console(line, robot, stop))
            await stop.wait()
            server.cancel()
            console.cancel()
    finally:
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(signum)
        await transport.aclose()
        _say("simulator stopped")


def _say(text: str) -> None:
    """Console output is best effort: once the path is out, the pty is what matters.

    A launcher that reads the path and closes the pipe (or a terminal that goes away)
    must not end the session: a failed write here would otherwise kill the simulator
    right after it printed the path, and its client would see the pty hang up.
    """
    with contextlib.suppress(OSError, ValueError):
        print(text, file=sys.stderr, flush=True)


async def _console(line: SimLine, robot: SimRobot, stop: asyncio.Event) -> None:
    """Read operator commands from stdin, if there is one."""
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
    while True:
        raw = await reader.readline()
        if not raw:
            return
        reply = _command(raw.decode(errors="replace").split(), line, robot, stop)
        if reply:
            _say(reply)


def _command(words: list[str], line: SimLine, robot: SimRobot, stop: asyncio.Event) -> str:
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
                f"{'docked' if s.docked else 'undocked'}; line {line.stats}; faults {faults}"
            )
        elif verb in ("quit", "exit"):
            stop.set()
        else:
            return f"unknown command {verb!r}; {_HELP_COMMANDS}"
    except (IndexError, ValueError):
        return f"{verb}: missing or bad argument"
    return "ok"
