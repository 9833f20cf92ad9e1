"""``ohmni servo``: HerkuleX servos (the neck, the external servos)."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Annotated, Any, NoReturn, TypeVar

import typer
from rich.markup import escape
from rich.table import Table

from ohmni_tb.bus import Bus
from ohmni_tb.cli import new_app
from ohmni_tb.cli.common import (
    DirectOption,
    JsonOption,
    PortOption,
    TimeoutOption,
    console,
    daemon_for,
    emit_json,
    error_line,
    open_bus,
    open_robot,
    parse_int,
    resolve_port,
    run,
)
from ohmni_tb.errors import (
    BusTimeoutError,
    DeviceStatusError,
    InvalidArgumentError,
    OutOfRangeError,
    StateError,
)
from ohmni_tb.herkulex import EEP, RAM, TorqueControl, parse_reply, stat
from ohmni_tb.herkulex.registers import Register, RegisterMap
from ohmni_tb.herkulex.servo import Servo, ServoStatus
from ohmni_tb.herkulex.units import (
    MAX_PLAYTIME_S,
    POSITION_MAX_RAW,
    angle_deg_from_raw,
    playtime_s_from_ticks,
    playtime_ticks_from_s,
)
from ohmni_tb.protocol import Memory, flag_names
from ohmni_tb.protocol.devices import NECK_RAW_RANGE, DeviceId, device_name
from ohmni_tb.robot.api import HerkulexHandle

__all__ = ["app"]

T = TypeVar("T")

app = new_app(
    help="HerkuleX servos: the neck (sid 3) and the external servos."
    "\n\nExample: ohmni servo scan --port sim://"
)

SidOption = Annotated[
    str,
    typer.Option(
        "--sid", "-s", help="Servo id 0..253 (the neck is 3; 0x.. accepted).", metavar="SID"
    ),
]
_NECK = str(int(DeviceId.HERKULEX_NECK))
_SCAN_TIMEOUT_S = 0.01
#: The largest servo id (0xFE is broadcast).
_MAX_SID = 0xFD


def _sid(text: str) -> int:
    """The servo id of ``--sid``.

    Raises:
        typer.BadParameter: Not an integer in 0..253.
    """
    return parse_int(text, "--sid", 0, _MAX_SID)


def _with_servo(
    port: str | None,
    sid: int,
    timeout_s: float,
    action: Callable[[Servo], Awaitable[T]],
    *,
    min_raw: int | None = None,
    max_raw: int | None = None,
    direct: bool = False,
) -> T:
    """Run ``action`` on the servo; the neck (sid 3) defaults to its safe range 280..650.

    Raises:
        StateError: ``ohmni serve`` holds the port (and neither ``--port`` nor ``direct``).
    """
    if not direct and daemon_for(port, False) is not None:
        error_line(
            "ohmni serve holds the port: for this command stop it, or name the port with --port"
        )
        raise typer.Exit(1)
    if sid == DeviceId.HERKULEX_NECK:
        min_raw = NECK_RAW_RANGE[0] if min_raw is None else min_raw
        max_raw = NECK_RAW_RANGE[1] if max_raw is None else max_raw

    async def main() -> T:
        async with await open_bus(port, timeout_s) as bus:
            return await action(Servo(bus, sid, min_raw=min_raw, max_raw=max_raw))

    return run(main)


def _via_daemon(
    via: str,
    sid: int,
    action: Callable[[HerkulexHandle], Awaitable[T]],
    *,
    control: bool = False,
) -> T:
    """Run ``action`` on servo ``sid`` of the daemon's robot at ``via``; ``control``: it
    commands the servo, refused at once while another client holds the control lease."""

    async def main() -> T:
        async with open_robot(resolve_port(None), via=via, control=control) as robot:
            return await action(robot.servo(sid))

    return run(main)


def _refuse_while_served() -> NoReturn:
    """Exit 1: this command opens the port, which ``ohmni serve`` holds."""
    error_line(
        "ohmni serve holds the port: ohmni servo scan probes every id on the bus, which "
        "it does not do through the daemon (ohmni info lists the robot's servos); for a "
        "scan stop it, or name the port with --port"
    )
    raise typer.Exit(1)


def _position_range(sid: int, min_text: str | None, max_text: str | None) -> tuple[int, int]:
    """The positions a move may ask for: ``--min-raw``/``--max-raw``, else the defaults.

    The neck (sid 3) defaults to its safe range 280..650, the others to the factory
    21..1002.

    Raises:
        typer.BadParameter: A bound is not an integer in 0..1023, or min > max.
    """
    if sid == DeviceId.HERKULEX_NECK:
        low, high = NECK_RAW_RANGE
    else:
        low, high = _factory("min_position"), _factory("max_position")
    if min_text is not None:
        low = parse_int(min_text, "--min-raw", 0, POSITION_MAX_RAW)
    if max_text is not None:
        high = parse_int(max_text, "--max-raw", 0, POSITION_MAX_RAW)
    if low > high:
        raise typer.BadParameter(f"--min-raw={low} is above --max-raw={high}")
    return low, high


def _factory(name: str) -> int:
    default = RAM[name].default
    assert default is not None, name  # the register table gives both position limits
    return default


def _playtime_ticks(playtime: float) -> int:
    """``--playtime`` in 11.2 ms ticks, the unit the servo is sent: the one range and
    rounding of every playtime (:func:`~ohmni_tb.herkulex.units.playtime_ticks_from_s`).

    Raises:
        typer.BadParameter: Outside 0..2.8448 s, NaN or infinite.
    """
    try:
        return playtime_ticks_from_s(playtime)
    except InvalidArgumentError:
        raise typer.BadParameter(
            f"--playtime={playtime!r} is out of range: allowed 0..{MAX_PLAYTIME_S:g} s "
            f"(sent in whole 11.2 ms ticks)"
        ) from None


def _register(name: str, table: RegisterMap) -> Register:
    """The register ``name`` of ``table`` (RAM or EEP): a name, or the address of its
    first byte (decimal or 0x..).

    Raises:
        typer.BadParameter: No such register, or no register at that address; the
            message lists the known ones or says why (reserved, inside a 2-byte
            register, out of the memory).
    """
    if name[:1].isdigit():
        address = parse_int(name, "REGISTER")
        try:
            return table.by_addr(address)
        except InvalidArgumentError as exc:
            raise typer.BadParameter(f"REGISTER: {exc}") from None
    if name not in table:
        known = ", ".join(reg.name for reg in table)
        raise typer.BadParameter(
            f"REGISTER: no {table.memory.name} register {name!r}; known: {known}"
        )
    return table[name]


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
    port: PortOption = None,
    first: Annotated[
        str, typer.Option(help="First id to try, 0..253 (0x.. accepted).", metavar="SID")
    ] = "0",
    last: Annotated[
        str, typer.Option(help="Last id to try, 0..253 (0x.. accepted).", metavar="SID")
    ] = "0xFD",
    as_json: JsonOption = False,
) -> None:
    """Find every HerkuleX servo on the bus (STAT to each id; boards are skipped).

    Example: ohmni servo scan --first 3 --last 12 --port sim://
    """
    low = parse_int(first, "--first", 0, _MAX_SID)
    high = parse_int(last, "--last", 0, _MAX_SID)
    if low > high:
        raise typer.BadParameter(f"--first={low} is after --last={high}")
    if daemon_for(port, False) is not None:
        _refuse_while_served()
    boards = {int(DeviceId.LEFT_DRIVE), int(DeviceId.RIGHT_DRIVE), int(DeviceId.CORE)}
    boards.add(int(DeviceId.WORM_NECK))

    async def main() -> list[dict[str, Any]]:
        found = []
        async with await open_bus(port, _SCAN_TIMEOUT_S) as bus:
            for sid in range(low, high + 1):
                if sid in boards:
                    continue
                servo = Servo(bus, sid)
                try:
                    status = await _quick(bus, servo)
                except BusTimeoutError:
                    continue
                model = await servo.model()
                pos = await servo.position_raw()
                # The torque mode as ohmni status names it (free, brake, on): the
                # register, not the status bit, which cannot tell free from brake.
                mode = await servo.read("torque_control")
                found.append(
                    {
                        "sid": sid,
                        "name": device_name(sid),
                        "model": model.name,
                        "position_raw": pos,
                        "angle_deg": round(angle_deg_from_raw(pos), 2),
                        "torque": _torque_name(mode),
                        **_status_dict(status),
                    }
                )
        return found

    found = run(main)
    if as_json:
        emit_json(found)
        return
    table = Table(title=f"HerkuleX servos on {escape(port or resolve_port(None))}")
    for column in ("sid", "name", "model", "position", "angle °", "torque", "errors"):
        table.add_column(column)
    for row in found:
        table.add_row(
            str(row["sid"]),
            row["name"],
            row["model"],
            str(row["position_raw"]),
            f"{row['angle_deg']:+.1f}",
            row["torque"],
            row["error_flags"] if row["error"] else "-",
        )
    console.print(table)
    if not found:
        console.print("no servo answered")


def _torque_name(value: int) -> str:
    """RAM 52 as ``ohmni status`` shows it: ``free``, ``brake``, ``on`` (else the value)."""
    try:
        return TorqueControl(value).name.lower()
    except ValueError:
        return f"0x{value:02X}"


async def _quick(bus: Bus, servo: Servo) -> ServoStatus:
    """A STAT with no retries, so a scan of 250 ids stays quick."""
    reply = await bus.request(stat(servo.sid), expect_reply=True, retries=0)
    assert reply is not None
    parsed = parse_reply(reply)
    return ServoStatus(parsed.status_error, parsed.status_detail)


@app.command()
def info(
    port: PortOption = None,
    sid: SidOption = _NECK,
    timeout: TimeoutOption = 0.05,
    as_json: JsonOption = False,
    direct: DirectOption = False,
) -> None:
    """Every EEP and RAM register of a servo (through ohmni serve when it runs).

    Example: ohmni servo info --sid 3 --port sim://
    """
    sid_value = _sid(sid)
    via = daemon_for(port, direct)
    if via is not None:
        values = _via_daemon(via, sid_value, lambda s: s.info())
    else:
        values = _with_servo(port, sid_value, timeout, lambda s: s.info(), direct=True)
    if as_json:
        emit_json(values)
        return
    for memory, regs in values.items():
        _print_kv(f"servo {sid_value} {memory.upper()}", regs)


@app.command()
def read(
    register: Annotated[
        str, typer.Argument(help="Register name (e.g. temperature) or address (0x.. accepted).")
    ],
    port: PortOption = None,
    sid: SidOption = _NECK,
    eep: Annotated[bool, typer.Option("--eep", help="Read the EEP copy.")] = False,
    timeout: TimeoutOption = 0.05,
    as_json: JsonOption = False,
    direct: DirectOption = False,
) -> None:
    """Read one register by name or address (of RAM, or EEP with --eep); through ohmni
    serve when it runs.

    Example: ohmni servo read temperature --sid 3 --port sim:// ; ohmni servo read 30 --eep
    """
    memory = Memory.EEP if eep else Memory.RAM
    reg = _register(register, EEP if eep else RAM)
    sid_value = _sid(sid)
    via = daemon_for(port, direct)
    if via is not None:
        value = _via_daemon(via, sid_value, lambda s: s.info())[memory.value][reg.name]
    else:
        value = _with_servo(port, sid_value, timeout, lambda s: s.read(reg, memory), direct=True)
    if as_json:
        emit_json({"register": reg.name, "memory": memory.name, "value": value})
    else:
        console.print(f"{memory.name} {reg.name} = {value}", highlight=False)


@app.command()
def write(
    register: Annotated[
        str,
        typer.Argument(
            help="Register name (e.g. led_control) or address (0x.. accepted), of RAM, or "
            "of EEP with --eep."
        ),
    ],
    value: Annotated[str, typer.Argument(help="Value (decimal or 0x..).")],
    port: PortOption = None,
    sid: SidOption = _NECK,
    persist: Annotated[
        bool, typer.Option("--persist", help="Also write the EEP copy (survives reboot).")
    ] = False,
    eep: Annotated[
        bool,
        typer.Option(
            "--eep",
            help="Write the EEP register alone (acts after a reboot; tb_control's "
            "servo_write_eep): REGISTER names or addresses an EEP register.",
        ),
    ] = False,
    timeout: TimeoutOption = 0.05,
    direct: DirectOption = False,
) -> None:
    """Write one RAM register (and its EEP copy with --persist), or with --eep one EEP
    register. Checked against the register map first: the register (or the address of
    its first byte) exists in that memory and is writable, the value is in its range;
    else exit 2 and nothing is sent. Through ohmni serve when it runs (it needs the
    control lease there).

    Examples: ohmni servo write led_control 1 --sid 3 --port sim:// ;
    ohmni servo write 30 200 --eep --sid 3 --port sim://  (EEP 30 = position_kp)
    """
    if eep and persist:
        raise typer.BadParameter(
            "--persist writes the EEP copy of a RAM register; --eep writes EEP alone: "
            "give one of them"
        )
    table = EEP if eep else RAM
    reg = _register(register, table)
    if reg.read_only:
        raise typer.BadParameter(
            f"REGISTER: {table.memory.name} {reg.addr} ({reg.name}) is read-only"
        )
    number = parse_int(value, "VALUE")
    regs = [reg]
    if persist:
        if reg.name not in EEP:
            raise typer.BadParameter(f"--persist: {reg.name} has no EEP copy")
        regs.append(EEP[reg.name])
    for checked in regs:
        parse_int(value, "VALUE", checked.low, checked.high, of=f" for {checked.name}")
        try:
            checked.check(number)
        except InvalidArgumentError as exc:  # OutOfRangeError too: names the register
            raise typer.BadParameter(f"VALUE={number}: {exc}") from None
    sid_value = _sid(sid)
    memory = table.memory
    via = daemon_for(port, direct)
    if via is not None:

        async def remote(handle: HerkulexHandle) -> int:
            await handle.write(reg.name, number, persist=persist, memory=memory)
            return (await handle.info())[memory.value][reg.name]

        read_back = _via_daemon(via, sid_value, remote)
    else:

        async def action(servo: Servo) -> int:
            await servo.write(reg, number, persist=persist, memory=memory)
            return await servo.read(reg, memory)

        read_back = _with_servo(port, sid_value, timeout, action, direct=True)
    where = f"EEP {reg.addr}" if eep else f"RAM {reg.addr}"
    also = " (and its EEP copy)" if persist else " (acts after a reboot)" if eep else ""
    console.print(f"{where} {reg.name} ← {number}{also}; reads back {read_back}", highlight=False)


@app.command()
def move(
    position: Annotated[
        str, typer.Argument(help="Goal position, raw counts 0..1023 (0x.. accepted).")
    ],
    port: PortOption = None,
    sid: SidOption = _NECK,
    playtime: Annotated[
        float,
        typer.Option(
            "--playtime",
            help=f"Seconds to get there, 0..{MAX_PLAYTIME_S:g}, sent in whole 11.2 ms ticks "
            "(the nearest).",
        ),
    ] = 1.0,
    min_raw: Annotated[
        str | None,
        typer.Option(help="Lowest position allowed [default: 280 for the neck, else 21]."),
    ] = None,
    max_raw: Annotated[
        str | None,
        typer.Option(help="Highest position allowed [default: 650 for the neck, else 1002]."),
    ] = None,
    torque_on: Annotated[
        bool, typer.Option("--torque-on", help="Turn the torque on first if it is off.")
    ] = False,
    timeout: TimeoutOption = 0.05,
    direct: DirectOption = False,
) -> None:
    """Move a servo to a position over a playtime (the neck's safe range is 280..650).

    Every argument is checked before the first byte goes out, --torque-on included.
    Through ohmni serve when it runs (it needs the control lease there; the daemon's
    robot holds the servo inside its own range too).

    Example: ohmni servo move 600 --sid 3 --playtime 0.5 --torque-on --port sim://
    """
    sid_value = _sid(sid)
    low, high = _position_range(sid_value, min_raw, max_raw)
    goal = parse_int(
        position, "POSITION", low, high, of=f" for servo {sid_value} (--min-raw/--max-raw)"
    )
    ticks = _playtime_ticks(playtime)

    async def action(servo: Servo) -> int:
        if torque_on:
            await servo.torque(TorqueControl.ON)
        await servo.move_to(goal, playtime_ticks=ticks)
        return await servo.position_raw()

    via = daemon_for(port, direct)
    if via is not None:
        start = _via_daemon(
            via,
            sid_value,
            lambda handle: _move_via_daemon(handle, goal, ticks, torque_on=torque_on),
            control=True,
        )
    else:
        start = _with_servo(
            port, sid_value, timeout, action, min_raw=low, max_raw=high, direct=True
        )
    # The playtime the servo got: whole ticks, not the seconds typed.
    seconds = round(playtime_s_from_ticks(ticks), 4)
    console.print(
        f"servo {sid_value}: moving {start} → {goal} over {seconds:g} s ({ticks} ticks)",
        highlight=False,
    )


async def _move_via_daemon(
    handle: HerkulexHandle, goal: int, ticks: int, *, torque_on: bool
) -> int:
    """``ohmni servo move`` through the daemon, as it is done directly: the goal checked
    against the daemon's range too and a servo with its torque off refused (without
    ``--torque-on``) before anything is sent; the position it starts from."""
    if not handle.min_raw <= goal <= handle.max_raw:
        # As the daemon's robot would refuse it, but before --torque-on sends anything.
        raise OutOfRangeError(
            f"servo {handle.sid} position", goal, handle.min_raw, handle.max_raw, "count"
        )
    status = await handle.status()
    if not torque_on and not status.torque_on:
        # The handle's move would turn it on; without --torque-on the command refuses.
        raise DeviceStatusError(
            f"servo {handle.sid} has torque off; call torque(TorqueControl.ON) first",
            sid=handle.sid,
            status_error=int(status.error),
            status_detail=int(status.detail),
        )
    start = (await handle.info())["ram"]["calibrated_position"] & POSITION_MAX_RAW
    if torque_on:
        await handle.torque(TorqueControl.ON)
    await handle.move(goal, playtime_s=playtime_s_from_ticks(ticks))
    return start


@app.command()
def torque(
    mode: Annotated[str, typer.Argument(help="free | brake | on")],
    port: PortOption = None,
    sid: SidOption = _NECK,
    timeout: TimeoutOption = 0.05,
    direct: DirectOption = False,
) -> None:
    """Set the torque: free (limp), brake (holds, ignores moves) or on; through ohmni
    serve when it runs (with the control lease).

    Example: ohmni servo torque free --sid 3 --port sim://
    """
    try:
        value = TorqueControl[mode.upper()]
    except KeyError:
        raise typer.BadParameter(f"MODE must be free, brake or on, not {mode!r}") from None
    sid_value = _sid(sid)
    via = daemon_for(port, direct)
    if via is not None:
        _via_daemon(via, sid_value, lambda s: s.torque(value), control=True)
    else:
        _with_servo(port, sid_value, timeout, lambda s: s.torque(value), direct=True)
    console.print(f"servo {sid_value}: torque {value.name.lower()}")


@app.command("stat")
def stat_cmd(
    port: PortOption = None,
    sid: SidOption = _NECK,
    timeout: TimeoutOption = 0.05,
    as_json: JsonOption = False,
    direct: DirectOption = False,
) -> None:
    """The servo's status bytes, decoded; through ohmni serve when it runs.

    Example: ohmni servo stat --sid 3 --port sim:// --json
    """
    sid_value = _sid(sid)
    via = daemon_for(port, direct)
    if via is not None:
        status = _via_daemon(via, sid_value, lambda s: s.status())
    else:
        status = _with_servo(port, sid_value, timeout, lambda s: s.status(), direct=True)
    if as_json:
        emit_json(_status_dict(status))
    else:
        _print_kv(f"servo {sid_value} status", _status_dict(status))


@app.command()
def clear(
    port: PortOption = None,
    sid: SidOption = _NECK,
    torque_on: Annotated[
        bool, typer.Option("--torque-on", help="Turn the torque on again after clearing.")
    ] = False,
    timeout: TimeoutOption = 0.05,
    as_json: JsonOption = False,
    direct: DirectOption = False,
) -> None:
    """Clear latched errors (RAM 48/49) and show the status after.

    A fault that released the torque leaves it off; --torque-on turns it on again.
    Through ohmni serve when it runs (with the control lease).

    Example: ohmni servo clear --sid 3 --torque-on --port sim://
    """
    sid_value = _sid(sid)

    async def action(servo: Servo) -> ServoStatus:
        status = await servo.clear_errors()
        if torque_on:
            await servo.torque(TorqueControl.ON)
            status = await servo.status()
        return status

    async def remote(handle: HerkulexHandle) -> ServoStatus:
        status = await handle.clear_errors()
        if torque_on:
            await handle.torque(TorqueControl.ON)
            status = await handle.status()
        return status

    via = daemon_for(port, direct)
    if via is not None:
        status = _via_daemon(via, sid_value, remote, control=True)
    else:
        status = _with_servo(port, sid_value, timeout, action, direct=True)
    if as_json:
        emit_json(_status_dict(status))
    else:
        _print_kv(f"servo {sid_value} status after clearing", _status_dict(status))


@app.command("set-id")
def set_id(
    new_id: Annotated[str, typer.Argument(help="The new id, 0..253 (0x.. accepted).")],
    port: PortOption = None,
    sid: SidOption = _NECK,
    timeout: TimeoutOption = 0.05,
    direct: DirectOption = False,
) -> None:
    """Give a servo a new id, in EEP and RAM (tb_control's reset_servo_id).

    Through ohmni serve (when it runs) the robot follows: its stream and
    robot.servo(NEW_ID) carry on from the new id. An id another device answers to is
    refused before anything is sent.

    Example: ohmni servo set-id 13 --sid 11 --port sim://
    """
    old = _sid(sid)
    new = parse_int(new_id, "NEW_ID", 0, _MAX_SID)
    via = daemon_for(port, direct)
    if via is not None:
        _via_daemon(via, old, lambda s: s.set_id(new))
    else:
        _with_servo(port, old, timeout, lambda s: _set_id_direct(s, new), direct=True)
    console.print(f"servo {old} is now servo {new}", highlight=False)


async def _set_id_direct(servo: Servo, new: int) -> None:
    """A new id on a bus this command opened: refused when a board's id or when a device
    answers to it already."""
    if new == servo.sid:
        return
    # The neck's id is a servo's: a new neck servo (factory id 253) may be given it.
    if new in {int(d) for d in DeviceId} - {int(DeviceId.HERKULEX_NECK)}:
        raise StateError(
            f"servo {servo.sid} cannot take id {new}: {device_name(new)} has it; nothing was sent"
        )
    probe = Servo(servo._requester, new)  # the same bus, another id
    try:
        await probe.status()
    except BusTimeoutError:
        await servo.set_id(new)
        return
    raise StateError(f"servo {servo.sid} cannot take id {new}: a device answers to it already")


@app.command("zero-offset")
def zero_offset(
    raw: Annotated[
        str,
        typer.Argument(
            help="Raw counts added to 512 for 0 rad, -512..511 (a negative one after --)."
        ),
    ],
    sid: SidOption = _NECK,
) -> None:
    """Set the zero of a servo's angles on the running robot (tb_control's
    set_servo_zero_offset); needs ohmni serve (it is the robot's setting, not the
    servo's: for every run, set neck_zero_offset_raw in the config file).

    Example: ohmni servo zero-offset --sid 3 -- -20
    """
    value = parse_int(raw, "RAW", -512, 511)
    sid_value = _sid(sid)
    via = daemon_for(None, False)
    if via is None:
        error_line(
            "the zero offset is a setting of the running robot and no ohmni serve runs: "
            "set neck_zero_offset_raw in the config file (or start ohmni serve)"
        )
        raise typer.Exit(1)
    _via_daemon(via, sid_value, lambda s: s.set_zero_offset(value))
    console.print(f"servo {sid_value}: zero offset {value}", highlight=False)


@app.command("board-id")
def board_id(
    board: Annotated[str, typer.Argument(help="The drive board's id now: 0 (left), 1 (right).")],
    new_id: Annotated[str, typer.Argument(help="Its new id, 0..253.")],
    confirm: Annotated[
        bool,
        typer.Option(
            "--confirm",
            help="Do it: a board at another id than 0 or 1 takes no wheel command.",
        ),
    ] = False,
    port: PortOption = None,
    direct: DirectOption = False,
) -> None:
    """Give a drive board a new id (tb_control's reset_servo_id on a motor board; the
    bytes are an assumption of the profile). The wheels are stopped first; refused
    without --confirm.

    Example: ohmni servo board-id 1 7 --confirm --port sim://
    """
    sid_value = parse_int(board, "BOARD", 0, _MAX_SID)
    new = parse_int(new_id, "NEW_ID", 0, _MAX_SID)
    via = daemon_for(port, direct)

    async def main() -> None:
        async with open_robot(resolve_port(port), via=via, control=True) as robot:
            await robot.reset_board_id(sid_value, new, confirm=confirm)

    run(main)
    console.print(f"drive board {sid_value} now answers to id {new}", highlight=False)
