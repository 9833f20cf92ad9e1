"""Simulated drive train: two motors with inertia, friction and a dead band, encoders,
and the robot's ground-truth pose.

Each wheel follows a DC-motor model in terms of its rim speed ``v`` (m/s)::

    dv/dt = accel * (duty - v / v_free) - coulomb * sign(v) - viscous * v

``duty`` is the board's PWM / 1000. Back-EMF (the ``v / v_free`` term) sets the no-load
top speed; Coulomb friction makes a dead band — at rest the wheel does not move until
``accel * |duty|`` beats ``coulomb`` (duty ≈ 0.06 by default) — and brings a coasting
wheel to a stop. Brake mode shorts the motor (strong damping); free mode cuts the drive.
The model is integrated in fixed 1 ms sub-steps; the pose integrates the true wheel
motion with exact arcs, so it is the ground truth that odometry is judged against.

A wheel can be blocked (:meth:`DriveTrain.block`, ``SimRobot.block_wheels``): an
obstacle holds it, so it stands still whatever the PWM, and its motor draws the stall
current of its duty (``motor_current_a``) until it is freed.

A wheel can lose its traction (:meth:`DriveTrain.slip`, ``SimRobot.slip_wheels``): on a
slippery patch, or lifted, it still turns and its encoder counts, but it no longer moves
the robot — the ground-truth pose moves as if that wheel's ground speed were zero, so
the robot pivots about it — and it turns free of the robot's load: its motor drives only
the wheel's own inertia (:data:`FREE_INERTIA_SHARE` of the loaded one) against the
drivetrain's own friction (:data:`FREE_FRICTION_SHARE` of the dead band; the ground's
rolling drag is the rest). So, at the same PWM, it runs faster than a wheel on the ground.

Board frame vs robot frame: each board counts up when driven with positive PWM. The
right motor is mounted mirrored (``DriveProfile.right_mirrored``), so the right wheel
moves the robot *forward* when its board turns *negative* — the vendor's
``move(700, -700)`` drives forward. The boards read the wheel command with the same
:class:`~ohmni_tb.protocol.drive.DriveProfile` as the host builds it with, so a change to
the table changes both sides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ohmni_tb.errors import MalformedReplyError
from ohmni_tb.protocol import BROADCAST_ID, Packet
from ohmni_tb.protocol.drive import (
    DRIVE_PROFILE,
    MOTOR_POSITION_MODULUS,
    PWM_LIMIT,
    DriveProfile,
    DriveTorque,
    decode_wheel_command,
)
from ohmni_tb.sim.board import BoardRegister, SimBoard

__all__ = [
    "FREE_FRICTION_SHARE",
    "FREE_INERTIA_SHARE",
    "DriveTrain",
    "MotorModel",
    "Pose",
    "SimDriveBoard",
]

#: Integration step of the motor model.
_STEP_S = 0.001
#: Motor encoder ticks per motor turn: the 14-bit motor position's modulus (an alias of
#: the one definition in protocol.drive).
TICKS_PER_MOTOR_TURN = MOTOR_POSITION_MODULUS
#: Motor turns per wheel turn (30/11, inferred from measurements).
GEAR_RATIO = 30 / 11
#: A wheel without traction (:meth:`DriveTrain.slip`) carries this share of the inertia it
#: carries on the ground (its own, not the robot's), and keeps this share of its
#: friction (the gearbox's: the ground's rolling drag is gone). Assumed, not measured.
FREE_INERTIA_SHARE = 0.1
FREE_FRICTION_SHARE = 0.25


@dataclass(frozen=True, slots=True)
class MotorModel:
    """Parameters of one wheel's drive.

    Attributes:
        accel_mps2: Acceleration at full duty from standstill.
        v_free_mps: Back-EMF speed: the speed where full duty gives no torque.
        coulomb_mps2: Friction deceleration (sets the dead band: coulomb / accel).
        viscous_per_s: Viscous friction coefficient.
        brake_per_s: Damping in brake mode.
        wheel_radius_m: True wheel radius.
    """

    accel_mps2: float = 8.0
    v_free_mps: float = 1.0 / (1 - 0.06)
    coulomb_mps2: float = 8.0 * 0.06
    viscous_per_s: float = 0.0
    brake_per_s: float = 40.0
    wheel_radius_m: float = 0.0760

    def free(self) -> MotorModel:
        """The same wheel off the ground (or with no grip): :data:`FREE_INERTIA_SHARE` of
        the inertia, :data:`FREE_FRICTION_SHARE` of the friction (its brake and back-EMF
        act on the lighter wheel alike)."""
        lighter = 1.0 / FREE_INERTIA_SHARE
        return MotorModel(
            accel_mps2=self.accel_mps2 * lighter,
            v_free_mps=self.v_free_mps,
            coulomb_mps2=self.coulomb_mps2 * FREE_FRICTION_SHARE * lighter,
            viscous_per_s=self.viscous_per_s * lighter,
            brake_per_s=self.brake_per_s * lighter,
            wheel_radius_m=self.wheel_radius_m,
        )

    @property
    def dead_band_duty(self) -> float:
        """The smallest duty that starts a wheel at rest."""
        return self.coulomb_mps2 / self.accel_mps2

    @property
    def top_speed_mps(self) -> float:
        """No-load top speed at full duty."""
        a, v0, c, b = self.accel_mps2, self.v_free_mps, self.coulomb_mps2, self.viscous_per_s
        return (a - c) / (a / v0 + b)


@dataclass(frozen=True, slots=True)
class Pose:
    """A planar pose: metres and radians (yaw unwrapped)."""

    x: float
    y: float
    yaw: float


class _Wheel:
    __slots__ = ("blocked", "count_offset", "duty", "slipping", "speed_mps", "torque", "turns")

    def __init__(self, count_offset: int) -> None:
        self.duty = 0.0  # board frame
        self.speed_mps = 0.0  # board frame, rim speed
        self.turns = 0.0  # board frame, wheel turns since start
        self.torque = DriveTorque.ON
        self.count_offset = count_offset
        self.blocked = False  # an obstacle holds the wheel still
        self.slipping = False  # no traction: it turns, the robot does not follow

    def step(self, model: MotorModel, dt: float) -> float:
        """Advance ``dt``; return the rim distance travelled (board frame)."""
        if self.blocked:
            self.speed_mps = 0.0
            return 0.0
        v = self.speed_mps
        if self.torque is DriveTorque.ON:
            drive = model.accel_mps2 * (self.duty - v / model.v_free_mps)
        elif self.torque is DriveTorque.BRAKE:
            drive = -model.brake_per_s * v
        else:
            drive = 0.0
        friction = model.coulomb_mps2
        if v == 0.0:
            # Static friction holds the wheel until the drive beats it.
            if abs(drive) <= friction:
                return 0.0
            accel = drive - math.copysign(friction, drive)
        else:
            accel = drive - math.copysign(friction, v) - model.viscous_per_s * v
        new_v = v + accel * dt
        if v != 0.0 and new_v * v < 0.0 and abs(drive) <= friction:
            # Friction stops the wheel; it does not reverse it.
            new_v = 0.0
        self.speed_mps = new_v
        distance = 0.5 * (v + new_v) * dt
        self.turns += distance / (2 * math.pi * model.wheel_radius_m)
        return distance

    @property
    def motor_ticks(self) -> int:
        return math.floor(self.turns * GEAR_RATIO * TICKS_PER_MOTOR_TURN)


class DriveTrain:
    """Both wheels and the chassis: the physics shared by the two drive boards.

    Args:
        model: Motor and wheel parameters.
        wheel_separation_m: True distance between the wheels.
        count_offsets: Initial accumulated counts (board frame) of the left and right
            boards, e.g. near 2**31 to exercise the int32 wrap.
        profile: The drive boards' table: how they read the wheel command, and whether
            the right motor is mounted mirrored. Both boards of the train use it.
    """

    def __init__(
        self,
        model: MotorModel | None = None,
        *,
        wheel_separation_m: float = 0.330,
        count_offsets: tuple[int, int] = (0, 0),
        profile: DriveProfile = DRIVE_PROFILE,
    ) -> None:
        self.model = model or MotorModel()
        self._free_model = self.model.free()
        self.profile = profile
        # Board frame → robot frame for the right wheel.
        self._right_sign = -1.0 if profile.right_mirrored else 1.0
        self.wheel_separation_m = wheel_separation_m
        self.wheels = (_Wheel(count_offsets[0]), _Wheel(count_offsets[1]))
        self._x = 0.0
        self._y = 0.0
        self._yaw = 0.0
        self._now_s = 0.0
        # Robot frame, forward-positive, left and right: each wheel's travel over the
        # ground (none while it slips).
        self.distance_m = [0.0, 0.0]

    @property
    def pose(self) -> Pose:
        """The true pose (yaw unwrapped)."""
        return Pose(self._x, self._y, self._yaw)

    def wheel_speeds_mps(self) -> tuple[float, float]:
        """True forward speed of the left and right wheel (robot frame)."""
        left, right = self.wheels
        return left.speed_mps, self._right_sign * right.speed_mps

    def set_duty(self, side: int, pwm: int) -> None:
        """Set a board's PWM (board frame, −1000..1000)."""
        self.wheels[side].duty = max(-PWM_LIMIT, min(PWM_LIMIT, pwm)) / PWM_LIMIT

    def block(self, side: int, blocked: bool) -> None:
        """Hold a wheel still (an obstacle against it), or free it: while blocked it does
        not turn whatever the PWM, and stops at once when blocked while turning."""
        wheel = self.wheels[side]
        wheel.blocked = blocked
        if blocked:
            wheel.speed_mps = 0.0

    def blocked(self) -> tuple[bool, bool]:
        """Whether the left and the right wheel are blocked."""
        left, right = self.wheels
        return left.blocked, right.blocked

    def slip(self, side: int, slipping: bool) -> None:
        """Take a wheel's traction away (a slippery patch, the wheel lifted), or give it
        back: while slipping it turns (and counts) free of the robot's load, and the
        robot moves as if that wheel stood (module docstring)."""
        self.wheels[side].slipping = slipping

    def slipping(self) -> tuple[bool, bool]:
        """Whether the left and the right wheel have lost their traction."""
        left, right = self.wheels
        return left.slipping, right.slipping

    def motor_current_a(self) -> float:
        """Rough motor current drawn from the pack (for the battery sag): a motor held
        still (a blocked wheel, or one starting) draws its duty's stall current."""
        total = 0.0
        for wheel in self.wheels:
            if wheel.torque is DriveTorque.ON:
                torque_share = abs(wheel.duty - wheel.speed_mps / self.model.v_free_mps)
                total += 0.5 + 6.0 * min(1.0, torque_share)
        return total

    def count(self, side: int) -> int:
        """A board's accumulated count as the register holds it: int32, wrapping."""
        raw = self.wheels[side].motor_ticks + self.wheels[side].count_offset
        return (raw + 2**31) % 2**32 - 2**31

    def motor_position(self, side: int) -> int:
        """A board's 14-bit motor position."""
        return (self.wheels[side].motor_ticks + self.wheels[side].count_offset) % (
            MOTOR_POSITION_MODULUS
        )

    def advance(self, now_s: float) -> None:
        """Integrate up to ``now_s`` (idempotent for the same time)."""
        while self._now_s < now_s:
            if self._held():
                # Nothing moves until a command changes: skip the sub-steps, so an idle
                # robot costs nothing however far virtual time jumps.
                self._now_s = now_s
                return
            dt = min(_STEP_S, now_s - self._now_s)
            left, right = self.wheels
            model, free = self.model, self._free_model
            d_left = left.step(free if left.slipping else model, dt)
            d_right = self._right_sign * right.step(free if right.slipping else model, dt)
            # A wheel without traction turns; the ground under it does not move.
            if left.slipping:
                d_left = 0.0
            if right.slipping:
                d_right = 0.0
            self.distance_m[0] += d_left
            self.distance_m[1] += d_right
            self._integrate(d_left, d_right)
            self._now_s += dt

    def _held(self) -> bool:
        """Both wheels at rest, held there by static friction (``_Wheel.step`` is a no-op)."""
        return all(
            w.blocked
            or (
                w.speed_mps == 0.0
                and (
                    w.torque is not DriveTorque.ON
                    or (m := self._free_model if w.slipping else self.model).accel_mps2
                    * abs(w.duty)
                    <= m.coulomb_mps2
                )
            )
            for w in self.wheels
        )

    def _integrate(self, d_left: float, d_right: float) -> None:
        ds = 0.5 * (d_left + d_right)
        dyaw = (d_right - d_left) / self.wheel_separation_m
        if abs(dyaw) < 1e-9:
            self._x += ds * math.cos(self._yaw + 0.5 * dyaw)
            self._y += ds * math.sin(self._yaw + 0.5 * dyaw)
        else:
            radius = ds / dyaw
            self._x += radius * (math.sin(self._yaw + dyaw) - math.sin(self._yaw))
            self._y -= radius * (math.cos(self._yaw + dyaw) - math.cos(self._yaw))
        self._yaw += dyaw


