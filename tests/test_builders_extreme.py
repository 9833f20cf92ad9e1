"""Every public builder and converter that takes numbers, fed extreme values.

Each one either returns a valid result (no NaN or infinity in it, a packet that encodes)
or raises an :class:`~ohmni_tb.errors.OhmniError` with a one-line message — never a bare
``TypeError``/``ValueError``/``OverflowError``/``ZeroDivisionError``.

:data:`CASES` lists them explicitly; :func:`test_the_table_covers_every_numeric_callable`
fails when a module gains a public callable taking numbers that is neither in the table
nor in :data:`NOT_FUZZED` with a reason.
"""

from __future__ import annotations

import enum
import inspect
import math
import types
import typing
from collections.abc import Callable
from dataclasses import fields, is_dataclass
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ohmni_tb.control import calibration, encoder, kinematics, limiter, odometry, pid
from ohmni_tb.errors import OhmniError
from ohmni_tb.herkulex import commands, registers, servo, units
from ohmni_tb.protocol import (
    Command,
    Memory,
    Packet,
    core,
    drive,
    encode_packet,
    jog,
    messages,
    worm_neck,
)

MODULES = (
    units,
    commands,
    registers,
    servo,
    drive,
    core,
    worm_neck,
    jog,
    messages,
    kinematics,
    pid,
    odometry,
    encoder,
    limiter,
    calibration,
)

#: The values that break naive code: non-finite, huge, tiny, signed zero, wrong types.
EXTREMES: tuple[object, ...] = (
    math.inf,
    -math.inf,
    math.nan,
    1e308,
    -1e308,
    -0.0,
    0.0,
    5e-324,
    -5e-324,
    2.2250738585072014e-308,
    10**400,
    -(10**400),
    10**5000,
    2**64,
    -1,
    0,
    1,
    3,
    255,
    1000,
    1.5,
    True,
    False,
    "1",
    None,
)
VALUES = st.one_of(
    st.sampled_from(EXTREMES),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**70), max_value=2**70),
)


class _Carrier:
    """The four calls a Servo needs; nothing here is ever awaited."""

    async def request(self, packet: Packet, **_: object) -> Packet | None:
        return None

    async def send(self, packet: Packet) -> None:
        return None

    def ack_policy(self, sid: int) -> int:
        return 1

    def set_ack_policy(self, sid: int, policy: int) -> None:
        return None


def _pid_steps(*values: Any) -> object:
    controller = pid.PidController(pid.PidGains(kp=400.0, ki=2000.0, kd=5.0, kff=900.0))
    controller.step(0.5, 0.0, 0.02)
    return controller.step(*values)


def _odometry_update(*values: Any) -> object:
    odo = odometry.Odometry()
    odo.update(0.01, 0.01, 0.0)
    return odo.update(*values)


def _estimator_update(count: Any, t_s: Any) -> object:
    estimator = encoder.VelocityEstimator()
    estimator.update(0, 0.0)
    return estimator.update(count, t_s)


def _wheel_encoder_update(raw: Any, t_s: Any) -> object:
    wheel = encoder.WheelEncoder()
    wheel.update(0, 0.0)
    return wheel.update(raw, t_s)


def _count_filter(max_mps: Any, slack_m: Any = 0.002, rebase_after: Any = 3) -> encoder.CountFilter:
    counts = encoder.CountFilter(
        encoder.WheelEncoder(), max_mps, slack_m=slack_m, rebase_after=rebase_after
    )
    counts.take(0, 0.0)
    return counts


def _pose_at(t_s: Any) -> object:
    odo = odometry.Odometry()
    odo.update(0.0, 0.0, 0.0)
    odo.update(0.01, 0.02, 0.02)
    return odo.pose_at(t_s)


