"""What the Robot's streams carry: one frozen dataclass per stream, named like tb_control's.

Every sample has ``stamp_s``: the event loop's clock (monotonic) at the moment the data
was taken — for bus reads, when the request went on the wire, not when the host saw the
reply (a USB adapter may hold replies up to 16 ms).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal, TypeAlias

from ohmni_tb.control.defaults import (
    CONTROL_HZ_RANGE,
    DEFAULT_BASE_FRAME,
    DEFAULT_ODOM_FRAME,
    PID_RATE_HZ,
)
from ohmni_tb.control.pid import PidStep
from ohmni_tb.herkulex import TorqueControl
from ohmni_tb.protocol.messages import StatusDetail, StatusError
from ohmni_tb.protocol.worm_neck import WormFlags

__all__ = [
    "ENCODER_POSITION_MODULUS",
    "ENCODER_VEL_PERIOD_HZ",
    "POSE_UNOBSERVED_VARIANCE",
    "POSE_VARIANCE_FLOOR",
    "STREAMS",
    "STREAM_NAMES",
    "TWIST_COVARIANCE",
    "DiagnosticEntry",
    "DiagnosticLevel",
    "DiagnosticValue",
    "DiagnosticsSample",
    "Link",
    "PidDebugSample",
    "RobotStateSample",
    "Sample",
    "ServoSample",
    "StreamSpec",
    "TbcoreStatusSample",
    "WheelEncoderSample",
    "WheelOdomSample",
    "WormNeckSample",
]


#: tb_control's wheel positions are on 0..2¹² (``motor_left_pos``, ``motor_right_pos``).
ENCODER_POSITION_MODULUS = 1 << 12
#: tb_control's control rate, whose period is the unit of its wheel speeds
#: (``motor_left_vel``: ticks per 50 Hz period).
ENCODER_VEL_PERIOD_HZ = PID_RATE_HZ
#: The variance given to what wheel odometry cannot observe — z, roll and pitch in the
#: pose, z speed, roll and pitch rates in the twist: large, so a filter fusing the
#: odometry (robot_localization, robot_pose_ekf) ignores it, as diff-drive drivers do.
POSE_UNOBSERVED_VARIANCE = 1e6
#: The least variance of x, y (m²) and yaw (rad²) in ``pose_covariance``: 1 mm and 1 mrad.
#: The odometry's own covariance starts at zero where the Robot opened; a filter that
#: inverts the matrix needs it positive.
POSE_VARIANCE_FLOOR = 1e-6
#: Forward and sideways speed variance in ``twist_covariance``, (m/s)²: ~3 cm/s, the
#: wheel speed estimate's spread under slip and its 0.1 s window. Sideways the robot
#: cannot move (a diff drive): the same small value says so.
_SPEED_VARIANCE = 1e-3
#: Yaw-rate variance, (rad/s)²: two wheels' speed variance over the separation squared
#: (2 × 1e-3 / 0.33²).
_YAW_RATE_VARIANCE = 0.02


def _diagonal(*variances: float) -> tuple[float, ...]:
    """A 6×6 row-major matrix with ``variances`` on its diagonal."""
    return tuple(variances[row] if row == col else 0.0 for row in range(6) for col in range(6))


#: ``wheel_odom``'s twist covariance, 6×6 row-major over (vx, vy, vz, wx, wy, wz) in
#: the body frame: one shared tuple (nav_msgs/Odometry's ``twist.covariance``).
TWIST_COVARIANCE: tuple[float, ...] = _diagonal(
    _SPEED_VARIANCE,
    _SPEED_VARIANCE,
    POSE_UNOBSERVED_VARIANCE,
    POSE_UNOBSERVED_VARIANCE,
    POSE_UNOBSERVED_VARIANCE,
    _YAW_RATE_VARIANCE,
)
#: Where the 3×3 (x, y, yaw) covariance's entries go in the 6×6 (x, y, z, roll, pitch,
#: yaw) one, row-major.
_POSE_SLOTS = tuple(row * 6 + col for row in (0, 1, 5) for col in (0, 1, 5))
#: The pose covariance's unobserved part: z, roll and pitch.
_POSE_UNOBSERVED = _diagonal(
    0.0, 0.0, POSE_UNOBSERVED_VARIANCE, POSE_UNOBSERVED_VARIANCE, POSE_UNOBSERVED_VARIANCE, 0.0
)


@dataclass(frozen=True, slots=True)
class WheelEncoderSample:
    """Both wheel counters and speeds (``wheel_encoder``, 50 Hz).

    Attributes:
        stamp_s: When the left count was read.
        left_raw: The left board's accumulated count as read (int32).
        right_raw: The right board's, as read (it counts mirrored).
        left_ticks: Left count since the Robot opened, forward positive.
        right_ticks: Right count since the Robot opened, forward positive.
        left_m: Distance the left rim rolled since the Robot opened.
        right_m: The right rim's.
        left_mps: Left rim speed estimate.
        right_mps: Right rim speed estimate.
        left_vel_raw: tb_control's ``motor_left_vel``: the left count's speed estimate in
            ticks per 50 Hz period (ticks/s ÷ 50, whatever ``wheel_hz`` is), in the
            board's own sense, like ``left_raw``.
        right_vel_raw: tb_control's ``motor_right_vel``: the right board's, in its own
            sense (negative while the robot drives forward: it counts mirrored).
    """

    stamp_s: float
    left_raw: int
    right_raw: int
    left_ticks: int
    right_ticks: int
    left_m: float
    right_m: float
    left_mps: float
    right_mps: float
    left_vel_raw: float
    right_vel_raw: float

    @property
    def left_pos_raw(self) -> int:
        """tb_control's ``motor_left_pos``: the left count as read, on 0..4095
        (``left_raw`` modulo 2¹²)."""
        return self.left_raw % ENCODER_POSITION_MODULUS

    @property
    def right_pos_raw(self) -> int:
        """tb_control's ``motor_right_pos``: the right count as read, on 0..4095."""
        return self.right_raw % ENCODER_POSITION_MODULUS


