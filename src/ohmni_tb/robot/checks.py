"""The argument checks both robots make before anything is sent, local and remote alike
(:class:`~ohmni_tb.robot.LocalRobot`, :class:`~ohmni_tb.robot.RemoteRobot`): one function
each, so a bad value raises the same error with the same message either way
(``tests/contract`` compares them)."""

from __future__ import annotations

import math
from typing import Literal

from ohmni_tb._checks import bounded, check_seconds, integer, number, show
from ohmni_tb.control.defaults import MAX_POSE_M, WHEEL_GAIN_RANGES
from ohmni_tb.control.pid import PidGains
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, StateError
from ohmni_tb.herkulex.registers import RAM, Register, memory_of, resolve, write_targets
from ohmni_tb.protocol import BROADCAST_ID, Memory
from ohmni_tb.protocol.drive import PWM_LIMIT
from ohmni_tb.robot.samples import STREAM_NAMES, STREAMS

__all__ = [
    "RELEASE_MAX_S",
    "RELEASE_MIN_S",
    "WHEELS",
    "Wheel",
    "check_board_id",
    "check_enabled",
    "check_gains",
    "check_port_name",
    "check_pose",
    "check_ramped",
    "check_rate",
    "check_release",
    "check_servo_id",
    "check_servo_write",
    "check_stream",
    "check_wheel",
    "gains_of",
    "pwm_command",
    "wheel_index",
]

#: A timed port release (``Robot.release_port``), seconds: long enough for the other
#: program to open the port at all, and at most an hour — longer, or open-ended, is
#: ``duration_s=None`` (until ``Robot.reclaim_port``).
RELEASE_MIN_S = 0.1
RELEASE_MAX_S = 3600.0


def check_stream(name: str) -> None:
    """Raises InvalidArgumentError: ``name`` is not a stream (the message lists them)."""
    if name not in STREAM_NAMES:
        raise InvalidArgumentError(f"no stream {name!r}: the streams are {', '.join(STREAM_NAMES)}")


def check_enabled(enabled: object) -> None:
    """Raises InvalidArgumentError: ``enabled`` is not a bool."""
    if not isinstance(enabled, bool):
        raise InvalidArgumentError(f"enabled must be True or False, not {enabled!r}")


def check_rate(name: str, hz: float) -> float:
    """``hz`` for ``Robot.set_rate`` of stream ``name``, checked by the streams table.

    Raises:
        InvalidArgumentError: No such stream, it is not polled, or ``hz`` is not a number.
        OutOfRangeError: Outside the stream's range.
    """
    check_stream(name)
    spec = STREAMS[name]
    if spec.rate_range_hz is None:
        how = (
            f"it comes with every {spec.follows} sample (set that one's rate)"
            if spec.follows
            else f"its rate is the {spec.rate_setting} setting"
        )
        raise InvalidArgumentError(f"stream {name!r} is not polled: {how}")
    low, high = spec.rate_range_hz
    if not low <= number("hz", hz) <= high:
        raise OutOfRangeError(f"{name} rate", hz, low, high, "Hz")
    return float(hz)


def pwm_command(
    left: float, right: float, left_enabled: bool = True, right_enabled: bool = True
) -> tuple[int, int]:
    """The PWM ``Robot.drive_pwm`` puts on the wire: each value checked, then rounded to
    the nearest whole step (:func:`round`: a half goes to the even step, 0.5 → 0,
    1.5 → 2), and a motor that is not enabled gets 0 (tb_control's ``motor_1_enable``).

    Raises:
        InvalidArgumentError: A value is not a finite number, or a flag not a bool.
        OutOfRangeError: A value is outside −1000..1000 (checked even for a disabled motor).
    """
    pwm = []
    for name, value, enabled in (
        ("left", left, left_enabled),
        ("right", right, right_enabled),
    ):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InvalidArgumentError(f"{name} PWM must be a number, not {show(value)}")
        if not isinstance(enabled, bool):
            raise InvalidArgumentError(f"{name}_enabled must be True or False, not {show(enabled)}")
        if isinstance(value, float) and not math.isfinite(value):
            raise InvalidArgumentError(f"{name} PWM={value!r} is not a finite number")
        if not -PWM_LIMIT <= value <= PWM_LIMIT:
            raise OutOfRangeError(f"{name} PWM", value, -PWM_LIMIT, PWM_LIMIT)
        pwm.append(round(value) if enabled else 0)
    return pwm[0], pwm[1]


#: A wheel by name (``Robot.set_pid``, ``get_pid``, ``enable_controllers``): ``None`` is both.
Wheel = Literal["left", "right"]
#: The wheels by name, in their index order (0 left, 1 right).
WHEELS: tuple[Wheel, Wheel] = ("left", "right")


def check_wheel(wheel: object) -> Wheel | None:
    """``wheel`` for the per-wheel calls: ``"left"``, ``"right"`` or ``None`` (both).

    Raises:
        InvalidArgumentError: Anything else.
    """
    if wheel is None:
        return None
    for name in WHEELS:
        if isinstance(wheel, str) and wheel == name:
            return name
    raise InvalidArgumentError(f"wheel must be 'left', 'right' or None (both), not {show(wheel)}")


