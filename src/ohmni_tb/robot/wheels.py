"""The wheel counts of each control slot turned into ``wheel_encoder`` and ``wheel_odom``.

Each control slot reads both drive boards' accumulated counts. A count is decoded by the
drive codec (:func:`~ohmni_tb.protocol.drive.parse_count`), checked for plausibility
(:class:`~ohmni_tb.control.encoder.CountFilter`: a bit flipped past the bus's checksum
is not a jump of metres), and both wheels' counts are taken or neither, so odometry
never integrates one wheel's motion without the other's.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from ohmni_tb.bus import ReplyPacket
from ohmni_tb.control.encoder import CountFilter, CountVerdict, WheelEncoder, WheelSample
from ohmni_tb.control.kinematics import Twist
from ohmni_tb.control.odometry import Odometry
from ohmni_tb.errors import OhmniError
from ohmni_tb.protocol import ReadReply
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import parse_count, read_count, wheel_command
from ohmni_tb.robot.samples import ENCODER_VEL_PERIOD_HZ, WheelEncoderSample, WheelOdomSample
from ohmni_tb.robot.schedule import CycleResult
from ohmni_tb.robot.state import RobotState

__all__ = ["TakenCounts", "WheelCounts"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class TakenCounts:
    """Both wheels' counts of one control slot, taken."""

    left: WheelSample
    right: WheelSample
    left_raw: int
    right_raw: int
    stamp_s: float


class WheelCounts:
    """Both wheels' encoders and the odometry they feed (module docstring)."""

    def __init__(self, state: RobotState) -> None:
        self._state = state
        config = state.config
        bus = state.bus
        left_cfg, right_cfg = config.encoders()
        self.wheels = (
            CountFilter(WheelEncoder(left_cfg), config.implausible_mps),
            CountFilter(WheelEncoder(right_cfg), config.implausible_mps),
        )
        self.odometry = Odometry(config.wheel_separation_m)
        self._frames = (config.frame_id_odom, config.frame_id_baselink)
        # A speed in m/s, forward positive → tb_control's ticks per 50 Hz period in the
        # board's own sense (the right board counts mirrored).
        self._vel_raw_per_mps = tuple(
            (-1.0 if cfg.mirrored else 1.0) / (cfg.metres_per_tick * ENCODER_VEL_PERIOD_HZ)
            for cfg in (left_cfg, right_cfg)
        )
        drive = self._drive = state.profile.drive
        self.reads = (
            read_count(DeviceId.LEFT_DRIVE, drive),
            read_count(DeviceId.RIGHT_DRIVE, drive),
        )
        self._unparsed = 0
        # Each count's time: when its read went on the wire, after the slot's command.
        self._write_cost_s = bus.cost_s(wheel_command(0, 0, drive))
        self._read_cost_s = bus.cost_s(self.reads[0])

    @property
    def rejected(self) -> int:
        """Counts received and not taken: unparsable or implausible."""
        return self._unparsed + sum(wheel.rejected for wheel in self.wheels)

    def speed_mps(self, index: int) -> float | None:
        """Wheel ``index``'s (0 left, 1 right) latest speed estimate, if it has one."""
        last = self.wheels[index].encoder.last
        return None if last is None else last.velocity_mps

    def take(self, result: CycleResult) -> TakenCounts | None:
        """A control slot's counts, both taken into the encoders, or ``None`` (neither)."""
        replies = result.replies
        t_left = result.started_s + self._write_cost_s
        t_right = t_left + self._read_cost_s
        self._state.topics["wheel_encoder"].note_lateness(result.started_s - result.due_s)
        # Both wheels or neither: an encoder that moved on alone would hand odometry an
        # increment the other wheel's never matches (the motion of a tick with one
        # failed read arrives whole with the next good pair).
        lw, rw = self.wheels
        raw_left = self._check(lw, replies[1], t_left)
        raw_right = self._check(rw, replies[2], t_right)
        if raw_left is None or raw_right is None:
            return None
        left = lw.take(raw_left, t_left)
        right = rw.take(raw_right, t_right)
        return TakenCounts(left, right, raw_left, raw_right, t_left)

    def publish(self, counts: TakenCounts, commanded: Twist, requested: Twist) -> None:
        """``wheel_encoder`` and ``wheel_odom`` from one slot's counts (``commanded``: the
        limited velocity target, ``requested``: what it was limited from, both carried in
        the odometry sample)."""
        topics = self._state.topics
        left, right, t_left = counts.left, counts.right, counts.stamp_s
        left_scale, right_scale = self._vel_raw_per_mps
        encoder = WheelEncoderSample(
            stamp_s=t_left,
            left_raw=counts.left_raw,
            right_raw=counts.right_raw,
            left_ticks=left.count,
            right_ticks=right.count,
            left_m=left.position_m,
            right_m=right.position_m,
            left_mps=left.velocity_mps,
            right_mps=right.velocity_mps,
            left_vel_raw=left.velocity_mps * left_scale,
            right_vel_raw=right.velocity_mps * right_scale,
        )
        if topics["wheel_encoder"].enabled:
            topics["wheel_encoder"].publish(encoder, t_left)
        odometry = self.odometry
        odom_topic = topics["wheel_odom"]
        if odometry.t_s is None or t_left > odometry.t_s:
            odometry.update(left.delta_m, right.delta_m, t_left)
            pose = odometry.pose
            twist = odometry.twist
            odom = WheelOdomSample(
                stamp_s=t_left,
                x_m=pose.x,
                y_m=pose.y,
                yaw_rad=pose.yaw,
                heading_rad=odometry.heading_rad,
                linear_mps=twist.linear_mps,
                angular_radps=twist.angular_radps,
                covariance=odometry.covariance_rows,
                commanded_linear_mps=commanded.linear_mps,
                commanded_angular_radps=commanded.angular_radps,
                requested_linear_mps=requested.linear_mps,
                requested_angular_radps=requested.angular_radps,
                frame_id=self._frames[0],
                child_frame_id=self._frames[1],
            )
            if odom_topic.enabled:
                odom_topic.publish(odom, t_left)

    def reset_odometry(self, x_m: float, y_m: float, yaw_rad: float) -> None:
        """Set the odometry pose (``Robot.reset_odometry``, checked there)."""
        self.odometry.reset(x_m, y_m, yaw_rad)

    def _check(self, wheel: CountFilter, reply: ReplyPacket | None, t: float) -> int | None:
        """The count in ``reply`` if it is one to take, else ``None`` (counted)."""
        if reply is None:
            return None
        try:
            raw = parse_count(ReadReply.parse(reply), self._drive)
        except OhmniError:
            self._unparsed += 1
            return None
        verdict = wheel.check(raw, t)
        if verdict is CountVerdict.TAKE:
            return raw
        if verdict is CountVerdict.REBASED:
            # The count really moved (a board reset): it starts again from here.
            _log.warning("wheel count jumped for %d reads in a row: new origin", wheel.rebase_after)
        return None