@dataclass(frozen=True, slots=True)
class WheelOdomSample:
    """Wheel odometry (``wheel_odom``, 50 Hz): pose in the odometry frame and body speed.

    Attributes:
        stamp_s: Time of the wheel counts it integrates.
        x_m: Position, metres.
        y_m: Position, metres.
        yaw_rad: Heading, wrapped into (−π, π].
        heading_rad: Heading, unwrapped (counts whole turns).
        linear_mps: Forward speed.
        angular_radps: Yaw rate, counter-clockwise positive.
        covariance: 3 × 3 covariance of (x, y, yaw), row-major.
        commanded_linear_mps: The limited command the wheels were following: the twist
            the limiter made of the request this control tick, within the speed and
            acceleration limits (diff_drive_controller's ``publish_limited_velocity``);
            0 while nothing drives or the PWM is open loop.
        commanded_angular_radps: Its yaw rate.
        requested_linear_mps: The request it was made from: the last ``drive`` command
            as given (``drive_wheels``: the twist of the wheel speeds asked), before any
            limit; 0 after a stop (``stop()``, the watchdog, an emergency stop …) and
            while the PWM is open loop.
        requested_angular_radps: Its yaw rate.
        frame_id: The frame the pose is in (``frame_id_odom``; tb_control's
            ``header.frame_id``).
        child_frame_id: The robot's body frame (``frame_id_baselink``).
    """

    stamp_s: float
    x_m: float
    y_m: float
    yaw_rad: float
    heading_rad: float
    linear_mps: float
    angular_radps: float
    covariance: tuple[float, ...]
    commanded_linear_mps: float
    commanded_angular_radps: float
    requested_linear_mps: float = 0.0
    requested_angular_radps: float = 0.0
    frame_id: str = DEFAULT_ODOM_FRAME
    child_frame_id: str = DEFAULT_BASE_FRAME

    @property
    def orientation(self) -> tuple[float, float, float, float]:
        """The heading as a unit quaternion ``(x, y, z, w)``, about the z axis."""
        half = 0.5 * self.yaw_rad
        return (0.0, 0.0, math.sin(half), math.cos(half))

    @property
    def pose_covariance(self) -> tuple[float, ...]:
        """6×6 row-major covariance of (x, y, z, roll, pitch, yaw), as nav_msgs/Odometry's
        ``pose.covariance``: the x, y, yaw block is :attr:`covariance` (it grows with the
        distance rolled) with at least :data:`POSE_VARIANCE_FLOOR` on its diagonal; z,
        roll and pitch, which wheels cannot observe, get :data:`POSE_UNOBSERVED_VARIANCE`."""
        matrix = list(_POSE_UNOBSERVED)
        for slot, value in zip(_POSE_SLOTS, self.covariance, strict=True):
            matrix[slot] = value
        for slot in (0, 7, 35):
            matrix[slot] = max(matrix[slot], POSE_VARIANCE_FLOOR)
        return tuple(matrix)

    @property
    def twist_covariance(self) -> tuple[float, ...]:
        """6×6 row-major covariance of (vx, vy, vz, wx, wy, wz), as nav_msgs/Odometry's
        ``twist.covariance``: the fixed :data:`TWIST_COVARIANCE` (one shared tuple)."""
        return TWIST_COVARIANCE


