"""``ohmni bus``: raw requests on the bus."""

from __future__ import annotations

from typing import Annotated

import typer

from ohmni_tb.cli.common import (
    DEFAULT_PORT,
    JsonOption,
    PortOption,
    TimeoutOption,
    console,
    emit_json,
    open_bus,
    parse_int,
    run,
)
from ohmni_tb.errors import MalformedReplyError
from ohmni_tb.protocol import Command, Packet, ReadReply, StatusReply

app = typer.Typer(help="Raw packets on the bus: send one request, see the decoded reply.")


def _parse_command(text: str) -> int:
    try:
        return int(Command[text.upper()])
    except KeyError:
        pass
    code = parse_int(text, "CMD")
    if not 0 <= code <= 0xFF:
        raise typer.BadParameter(f"CMD={code} is out of range: allowed 0..255")
    return code


@app.command()
def send(
    sid: Annotated[str, typer.Argument(help="Device id, e.g. 0, 20, 0x14.")],
    cmd: Annotated[str, typer.Argument(help="Command name (RAM_READ, STAT...) or code.")],
    data: Annotated[list[str] | None, typer.Argument(help="Data bytes in hex, e.g. 3B 04.")] = None,
    port: PortOption = DEFAULT_PORT,
    timeout: TimeoutOption = 0.05,
    no_reply: Annotated[bool, typer.Option("--no-reply", help="Do not wait for a reply.")] = False,
    as_json: JsonOption = False,
) -> None:
    """Send one raw request and print the decoded reply.

    Example: ``ohmni bus send 0 RAM_READ 3B 04`` reads the left wheel count.
    """
    sid_value = parse_int(sid, "SID")
    code = _parse_command(cmd)
    try:
        payload = bytes.fromhex("".join(data or []))
    except ValueError:
        text = " ".join(data or [])
        raise typer.BadParameter(f"DATA must be hex bytes, not {text!r}") from None
    packet = Packet(sid_value, code, payload)

    async def main() -> Packet | None:
        async with await open_bus(port, timeout) as bus:
            return await bus.request(packet, expect_reply=False if no_reply else None)

    reply = run(main)
    if reply is None:
        if as_json:
            emit_json({"request": repr(packet), "reply": None})
        else:
            console.print(f"sent {packet!r}; no reply expected")
        return
    decoded: dict[str, object] = {"sid": reply.sid, "cmd": reply.cmd, "data": reply.data.hex(" ")}
    try:
        if reply.cmd in (Command.RAM_READ | 0x40, Command.EEP_READ | 0x40):
            rr = ReadReply.parse(reply)
            decoded.update(
                addr=rr.addr,
                value_hex=rr.data.hex(" "),
                status_error=str(rr.status_error),
                status_detail=str(rr.status_detail),
            )
        elif len(reply.data) == 2:
            sr = StatusReply.parse(reply)
            decoded.update(status_error=str(sr.status_error), status_detail=str(sr.status_detail))
    except MalformedReplyError as exc:
        decoded["malformed"] = str(exc)
    if as_json:
        emit_json({"request": repr(packet), "reply": decoded})
    else:
        console.print(f"request  {packet!r}")
        console.print(f"reply    {reply!r}")
        for key, value in decoded.items():
            if key not in ("sid", "cmd", "data"):
                console.print(f"  {key:14} {value}")
