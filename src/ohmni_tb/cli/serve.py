"""``ohmni serve``: run the Robot and share it with local clients over WebSocket."""

from __future__ import annotations

import asyncio
import logging
import sys
import time
from typing import Annotated

import typer

from ohmni_tb.cli.common import PortOption, open_robot, resolve_port, run, write_line
from ohmni_tb.errors import ConfigError

__all__ = ["serve"]

#: ``--listen``'s default: the daemon's loopback address (ohmni_tb.daemon.server).
_DEFAULT_LISTEN = "127.0.0.1:8766"


def serve(
    port: PortOption = None,
    listen: Annotated[
        str,
        typer.Option(
            "--listen",
            help="HOST:PORT to serve on; loopback only in this version (127.0.0.1, [::1], "
            "localhost). Port 0 picks a free one.",
        ),
    ] = _DEFAULT_LISTEN,
    foreground: Annotated[
        bool,
        typer.Option(
            "--foreground",
            help="Log every connection, refusal and departure to stderr, one structured "
            "line each (it always runs in the foreground in this version).",
        ),
    ] = False,
) -> None:
    """Serve the robot to many local clients over WebSocket (read-only in this version).

    Opens the port like every command, then prints the address (ws://HOST:PORT) alone on
    the first line of stdout. Clients subscribe to the Robot's streams and call stats,
    info, latest and schedule (ohmni_tb.client.RobotClient; docs/daemon.md). Ctrl-C or
    SIGTERM closes the clients, stops the wheels and exits.

    Example: ohmni serve --port sim:// --listen 127.0.0.1:8766
    """
    host, tcp_port = _parse_listen(listen)
    if foreground:
        _log_to_stderr()
    url = resolve_port(port)
    run(lambda: _serve(url, host, tcp_port))


async def _serve(url: str, host: str, tcp_port: int) -> None:
    # The server and the Robot load when serving: `ohmni serve --help` starts without them.
    from ohmni_tb.daemon.server import RobotServer, check_loopback  # noqa: PLC0415

    check_loopback(host)  # before the port opens: a refused address moves nothing
    async with open_robot(url) as robot, RobotServer(robot, host=host, port=tcp_port) as server:
        write_line(server.url)
        await asyncio.Event().wait()  # until a signal cancels it


def _parse_listen(listen: str) -> tuple[str, int]:
    host, sep, port_text = listen.rpartition(":")
    if not sep or not host or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise typer.BadParameter(
            f"--listen must be HOST:PORT with a port 0..65535, not {listen!r}",
            param_hint="--listen",
        )
    host = host.removeprefix("[").removesuffix("]")
    try:
        from ohmni_tb.daemon.server import check_loopback  # noqa: PLC0415

        check_loopback(host)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--listen") from None
    return host, int(port_text)


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