#: Qualified name → (number of values, a call that puts them in every numeric slot).
CASES: dict[str, tuple[int, Callable[..., object]]] = {
    # herkulex.units
    "units.angle_deg_from_raw": (2, lambda a, b: units.angle_deg_from_raw(a, zero_offset_raw=b)),
    "units.angle_rad_from_raw": (2, lambda a, b: units.angle_rad_from_raw(a, zero_offset_raw=b)),
    "units.check_playtime_ticks": (1, units.check_playtime_ticks),
    "units.check_zero_offset_raw": (1, units.check_zero_offset_raw),
    "units.playtime_s_from_ticks": (1, units.playtime_s_from_ticks),
    "units.playtime_sent_s": (1, units.playtime_sent_s),
    "units.playtime_ticks_from_s": (1, units.playtime_ticks_from_s),
    "units.check_playtime_s": (1, units.check_playtime_s),
    "units.pos_raw_from_deg": (
        4,
        lambda a, b, c, d: units.pos_raw_from_deg(a, zero_offset_raw=b, min_raw=c, max_raw=d),
    ),
    "units.pos_raw_from_rad": (
        4,
        lambda a, b, c, d: units.pos_raw_from_rad(a, zero_offset_raw=b, min_raw=c, max_raw=d),
    ),
    "units.speed_dps_from_raw": (1, units.speed_dps_from_raw),
    "units.speed_rad_s_from_raw": (1, units.speed_rad_s_from_raw),
    "units.voltage_raw_from_v": (1, units.voltage_raw_from_v),
    "units.voltage_v_from_raw": (1, units.voltage_v_from_raw),
    # herkulex.commands
    "commands.JogTarget": (
        3,
        lambda a, b, c: commands.JogTarget(a, b, playtime_ticks=c),
    ),
    "commands.JogTarget.from_wire": (4, commands.JogTarget.from_wire),
    "commands.clear_status": (1, commands.clear_status),
    "commands.eep_read": (1, lambda a: commands.eep_read(a, "id")),
    "commands.eep_write": (2, lambda a, b: commands.eep_write(a, "id", b)),
    "commands.eep_write_many": (2, lambda a, b: commands.eep_write_many(a, {"max_pwm": b})),
    "commands.model_read": (1, commands.model_read),
    "commands.ram_read": (1, lambda a: commands.ram_read(a, "voltage")),
    "commands.ram_write": (2, lambda a, b: commands.ram_write(a, "led_control", b)),
    "commands.ram_write_many": (
        3,
        lambda a, b, c: commands.ram_write_many(a, {"position_kp": b, "position_kd": c}),
    ),
    "commands.reboot": (1, commands.reboot),
    "commands.rollback": (1, commands.rollback),
    "commands.s_jog": (2, lambda a, b: commands.s_jog(a, commands.JogTarget(3, 400))),
    "commands.stat": (1, commands.stat),
    # herkulex.registers
    "registers.Register.check": (1, registers.RAM["max_pwm"].check),
    "registers.Register.encode": (1, registers.RAM["pwm_offset"].encode),
    "registers.RegisterMap.by_addr": (1, registers.RAM.by_addr),
    "registers.resolve": (1, lambda a: registers.resolve(a, Memory.EEP)),
    "registers.RegisterMap.writable": (2, registers.RAM.writable),
    "registers.write_targets": (
        2,
        lambda a, b: registers.write_targets(a, b, persist=True),
    ),
    # herkulex.servo (the synchronous half; the moves go through Servo.target)
    "servo.Servo": (
        4,
        lambda a, b, c, d: servo.Servo(
            _Carrier(), a, zero_offset_raw=b, min_raw=c, max_raw=d, status_max_age_s=0.1
        ),
    ),
    "servo.Servo.target": (1, lambda a: servo.Servo(_Carrier(), 3).target(angle_rad=a)),
    # protocol.drive
    "drive.DriveProfile": (
        2,
        lambda a, b: drive.read_count(0, drive.DriveProfile(count_addr=a, count_size=b)),
    ),
    "drive.read_count": (1, drive.read_count),
    "drive.read_firmware_tag": (2, drive.read_firmware_tag),
    "drive.read_motor_position": (1, drive.read_motor_position),
    "drive.set_board_id": (2, drive.set_board_id),
    "drive.set_torque": (2, drive.set_torque),
    "drive.wheel_command": (2, drive.wheel_command),
    # protocol.core
    "core.CoreProfile": (1, lambda a: core.read_status(core.CoreProfile(status_addr=a))),
    "core.TbcoreStatus": (
        3,
        lambda a, b, c: core.encode_status(
            core.TbcoreStatus((a, 3300, 3300, 3300, 3300), b, True, c, (0, 0, 0, 0))
        ),
    ),
    "core.cells_plausible": (2, lambda a, b: core.cells_plausible((a, b, 3300, 3300, 3300))),
    "core.percent_from_cells": (2, lambda a, b: core.percent_from_cells((a, b))),
    "core.set_light_ring": (3, core.set_light_ring),
    # protocol.worm_neck
    "worm_neck.WormFeedback": (
        1,
        lambda a: worm_neck.encode_feedback(worm_neck.WormFeedback(a, worm_neck.WormFlags.NONE)),
    ),
    "worm_neck.WormProfile": (1, lambda a: worm_neck.set_target(0, worm_neck.WormProfile(a))),
    "worm_neck.check_worm_target": (1, worm_neck.check_worm_target),
    "worm_neck.set_target": (1, worm_neck.set_target),
    # protocol.jog
    "jog.JogSet": (1, lambda a: jog.JogSet(led=a).to_byte()),
    "jog.JogSet.from_byte": (1, jog.JogSet.from_byte),
    "jog.JogTag": (4, jog.JogTag),
    "jog.decode_jog_word": (1, lambda a: jog.decode_jog_word(a, turn=True)),
    "jog.encode_jog_word": (1, lambda a: jog.encode_jog_word(a, turn=True)),
    "jog.jog_data": (
        1,
        lambda a: jog.jog_data(Command.S_JOG, [jog.JogTag(0, 0, 3)], playtime_ticks=a),
    ),
    # protocol.messages
    "messages.check_sid": (1, lambda a: messages.check_sid(a, allow_broadcast=True)),
    "messages.read_request": (3, messages.read_request),
    "messages.reply_expected": (3, messages.reply_expected),
    "messages.write_request": (2, lambda a, b: messages.write_request(a, b, b"\x01")),
    # control.kinematics
    "kinematics.DiffDrive": (
        4,
        lambda a, b, c, d: kinematics.DiffDrive(a, b).wheel_speeds(kinematics.Twist(c, d)),
    ),
    "kinematics.DiffDrive.rim_speed_mps": (
        2,
        lambda a, b: kinematics.DiffDrive(wheel_radius_m=b).rim_speed_mps(a),
    ),
    "kinematics.DiffDrive.wheel_speed_radps": (
        2,
        lambda a, b: kinematics.DiffDrive(wheel_radius_m=b).wheel_speed_radps(a),
    ),
    "kinematics.Twist": (
        2,
        lambda a, b: kinematics.limit_twist(kinematics.Twist(a, b)),
    ),
    "kinematics.VelocityLimits": (
        5,
        lambda a, b, c, d, e: kinematics.limit_twist(
            kinematics.Twist(d, e), kinematics.VelocityLimits(a, b, c)
        ),
    ),
    "kinematics.WheelSpeeds": (
        3,
        lambda a, b, c: kinematics.DiffDrive(wheel_separation_m=c).twist(
            kinematics.WheelSpeeds(a, b)
        ),
    ),
    "kinematics.saturate_wheel_speeds": (
        3,
        lambda a, b, c: kinematics.saturate_wheel_speeds(kinematics.WheelSpeeds(a, b), c),
    ),
    # control.pid
    "pid.PidGains": (
        5,
        lambda a, b, c, d, e: pid.PidController(pid.PidGains(a, b, c, d, e)).step(1.0, 0.0, 0.02),
    ),
    "pid.PidController": (
        3,
        lambda a, b, c: pid.PidController(
            pid.PidGains(kp=1.0), output_min=a, output_max=b, derivative_tau_s=c
        ).step(1.0, 0.0, 0.02),
    ),
    "pid.PidController.step": (3, _pid_steps),
    "pid.PidController.reset": (1, lambda a: pid.PidController(pid.PidGains()).reset(a)),
    # control.odometry
    "odometry.Odometry": (
        3,
        lambda a, b, c: odometry.Odometry(a, twist_window=b, history_size=c).update(
            0.01, 0.02, 0.0
        ),
    ),
    "odometry.Odometry.update": (3, _odometry_update),
    "odometry.Odometry.reset": (3, lambda a, b, c: odometry.Odometry().reset(a, b, c)),
    "odometry.Odometry.pose_at": (1, _pose_at),
    "odometry.Pose": (3, odometry.Pose),
    "odometry.WheelNoise": (
        2,
        lambda a, b: odometry.Odometry(noise=odometry.WheelNoise(a, b)).update(0.5, 0.2, 0.0).x,
    ),
    "odometry.integrate_batch": (
        3,
        lambda a, b, c: odometry.integrate_batch([a, 0.01], [b, 0.02], c),
    ),
    "odometry.wrap_angle": (1, odometry.wrap_angle),
    # control.encoder
    "encoder.EncoderConfig": (
        3,
        lambda a, b, c: encoder.EncoderConfig(a, b, counter_bits=c).ticks_to_m(100.0),
    ),
    "encoder.EncoderConfig.left": (1, lambda a: encoder.EncoderConfig.left(a).m_to_ticks(1.0)),
    "encoder.EncoderConfig.right": (1, lambda a: encoder.EncoderConfig.right(a).m_to_ticks(1.0)),
    "encoder.EncoderConfig.ticks_to_m": (1, lambda a: encoder.EncoderConfig().ticks_to_m(a)),
    "encoder.EncoderConfig.m_to_ticks": (1, lambda a: encoder.EncoderConfig().m_to_ticks(a)),
    "encoder.Unwrapper": (2, lambda a, b: encoder.Unwrapper(a).update(b)),
    "encoder.Unwrapper.update": (1, lambda a: encoder.Unwrapper.for_motor_position().update(a)),
    "encoder.VelocityEstimator": (
        3,
        lambda a, b, c: encoder.VelocityEstimator(window_s=a, min_ticks=b, stop_after_s=c).update(
            5, 1.0
        ),
    ),
    "encoder.VelocityEstimator.update": (2, _estimator_update),
    "encoder.WheelEncoder.update": (2, _wheel_encoder_update),
    "encoder.unwrap_delta": (3, encoder.unwrap_delta),
    "encoder.CountFilter": (3, lambda a, b, c: _count_filter(a, b, c).check(5_000, 0.02)),
    "encoder.CountFilter.check": (2, lambda a, b: _count_filter(3.0).check(a, b)),
    "encoder.CountFilter.take": (2, lambda a, b: _count_filter(3.0).take(a, b)),
    # control.limiter
    "limiter.AccelLimits": (
        3,
        lambda a, b, c: limiter.jerk_ramp(0.5, 0.0, -0.5, 0.02, limiter.AccelLimits(a, b, c)),
    ),
    "limiter.TwistLimiter.step": (
        3,
        lambda a, b, c: limiter.TwistLimiter().step(kinematics.Twist(a, b), c),
    ),
    "limiter.accel_from_delta_velo_raw": (1, limiter.accel_from_delta_velo_raw),
    "limiter.ramp": (
        3,
        lambda a, b, c: limiter.ramp(a, b, c, limiter.AccelLimits(1.0, 2.0)),
    ),
    "limiter.jerk_ramp": (
        4,
        lambda a, b, c, d: limiter.jerk_ramp(a, b, c, d, limiter.AccelLimits(1.0, 2.0, 5.0)),
    ),
    # control.calibration
    "calibration.calibrate_straight_line": (
        5,
        lambda a, b, c, d, e: calibration.calibrate_straight_line(
            a, b, c, wheel_radius_m=d, wheel_separation_m=e
        ),
    ),
    "calibration.calibrate_umbmark": (
        4,
        lambda a, b, c, d: calibration.calibrate_umbmark([(a, b)], [(c, 0.0)], d),
    ),
}