def check_gains(gains: object) -> PidGains:
    """``gains`` for ``Robot.set_pid``, each within its range.

    Raises:
        InvalidArgumentError: Not a :class:`PidGains`.
        OutOfRangeError: A gain outside its range.
    """
    if not isinstance(gains, PidGains):
        raise InvalidArgumentError(f"gains must be PidGains, not {type(gains).__name__}")
    for name, (low, high) in WHEEL_GAIN_RANGES.items():
        value = getattr(gains, name)
        if not low <= value <= high:
            raise OutOfRangeError(f"pid {name}", value, low, high)
    return gains


def check_pose(x_m: float, y_m: float, yaw_rad: float) -> tuple[float, float, float]:
    """The pose for ``Robot.set_odometry`` and ``Robot.reset_odometry``.

    Raises:
        InvalidArgumentError: A value is not a finite number.
        OutOfRangeError: A value beyond ±1e6.
    """
    x, y, yaw = (
        bounded(name, number(name, value), -MAX_POSE_M, MAX_POSE_M, unit)
        for name, value, unit in (("x_m", x_m, "m"), ("y_m", y_m, "m"), ("yaw_rad", yaw_rad, "rad"))
    )
    return x, y, yaw


def check_release(duration_s: float | None) -> float | None:
    """``duration_s`` for ``Robot.release_port``.

    Raises:
        OutOfRangeError: Not a number of seconds in 0.1..3600.
    """
    if duration_s is None:
        return None
    check_seconds("duration_s", duration_s, RELEASE_MIN_S, RELEASE_MAX_S)
    return float(duration_s)


def check_servo_write(
    sid: int,
    register: Register | str | int,
    value: int,
    persist: bool,
    memory: Memory | str = Memory.RAM,
) -> None:
    """A servo register write (``HerkulexHandle.write``), by name or address, to RAM (with
    ``persist`` its EEP copy too) or to EEP alone.

    Raises:
        InvalidArgumentError: Unknown register or memory, no register at that address, a
            read-only one, the id (``set_id`` changes it), a value that is not an int,
            ``persist`` with an EEP write, or ``persist`` of a register without an EEP
            copy.
        OutOfRangeError: The value is outside the register's range.
    """
    reg = resolve(register, memory_of(memory))
    if reg.name == "id":
        raise InvalidArgumentError(
            f"servo {sid}'s id is changed with set_id({value!r}), which the robot follows; "
            "nothing was sent"
        )
    if not isinstance(persist, bool):
        raise InvalidArgumentError(f"persist must be True or False, not {persist!r}")
    write_targets(register, value, persist=persist, memory=memory)


def check_board_id(sid: int, new_sid: int, confirm: bool) -> None:
    """A drive board's id change (``Robot.reset_board_id``).

    Raises:
        InvalidArgumentError: An id is not an int, or ``confirm`` is not ``True``.
        OutOfRangeError: An id is not 0..253.
    """
    integer("sid", sid, 0, BROADCAST_ID - 1)
    integer("new_sid", new_sid, 0, BROADCAST_ID - 1)
    if confirm is not True:
        raise InvalidArgumentError(
            f"changing drive board {sid}'s id to {new_sid} takes its wheel off the robot's "
            "control (the wheels are driven by ids 0 and 1) until it is changed back: pass "
            "confirm=True to do it; nothing was sent"
        )


def check_servo_id(new_sid: int) -> int:
    """A servo's new id (``HerkulexHandle.set_id``).

    Raises:
        InvalidArgumentError: Not an int.
        OutOfRangeError: Not 0..253.
    """
    return RAM["id"].check(new_sid)


def check_port_name(port: object) -> None:
    """A port to connect to (``Robot.connect``): ``None``, or a serial device or URL.

    Raises:
        InvalidArgumentError: Anything else (a daemon's URL included).
    """
    if port is None:
        return
    if not isinstance(port, str) or not port.strip() or port.lower().startswith(("ws:", "wss:")):
        raise InvalidArgumentError(
            "port must be a serial device or URL (/dev/ttyUSB0, serial://…, sim://, auto), "
            f"not {port!r}"
        )


def wheel_index(wheel: Wheel | None) -> int | None:
    """A checked wheel's index (0 left, 1 right), ``None`` for both."""
    return None if wheel is None else WHEELS.index(wheel)


def gains_of(wheel: Wheel | None, left: PidGains, right: PidGains) -> PidGains:
    """What ``Robot.get_pid(wheel)`` answers, from both wheels' gains: one wheel's, or
    (``None``) the gains both wheels share.

    Raises:
        StateError: ``wheel`` is ``None`` and the wheels' gains differ (the message
            shows both and says to name a wheel).
    """
    if wheel is not None:
        return left if wheel == "left" else right
    if left != right:
        raise StateError(
            f"the wheels' PID gains differ (left {_shown_gains(left)}; right "
            f"{_shown_gains(right)}): ask get_pid(wheel='left') or get_pid(wheel='right')"
        )
    return left


def check_ramped(ramped: object) -> None:
    """Raises InvalidArgumentError: ``ramped`` (``Robot.drive``) is not a bool."""
    if not isinstance(ramped, bool):
        raise InvalidArgumentError(f"ramped must be True or False, not {show(ramped)}")


def _shown_gains(gains: PidGains) -> str:
    return ", ".join(
        f"{name}={getattr(gains, name):g}" for name in ("kp", "ki", "kd", "kff", "ff_offset")
    )
