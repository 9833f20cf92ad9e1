"""The bus profile: every part of the bus the project assumes, as one value (sans-IO).

The framing, the device ids, the wheel counts and the light ring are confirmed by public
sources; the rest is the project's **assumed** profile until a capture or ``ohmni probe``
says otherwise. :class:`BusProfile` gathers those assumptions — the drive boards'
(:class:`~ohmni_tb.protocol.drive.DriveProfile`), the core board's
(:class:`~ohmni_tb.protocol.core.CoreProfile`), the worm neck's
(:class:`~ohmni_tb.protocol.worm_neck.WormProfile`) and the external servo ids — so the
Robot, the simulator and the bus monitor all take the same object::

    from ohmni_tb.protocol.profile import BusProfile

    profile = BusProfile.from_settings({"wheel_form": "i_jog", "battery_addr": "0xB0"})
    print(profile.settings()["battery_addr"])     # 176

Each part is also a setting of :class:`~ohmni_tb.config.RobotConfig` under the names of
:data:`PROFILE_SETTINGS` (a config file, ``OHMNI_*``, or ``Robot.open(port,
profile=...)``), and an option of ``sim://`` URLs.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ohmni_tb.errors import InvalidArgumentError, OhmniError, OutOfRangeError
from ohmni_tb.protocol.core import CORE_PROFILE, BatteryLayout, CoreProfile
from ohmni_tb.protocol.devices import DEFAULT_EXT_SERVO_IDS, DeviceId
from ohmni_tb.protocol.drive import DRIVE_PROFILE, DriveProfile, WheelJogForm
from ohmni_tb.protocol.worm_neck import WORM_PROFILE, WormProfile

__all__ = [
    "DEFAULT_PROFILE",
    "PROFILE_SETTINGS",
    "BusProfile",
    "check_ext_servo_ids",
    "parse_ext_servo_ids",
]

#: The setting names of the profile, in the order a report lists them.
PROFILE_SETTINGS: tuple[str, ...] = (
    "wheel_form",
    "right_mirrored",
    "drive_torque_addr",
    "battery_addr",
    "battery_length",
    "battery_layout",
    "worm_target_addr",
    "worm_feedback_addr",
    "ext_servo_ids",
)
#: Settings whose values are register addresses (shown in hex).
ADDRESS_SETTINGS = frozenset(
    {"drive_torque_addr", "battery_addr", "worm_target_addr", "worm_feedback_addr"}
)
#: External servo ids: HerkuleX ids, not a board's, at most this many.
_MAX_EXT_SERVOS = 2
_MAX_SERVO_ID = 0xFD
_BOARD_IDS = frozenset(int(d) for d in DeviceId if d != DeviceId.BROADCAST)


@dataclass(frozen=True, slots=True)
class BusProfile:
    """What the Robot assumes of the bus: which packets it sends, where it reads.

    Attributes:
        drive: The drive boards' table (wheel command form, right-wheel mirror, torque).
        core: The core board's table (battery/dock block address, length, layout).
        worm: The worm neck's table (target and feedback registers).
        ext_servo_ids: Bus ids of the external HerkuleX servos.

    Raises:
        InvalidArgumentError: A part is not its table type, or an id repeats.
        OutOfRangeError: An external servo id is not 0..253, is a board's, or there are
            more than two.
    """

    drive: DriveProfile = DRIVE_PROFILE
    core: CoreProfile = CORE_PROFILE
    worm: WormProfile = WORM_PROFILE
    ext_servo_ids: tuple[int, ...] = field(default=DEFAULT_EXT_SERVO_IDS)

    def __post_init__(self) -> None:
        for name, value, kind in (
            ("drive", self.drive, DriveProfile),
            ("core", self.core, CoreProfile),
            ("worm", self.worm, WormProfile),
        ):
            if not isinstance(value, kind):
                raise InvalidArgumentError(f"{name} must be a {kind.__name__}, not {value!r}")
        object.__setattr__(self, "ext_servo_ids", check_ext_servo_ids(self.ext_servo_ids))

    def settings(self) -> dict[str, Any]:
        """The profile as settings: :data:`PROFILE_SETTINGS` → value (a config file's)."""
        return {
            "wheel_form": self.drive.wheel_form.name.lower(),
            "right_mirrored": self.drive.right_mirrored,
            "drive_torque_addr": self.drive.torque_addr,
            "battery_addr": self.core.status_addr,
            "battery_length": self.core.status_size,
            "battery_layout": self.core.layout.value,
            "worm_target_addr": self.worm.target_addr,
            "worm_feedback_addr": self.worm.feedback_addr,
            "ext_servo_ids": self.ext_servo_ids,
        }

    def as_json(self) -> dict[str, Any]:
        """:meth:`settings` as JSON values (the servo ids a list)."""
        return {
            name: list(value) if isinstance(value, tuple) else value
            for name, value in self.settings().items()
        }

    def replace(self, **settings: object) -> BusProfile:
        """This profile with some settings changed (names of :data:`PROFILE_SETTINGS`).

        Raises:
            InvalidArgumentError: An unknown name, or a value of the wrong kind.
            OutOfRangeError: A value out of its range; the message names it.
        """
        return BusProfile.from_settings({**self.settings(), **settings})

    @classmethod
    def from_settings(cls, settings: Mapping[str, object]) -> BusProfile:
        """Build from settings; missing ones take the default profile's values. Strings
        are parsed as a URL or the environment gives them (``"i_jog"``, ``"0xB0"``,
        ``"13,14"``, ``"none"``, ``"1"``/``"0"``).

        Raises:
            InvalidArgumentError: An unknown name, or a value of the wrong kind.
            OutOfRangeError: A value out of its range; the message names it.
        """
        unknown = sorted(set(settings) - set(PROFILE_SETTINGS))
        if unknown:
            raise InvalidArgumentError(
                f"unknown profile setting(s) {', '.join(unknown)}: "
                f"allowed {', '.join(PROFILE_SETTINGS)}"
            )
        merged = {**DEFAULT_PROFILE.settings(), **settings}
        form = _choice("wheel_form", merged["wheel_form"], [f.name.lower() for f in WheelJogForm])
        layout = _choice(
            "battery_layout", merged["battery_layout"], [v.value for v in BatteryLayout]
        )
        try:
            drive = DriveProfile(
                wheel_form=WheelJogForm[form.upper()],
                right_mirrored=_bool("right_mirrored", merged["right_mirrored"]),
                torque_addr=_int("drive_torque_addr", merged["drive_torque_addr"]),
            )
            core = CoreProfile(
                status_addr=_int("battery_addr", merged["battery_addr"]),
                status_size=_int("battery_length", merged["battery_length"]),
                layout=BatteryLayout(layout),
            )
            worm = WormProfile(
                target_addr=_int("worm_target_addr", merged["worm_target_addr"]),
                feedback_addr=_int("worm_feedback_addr", merged["worm_feedback_addr"]),
            )
        except OutOfRangeError as exc:
            raise _renamed(exc) from None
        ids = merged["ext_servo_ids"]
        if isinstance(ids, str):
            ids = parse_ext_servo_ids(ids)
        if not isinstance(ids, (tuple, list)):
            raise InvalidArgumentError(f"ext_servo_ids must be a list of ids, not {ids!r}")
        return cls(drive=drive, core=core, worm=worm, ext_servo_ids=tuple(ids))


#: A part's field name in an error → the setting's name.
_SETTING_OF_FIELD = {
    "drive board torque_addr": "drive_torque_addr",
    "status_addr": "battery_addr",
    "status_size": "battery_length",
    "worm neck target_addr": "worm_target_addr",
    "worm neck feedback_addr": "worm_feedback_addr",
}


def _renamed(exc: OutOfRangeError) -> OhmniError:
    """The part's range error under the setting's name (what a user typed)."""
    setting = _SETTING_OF_FIELD.get(exc.name)
    if setting is None:
        return exc
    return OutOfRangeError(setting, exc.value, exc.low, exc.high, exc.unit)


def check_ext_servo_ids(ids: object) -> tuple[int, ...]:
    """``ids`` as a tuple of external servo ids (the one check, for the profile and for
    ``RobotConfig.ext_servo_ids``).

    Raises:
        InvalidArgumentError: Not a sequence of ints, an id repeats, an id is a board's,
            or more than two.
        OutOfRangeError: An id out of 0..253.
    """
    if not isinstance(ids, (tuple, list)):
        raise InvalidArgumentError(f"ext_servo_ids must be a list of ids, not {ids!r}")
    shown = f"ext_servo_ids={tuple(ids)}"
    for sid in ids:
        if isinstance(sid, bool) or not isinstance(sid, int):
            raise InvalidArgumentError(f"{shown}: {sid!r} is not a bus id (an int)")
        if not 0 <= sid <= _MAX_SERVO_ID:
            raise OutOfRangeError("ext_servo_ids", sid, 0, _MAX_SERVO_ID)
        if sid in _BOARD_IDS:
            raise InvalidArgumentError(
                f"{shown}: id {sid} is the {DeviceId(sid).name.lower()} board's; board ids "
                f"{', '.join(map(str, sorted(_BOARD_IDS)))} are taken"
            )
        if ids.count(sid) > 1:
            raise InvalidArgumentError(f"{shown} repeats id {sid}")
    if len(ids) > _MAX_EXT_SERVOS:
        raise InvalidArgumentError(f"{shown} lists {len(ids)} servos: at most {_MAX_EXT_SERVOS}")
    return tuple(ids)


def parse_ext_servo_ids(text: str) -> tuple[int, ...]:
    """``"13,14"`` or ``"[13, 14]"`` (decimal or ``0x``), or ``""``/``"none"`` for none.

    Raises:
        InvalidArgumentError: A part is not an integer.
        OutOfRangeError: An id is out of range (see :func:`check_ext_servo_ids`).
    """
    body = text.strip()
    if body.startswith("[") and body.endswith("]"):
        body = body[1:-1].strip()
    if body.lower() in {"", "none"}:
        return ()
    ids: list[int] = []
    for part in body.split(","):
        try:
            ids.append(int(part.strip(), 0))
        except ValueError:
            raise InvalidArgumentError(
                f"ext_servo_ids={text!r}: {part.strip()!r} is not a bus id "
                "(write ids like 11,12, or none)"
            ) from None
    return check_ext_servo_ids(ids)


def _choice(name: str, value: object, allowed: list[str]) -> str:
    text = value.name if isinstance(value, WheelJogForm) else value
    text = text.value if isinstance(text, BatteryLayout) else text
    if isinstance(text, str) and text.strip().lower() in allowed:
        return text.strip().lower()
    raise InvalidArgumentError(f"{name}={value!r} is not one of {', '.join(allowed)}")


def _bool(name: str, value: object) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip().lower() in {"1", "true", "yes", "on"}:
        return True
    if isinstance(value, str) and value.strip().lower() in {"0", "false", "no", "off"}:
        return False
    raise InvalidArgumentError(f"{name}={value!r} is not a bool (true/false, 1/0)")


def _int(name: str, value: object) -> int:
    if isinstance(value, str):
        try:
            return int(value.strip(), 0)
        except ValueError:
            raise InvalidArgumentError(
                f"{name}={value!r} is not an integer (decimal or 0x hex)"
            ) from None
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidArgumentError(f"{name}={value!r} is not an integer")
    return value


#: The assumed profile (every default).
DEFAULT_PROFILE = BusProfile()
