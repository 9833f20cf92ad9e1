"""``ohmni bus``: raw requests on the bus."""

from __future__ import annotations

import asyncio
import importlib.util
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from ohmni_tb._files import open_regular
from ohmni_tb.cli import new_app
from ohmni_tb.cli.bus_capture import convert, tbnode_plugin
from ohmni_tb.cli.common import (
    JsonOption,
    PortOption,
    TimeoutOption,
    console,
    emit_json,
    error_line,
    load_config,
    open_bus,
    parse_int,
    resolve_port,
    run,
)
from ohmni_tb.errors import MalformedReplyError, OhmniError
from ohmni_tb.monitor import BusMonitor, MonitorEvent
from ohmni_tb.protocol import (
    BROADCAST_ID,
    MAX_PACKET_SIZE,
    Command,
    Packet,
    ReadReply,
    StatusReply,
    encode_packet,
    flag_names,
)
from ohmni_tb.protocol.devices import device_name
from ohmni_tb.protocol.framing import HEADER_SIZE
from ohmni_tb.protocol.timing import reply_size_range
from ohmni_tb.transport import open_transport

app = new_app(
    help="Raw packets on the bus: send one request, see the decoded reply; decode traffic."
    "\n\nExample: ohmni bus send 20 EEP_READ F1 00 --port sim://"
)

# A capture logged on the robot by the vendor's own software: the plugin, its log's converter.
app.command("tbnode-plugin")(tbnode_plugin)
app.command()(convert)

#: The longest --duration: a week. Without one, a live monitor runs until Ctrl-C.
_MAX_DURATION_S = 7 * 24 * 3600.0


def _parse_command(text: str) -> int:
    try:
        return int(Command[text.upper()])
    except KeyError:
        pass
    if not (text.isascii() and text.lstrip("+-")[:1].isdigit()):
        names = ", ".join(c.name for c in Command)
        raise typer.BadParameter(
            f"CMD must be a command name ({names}) or a code 0..255, not {text!r}"
        )
    return parse_int(text, "CMD", 0, 0xFF)


@app.command()
def send(
    sid: Annotated[str, typer.Argument(help="Device id, e.g. 0, 20, 0x14.")],
    cmd: Annotated[str, typer.Argument(help="Command name (RAM_READ, STAT...) or code.")],
    data: Annotated[list[str] | None, typer.Argument(help="Data bytes in hex, e.g. 3B 04.")] = None,
    port: PortOption = None,
    timeout: TimeoutOption = 0.05,
    no_reply: Annotated[bool, typer.Option("--no-reply", help="Do not wait for a reply.")] = False,
    as_json: JsonOption = False,
) -> None:
    """Send one raw request and print the decoded reply.

    Example: ``ohmni bus send 0 RAM_READ 3B 04`` reads the left wheel count.
    """
    sid_value = parse_int(sid, "SID", 0, BROADCAST_ID)
    code = _parse_command(cmd)
    text = " ".join(data or [])
    try:
        if not text.isascii():
            raise ValueError(text)
        payload = bytes.fromhex(text.replace(" ", ""))
    except ValueError:
        raise typer.BadParameter(f"DATA must be hex bytes, not {text!r}") from None
    packet = Packet(sid_value, code, payload)
    _check_packet(packet)

    async def main() -> Packet | None:
        async with await open_bus(port, timeout) as bus:
            return await bus.request(packet, expect_reply=False if no_reply else None)

    reply = run(main)
    if reply is None:
        if as_json:
            emit_json({"request": _packet_json(packet), "reply": None})
        else:
            console.print(f"sent {packet!r}; no reply expected")
        return
    decoded: dict[str, object] = _packet_json(reply)
    try:
        if reply.cmd in (Command.RAM_READ | 0x40, Command.EEP_READ | 0x40):
            rr = ReadReply.parse(reply)
            decoded.update(
                addr=rr.addr,
                value_hex=rr.data.hex(" "),
                status_error=flag_names(rr.status_error),
                status_detail=flag_names(rr.status_detail),
            )
            as_text = _printable(rr.data)
            if as_text is not None:
                decoded["value_text"] = as_text  # a firmware tag, say
        elif len(reply.data) == 2:
            sr = StatusReply.parse(reply)
            decoded.update(
                status_error=flag_names(sr.status_error), status_detail=flag_names(sr.status_detail)
            )
    except MalformedReplyError as exc:
        decoded["malformed"] = str(exc)
    if as_json:
        emit_json({"request": _packet_json(packet), "reply": decoded})
    else:
        console.print(f"request  {packet!r}", highlight=False)
        console.print(f"reply    {reply!r}", highlight=False)
        for key, value in decoded.items():
            if key not in ("sid", "cmd", "command", "data", "bytes"):
                shown = repr(value) if key == "value_text" else value
                console.print(f"  {key:14} {shown}", highlight=False)