#: Public callables taking numbers that are not fuzzed here, and why.
NOT_FUZZED: dict[str, str] = {
    "commands.Reply": "a parsed reply: built by parse_reply from bytes, not from numbers",
    "registers.Register": "the register table's rows, fixed at import; Register.check is fuzzed",
    "registers.RegisterMap": "built once from the table at import",
    "servo.Requester.request": "a protocol for carriers, implemented elsewhere",
    "servo.Requester.ack_policy": "a protocol for carriers, implemented elsewhere",
    "servo.Requester.set_ack_policy": "a protocol for carriers, implemented elsewhere",
    "servo.Servo.write": "async; its value is checked by Register.check, fuzzed",
    "servo.Servo.read": "async; its address is checked by registers.resolve, fuzzed",
    "servo.Servo.note_status": "async-loop bound; tested in tests/herkulex",
    "servo.Servo.move_to": "async; checks through Servo.target and the playtime converters",
    "servo.Servo.spin": "async; checks through JogTarget, fuzzed",
    "servo.Servo.set_id": "async; checks through Register.check, fuzzed",
    "servo.Servo.reboot": "async; tested in tests/herkulex",
    "servo.move_group": "async; checks through Servo.target and the playtime converters",
    "messages.ReadReply": "a parsed reply: built from bytes by ReadReply.parse",
    "messages.StatusReply": "a parsed reply: built from bytes by StatusReply.parse",
    "kinematics.LimitedTwist": "a result record of limit_twist, fuzzed",
    "pid.PidStep": "a result record of PidController.step, fuzzed",
    "encoder.WheelSample": "a result record of WheelEncoder.update, fuzzed",
    "registers.ServoFeedback": "a parsed block: built from bytes by decode_feedback",
    "calibration.WheelCalibration": "a result record of the calibrate functions, fuzzed",
}