@dataclass(frozen=True, slots=True)
class TbcoreStatusSample:
    """Battery and dock (``tbcore_status``, 10 Hz).

    Attributes:
        stamp_s: When it was read.
        cell_v: The five cell voltages.
        pack_v: Pack voltage (sum of the cells).
        current_a: Pack current; positive while charging.
        docked: On the dock.
        charging: Current flows into the pack.
        percent: The vendor's coarse state of charge (20, 50, 80 or 100).
        fet_status: Charge/discharge FET bits as reported.
        status: Status bytes 1..4 as reported.
    """

    stamp_s: float
    cell_v: tuple[float, ...]
    pack_v: float
    current_a: float
    docked: bool
    charging: bool
    percent: int
    fet_status: int
    status: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class ServoSample:
    """A HerkuleX servo's feedback (``servo_neck``, ``servo_ext1``, ``servo_ext2``; 30 Hz).

    Attributes:
        stamp_s: When it was read.
        sid: The servo's id.
        position_raw: Calibrated position, 0..1023.
        angle_rad: Its angle (0 at 512 + the zero offset).
        temperature_raw: The temperature sensor, raw (compare with the servo's max).
        voltage_v: Supply voltage.
        torque: Torque mode (free, brake, on).
        status_error: RAM 48 error bits.
        status_detail: RAM 49 detail bits (moving, in position, motor on …).
        position_raw_cmd: The last position target this Robot sent the servo, raw;
            ``None`` before its first move.
        pos_rad_cmd: That target in radians (tb_control's ``servo_pos_rad_cmd``, with
            the zero offset of ``angle_rad``); ``None`` before the first move.
        torque_cmd: The last torque mode this Robot set (tb_control's ``torque_cmd``);
            ``None`` before it set one.
    """

    stamp_s: float
    sid: int
    position_raw: int
    angle_rad: float
    temperature_raw: int
    voltage_v: float
    torque: TorqueControl
    status_error: StatusError
    status_detail: StatusDetail
    position_raw_cmd: int | None = None
    pos_rad_cmd: float | None = None
    torque_cmd: TorqueControl | None = None

    @property
    def moving(self) -> bool:
        """The servo is moving."""
        return bool(self.status_detail & StatusDetail.MOVING)


@dataclass(frozen=True, slots=True)
class WormNeckSample:
    """The worm-gear neck's feedback (``new_neck``, 30 Hz).

    It has the shape of the HerkuleX neck's sample, as tb_control's ``new_neck``: but the
    worm gear's raw units have no known angle (its gear and zero are not public), so
    :attr:`pos_rad` and :attr:`pos_rad_cmd` are always ``None``; and it has no torque
    mode to command (the worm gear holds its position without power), so
    :attr:`torque_cmd` is always ``None``. The last target is :attr:`position_raw_cmd`.

    Attributes:
        stamp_s: When it was read.
        position_raw: −127000 (up) … 120000 (down).
        flags: Moving / stalled.
        position_raw_cmd: The last target this Robot sent, raw; ``None`` before the
            first move.
    """

    stamp_s: float
    position_raw: int
    flags: WormFlags
    position_raw_cmd: int | None = None

    @property
    def pos_rad(self) -> None:
        """Always ``None``: no angle is known for the worm gear's raw units."""
        return None

    @property
    def pos_rad_cmd(self) -> None:
        """Always ``None``: no angle is known for the worm gear's raw units."""
        return None

    @property
    def torque_cmd(self) -> None:
        """Always ``None``: the worm gear has no torque mode to command."""
        return None

    @property
    def moving(self) -> bool:
        """Travelling to its target."""
        return bool(self.flags & WormFlags.MOVING)

    @property
    def stalled(self) -> bool:
        """The motor stalled (only a power cycle clears it)."""
        return bool(self.flags & WormFlags.STALLED)


class Link(enum.StrEnum):
    """The state of the Robot's serial link."""

    #: The port is open and the schedule runs.
    CONNECTED = "connected"
    #: The link failed; the Robot reopens it (``reconnect``).
    LOST = "lost"
    #: Handed to another program (:meth:`Robot.release_port`): the port is closed until
    #: :meth:`Robot.reclaim_port` (or the release's ``duration_s``) takes it back.
    RELEASED = "released"
    #: The Robot was closed.
    CLOSED = "closed"


