"""The error tree: one root, built-in bases where callers expect them, informative messages."""

from __future__ import annotations

import re

import pytest

from ohmni_tb import errors
from ohmni_tb.errors import (
    BusClosedError,
    BusTimeoutError,
    ConfigError,
    DeadlineMissedError,
    DeviceError,
    DeviceStatusError,
    DeviceUnavailableError,
    InvalidArgumentError,
    LeaseError,
    MalformedReplyError,
    MotionAbortedError,
    MotionError,
    MotionPreemptedError,
    MotionResult,
    MotionTimeoutError,
    OhmniError,
    OutOfRangeError,
    PositionError,
    PositionTimeoutError,
    ProtocolError,
    RobotClosedError,
    SourceOverriddenError,
    StateError,
    StopNotConfirmedError,
    TransportClosedError,
    TransportError,
    WheelSlipError,
    WheelStallError,
)

ALL_ERRORS: list[type[OhmniError]] = [
    BusClosedError,
    BusTimeoutError,
    ConfigError,
    DeadlineMissedError,
    DeviceError,
    DeviceStatusError,
    DeviceUnavailableError,
    InvalidArgumentError,
    LeaseError,
    MalformedReplyError,
    MotionAbortedError,
    MotionError,
    MotionPreemptedError,
    MotionTimeoutError,
    OhmniError,
    OutOfRangeError,
    PositionError,
    PositionTimeoutError,
    ProtocolError,
    RobotClosedError,
    SourceOverriddenError,
    StateError,
    StopNotConfirmedError,
    TransportClosedError,
    TransportError,
    WheelSlipError,
    WheelStallError,
]

#: Each error and the ohmni_tb error it derives from, as the module docstring draws it.
PARENT: dict[type[OhmniError], type[OhmniError] | None] = {
    OhmniError: None,
    TransportError: OhmniError,
    TransportClosedError: TransportError,
    ProtocolError: OhmniError,
    MalformedReplyError: ProtocolError,
    DeviceError: OhmniError,
    BusTimeoutError: DeviceError,
    DeviceUnavailableError: BusTimeoutError,
    DeviceStatusError: DeviceError,
    StopNotConfirmedError: DeviceError,
    PositionError: DeviceError,
    PositionTimeoutError: PositionError,
    StateError: OhmniError,
    BusClosedError: StateError,
    DeadlineMissedError: StateError,
    LeaseError: StateError,
    RobotClosedError: StateError,
    SourceOverriddenError: StateError,
    MotionError: StateError,
    MotionPreemptedError: MotionError,
    MotionAbortedError: MotionError,
    MotionTimeoutError: MotionError,
    WheelStallError: MotionError,
    WheelSlipError: MotionError,
    ConfigError: OhmniError,
    InvalidArgumentError: OhmniError,
    OutOfRangeError: InvalidArgumentError,
}


def test_all_is_pinned() -> None:
    assert errors.__all__ == [cls.__name__ for cls in ALL_ERRORS]
    assert sorted(errors.__all__) == errors.__all__


@pytest.mark.parametrize("cls", ALL_ERRORS, ids=lambda c: c.__name__)
def test_every_error_derives_from_the_root(cls: type[OhmniError]) -> None:
    assert issubclass(cls, OhmniError)
    assert getattr(errors, cls.__name__) is cls


@pytest.mark.parametrize("cls", ALL_ERRORS, ids=lambda c: c.__name__)
def test_tree_matches_the_table(cls: type[OhmniError]) -> None:
    own_bases = [b for b in cls.__bases__ if issubclass(b, OhmniError)]
    expected = PARENT[cls]
    assert own_bases == ([] if expected is None else [expected])


def test_module_docstring_draws_the_real_tree() -> None:
    doc = errors.__doc__
    assert doc is not None
    drawn: dict[str, str | None] = {}
    stack: list[tuple[int, str]] = []
    for line in doc.splitlines():
        match = re.match(r"^(\s*(?:[│├└─ ]*))(\w+Error)\b", line)
        if match is None:
            continue
        depth, name = len(match.group(1)), match.group(2)
        while stack and stack[-1][0] >= depth:
            stack.pop()
        drawn[name] = stack[-1][1] if stack else None
        stack.append((depth, name))
    actual = {cls.__name__: (p.__name__ if p else None) for cls, p in PARENT.items()}
    assert drawn == actual


