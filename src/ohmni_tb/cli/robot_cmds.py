"""``ohmni info``, ``ohmni ports``, ``ohmni light`` and ``ohmni pid``: small robot commands.

``info``, ``light`` and ``pid`` open the :class:`~ohmni_tb.robot.Robot` (the daemon's
when ``ohmni serve`` runs); ``ports`` opens no port at all. ``pid get/set`` act on the
running robot's wheel PIDs (``robot.get_pid``, ``robot.set_pid``, per wheel with
``--wheel``), ``pid enable/disable`` turn them on and off; with ``--config`` (or
``--file``) ``pid get/set`` read or write the gains in the config file instead, which every
Robot opened later starts with.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Final, NoReturn

import typer
from rich.markup import escape

from ohmni_tb.cli import new_app
from ohmni_tb.cli.common import (
    DirectOption,
    JsonOption,
    PortOption,
    console,
    daemon_for,
    emit_json,
    error_line,
    open_robot,
    parse_int,
    resolve_port,
    run,
)

if TYPE_CHECKING:
    from ohmni_tb.control.pid import PidGains
    from ohmni_tb.robot import Robot
    from ohmni_tb.robot.checks import Wheel

__all__ = [
    "PID_FIELDS",
    "device_info",
    "info",
    "light",
    "pid_app",
    "ports",
]

#: Read-only commands leave the neck as they found it (the default frees it on exit).
READ_ONLY: Final[dict[str, Any]] = {"on_exit_neck": "keep"}
#: The light ring's components: bytes, as :func:`ohmni_tb.protocol.core.set_light_ring`
#: (and so ``Robot.light_ring``) checks them.
LIGHT_MIN, LIGHT_MAX = 0, 0xFF
#: ``ohmni pid set`` option → the RobotConfig field it writes.
PID_FIELDS: Final[dict[str, str]] = {
    "--kp": "pid_kp",
    "--ki": "pid_ki",
    "--kd": "pid_kd",
    "--kff": "pid_kff",
    "--ff-offset": "pid_ff_offset",
}
#: The firmware tag of a board: EEP 0xF1, length 0 (as ``Robot.info`` reads it).
_TAG_ADDR = 0xF1


# -- info -------------------------------------------------------------------------------


async def device_info(robot: Robot) -> dict[str, Any]:
    """``robot.info()`` for JSON: firmware tags (the worm neck's too), servos by role.

    Returns:
        ``firmware`` (``left_drive``, ``right_drive``, ``core``, ``worm_neck``: the tag or
        ``None``), ``neck_kind``, ``servos`` (``sid``, ``role``, ``model``), ``present``,
        ``absent``, ``neck_settings`` (what the last load of the HerkuleX neck's own
        settings read back, or ``None``), ``profile`` (the bus profile's settings).
    """
    from ohmni_tb.errors import OhmniError, StateError  # noqa: PLC0415
    from ohmni_tb.protocol import Memory  # noqa: PLC0415
    from ohmni_tb.protocol.devices import DeviceId  # noqa: PLC0415
    from ohmni_tb.robot import Link, LocalRobot  # noqa: PLC0415

    try:
        found = await robot.info()
    except StateError:
        if robot.state.link is not Link.RELEASED:
            raise
        # The port is handed to another program (ohmni serve --handoff): no device can be
        # asked; what the Robot found when it had the port is in its state.
        found = _info_from_state(robot)
    firmware: dict[str, str | None] = {**found["firmware"], "worm_neck": None}
    if robot.neck_kind == "worm" and isinstance(robot, LocalRobot):  # the daemon's: no bus
        # Robot.info() tags the drive and core boards; the worm neck's board has one too.
        try:
            reply = await robot.bus.read(DeviceId.WORM_NECK, _TAG_ADDR, 0, Memory.EEP)
            firmware["worm_neck"] = reply.data.decode("ascii", errors="replace")
        except OhmniError:
            pass
    roles = servo_roles(robot)
    models: dict[int, str | None] = found["servos"]
    return {
        "firmware": firmware,
        "neck_kind": found["neck"],
        "servos": [
            {"sid": sid, "role": roles.get(sid, f"sid{sid}"), "model": models[sid]}
            for sid in sorted(models)
        ],
        "present": list(found["present"]),
        "absent": list(found["absent"]),
        "neck_settings": found.get("neck_settings"),
        "profile": found.get("profile"),
    }


def _info_from_state(robot: Robot) -> dict[str, Any]:
    """``Robot.info()``'s shape from the Robot's state, without asking the devices: the
    firmware tags and servo models unknown (``None``)."""
    state = robot.state
    servos = [sid for sid in robot.config.ext_servo_ids if sid in state.present]
    if state.neck == "herkulex":
        servos.insert(0, robot.config.neck_id)
    return {
        "firmware": {"left_drive": None, "right_drive": None, "core": None},
        "servos": dict.fromkeys(servos),
        "neck": state.neck,
        "present": list(state.present),
        "absent": list(state.absent),
    }


def servo_roles(robot: Robot) -> dict[int, str]:
    """HerkuleX servo id → ``neck``, ``ext1`` or ``ext2`` (from the Robot's config)."""
    roles = {sid: f"ext{n}" for n, sid in enumerate(robot.config.ext_servo_ids, 1)}
    if robot.neck_kind == "herkulex":
        roles[robot.config.neck_id] = "neck"
    return roles


def info(
    port: PortOption = None, direct: DirectOption = False, as_json: JsonOption = False
) -> None:
    """Firmware tags of the boards, the HerkuleX servos' models and the neck kind.

    Every expected device is asked; the ones that do not answer are listed too.

    Example: ohmni info --port sim://?neck=worm
    """

    async def main() -> dict[str, Any]:
        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, **READ_ONLY) as robot:
            return {"port": url, **(await device_info(robot))}

    found = run(main)
    if as_json:
        emit_json(found)
        return
    _print_info(found)


def _print_info(found: Mapping[str, Any]) -> None:
    from rich.table import Table  # noqa: PLC0415

    from ohmni_tb.protocol.devices import DEVICE_MAP, device_name  # noqa: PLC0415

    firmware: dict[str, str | None] = found["firmware"]
    tag_of = {0: "left_drive", 1: "right_drive", 4: "worm_neck", 20: "core"}
    servos = {row["sid"]: row for row in found["servos"]}
    table = Table(title=f"devices on {escape(found['port'])}")
    for column in ("sid", "name", "device", "answer"):
        table.add_column(column)
    for sid in sorted({*found["present"], *found["absent"]}):
        entry = DEVICE_MAP.get(sid)
        name = servos[sid]["role"] if sid in servos else device_name(sid)
        if sid not in found["present"]:
            answer = "[red]no answer[/red]"
        elif sid in servos:
            answer = escape(servos[sid]["model"] or "HerkuleX, model unread")
        else:
            tag = firmware.get(tag_of.get(sid, ""))
            answer = "[dim]no firmware tag[/dim]" if tag is None else f"firmware {escape(tag)}"
        table.add_row(str(sid), name, "" if entry is None else escape(entry.description), answer)
    console.print(table)
    console.print(f"neck: {found['neck_kind']}", highlight=False)
    settings = found.get("neck_settings")
    if settings is not None:
        console.print(_settings_line(settings), highlight=False)
    profile = found.get("profile")
    if profile is not None:
        shown = ", ".join(
            f"{name}={_profile_value(name, value)}" for name, value in profile.items()
        )
        console.print(f"bus profile: {shown}", highlight=False)


def _profile_value(name: str, value: object) -> str:
    """A profile setting as a config file holds it: addresses in hex."""
    if name.endswith("_addr") and isinstance(value, int):
        return f"0x{value:02X}"
    if isinstance(value, list):
        return ",".join(map(str, value)) or "none"
    return str(value)


def _settings_line(report: Mapping[str, Any]) -> str:
    """One line on the neck servo's own settings: what the last load read back (the
    rest of it is in --json)."""
    sid, memory = report["sid"], "RAM and EEP" if report["memory"] == "eep" else "RAM"
    got: Mapping[str, int] | None = report["read_back"]
    if got is None:
        return f"neck servo {sid}: settings not loaded: {report['error']}"
    verdict = "as set" if report["ok"] else "NOT as set"
    return (
        f"neck servo {sid}: settings in {memory} {verdict}: position "
        f"{got['min_position']}..{got['max_position']}, kp/ki/kd "
        f"{got['position_kp']}/{got['position_ki']}/{got['position_kd']}"
    )


# -- ports ------------------------------------------------------------------------------


def ports(as_json: JsonOption = False) -> None:
    """List the serial ports of this machine with their USB ids; mark the bus adapter.

    The bus adapter is USB 0403:6015 (or the robot's /dev/usb/tty1-2.1): --port auto opens it.

    No port is opened.

    Example: ohmni ports --json
    """
    from ohmni_tb.transport import ports as port_list  # noqa: PLC0415  # pyserial: slow

    found = port_list.list_ports()
    if as_json:
        emit_json([port.as_dict() for port in found])
        return
    vid, pid = port_list.BUS_USB_ID
    adapter = f"USB {vid:04x}:{pid:04x}"
    if not found:
        console.print(
            f"no serial ports found (the bus adapter is {adapter}): is it plugged in? "
            "Try --port sim:// for the simulator",
            highlight=False,
        )
        return
    from rich.table import Table  # noqa: PLC0415

    table = Table(title="serial ports")
    for column in ("device", "usb id", "description", "serial number", ""):
        table.add_column(column)
    for port in found:
        table.add_row(
            escape(port.device),
            port.usb_id or "-",
            escape(port.description) or "-",
            escape(port.serial_number or "-"),
            "[bold green]← likely the bus[/bold green]" if port.likely_bus else "",
        )
    console.print(table)
    if not any(port.likely_bus for port in found):
        console.print(
            f"none looks like the Ohmni bus adapter ({adapter}); pass --port PATH",
            highlight=False,
        )


# -- light ------------------------------------------------------------------------------


def light(
    hue: Annotated[str, typer.Argument(help="Hue, 0..255.", show_default=False)],
    saturation: Annotated[str, typer.Argument(help="Saturation, 0..255.", show_default=False)],
    value: Annotated[str, typer.Argument(help="Value (brightness), 0..255.", show_default=False)],
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Set the light ring's colour: hue, saturation and value, 0..255 each.

    0 0 0 turns it off. The values are checked before the port is opened.

    Example: ohmni light 120 255 128 --port sim://
    """
    h, s, v = (
        parse_int(text, name, LIGHT_MIN, LIGHT_MAX)
        for text, name in ((hue, "HUE"), (saturation, "SATURATION"), (value, "VALUE"))
    )

    async def main() -> str:
        from ohmni_tb.errors import StateError  # noqa: PLC0415
        from ohmni_tb.protocol.devices import DeviceId  # noqa: PLC0415

        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, control=True, **READ_ONLY) as robot:
            if DeviceId.CORE not in robot.state.present:
                raise StateError(
                    f"the core board (sid {int(DeviceId.CORE)}) does not answer: "
                    "the light ring was not set"
                )
            await robot.light_ring(h, s, v)
        return url

    url = run(main)
    if as_json:
        emit_json({"port": url, "hue": h, "saturation": s, "value": v})
        return
    console.print(f"light ring ← hue {h}, saturation {s}, value {v}", highlight=False)


# -- pid --------------------------------------------------------------------------------

pid_app = new_app(
    help="The wheel PIDs of the running robot (the daemon's when ohmni serve runs, else "
    "the port's): get and set their gains, per wheel with --wheel, enable or disable them. "
    "--config: the gains in the config file instead, which every Robot opened later starts "
    "with.\n\nExample: ohmni pid set --kp 600 --ki 300 --wheel left",
    no_args_is_help=True,
)

FileOption = Annotated[
    Path | None,
    typer.Option(
        "--file",
        "-f",
        help="The TOML config file. Default: the file the commands read ($OHMNI_CONFIG, "
        "./ohmni.toml, $XDG_CONFIG_HOME/ohmni/ohmni.toml, the first that exists), else "
        "the user's $XDG_CONFIG_HOME/ohmni/ohmni.toml.",
        show_default=False,
        dir_okay=False,
    ),
]


#: What each gain is and allows, for --help and errors (a test checks them against
#: RobotConfig's: importing the config here would load pydantic for every --help).
GAINS: Final[dict[str, tuple[str, str]]] = {
    "--kp": ("Proportional gain, PWM per m/s of error", "0..10000 PWM/(m/s)"),
    "--ki": ("Integral gain, PWM per m/s of error and second", "0..10000 PWM/m"),
    "--kd": ("Derivative gain on the measured speed, PWM per m/s²", "0..1000 PWM/(m/s²)"),
    "--kff": ("Velocity feed-forward, PWM per m/s of setpoint", "0..10000 PWM/(m/s)"),
    "--ff-offset": (
        "PWM added toward a non-zero setpoint (the motors' dead band)",
        "0..200 PWM",
    ),
}


def _gain_option(flag: str) -> Any:
    what, allowed = GAINS[flag]
    return typer.Option(
        flag, help=f"{what}; allowed {allowed}.", show_default=False, metavar="GAIN"
    )


def _env_overrides(fields: list[str]) -> dict[str, str]:
    """Settings among ``fields`` that an ``OHMNI_*`` variable sets: field → variable."""
    from ohmni_tb.config import ENV_PREFIX  # noqa: PLC0415

    found = {}
    for key in os.environ:
        name = key.lower().removeprefix(ENV_PREFIX.lower())
        if key.lower().startswith(ENV_PREFIX.lower()) and name in fields:
            found[name] = key
    return found


WheelOption = Annotated[
    str | None,
    typer.Option(
        "--wheel",
        help="left or right: that wheel's PID only. Default: both wheels.",
        show_default=False,
        metavar="left|right",
    ),
]
ConfigOption = Annotated[
    bool,
    typer.Option(
        "--config",
        help="The gains in the config file (what every Robot opened later starts with), "
        "not the running robot's; no port is opened. Implied by --file.",
    ),
]


@pid_app.command("get")
def pid_get(
    wheel: WheelOption = None,
    config: ConfigOption = False,
    file: FileOption = None,
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Print the running robot's wheel PID gains (robot.get_pid), each wheel's, and
    whether each PID runs.

    Through the daemon when ohmni serve runs, else it opens the port. With --config (or
    --file): the gains in the config file instead, from $OHMNI_PID_*, else the file, else
    the defaults, each one's source shown, and no port is opened.

    Example: ohmni pid get --json
    """
    if config or file is not None:
        if wheel is not None:
            raise typer.BadParameter(
                "--wheel is for the running robot: the config file's gains are both wheels'"
            )
        _pid_get_file(file, as_json)
        return
    _pid_get_robot(_wheel_name(wheel), port, direct, as_json)


def _pid_get_file(file: Path | None, as_json: bool) -> None:
    """``ohmni pid get --config``: the gains in force by the config file."""
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415
    from ohmni_tb.config_file import loaded_config_file, read_settings  # noqa: PLC0415
    from ohmni_tb.errors import ConfigError  # noqa: PLC0415

    if file is not None and not file.is_file():
        raise typer.BadParameter(f"--file={str(file)!r}: no such file")
    path = file if file is not None else loaded_config_file()
    try:
        config = RobotConfig.load(file)
        in_file = read_settings(path) if path is not None else {}
    except ConfigError as exc:
        _fail(str(exc))
    gains = config.pid_gains()
    env = _env_overrides(list(PID_FIELDS.values()))
    rows = []
    for flag, field in PID_FIELDS.items():
        name = field.removeprefix("pid_")
        if field in env:
            source = f"${env[field]}"
        elif field in in_file:
            source = str(path)
        else:
            source = "default"
        rows.append((flag, name, float(getattr(gains, name)), source))
    if as_json:
        emit_json(
            {
                "file": None if path is None else str(path),
                "gains": {name: value for _, name, value, _ in rows},
                "sources": {name: source for _, name, _, source in rows},
            }
        )
        return
    from rich.table import Table  # noqa: PLC0415

    table = Table(title="wheel PID gains in force")
    table.add_column("option")
    table.add_column("gain")
    table.add_column("value", justify="right")
    table.add_column("from")
    for flag, name, value, source in rows:
        table.add_row(flag, name, f"{value:g}", escape(source))
    console.print(table)
    console.print(
        f"config file: {escape(str(path)) if path else 'none (defaults and environment)'}",
        highlight=False,
    )


@pid_app.command("set")
def pid_set(
    kp: Annotated[str | None, _gain_option("--kp")] = None,
    ki: Annotated[str | None, _gain_option("--ki")] = None,
    kd: Annotated[str | None, _gain_option("--kd")] = None,
    kff: Annotated[str | None, _gain_option("--kff")] = None,
    ff_offset: Annotated[str | None, _gain_option("--ff-offset")] = None,
    wheel: WheelOption = None,
    config: ConfigOption = False,
    file: FileOption = None,
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Set the running robot's wheel PID gains (robot.set_pid), bumplessly; --wheel for one.

    Only the gains given change. Through the daemon when ohmni serve runs (the daemon's
    robot keeps them until it stops), else it opens the port (they last while this command
    runs: use --config to keep them). With --config (or --file): write them to the config
    file instead, for every Robot opened later; the rest of the file stays as it is,
    comments too, and no port is opened.

    Every value is range-checked first.

    Example: ohmni pid set --kp 650 --ki 300 --kd 0
    """
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415
    from ohmni_tb.errors import ConfigError  # noqa: PLC0415

    which = _wheel_name(wheel)
    if which is not None and (config or file is not None):
        raise typer.BadParameter(
            "--wheel is for the running robot: the config file's gains are both wheels'"
        )

    given = {
        flag: text
        for flag, text in zip(PID_FIELDS, (kp, ki, kd, kff, ff_offset), strict=True)
        if text is not None
    }
    if not given:
        raise typer.BadParameter(
            f"give at least one gain: {', '.join(PID_FIELDS)}", param_hint="'pid set'"
        )
    values: dict[str, float] = {}
    for flag, text in given.items():
        field = PID_FIELDS[flag]
        number = _parse_number(text, flag)
        try:
            setting: dict[str, Any] = {field: number}
            RobotConfig(**setting)
        except ConfigError as exc:
            lines = [line for line in str(exc).splitlines() if line.startswith(f"{field}=")]
            if not lines:
                _fail(str(exc))  # another setting (from the environment) is invalid
            raise typer.BadParameter(f"{flag}: {lines[0].removesuffix(' (argument)')}") from None
        values[field] = number
    if not (config or file is not None):
        _pid_set_robot(values, which, port, direct, as_json)
        return
    from ohmni_tb.config_file import default_config_file, loaded_config_file  # noqa: PLC0415

    path = file if file is not None else default_config_file()
    from ohmni_tb.config_file import write_settings  # noqa: PLC0415

    try:
        outcome = write_settings(path, values)
    except ConfigError as exc:
        _fail(str(exc))
    read_by_default = loaded_config_file()
    env = _env_overrides(list(values))
    if as_json:
        emit_json(
            {
                "file": str(path),
                "created": outcome.created,
                "written": values,
                "previous": outcome.previous,
                "read_by_commands": read_by_default is not None
                and read_by_default.resolve() == path.resolve(),
                "overridden_by": env,
            }
        )
        return
    verb = "created" if outcome.created else "updated"
    console.print(f"{verb} {escape(str(path))}:", highlight=False)
    for field, number in values.items():
        before = outcome.previous.get(field)
        was = "not set before" if before is None else f"was {before!r}"
        console.print(f"  {field} = {number!r}   ({was})", highlight=False)
    if read_by_default is None or read_by_default.resolve() != path.resolve():
        shown = "no file" if read_by_default is None else str(read_by_default)
        console.print(
            f"[yellow]note:[/yellow] the commands read {escape(shown)}, not this file: "
            f"set OHMNI_CONFIG={escape(str(path))} to use it",
            highlight=False,
        )
    for field, variable in env.items():
        console.print(
            f"[yellow]note:[/yellow] ${escape(variable)} is set and overrides {field} "
            "from the file",
            highlight=False,
        )


def _wheel_name(wheel: str | None) -> Wheel | None:
    """``--wheel``, checked: ``left``, ``right`` or not given (both)."""
    if wheel is None:
        return None
    if wheel == "left":
        return "left"
    if wheel == "right":
        return "right"
    raise typer.BadParameter(f"--wheel must be left or right, not {wheel!r}")


def _gains_dict(gains: PidGains) -> dict[str, float]:
    return {name: float(getattr(gains, name)) for name in ("kp", "ki", "kd", "kff", "ff_offset")}


async def _pid_state(robot: Robot, wheel: Wheel | None) -> dict[str, Any]:
    """Each wheel's gains and whether its PID runs (only ``wheel``'s when given)."""
    await robot.confirm()  # a remote robot's copy: after this command's own changes
    enabled = robot.controllers_enabled()
    wheels: tuple[Wheel, ...] = ("left", "right") if wheel is None else (wheel,)
    return {
        name: {**_gains_dict(robot.get_pid(wheel=name)), "enabled": enabled[name]}
        for name in wheels
    }


def _robot_note(via: str | None) -> str:
    if via is not None:
        return f"the daemon's robot at {via}: for every client, until the daemon stops"
    return "this command's own robot: the change ended with it (ohmni serve keeps one)"


def _print_pid_state(url: str, state: dict[str, Any], note: str | None = None) -> None:
    from rich.table import Table  # noqa: PLC0415

    table = Table(title=f"wheel PIDs on {escape(url)}")
    table.add_column("gain")
    for name in state:
        table.add_column(name, justify="right")
    for gain in ("kp", "ki", "kd", "kff", "ff_offset", "enabled"):
        cells = [
            ("on" if state[name][gain] else "off")
            if gain == "enabled"
            else f"{state[name][gain]:g}"
            for name in state
        ]
        table.add_row(gain, *cells)
    console.print(table)
    if note is not None:
        console.print(note, highlight=False, soft_wrap=True)


def _pid_get_robot(wheel: Wheel | None, port: str | None, direct: bool, as_json: bool) -> None:
    async def main() -> tuple[str, dict[str, Any]]:
        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, **READ_ONLY) as robot:
            return url, await _pid_state(robot, wheel)

    url, state = run(main)
    if as_json:
        emit_json({"port": url, "wheels": state})
        return
    _print_pid_state(url, state)


def _pid_set_robot(
    values: dict[str, float], wheel: Wheel | None, port: str | None, direct: bool, as_json: bool
) -> None:
    import dataclasses  # noqa: PLC0415

    changes = {field.removeprefix("pid_"): value for field, value in values.items()}

    async def main() -> tuple[str, str | None, dict[str, Any]]:
        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, control=True, **READ_ONLY) as robot:
            for name in ("left", "right") if wheel is None else (wheel,):
                gains = dataclasses.replace(robot.get_pid(wheel=name), **changes)
                robot.set_pid(gains, wheel=name)
            await robot.confirm()
            return url, via, await _pid_state(robot, wheel)

    url, via, state = run(main)
    if as_json:
        emit_json({"port": url, "via_daemon": via is not None, "set": changes, "wheels": state})
        return
    _print_pid_state(url, state, f"set on {_robot_note(via)}")


def _controllers(
    enabled: bool, wheel: str | None, port: str | None, direct: bool, as_json: bool
) -> None:
    which = _wheel_name(wheel)

    async def main() -> tuple[str, str | None, dict[str, Any]]:
        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, control=True, **READ_ONLY) as robot:
            robot.enable_controllers(enabled, wheel=which)
            await robot.confirm()
            return url, via, await _pid_state(robot, None)

    url, via, state = run(main)
    if as_json:
        emit_json({"port": url, "via_daemon": via is not None, "wheels": state})
        return
    _print_pid_state(url, state, f"{'enabled' if enabled else 'disabled'} on {_robot_note(via)}")


@pid_app.command("enable")
def pid_enable(
    wheel: WheelOption = None,
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Run the wheel PIDs again (robot.enable_controllers(True)); --wheel for one.

    Through the daemon when ohmni serve runs, else it opens the port.

    Example: ohmni pid enable --wheel left
    """
    _controllers(True, wheel, port, direct, as_json)


@pid_app.command("disable")
def pid_disable(
    wheel: WheelOption = None,
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Stop the wheel PIDs (robot.enable_controllers(False)); --wheel for one.

    While a wheel's PID is off the robot stands, drive commands are refused, and only
    open-loop PWM (ohmni drive --pwm) moves the wheels. Through the daemon when ohmni serve
    runs, else it opens the port.

    Example: ohmni pid disable --wheel right
    """
    _controllers(False, wheel, port, direct, as_json)


def _fail(message: str) -> NoReturn:
    """Print ``message`` as an error line and exit with code 1."""
    error_line(message)
    raise typer.Exit(1)


def _parse_number(text: str, flag: str) -> float:
    """A gain as typed: a finite number in ASCII digits (``0x..`` integers accepted).

    Raises:
        typer.BadParameter: Names the option, the text and what is allowed.
    """
    number: float | None = None
    if text.isascii():
        try:
            number = float(text)
        except ValueError:
            try:
                number = float(int(text, 0))
            except (ValueError, OverflowError):
                number = None
    if number is None or not math.isfinite(number):
        shown = repr(text) if len(text) <= 40 else f"{text[:20]!r}… ({len(text)} characters)"
        raise typer.BadParameter(
            f"{flag} must be a finite number, not {shown}: allowed {GAINS[flag][1]}"
        )
    return number + 0.0  # -0.0 is written as 0.0
