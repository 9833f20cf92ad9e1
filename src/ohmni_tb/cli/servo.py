"""``ohmni servo``: HerkuleX servos (the neck, the external servos)."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated, Any, TypeVar

import typer
from rich.table import Table

from ohmni_tb.bus import Bus
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
from ohmni_tb.errors import BusTimeoutError
from ohmni_tb.herkulex import EEP, RAM, TorqueControl, parse_reply, stat
from ohmni_tb.herkulex.servo import Servo, ServoStatus
from ohmni_tb.herkulex.units import angle_deg_from_raw
from ohmni_tb.protocol import Memory, flag_names
from ohmni_tb.protocol.devices import NECK_RAW_RANGE, DeviceId, device_name

__all__ = ["app"]

T = TypeVar("T")

app = typer.Typer(help="HerkuleX servos: the neck (sid 3) and the external servos.")

SidOption = Annotated[
    str, typer.Option("--sid", "-s", help="Servo id (the neck is 3; 0x.. accepted).")
]
_NECK = str(int(DeviceId.HERKULEX_NECK))
_SCAN_TIMEOUT_S = 0.01


def _with_servo(
    port: str,
    sid_text: str,
    timeout_s: float,
    action: Callable[[Servo], Awaitable[T]],
    *,
    min_raw: int | None = None,
    max_raw: int | None = None,
) -> T:
    """Run ``action`` on the servo; the neck (sid 3) defaults to its safe range 280..650."""
    sid = parse_int(sid_text, "--sid")
    if sid == DeviceId.HERKULEX_NECK:
        min_raw = NECK_RAW_RANGE[0] if min_raw is None else min_raw
        max_raw = NECK_RAW_RANGE[1] if max_raw is None else max_raw

    async def main() -> T:
        async with await open_bus(port, timeout_s) as bus:
            return await action(Servo(bus, sid, min_raw=min_raw, max_raw=max_raw))

    return run(main)


def _status_dict(status: ServoStatus) -> dict[str, Any]:
    return {
        "error": int(status.error),
        "error_flags": flag_names(status.error),
        "detail": int(status.detail),
        "detail_flags": flag_names(status.detail),
        "torque_on": status.torque_on,
        "moving": status.moving,
        "in_position": status.in_position,
    }


def _print_kv(title: str, values: dict[str, Any]) -> None:
    table = Table(title=title)
    table.add_column("name")
    table.add_column("value", justify="right")
    for key, value in values.items():
        table.add_row(key, str(value))
    console.print(table)


@app.command()
def scan(
    port: PortOption = DEFAULT_PORT,
    first: Annotated[int, typer.Option(help="First id to try.", min=0, max=0xFD)] = 0,
    last: Annotated[int, typer.Option(help="Last id to try.", min=0, max=0xFD)] = 0xFD,
    as_json: JsonOption = False,
) -> None:
    """Find every HerkuleX servo on the bus (STAT to each id; boards are skipped)."""
    boards = {int(DeviceId.LEFT_DRIVE), int(DeviceId.RIGHT_DRIVE), int(DeviceId.CORE)}
    boards.add(int(DeviceId.WORM_NECK))

    async def main() -> list[dict[str, Any]]:
        found = []
        async with await open_bus(port, _SCAN_TIMEOUT_S) as bus:
            for sid in range(first, last + 1):
                if sid in boards:
                    continue
                servo = Servo(bus, sid)
                try:
                    status = await _quick(bus, servo)
                except BusTimeoutError:
                    continue
                model = await servo.model()
                pos = await servo.position_raw()
                found.append(
                    {
                        "sid": sid,
                        "name": device_name(sid),
                        "model": model.name,
                        "position_raw": pos,
                        "angle_deg": round(angle_deg_from_raw(pos), 2),
                        **_status_dict(status),
                    }
                )
        return found

    found = run(main)
    if as_json:
        emit_json(found)
        return
    table = Table(title=f"HerkuleX servos on {port}")
    for column in ("sid", "name", "model", "position", "angle °", "torque", "errors"):
        table.add_column(column)
    for row in found:
        table.add_row(
            str(row["sid"]),
            row["name"],
            row["model"],
            str(row["position_raw"]),
            f"{row['angle_deg']:+.1f}",
            "on" if row["torque_on"] else "off",
            row["error_flags"] if row["error"] else "-",
        )
    console.print(table)
    if not found:
        console.print("no servo answered")


async def _quick(bus: Bus, servo: Servo) -> ServoStatus:
    """A STAT with no retries, so a scan of 250 ids stays quick."""
    reply = await bus.request(stat(servo.sid), expect_reply=True, retries=0)
    assert reply is not None
    parsed = parse_reply(reply)
    return ServoStatus(parsed.status_error, parsed.status_detail)


@app.command()
def info(
    port: PortOption = DEFAULT_PORT,
    sid: SidOption = _NECK,
    timeout: TimeoutOption = 0.05,
    as_json: JsonOption = False,
) -> None:
    """Every EEP and RAM register of a servo."""
    values = _with_servo(port, sid, timeout, lambda s: s.info())
    if as_json:
        emit_json(values)
        return
    for memory, regs in values.items():
        _print_kv(f"servo {sid} {memory.upper()}", regs)


@app.command()
def read(
    register: Annotated[str, typer.Argument(help="Register name, e.g. temperature.")],
    port: PortOption = DEFAULT_PORT,
    sid: SidOption = _NECK,
    eep: Annotated[bool, typer.Option("--eep", help="Read the EEP copy.")] = False,
    timeout: TimeoutOption = 0.05,
    as_json: JsonOption = False,
) -> None:
    """Read one register by name."""
    memory = Memory.EEP if eep else Memory.RAM
    table = EEP if eep else RAM
    if register not in table:
        known = ", ".join(reg.name for reg in table)
        raise typer.BadParameter(f"no {memory.name} register {register!r}; known: {known}")
    value = _with_servo(port, sid, timeout, lambda s: s.read(register, memory))
    if as_json:
        emit_json({"register": register, "memory": memory.name, "value": value})
    else:
        console.print(f"{memory.name} {register} = {value}")


@app.command()
def write(
    register: Annotated[str, typer.Argument(help="RAM register name, e.g. led_control.")],
    value: Annotated[str, typer.Argument(help="Value (decimal or 0x..).")],
    port: PortOption = DEFAULT_PORT,
    sid: SidOption = _NECK,
    persist: Annotated[
        bool, typer.Option("--persist", help="Also write the EEP copy (survives reboot).")
    ] = False,
    timeout: TimeoutOption = 0.05,
) -> None:
    """Write one RAM register (and its EEP copy with --persist). Range-checked first."""
    number = parse_int(value, "VALUE")
    _with_servo(port, sid, timeout, lambda s: s.write(register, number, persist=persist))
    console.print(f"{register} ← {number}" + (" (RAM and EEP)" if persist else ""))


@app.command()
def move(
    position: Annotated[int, typer.Argument(help="Goal position, raw counts 0..1023.")],
    port: PortOption = DEFAULT_PORT,
    sid: SidOption = _NECK,
    playtime: Annotated[
        float, typer.Option("--playtime", help="Seconds to get there (0..2.84).")
    ] = 1.0,
    min_raw: Annotated[
        int | None,
        typer.Option(help="Lowest position allowed [default: 280 for the neck, else 21]."),
    ] = None,
    max_raw: Annotated[
        int | None,
        typer.Option(help="Highest position allowed [default: 650 for the neck, else 1002]."),
    ] = None,
    torque_on: Annotated[
        bool, typer.Option("--torque-on", help="Turn the torque on first if it is off.")
    ] = False,
    timeout: TimeoutOption = 0.05,
) -> None:
    """Move a servo to a position over a playtime (the neck's safe range is 280..650)."""

    async def action(servo: Servo) -> int:
        servo.target(position)  # range check before anything is sent
        if torque_on:
            await servo.torque(TorqueControl.ON)
        await servo.move_to(position, playtime_s=playtime)
        return await servo.position_raw()

    start = _with_servo(port, sid, timeout, action, min_raw=min_raw, max_raw=max_raw)
    console.print(f"servo {sid}: moving {start} → {position} over {playtime:.2f} s")


@app.command()
def torque(
    mode: Annotated[str, typer.Argument(help="free | brake | on")],
    port: PortOption = DEFAULT_PORT,
    sid: SidOption = _NECK,
    timeout: TimeoutOption = 0.05,
) -> None:
    """Set the torque: free (limp), brake (holds, ignores moves) or on."""
    try:
        value = TorqueControl[mode.upper()]
    except KeyError:
        raise typer.BadParameter(f"mode must be free, brake or on, not {mode!r}") from None
    _with_servo(port, sid, timeout, lambda s: s.torque(value))
    console.print(f"servo {sid}: torque {value.name.lower()}")


@app.command("stat")
def stat_cmd(
    port: PortOption = DEFAULT_PORT,
    sid: SidOption = _NECK,
    timeout: TimeoutOption = 0.05,
    as_json: JsonOption = False,
) -> None:
    """The servo's status bytes, decoded."""
    status = _with_servo(port, sid, timeout, lambda s: s.status())
    if as_json:
        emit_json(_status_dict(status))
    else:
        _print_kv(f"servo {sid} status", _status_dict(status))


@app.command()
def clear(
    port: PortOption = DEFAULT_PORT,
    sid: SidOption = _NECK,
    torque_on: Annotated[
        bool, typer.Option("--torque-on", help="Turn the torque on again after clearing.")
    ] = False,
    timeout: TimeoutOption = 0.05,
    as_json: JsonOption = False,
) -> None:
    """Clear latched errors (RAM 48/49) and show the status after.

    A fault that released the torque leaves it off; --torque-on turns it on again.
    """

    async def action(servo: Servo) -> ServoStatus:
        status = await servo.clear_errors()
        if torque_on:
            await servo.torque(TorqueControl.ON)
            status = await servo.status()
        return status

    status = _with_servo(port, sid, timeout, action)
    if as_json:
        emit_json(_status_dict(status))
    else:
        _print_kv(f"servo {sid} status after clearing", _status_dict(status))