class SimDriveBoard(SimBoard):
    """One drive board (sid 0 left, 1 right) on a shared :class:`DriveTrain`."""

    def __init__(self, side: int, train: DriveTrain, tag: str = "sim-drive-1.0") -> None:
        super().__init__(side, tag)
        self.side = side
        self.train = train
        p = train.profile
        self.ram[p.count_addr] = BoardRegister(
            p.count_size, lambda: train.count(side).to_bytes(4, "little", signed=True)
        )
        self.ram[p.motor_position_addr] = BoardRegister(
            p.motor_position_size, lambda: train.motor_position(side).to_bytes(2, "little")
        )
        self.ram[60] = self.ram[p.motor_position_addr]
        self.ram[62] = BoardRegister(2, self._differential)
        self.ram[p.torque_addr] = BoardRegister(1, self._torque_bytes, self._set_torque)
        # Polled by the vendor's driver; its meaning is unknown, so it reads as zero.
        self.ram[0x6B] = BoardRegister(1, lambda: b"\x00")
        # The bus id (assumed HerkuleX-like, DriveProfile.id_eep_addr): the EEP copy is
        # what the board takes at power-up, the RAM one what it answers to now.
        self.boot_sid = side
        self.eep[p.id_eep_addr] = BoardRegister(
            1, lambda: bytes((self.boot_sid,)), self._set_boot_id
        )
        self.ram[p.id_ram_addr] = BoardRegister(1, lambda: bytes((self.sid,)), self._set_id)

    def advance(self, now_s: float) -> None:
        self.train.advance(now_s)

    def power_cycle(self, now_s: float) -> None:
        self.sid = self.boot_sid
        wheel = self.train.wheels[self.side]
        wheel.duty = 0.0
        wheel.torque = DriveTorque.ON
        self.status_error = type(self.status_error).NONE
        self.status_detail = type(self.status_detail).NONE

    def handle_foreign(self, packet: Packet, now_s: float) -> Packet | None:
        if packet.cmd == self.train.profile.wheel_form:
            self.handle_jog(packet, now_s)
        return None

    def handle_jog(self, packet: Packet, now_s: float) -> None:
        try:
            # The tag naming the id it answers to now (a board given another id no
            # longer takes the wheel command of its old one).
            pwm = decode_wheel_command(packet, self.train.profile).get(self.sid)
        except MalformedReplyError:
            # Not the wheel command the profile describes (or a broken one): a board
            # skips what it cannot read, as it does a jog for a servo.
            return
        if pwm is not None:
            self.train.set_duty(self.side, pwm)

    def _differential(self) -> bytes:
        # Rim speed as motor ticks per 11.2 ms tick, signed (HerkuleX-like).
        wheel = self.train.wheels[self.side]
        m = self.train.model
        ticks_per_s = (
            wheel.speed_mps / (2 * math.pi * m.wheel_radius_m) * GEAR_RATIO * TICKS_PER_MOTOR_TURN
        )
        value = max(-32768, min(32767, round(ticks_per_s * 0.0112)))
        return value.to_bytes(2, "little", signed=True)

    def _set_boot_id(self, data: bytes) -> None:
        if data[0] < BROADCAST_ID:
            self.boot_sid = data[0]

    def _set_id(self, data: bytes) -> None:
        if data[0] < BROADCAST_ID:
            self.sid = data[0]

    def _torque_bytes(self) -> bytes:
        return bytes((int(self.train.wheels[self.side].torque),))

    def _set_torque(self, data: bytes) -> None:
        try:
            self.train.wheels[self.side].torque = DriveTorque(data[0])
        except ValueError:
            self._flag_invalid(type(self.status_detail).EXCEED_REG_RANGE)