def test_builtin_bases() -> None:
    assert issubclass(BusTimeoutError, TimeoutError)
    for bad_argument in (OutOfRangeError, ConfigError, InvalidArgumentError):
        assert issubclass(bad_argument, ValueError)
    for other in (TransportError, ProtocolError, DeviceError, StateError):
        assert not issubclass(other, ValueError | TimeoutError)


def test_out_of_range_names_value_and_range() -> None:
    err = OutOfRangeError("playtime_ticks", 255, 0, 254, "ticks")
    assert str(err) == "playtime_ticks=255 is out of range: allowed 0..254 ticks"
    assert (err.name, err.value, err.low, err.high, err.unit) == (
        "playtime_ticks",
        255,
        0,
        254,
        "ticks",
    )
    with pytest.raises(ValueError, match=r"sid=-1 .*0\.\.253"):
        raise OutOfRangeError("sid", -1, 0, 253)


def test_bus_timeout_names_device_command_and_attempts() -> None:
    err = BusTimeoutError(sid=20, cmd=0x04, attempts=3, timeout_s=0.025)
    message = str(err)
    assert "sid 20 (0x14)" in message
    assert "0x04" in message
    assert "3 attempt" in message
    assert "25.0 ms" in message
    assert (err.sid, err.cmd, err.attempts, err.timeout_s) == (20, 0x04, 3, 0.025)
    with pytest.raises(TimeoutError):
        raise err


def test_new_engine_errors_are_timeouts_with_their_figures() -> None:
    missed = DeadlineMissedError(deadline=12.5, late_s=0.0031)
    assert isinstance(missed, TimeoutError)
    assert "3.1 ms late" in str(missed)
    assert "nothing was sent" in str(missed)
    assert (missed.deadline, missed.late_s) == (12.5, 0.0031)
    gone = DeviceUnavailableError(sid=11, cmd=0x04, silent_s=None, retry_in_s=0.7)
    assert isinstance(gone, BusTimeoutError)
    assert "sid 11 (0x0B)" in str(gone)
    assert "never answered" in str(gone)
    assert "next probe in 0.7 s" in str(gone)
    assert (gone.sid, gone.cmd, gone.attempts, gone.retry_in_s) == (11, 0x04, 0, 0.7)
    quiet = DeviceUnavailableError(sid=3, cmd=0x07, silent_s=2.25, retry_in_s=0.1)
    assert "no reply for 2.2 s" in str(quiet)


def test_device_errors_carry_the_sid_and_status() -> None:
    err = DeviceStatusError("overload", sid=3, status_error=0x10, status_detail=0x40)
    assert (err.sid, err.status_error, err.status_detail) == (3, 0x10, 0x40)
    assert str(err) == "overload"
    assert DeviceError("gone", sid=4).sid == 4


def _result(reason: str = "timeout") -> MotionResult:
    return MotionResult(
        kind="drive_distance",
        reason=reason,  # type: ignore[arg-type]  # one of MotionEnd's, as the goals give it
        distance_m=0.25,
        heading_change_rad=0.0,
        x_m=0.25,
        y_m=0.0,
        yaw_rad=0.0,
        remaining_m=0.25,
        remaining_rad=0.0,
        elapsed_s=1.5,
    )


def test_motion_errors_carry_what_the_goal_did_and_timeouts_are_timeouts() -> None:
    late = MotionTimeoutError("late", result=_result(), timeout_s=3.0)
    assert isinstance(late, TimeoutError)
    assert (late.result.distance_m, late.timeout_s) == (0.25, 3.0)
    taken = MotionPreemptedError("taken", result=_result("preempted"), by="stop")
    assert (taken.by, taken.result.reason) == ("stop", "preempted")
    stalled = WheelStallError("stuck", result=_result("stalled"), wheels=("left",))
    assert stalled.wheels == ("left",)
    assert MotionAbortedError("gone", result=_result("closed")).result.reason == "closed"
    for error in (taken, stalled):
        assert not isinstance(error, TimeoutError | ValueError)


def test_position_errors_carry_the_target_and_the_last_sample() -> None:
    late = PositionTimeoutError("late", sid=3, target_raw=400, sample=None)
    assert isinstance(late, TimeoutError)
    assert isinstance(late, DeviceError)
    assert (late.sid, late.target_raw, late.sample) == (3, 400, None)
    stalled = PositionError("stalled", sid=4, target_raw=-1000, sample="last")
    assert not isinstance(stalled, TimeoutError)
    assert stalled.sample == "last"
