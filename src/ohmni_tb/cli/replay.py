"""``ohmni replay FILE.mcap``: serve a recording to the Foxglove app as if it were live.

The channels are the file's, as recorded (``ohmni record`` writes the live view's), so
the app's layout for the robot shows the replay unchanged. The server's address is the
first line of stdout; the replay runs once at ``--speed`` and ends with a one-line
summary on stderr (exit code 0). Ctrl-C ends it early (exit code 130, as every command).
A file that is not a regular file, not MCAP, or damaged inside ends it with one error
line naming the file and what is wrong (exit code 1); a chunk that declares more than
64 MiB uncompressed is refused unread, so a hostile file cannot exhaust memory.
"""

from __future__ import annotations

import asyncio
import importlib.util
from typing import Annotated

import typer

from ohmni_tb.cli.common import error_line, run, write_line
from ohmni_tb.cli.serve import parse_foxglove

__all__ = ["replay"]


def replay(
    file: Annotated[
        str,
        typer.Argument(metavar="FILE.mcap", help="The recording to serve.", show_default=False),
    ],
    foxglove: Annotated[
        str,
        typer.Option(
            "--foxglove",
            metavar="[HOST:]PORT",
            help="Where the Foxglove app connects (loopback unless a host is given; port 0: "
            "a free one).",
        ),
    ] = "127.0.0.1:8765",
    speed: Annotated[
        float,
        typer.Option("--speed", help="Playback speed, 0.01..40 (1: as recorded)."),
    ] = 1.0,
    linger: Annotated[
        float,
        typer.Option(
            "--linger",
            metavar="S",
            help="Seconds to wait before the first message, for the app to connect (0..600).",
        ),
    ] = 2.0,
) -> None:
    """Serve FILE.mcap to the Foxglove app as if the robot were live.

    Connect the app to the address printed on the first line ("Foxglove WebSocket"); the
    messages go out on their recorded times (divided by --speed), then the command ends.
    The app can also open the file directly; this is for panels and tools that want a
    live connection. A damaged file ends the replay with one error line (exit code 1).

    Example: ohmni replay run.mcap --speed 2 ; ohmni replay run.mcap --foxglove 0.0.0.0:8765
    """
    if importlib.util.find_spec("foxglove") is None or importlib.util.find_spec("mcap") is None:
        error_line("ohmni replay needs foxglove-sdk and mcap: pip install 'ohmni_tb[foxglove]'")
        raise typer.Exit(1)
    if not 0.01 <= speed <= 40.0:
        raise typer.BadParameter(
            f"--speed={speed!r} is out of range: allowed 0.01..40", param_hint="--speed"
        )
    if not 0.0 <= linger <= 600.0:
        raise typer.BadParameter(
            f"--linger={linger!r} is out of range: allowed 0..600 s", param_hint="--linger"
        )
    host, port = parse_foxglove(foxglove)
    run(lambda: _replay(file, host, port, speed, linger))


async def _replay(path: str, host: str, port: int, speed: float, linger_s: float) -> None:
    from ohmni_tb.foxglove import McapReplay  # noqa: PLC0415  # the SDK loads here

    loop = asyncio.get_running_loop()
    async with McapReplay(path, host=host, port=port, speed=speed) as replay:
        write_line(replay.url)
        await asyncio.sleep(linger_s)
        started = loop.time()
        sent = await replay.run()
        took = loop.time() - started
    typer.echo(
        f"replayed {sent} messages on {len(replay.sent)} channels in {took:.1f} s "
        f"(speed {speed:g})",
        err=True,
    )