@dataclass(frozen=True, slots=True)
class RobotStateSample:
    """The Robot's own state (``robot_state``: on every change and at ``state_hz``).

    Attributes:
        stamp_s: When it was published.
        link: The serial link (``released`` while another program has the port).
        estopped: An emergency stop is latched (:meth:`Robot.clear_estop`).
        watchdog_tripped: No drive command for ``watchdog_s``: the wheels were stopped.
        faults: What is wrong now, short names: ``stale_feedback``, ``link_lost``,
            ``thermal:<sid>``, ``drive_absent:<sid>``, ``wheel_stall:<sid>`` (a wheel
            driven did not turn: the wheels are held stopped), ``wheel_slip:<sid>`` (the
            wheels off the commanded curve), ``neck_settings:<sid>``, ``neck_stalled``,
            ``battery_implausible`` (the battery block does not read as a pack: the
            profile's battery settings are likely not this robot's).
        neck: ``herkulex``, ``worm`` or ``none`` (found at open).
        present: Ids of the devices that answer.
        absent: Ids of expected devices that do not (re-probed slowly).
        event: What changed, in words (``None`` on a periodic sample).
        active_source: The command source that drives (``"local"``, ``"remote"``…: the
            highest one live, whose drive commands are taken), or ``None`` when none is
            live (``command_sources``; a change is published with an event).
    """

    stamp_s: float
    link: Link
    estopped: bool
    watchdog_tripped: bool
    faults: tuple[str, ...]
    neck: str
    present: tuple[int, ...]
    absent: tuple[int, ...]
    event: str | None = None
    active_source: str | None = None


@dataclass(frozen=True, slots=True)
class PidDebugSample:
    """Both wheel PID steps of one control tick (``pid_debug``, on request).

    Attributes:
        stamp_s: Time of the wheel counts the step used.
        left: The left wheel's terms (setpoint, feedback, p, i, d, feed-forward, output).
        right: The right wheel's.
    """

    stamp_s: float
    left: PidStep
    right: PidStep


class DiagnosticLevel(enum.StrEnum):
    """How a ``diagnostics`` entry stands (ROS's diagnostic levels), best first."""

    #: Working as it should.
    OK = "ok"
    #: Working, but something is worth a look (the message says what).
    WARN = "warn"
    #: Not working: a fault, a silent or absent device, a lost link.
    ERROR = "error"

    @property
    def rank(self) -> int:
        """0, 1, 2 for OK, WARN, ERROR: the larger, the worse."""
        return _LEVEL_RANK[self]

    @classmethod
    def worst(cls, levels: Iterable[DiagnosticLevel]) -> DiagnosticLevel:
        """The worst of ``levels`` (``OK`` when there are none)."""
        return max(levels, key=_LEVEL_RANK.__getitem__, default=cls.OK)


_LEVEL_RANK: Mapping[DiagnosticLevel, int] = MappingProxyType(
    {level: rank for rank, level in enumerate(DiagnosticLevel)}
)
#: A value of a ``diagnostics`` entry: a number, a word, a flag, or ``None`` (not known).
DiagnosticValue: TypeAlias = bool | int | float | str | None


@dataclass(frozen=True, slots=True)
class DiagnosticEntry:
    """One device's health, or the link's, in a ``diagnostics`` sample.

    Attributes:
        name: Which: ``left_drive``, ``right_drive``, ``core``, ``neck`` (HerkuleX or worm
            gear: ``sid`` says which), ``ext1``, ``ext2`` (the external servos) or
            ``link``.
        sid: The device's bus id; ``None`` for the link.
        level: OK, WARN or ERROR, by the thresholds of :mod:`ohmni_tb.robot.diagnostics`.
        message: What stands out, in words (``"ok"`` when nothing does).
        values: Its figures by name (docs/robot.md lists them): firmware, reply latency,
            timeouts, battery cells, temperature, load …; ``None`` where not known.
    """

    name: str
    sid: int | None
    level: DiagnosticLevel
    message: str
    values: dict[str, DiagnosticValue]


@dataclass(frozen=True, slots=True)
class DiagnosticsSample:
    """The robot's health (``diagnostics``, 1 Hz: ``diagnostics_hz``): one entry per device
    the robot expects and one for the link.

    Attributes:
        stamp_s: When it was taken.
        level: The worst level of the entries.
        entries: Each device's entry (the drive boards, the core board, the neck, each
            external servo), then the link's.
        event: The levels that changed since the previous sample, in words (``None``
            when none did).
    """

    stamp_s: float
    level: DiagnosticLevel
    entries: tuple[DiagnosticEntry, ...]
    event: str | None = None

    def entry(self, key: str | int) -> DiagnosticEntry | None:
        """The entry named ``key`` (``"link"``, ``"core"`` …), or of the device with bus id
        ``key``; ``None`` when there is none."""
        field = "sid" if isinstance(key, int) and not isinstance(key, bool) else "name"
        return next((e for e in self.entries if getattr(e, field) == key), None)