def _label(value: object) -> str:
    """A test id for a value; an int past the digit limit has no repr."""
    try:
        text = repr(value)
    except ValueError:
        return f"int of {value.bit_length()} bits" if isinstance(value, int) else "value"
    return text if len(text) <= 20 else f"{text[:10]}…"


def _module_key(module: types.ModuleType) -> str:
    return module.__name__.rsplit(".", 1)[-1]


def _is_numeric(annotation: object) -> bool:
    if annotation in (int, float):
        return True
    return any(_is_numeric(arg) for arg in typing.get_args(annotation))


def _takes_numbers(function: Callable[..., object]) -> bool:
    hints = typing.get_type_hints(function)
    return any(_is_numeric(kind) for name, kind in hints.items() if name != "return")


def numeric_callables() -> set[str]:
    """Every public callable of :data:`MODULES` with a parameter typed int or float."""
    found: set[str] = set()
    for module in MODULES:
        key = _module_key(module)
        for name in module.__all__:
            obj = getattr(module, name)
            if inspect.isclass(obj):
                if issubclass(obj, enum.Enum):
                    continue  # value lookups; the builders that take them are fuzzed
                if _takes_numbers(obj.__init__):
                    found.add(f"{key}.{name}")
                for attr, member in vars(obj).items():
                    function = getattr(member, "__func__", member)
                    public = not attr.startswith("_") and inspect.isfunction(function)
                    if public and _takes_numbers(function):
                        found.add(f"{key}.{name}.{attr}")
            elif inspect.isfunction(obj) and _takes_numbers(obj):
                found.add(f"{key}.{name}")
    return found