def _packet_json(packet: Packet) -> dict[str, object]:
    """A packet for JSON: its id, command (number and name), data, and its bytes on the
    wire."""
    base = packet.cmd & ~0x40
    try:
        name = Command(base).name + (" reply" if packet.is_reply else "")
    except ValueError:
        name = f"0x{packet.cmd:02X}"
    return {
        "sid": packet.sid,
        "cmd": packet.cmd,
        "command": name,
        "data": packet.data.hex(" "),
        "bytes": encode_packet(packet).hex(" "),
    }


def _printable(data: bytes) -> str | None:
    """``data`` as text when it is printable ASCII (a firmware tag), else ``None``."""
    text = data.rstrip(b"\x00")
    if text and all(0x20 <= b < 0x7F for b in text):
        return text.decode("ascii")
    return None


@app.command()
def monitor(
    port: Annotated[
        str | None,
        typer.Option("--port", "-p", help="Listen on a live port (a tap on the line)."),
    ] = None,
    capture: Annotated[
        Path | None,
        typer.Option(
            "--capture",
            help="Decode a file of raw captured bytes instead, or an MCAP recording made "
            "with ohmni record --raw (with the bytes' times).",
        ),
    ] = None,
    duration: Annotated[
        float | None,
        typer.Option(
            "--duration",
            help="Stop listening after this many seconds (at most a week) [default: Ctrl-C].",
            min=0.0,
            max=_MAX_DURATION_S,
        ),
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print only the summary.")] = False,
    as_json: JsonOption = False,
) -> None:
    """Decode bus traffic: packets by device and register name, rates, latencies, errors.

    Use --capture for bytes logged from the real robot (see docs/hardware.md), or --port
    on an adapter that listens to the line. Ctrl-C ends a live session. The boards'
    registers are read as the configured bus profile says (battery_addr, ...).

    Example: ohmni record bus.mcap --raw --duration 2 --port sim:// ; ohmni bus monitor
    --capture bus.mcap --json > decoded.ndjson
    """
    if (port is None) == (capture is None):
        raise typer.BadParameter("give exactly one of --port or --capture")
    # The boards' registers are named where the configured profile puts them.
    mon = BusMonitor(load_config().profile())

    def show(events: list[MonitorEvent]) -> None:
        if quiet:
            return
        for ev in events:
            if as_json:
                sys.stdout.write(json.dumps(_event_json(ev)) + "\n")
            else:
                t = "" if ev.t_s is None else f"{ev.t_s:10.4f} "
                lat = "" if ev.latency_s is None else f"  ({ev.latency_s * 1e3:.2f} ms)"
                console.print(f"{t}{ev.device:>9} {ev.text}{lat}", highlight=False)

    if capture is not None:
        _feed_capture(mon, capture, show)
    else:
        assert port is not None

        async def listen() -> None:
            transport = await open_transport(resolve_port(port))
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            try:
                async with asyncio.timeout(duration):
                    while True:
                        chunk = await transport.read()
                        show(mon.feed(chunk, loop.time() - t0))
            except TimeoutError:
                pass
            finally:
                await transport.aclose()

        # Ctrl-C ends a live session: the summary still comes, then exit code 130.
        run(listen, on_interrupt=lambda: _summary(mon, as_json))
    _summary(mon, as_json)


#: The first bytes of an MCAP file.
_MCAP_MAGIC = b"\x89MCAP0\r\n"
#: A raw capture is decoded this much at a time: the monitor holds a block, not the file.
_CAPTURE_BLOCK = 1 << 16


def _feed_capture(mon: BusMonitor, path: Path, show: Callable[[list[MonitorEvent]], None]) -> None:
    """A capture file: raw bytes read a block at a time, or an ``ohmni record --raw``
    recording. Only a regular file: a FIFO or a device (``/dev/zero``) would block, or
    never end; opening one never waits.

    Raises:
        typer.BadParameter: It cannot be opened (exit code 2).
        typer.Exit: Code 1, after one line, when it is not a regular file or a read fails.
    """
    try:
        file = open_regular(path)
    except OSError as exc:
        raise typer.BadParameter(f"cannot read capture {path}: {exc}") from None
    except ValueError as exc:  # not a regular file, or a NUL in the path
        error_line(f"cannot read capture {path}: {exc}")
        raise typer.Exit(1) from None
    with file:
        try:
            data = file.read(len(_MCAP_MAGIC))
            if data == _MCAP_MAGIC:
                file.close()
                _feed_recording(mon, path, show)
                return
            while data:
                show(mon.feed(data))
                data = file.read(_CAPTURE_BLOCK)
        except OSError as exc:
            error_line(f"cannot read capture {path}: {exc.strerror or exc}")
            raise typer.Exit(1) from None


def _feed_recording(
    mon: BusMonitor, path: Path, show: Callable[[list[MonitorEvent]], None]
) -> None:
    """The bytes of an ``ohmni record --raw`` recording, written and read, in the order
    they happened, with their times (seconds from the first)."""
    if importlib.util.find_spec("mcap") is None:
        error_line("an MCAP capture needs the mcap reader: pip install 'ohmni_tb[foxglove]'")
        raise typer.Exit(1)
    from ohmni_tb.foxglove.replay import raw_bus_bytes  # noqa: PLC0415  # the extra

    try:
        for t_s, _sent, data in raw_bus_bytes(path):
            show(mon.feed(data, t_s))
    except OhmniError as exc:
        error_line(str(exc))
        raise typer.Exit(1) from None


def _check_packet(packet: Packet) -> None:
    """Refuse what the bus would refuse, or never see answered, before opening the port.

    Raises:
        typer.BadParameter: Names DATA or CMD and says why.
    """
    if HEADER_SIZE + len(packet.data) > MAX_PACKET_SIZE:
        high = MAX_PACKET_SIZE - HEADER_SIZE
        raise typer.BadParameter(
            f"DATA is {len(packet.data)} bytes: allowed 0..{high} in one packet"
        )
    if packet.sid == BROADCAST_ID and packet.cmd == Command.STAT:
        raise typer.BadParameter(
            f"CMD STAT to SID {BROADCAST_ID} (broadcast): every device would answer at once"
        )
    if packet.cmd in (Command.RAM_READ, Command.EEP_READ) and len(packet.data) >= 2:
        length = packet.data[1]
        smallest, _ = reply_size_range(packet)
        if smallest > MAX_PACKET_SIZE:
            high = MAX_PACKET_SIZE - (smallest - length)
            raise typer.BadParameter(
                f"DATA asks for a read of {length} bytes: allowed 0..{high}, or its reply "
                f"would not fit a packet"
            )


def _event_json(ev: MonitorEvent) -> dict[str, object]:
    return {
        "t_s": ev.t_s,
        "sid": ev.packet.sid,
        "device": ev.device,
        "cmd": ev.packet.cmd,
        "data": ev.packet.data.hex(" "),
        "text": ev.text,
        "latency_ms": None if ev.latency_s is None else ev.latency_s * 1e3,
    }


_SUMMARY_HEADERS = ("sid", "device", "req", "rep", "unanswered", "err", "Hz", "p50 ms", "max ms")


def _summary(mon: BusMonitor, as_json: bool) -> None:
    mon.finish()
    rows = []
    for t in sorted(mon.devices.values(), key=lambda d: d.sid):
        lat = sorted(t.latencies_s)
        rate = t.rate_hz()
        rows.append(
            {
                "sid": t.sid,
                "device": device_name(t.sid),
                "requests": t.requests,
                "replies": t.replies,
                "unanswered": t.unanswered,
                "error_replies": t.error_replies,
                "rate_hz": None if rate is None else round(rate, 2),
                "latency_p50_ms": round(lat[len(lat) // 2] * 1e3, 3) if lat else None,
                "latency_max_ms": round(lat[-1] * 1e3, 3) if lat else None,
            }
        )
    dec = mon.decoder_stats
    decoder = {
        "packets": dec.packets,
        "bytes_in": dec.bytes_in,
        "bytes_discarded": dec.bytes_discarded,
        "checksum_errors": dec.checksum_errors,
        "bad_headers": dec.bad_headers + dec.bad_sizes + dec.unknown_commands,
        "bytes_pending": dec.bytes_pending,
    }
    if as_json:
        sys.stdout.write(json.dumps({"devices": rows, "decoder": decoder}) + "\n")
        return
    table = Table(title="bus summary")
    for header in _SUMMARY_HEADERS:
        table.add_column(header, justify="right")
    for row in rows:
        table.add_row(*("-" if v is None else str(v) for v in row.values()))
    console.print(table)
    console.print("decoder: " + ", ".join(f"{k} {v}" for k, v in decoder.items()), highlight=False)