Sample = (
    WheelEncoderSample
    | WheelOdomSample
    | TbcoreStatusSample
    | ServoSample
    | WormNeckSample
    | RobotStateSample
    | PidDebugSample
    | DiagnosticsSample
)


@dataclass(frozen=True, slots=True)
class StreamSpec:
    """What one stream is: the one table (:data:`STREAMS`) the Robot, the daemon, its
    client, the Foxglove bridge and the documentation read.

    Attributes:
        name: The stream's name (tb_control's topic name).
        sample_type: The dataclass its samples are.
        source: Where its samples come from: ``"control"``, the control slot's wheel
            counts (its rate is the control tick's); ``"derived"``, computed from another
            stream's reads (:attr:`follows`); ``"polled"``, reads of its own on the
            schedule; ``"state"``, the Robot's own state or health, at a steady rate
            (``robot_state`` also on every change).
        rate_setting: The :class:`~ohmni_tb.config.RobotConfig` field with its rate.
        rate_range_hz: What :meth:`Robot.set_rate` takes for it, or None when its rate is
            not set on its own (a derived stream follows its source; the state's rate is
            a setting only).
        follows: For a derived stream, the stream whose reads it is computed from.
        tb_control: The vendor node's topic for it, if it has one.
    """

    name: str
    sample_type: type[Sample]
    source: Literal["control", "derived", "polled", "state"]
    rate_setting: str
    rate_range_hz: tuple[float, float] | None
    follows: str | None = None
    tb_control: str | None = None

    @property
    def polled(self) -> bool:
        """Whether it has bus reads of its own whose rate can be set."""
        return self.rate_range_hz is not None


#: A polled feedback stream's rate range for :meth:`Robot.set_rate`, Hz: the top of
#: its setting's range (0, off, is :meth:`Robot.enable_stream`'s job).
_SERVO_HZ = (0.1, 50.0)


def _table(*specs: StreamSpec) -> Mapping[str, StreamSpec]:
    return MappingProxyType({spec.name: spec for spec in specs})


#: Every stream of a Robot, in schedule order: the one declaration of the streams.
STREAMS: Mapping[str, StreamSpec] = _table(
    StreamSpec(
        "wheel_encoder",
        WheelEncoderSample,
        "control",
        "wheel_hz",
        CONTROL_HZ_RANGE,
        tb_control="/tb_control/wheel_encoder",
    ),
    StreamSpec(
        "wheel_odom",
        WheelOdomSample,
        "derived",
        "wheel_hz",
        None,
        follows="wheel_encoder",
        tb_control="/tb_control/wheel_odom",
    ),
    StreamSpec(
        "tbcore_status",
        TbcoreStatusSample,
        "polled",
        "core_hz",
        (0.1, 20.0),
        tb_control="/tb_control/tbcore_status",
    ),
    StreamSpec(
        "servo_neck",
        ServoSample,
        "polled",
        "servo_hz",
        _SERVO_HZ,
        tb_control="/tb_control/servo/neck",
    ),
    StreamSpec(
        "servo_ext1",
        ServoSample,
        "polled",
        "servo_hz",
        _SERVO_HZ,
        tb_control="/tb_control/servo/ext1",
    ),
    StreamSpec(
        "servo_ext2",
        ServoSample,
        "polled",
        "servo_hz",
        _SERVO_HZ,
        tb_control="/tb_control/servo/ext2",
    ),
    StreamSpec(
        "new_neck",
        WormNeckSample,
        "polled",
        "new_neck_hz",
        _SERVO_HZ,
        tb_control="/tb_control/servo/new_neck",
    ),
    StreamSpec("robot_state", RobotStateSample, "state", "state_hz", None),
    StreamSpec(
        "pid_debug",
        PidDebugSample,
        "derived",
        "wheel_hz",
        None,
        follows="wheel_encoder",
        tb_control="/tb_control/motor_pid_debug",
    ),
    StreamSpec("diagnostics", DiagnosticsSample, "state", "diagnostics_hz", None),
)
#: Every stream's name, in schedule order.
STREAM_NAMES: tuple[str, ...] = tuple(STREAMS)