def test_the_table_covers_every_numeric_callable() -> None:
    found = numeric_callables()
    missing = found - CASES.keys() - NOT_FUZZED.keys()
    assert not missing, f"add these to CASES (or NOT_FUZZED with a reason): {sorted(missing)}"
    stale = (CASES.keys() | NOT_FUZZED.keys()) - found
    assert not stale, f"no longer public callables taking numbers: {sorted(stale)}"
    assert not CASES.keys() & NOT_FUZZED.keys()


def _finite_everywhere(value: object) -> bool:
    """No NaN or infinity anywhere in a result; a packet must encode."""
    if isinstance(value, Packet):
        encode_packet(value)
        return True
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, np.ndarray):
        return bool(np.all(np.isfinite(value)))
    if isinstance(value, tuple | list):
        return all(_finite_everywhere(v) for v in value)
    if is_dataclass(value) and not isinstance(value, type):
        return all(_finite_everywhere(getattr(value, f.name)) for f in fields(value))
    return True


def check_outcome(call: Callable[..., object], values: tuple[object, ...]) -> None:
    try:
        result = call(*values)
    except OhmniError as exc:
        message = str(exc)
        assert message, f"empty message for {values!r}"
        assert "\n" not in message, message
        return
    assert _finite_everywhere(result), f"{values!r} gave {result!r}"


@pytest.mark.parametrize("name", sorted(CASES))
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_extreme_values_give_a_result_or_a_one_line_ohmni_error(
    name: str, data: st.DataObject
) -> None:
    arity, call = CASES[name]
    values = tuple(data.draw(VALUES, label=f"arg{i}") for i in range(arity))
    check_outcome(call, values)


@pytest.mark.parametrize("name", sorted(CASES))
@pytest.mark.parametrize("extreme", EXTREMES, ids=_label)
def test_each_extreme_in_every_slot(name: str, extreme: object) -> None:
    arity, call = CASES[name]
    for slot in range(arity):
        values = tuple(extreme if i == slot else 1 for i in range(arity))
        check_outcome(call, values)
