"""The control loop: drive targets, watchdog, emergency stop, wheel PIDs, speed governor.

Its slot on the bus runs every control period at top priority: the wheel command is
computed when the slot is sent (:meth:`ControlLoop.packets`), then both wheel counts are
read in the same atomic slot and handed to :mod:`ohmni_tb.robot.wheels` (encoders and
odometry); the PIDs' terms go out as ``pid_debug``. Too many slots without the counts
stop the wheels (``stale_ticks``). A changed command does not wait for the next slot
when that is far off (:meth:`ControlLoop.write_early`).

Two guards judge every slot's counts against what the wheels were told (a few
comparisons a wheel; the rest only when one trips):

- **Stall** (``stall_s``): a wheel *driven* — its setpoint at least
  :data:`STALL_MIN_SETPOINT_MPS` either way, or its PWM :data:`STALL_PWM_MARGIN` beyond
  the configured dead band (``pid_ff_offset``; open-loop PWM has no setpoint) — whose
  count moved less than :data:`STALL_SPEED_MPS` would over a control period, for
  ``stall_s``: an obstacle, a jammed motor, a board that does not take the wheel command.
  The fault ``wheel_stall:<sid>`` is raised, the wheels get no power from that slot on
  (the brake goes out at once) and a motion goal ends with
  :class:`~ohmni_tb.errors.WheelStallError`. The fault holds the wheels stopped until
  ``stop()`` or a drive command other than the one that stalled: a loop that keeps
  sending the same command does not push against the obstacle again.
- **Slip** (``slip_s``): with both wheels' setpoints holding steady (a ramp's lag, which
  the PIDs share, is not judged), the measured wheel speeds' difference off the one the
  setpoints ask by more than :data:`SLIP_MIN_MPS` + :data:`SLIP_SHARE` of the larger
  setpoint, for ``slip_s``: one wheel slipping, lifted or dragging. The fault
  ``wheel_slip:<sid>`` names the wheel furthest off its setpoint; a motion goal ends with
  :class:`~ohmni_tb.errors.WheelSlipError`. The wheels keep their command (a wheel that
  slips pushes against nothing, and a driver at the keys sees the robot); the fault
  clears once the wheels agree again or stand.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from ohmni_tb.bus import ReplyPacket, Slot
from ohmni_tb.control.kinematics import (
    LimitedTwist,
    Twist,
    WheelSpeeds,
    limit_twist,
    saturate_wheel_speeds,
)
from ohmni_tb.control.pid import PidController, PidGains, PidStep
from ohmni_tb.errors import OhmniError, StateError
from ohmni_tb.protocol import Packet
from ohmni_tb.protocol.drive import PWM_LIMIT, wheel_command
from ohmni_tb.robot.samples import Link, PidDebugSample
from ohmni_tb.robot.schedule import CycleResult, Periodic
from ohmni_tb.robot.state import RobotState
from ohmni_tb.robot.wheels import TakenCounts, WheelCounts

__all__ = [
    "CONTROL_PRIORITY",
    "CONTROL_SLACK",
    "OVERSPEED_MARGIN_MPS",
    "OVERSPEED_SHARE",
    "SLIP_MIN_MPS",
    "SLIP_SHARE",
    "SLIP_STEADY_MPS",
    "STALL_MIN_SETPOINT_MPS",
    "STALL_PWM_MARGIN",
    "STALL_SPEED_MPS",
    "WHEEL_NAMES",
    "ControlLoop",
    "WheelFault",
]

_log = logging.getLogger(__name__)

#: Bus priority of the control slot: ahead of every command and feedback read.
CONTROL_PRIORITY = 10
#: Control-slot tuples kept by command value (``ControlLoop._cycles``).
_CONTROL_CYCLES_MAX = 256
#: The control slot must start this share of a period after its due time, or it is
#: skipped (a late wheel command is worse than the next one on time). Its count reads
#: wait until the previous cycle's replies are seen, which an adapter's latency timer
#: can hold 16 ms (of a 20 ms period): at half a period 2 % of the cycles were lost
#: that way (49.0 Hz); a slot that starts at three quarters still ends, with its
#: command computed at send time, before the next cycle is due.
CONTROL_SLACK = 0.75
#: The speed governor, on the PWM after the PID (or the open-loop PWM): at most the PWM
#: the configured feed-forward (``pid_kff``, ``pid_ff_offset``) gives for this share of
#: ``max_wheel_mps``; and none at all for a wheel measured faster than that share of it
#: plus a margin for the speed estimate's noise (a model that is wrong, a slope).
OVERSPEED_SHARE = 1.1
OVERSPEED_MARGIN_MPS = 0.03
#: The stall guard (module docstring): a setpoint this fast either way drives a wheel
#: (the motion goals creep at no less than 0.03 m/s); so does a PWM this far beyond the
#: configured dead band (``pid_ff_offset``), which moves a free wheel at once.
STALL_MIN_SETPOINT_MPS = 0.02
STALL_PWM_MARGIN = 40
#: A driven wheel whose count moved less than this speed's worth over a control period
#: is not turning: 0.1 mm at 50 Hz, about nine ticks — slower than any motion the PIDs
#: hold, far above a count's jitter.
STALL_SPEED_MPS = 0.005
#: The slip guard (module docstring): the wheel speeds' difference may be off the one
#: the setpoints ask by SLIP_MIN_MPS (the speed estimate's noise, a bump) + SLIP_SHARE of
#: the larger setpoint (the PIDs' steady error, a few per cent of each wheel's speed);
#: a tick whose setpoints moved more than SLIP_STEADY_MPS since the tick before is not
#: judged (a ramp: both PIDs trail it). A wheel that loses its grip loses its load and
#: runs ahead of its setpoint by what the ground's drag took (~0.04 m/s on the
#: simulator), until its PID's integral catches up a few seconds later; so the margins are
#: small, and a slip that the PID already holds at its setpoint is not seen.
SLIP_MIN_MPS = 0.015
SLIP_SHARE = 0.01
SLIP_STEADY_MPS = 0.001
#: The wheels by index, as faults and errors name them.
WHEEL_NAMES = ("left", "right")


@dataclass(frozen=True, slots=True)
class WheelFault:
    """What a stall or slip guard saw when it tripped.

    Attributes:
        kind: ``"stall"`` or ``"slip"``.
        wheels: The wheels it names (0 left, 1 right): the stalled ones, or the one
            furthest off its setpoint.
        pwm: The PWM each of them was driven with (forward positive).
        setpoint_mps: Each one's setpoint (0 for open-loop PWM).
        measured_mps: Each one's measured speed.
        duration_s: How long the guard's condition held.
    """

    kind: Literal["stall", "slip"]
    wheels: tuple[int, ...]
    pwm: tuple[int, ...]
    setpoint_mps: tuple[float, ...]
    measured_mps: tuple[float, ...]
    duration_s: float

    @property
    def names(self) -> tuple[str, ...]:
        """The wheels' names: ``("left",)``, ``("right",)`` or both."""
        return tuple(WHEEL_NAMES[index] for index in self.wheels)


@dataclass(eq=False)
class _Wheel:
    """One wheel's PID, the PID's last step, and its steps whose output sat at the PWM
    limit (the diagnostics' saturation time)."""

    pid: PidController
    last_step: PidStep | None = None
    saturated_steps: int = 0


class ControlLoop:
    """The wheels' part of the Robot (module docstring)."""

    def __init__(self, state: RobotState, counts: WheelCounts) -> None:
        self._state = state
        self._counts = counts
        self._loop = state.loop
        config = self._config = state.config
        self._bus = state.bus
        self._drive = config.drive()
        #: The drive boards' profile: the form of every wheel command built here.
        self._boards = state.profile.drive
        self._limits = config.velocity_limits()
        self._limiter = config.twist_limiter()
        gains = config.pid_gains()
        self._wheels = (_Wheel(PidController(gains)), _Wheel(PidController(gains)))
        self._mode: Literal["twist", "wheels", "pwm"] = "twist"
        self._target = Twist()
        self._target_wheels = WheelSpeeds(0.0, 0.0)
        self._target_pwm = (0, 0)
        # The twist asked for before any limit (wheel_odom's requested_*).
        self._requested = Twist()
        # Each wheel's PID on or off (tb_control's enable_controllers, per wheel).
        self._enabled = [config.controllers, config.controllers]
        # Whether the twist target goes through the acceleration limiter (drive's ramped).
        self._ramped = True
        # Whether the twist target is held to the jerk limit: a drive command's is; a
        # stop's (stop, the watchdog, a fault) is not, the jerk limit would lengthen it;
        # nor a motion goal's, which plans its own speed profile.
        self._jerk_limited = True
        self._pwm = (0, 0)
        # A braking command (0, 0) known to be on the wire since the last command that was
        # not one: while cycles are skipped, the brake goes out until this is so.
        self._brake_out = False
        self._last_step_s: float | None = None
        self._last_command_s = -math.inf
        self._watchdog_timer: asyncio.TimerHandle | None = None
        self._overspeed_max_mps = self._limits.max_wheel_mps * OVERSPEED_SHARE + (
            OVERSPEED_MARGIN_MPS
        )
        self._pwm_cap = (
            min(
                PWM_LIMIT,
                round(
                    config.pid_kff * self._limits.max_wheel_mps * OVERSPEED_SHARE
                    + config.pid_ff_offset
                ),
            )
            if config.pid_kff > 0
            else PWM_LIMIT
        )
        self._overspeed = 0
        self._stale_ticks = 0
        self._count_reads = counts.reads
        self._cycles: dict[tuple[int, int], tuple[Packet, ...]] = {}
        state.packets["wheel_encoder"] = [wheel_command(0, 0, self._boards), *self._count_reads]
        self._early_pending = False
        self._early_slot: Slot | None = None
        self._early_writes = 0
        self._init_guards()

    def periodic(self) -> Periodic:
        """The control slot on the schedule, at ``wheel_hz``."""
        hz = self._config.wheel_hz
        return Periodic(
            self._bus,
            "control",
            hz,
            phase_s=0.0,
            priority=CONTROL_PRIORITY,
            slack_s=1.0 / hz * CONTROL_SLACK,
            build=self.packets,
            handle=self.result,
            fail=self.failed,
            skipped=self.skipped,
        )

    # -- commands ------------------------------------------------------------------------

    def check_can_drive(self) -> None:
        """Refuse a drive command (port released, Robot closed, estop latched)."""
        self._state.check_port()
        if self._state.estopped:
            raise StateError("an emergency stop is latched: call robot.clear_estop() first")

    def check_closed_loop(self, method: str) -> None:
        """Refuse a closed-loop drive command (``drive``, ``drive_wheels``, a motion goal)
        while a wheel's controller is off: that wheel would get no power, and the robot
        would not go where it was told."""
        off = [name for name, on in zip(("left", "right"), self._enabled, strict=True) if not on]
        if off:
            which = (
                "both wheels' controllers are"
                if len(off) == 2
                else f"the {off[0]} wheel's controller is"
            )
            raise StateError(
                f"{method} needs the wheel controllers, and {which} off: call "
                "robot.enable_controllers(True) first (drive_pwm() drives without them)"
            )

    def drive(
        self, twist: Twist, *, ramped: bool = True, jerk_limited: bool = True
    ) -> LimitedTwist:
        """Make ``twist``, within the speed limits, the target (``Robot.drive``): through
        the acceleration limiter, or (``ramped=False``) at once; ``jerk_limited=False``
        for a motion goal's own command (it plans its own speed profile)."""
        limited = limit_twist(twist, self._limits, self._drive)
        if limited.limited:
            self._state.clamped += 1
            _log.debug(
                "drive(%g, %g) scaled by %.3f into the limits",
                twist.linear_mps,
                twist.angular_radps,
                limited.scale,
            )
        changed = self._mode != "twist" or self._target != limited.twist or self._ramped != ramped
        self._mode = "twist"
        self._target = limited.twist
        self._requested = twist
        self._ramped = ramped
        self._jerk_limited = jerk_limited
        self._commanded(changed)
        return limited

    def drive_wheels(self, asked: WheelSpeeds) -> WheelSpeeds:
        """Make ``asked``, scaled into ``max_wheel_mps``, the target (``Robot.drive_wheels``)."""
        wheels = saturate_wheel_speeds(asked, self._limits.max_wheel_mps)
        if wheels != asked:
            self._state.clamped += 1
        changed = self._mode != "wheels" or self._target_wheels != wheels
        self._mode = "wheels"
        self._target_wheels = wheels
        self._requested = self._drive.twist(asked)
        self._commanded(changed)
        return wheels

    def drive_pwm(self, left: int, right: int) -> None:
        """Make the open-loop PWM, checked, the target (``Robot.drive_pwm``)."""
        changed = self._mode != "pwm" or self._target_pwm != (left, right)
        self._mode = "pwm"
        self._target_pwm = (left, right)
        self._requested = Twist()  # open loop: no twist is followed
        self._commanded(changed)

    def stop(self) -> None:
        """Target zero; the first braking command goes at once (``Robot.stop``). Clears a
        stall's hold."""
        self.stop_targets()
        if self._held:
            self._release("stop()")
        self._last_command_s = self._loop.time()
        if self._state.link is Link.CONNECTED:
            self.write_early(force=True)

    async def estop(self) -> None:
        """Latch the emergency stop: zero PWM from now on, no wheel command computed
        before now goes out, and a stop goes ahead of everything queued (``Robot.estop``)."""
        self._state.estopped = True
        self.stop_targets()
        self._limiter.reset()
        self._reset_pids()
        self._pwm = (0, 0)
        control = self._state.periodic.get("wheel_encoder")
        if control is not None:
            control.withdraw_unstarted()
        early = self._early_slot
        if early is not None and early.started_at is None:
            self._bus.cancel(early)
        self._state.publish("emergency stop latched")
        if self._bus.connected:
            await self._bus.send_now(wheel_command(0, 0, self._boards))

    def clear_estop(self) -> None:
        """Release a latched emergency stop (``Robot.clear_estop``)."""
        if self._state.estopped:
            self._state.estopped = False
            self._state.publish("emergency stop cleared")

    def enable_controllers(self, enabled: bool, index: int | None = None) -> None:
        """Run wheel ``index``'s PID (0 left, 1 right; ``None``: both), or not
        (``Robot.enable_controllers``, checked there). Turning one off drops a closed-loop
        target: the robot stands until commanded again."""
        for i in (0, 1) if index is None else (index,):
            self._enabled[i] = enabled
        if not enabled and self._mode != "pwm":
            self.stop_targets()
        self._reset_pids()

    def controllers(self) -> tuple[bool, bool]:
        """Whether each wheel's PID runs: (left, right)."""
        return self._enabled[0], self._enabled[1]

    def saturated_steps(self) -> tuple[int, int]:
        """Each wheel's PID steps so far whose output sat at the PWM limit: (left, right)."""
        return self._wheels[0].saturated_steps, self._wheels[1].saturated_steps

    def gains_of(self, index: int) -> PidGains:
        """Wheel ``index``'s PID gains (0 left, 1 right)."""
        return self._wheels[index].pid.gains

    def set_gains(self, gains: PidGains, index: int | None = None) -> None:
        """Change wheel ``index``'s PID gains (``None``: both), bumplessly
        (``Robot.set_pid``, checked there)."""
        for i in (0, 1) if index is None else (index,):
            self._wheels[i].pid.set_gains(gains)

    def halt(self) -> None:
        """Drop the drive targets, the ramp and the PIDs' state (the link went)."""
        self.stop_targets()
        self._limiter.reset()
        self._reset_pids()

    def restart(self) -> None:
        """The link is back: the next control step starts afresh."""
        self._last_step_s = None

    def close(self) -> None:
        """Stop the watchdog's timer."""
        if self._watchdog_timer is not None:
            self._watchdog_timer.cancel()

    def stop_targets(self) -> None:
        """Every drive target to zero (open-loop PWM falls back to twist mode)."""
        self._target = Twist()
        self._target_wheels = WheelSpeeds(0.0, 0.0)
        self._target_pwm = (0, 0)
        self._requested = Twist()
        # A stop ramps down at the deceleration limits, whatever the last drive was.
        self._ramped = True
        self._jerk_limited = False
        if self._mode == "pwm":
            self._mode = "twist"

    def _commanded(self, changed: bool) -> None:
        if self._held and self._command_key() != self._held_command:
            self._release("a new drive command")
        now = self._last_command_s = self._loop.time()
        if self._watchdog_timer is None and self._config.watchdog_s > 0:
            self._watchdog_timer = self._loop.call_at(
                now + self._config.watchdog_s, self._watchdog_due
            )
        if changed:
            self.write_early()
        if self._state.watchdog_tripped:
            self._state.watchdog_tripped = False
            self._state.publish("watchdog re-armed by a drive command")

    # -- the control step ----------------------------------------------------------------

    def packets(self, due: float) -> tuple[Packet, ...]:
        """The control slot's packets: the wheel command computed now, both count reads."""
        pwm = self._command(self._loop.time())
        cycle = self._cycles.get(pwm)
        if cycle is None:
            # One tuple per command value: the bus checks a tuple it has seen only once.
            if len(self._cycles) >= _CONTROL_CYCLES_MAX:
                self._cycles.clear()
            cycle = self._cycles[pwm] = (wheel_command(*pwm, self._boards), *self._count_reads)
        return cycle

    def _command(self, now: float) -> tuple[int, int]:
        """The wheel PWM to send now (:meth:`_step`); one that is not a brake is not out yet."""
        pwm = self._step(now)
        if pwm != (0, 0):
            self._brake_out = False
        return pwm

    def _step(self, now: float) -> tuple[int, int]:
        """The wheel PWM to send now: watchdog, estop, limits, ramps and the PIDs."""
        config = self._config
        previous = self._last_step_s
        self._last_step_s = now
        dt = 1.0 / config.wheel_hz if previous is None else max(now - previous, 1e-6)
        state = self._state
        self._watchdog_check(now)
        if (
            self._held
            or state.estopped
            or state.link is not Link.CONNECTED
            or "stale_feedback" in state.faults
        ):
            self._limiter.reset()
            self._reset_pids()
            self._pwm = (0, 0)
            return self._pwm
        if self._mode == "pwm" or not all(self._enabled):
            self._limiter.reset()
            self._pwm = self._governed(*self._target_pwm) if self._mode == "pwm" else (0, 0)
            return self._pwm
        if self._mode == "wheels":
            wheels = self._target_wheels
            twist = self._drive.twist(wheels)
            self._limiter.reset(twist)
        elif not self._ramped:
            # The pure velocity command: the setpoints jump to the (limited) target.
            twist = self._target
            self._limiter.reset(twist)
            wheels = saturate_wheel_speeds(
                self._drive.wheel_speeds(twist), self._limits.max_wheel_mps
            )
        else:
            twist = self._limiter.step(self._target, dt, jerk_limited=self._jerk_limited)
            wheels = saturate_wheel_speeds(
                self._drive.wheel_speeds(twist), self._limits.max_wheel_mps
            )
        if twist.linear_mps == 0.0 and twist.angular_radps == 0.0:
            # Standing: no PWM at all, and no integral left to creep with.
            self._reset_pids()
            self._pwm = (0, 0)
            return self._pwm
        outputs = []
        speed_mps = self._counts.speed_mps
        for index, setpoint in enumerate((wheels.left_mps, wheels.right_mps)):
            wheel = self._wheels[index]
            measured = speed_mps(index)
            step = wheel.pid.step(setpoint, 0.0 if measured is None else measured, dt)
            wheel.last_step = step
            if step.saturated:
                wheel.saturated_steps += 1
            outputs.append(round(step.output))
        self._pwm = self._governed(outputs[0], outputs[1])
        return self._pwm

    def _governed(self, left: int, right: int) -> tuple[int, int]:
        """The PWM that reaches the wheels, whatever the command, the gains or the
        open-loop PWM asked: within the PWM that ``max_wheel_mps`` needs by the configured
        feed-forward, and none for a wheel measured faster than ``max_wheel_mps`` (with a
        margin) in the direction it is driven (each counted in ``clamped_commands``)."""
        limit = self._overspeed_max_mps
        cap = self._pwm_cap
        pwm = [left, right]
        for index in (0, 1):
            if pwm[index] == 0:
                continue
            if abs(pwm[index]) > cap:
                pwm[index] = cap if pwm[index] > 0 else -cap
                self._state.clamped += 1
            speed = self._counts.speed_mps(index)
            if speed is None:
                continue
            if abs(speed) > limit and (pwm[index] > 0) == (speed > 0):
                pwm[index] = 0
                self._overspeed += 1
                self._state.clamped += 1
                if self._overspeed == 1:
                    _log.warning(
                        "a wheel measured %.2f m/s, over max_wheel_mps=%g: its power is cut "
                        "until it slows (counted in clamped_commands)",
                        speed,
                        self._limits.max_wheel_mps,
                    )
        return pwm[0], pwm[1]

    def _watchdog_check(self, now: float) -> bool:
        """Trip the motion watchdog if the last drive command is older than ``watchdog_s``
        and the target still moves; whether it tripped now."""
        config = self._config
        state = self._state
        if (
            config.watchdog_s <= 0
            or state.watchdog_tripped
            or not self._moving_target()
            # The timer's own sum (_watchdog_due): a difference can round below
            # watchdog_s at the very instant the timer fires, and trip a tick late.
            or now < self._last_command_s + config.watchdog_s
        ):
            return False
        state.watchdog_tripped = True
        state.watchdog_trips += 1
        self.stop_targets()
        state.publish(f"watchdog: no drive command for {config.watchdog_s:g} s, stopping")
        return True

    def _watchdog_due(self) -> None:
        """The watchdog's own timer: it trips at ``watchdog_s`` after the last drive command
        whatever the control tick's rate, and puts the braking command on the wire at once."""
        self._watchdog_timer = None
        if self._state.closed:
            return
        due = self._last_command_s + self._config.watchdog_s
        if self._loop.time() < due:  # commanded again meanwhile: wait for the new time
            self._watchdog_timer = self._loop.call_at(due, self._watchdog_due)
        elif self._watchdog_check(self._loop.time()):
            self.write_early(force=True)

    def skipped(self, cycles: int) -> None:
        """Control cycles that did not run (a late loop, a busy line): counted; while the
        wheels are braking, the braking command goes anyway, late rather than never."""
        self._state.topics["wheel_encoder"].skipped += cycles
        # Not the last command computed (its cycle may be the one skipped) but the last
        # one known written: a brake computed for a skipped cycle never reached the wheels.
        if not self._brake_out and not self._moving_target():
            self.write_early(force=True)

    def failed(self, due: float, exc: BaseException) -> None:
        """A control cycle that failed: counted as missed."""
        self._state.topics["wheel_encoder"].missed += 1
        if not isinstance(exc, OhmniError):
            _log.error("control cycle failed", exc_info=exc)

    def moving(self) -> bool:
        """Whether the drive target moves the wheels (not zero, not a stop)."""
        return self._moving_target()

    def _moving_target(self) -> bool:
        if self._mode == "pwm":
            return self._target_pwm != (0, 0)
        if self._mode == "wheels":
            wheels = self._target_wheels  # fields compared: no call, every tick
            return wheels.left_mps != 0.0 or wheels.right_mps != 0.0
        target = self._target
        return target.linear_mps != 0.0 or target.angular_radps != 0.0

    def _reset_pids(self) -> None:
        for wheel in self._wheels:
            wheel.pid.reset()
            wheel.last_step = None

    def write_early(self, *, force: bool = False) -> None:
        """Get a changed command to the wheels well within one control period.

        A control slot (or an early command) still waiting for the line gets the new
        command in place of the one computed before. Otherwise, when the next control slot
        is over a quarter period away (or ``force``: the control cycles are being skipped),
        the command goes now in a slot of its own (at most one between two control slots).
        A command that moves is due before the next control slot; one that stops or brakes
        has no deadline: late, it still goes.
        """
        control = self._state.periodic.get("wheel_encoder")
        if control is None or not control.running:
            return
        now = self._loop.time()
        for waiting in (control.unstarted(), self._early_slot):
            if waiting is not None and waiting.started_at is None:
                with contextlib.suppress(OhmniError):
                    waiting.replace_unsent(0, wheel_command(*self._command(now), self._boards))
                    self._early_writes += 1
                    return
        if self._early_pending or (not force and control.next_due_s - now <= control.period_s / 4):
            return
        pwm = self._command(now)
        try:
            slot = self._bus.submit(
                [wheel_command(*pwm, self._boards)],
                priority=CONTROL_PRIORITY,
                deadline=control.next_due_s if self._moving_target() else None,
            )
        except OhmniError:
            return
        self._early_pending = True
        self._early_slot = slot
        self._early_writes += 1

        def done(future: asyncio.Future[list[ReplyPacket | None]]) -> None:
            self._early_pending = False
            self._early_slot = None
            if pwm == (0, 0) and slot.started_at is not None:
                self._brake_out = True
            if not future.cancelled():
                future.exception()  # retrieved: a missed deadline needs no report

        slot.future.add_done_callback(done)

    # -- the counts ----------------------------------------------------------------------

    def result(self, result: CycleResult) -> None:
        """A control slot's replies: both wheel counts, or neither, into the encoders and
        the odometry; too many slots without them stop the wheels."""
        counts = self._counts.take(result)
        state = self._state
        if counts is None:
            state.topics["wheel_encoder"].missed += 1
            self._stale_ticks += 1
            if (
                self._stale_ticks >= self._config.stale_ticks
                and "stale_feedback" not in state.faults
            ):
                state.faults.add("stale_feedback")
                self.stop_targets()
                state.publish(
                    f"stale feedback: no wheel counts for {self._stale_ticks} ticks, stopping"
                )
            return
        self._stale_ticks = 0
        if "stale_feedback" in state.faults:
            state.faults.discard("stale_feedback")
            state.publish("wheel feedback is back")
        self._guard(counts)
        self._counts.publish(counts, self._limiter.current, self._requested)
        debug = state.topics["pid_debug"]
        lw, rw = self._wheels
        if debug.enabled and lw.last_step is not None and rw.last_step is not None:
            stamp_s = counts.stamp_s
            debug.publish(PidDebugSample(stamp_s, lw.last_step, rw.last_step), stamp_s)

    # -- the stall and slip guards ---------------------------------------------------------

    def _init_guards(self) -> None:
        config = self._config
        #: Set from outside (the motion goals): told of every guard that trips.
        self.on_wheel_fault: Callable[[WheelFault], None] | None = None
        self._stall_s = config.stall_s
        self._slip_s = config.slip_s
        # A count moved less than this over a period is a wheel standing still.
        self._still_m = STALL_SPEED_MPS / config.wheel_hz
        self._stall_pwm = config.pid_ff_offset + STALL_PWM_MARGIN
        # Each wheel's last tick not driven or turning (inf: none since open or a stall).
        self._stall_since = [math.inf, math.inf]
        # A stall holds the wheels at zero until stop() or another command than this one.
        self._held = False
        self._held_command: tuple[object, ...] = ()
        self._slip_since = math.inf
        self._slip_prev = (0.0, 0.0)
        self._slipping: int | None = None
        #: Times each guard tripped since open, per wheel.
        self.stalls = [0, 0]
        self.slips = [0, 0]

    def guard_trips(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """Each wheel's stalls and slips since open: ((left, right), (left, right))."""
        return (self.stalls[0], self.stalls[1]), (self.slips[0], self.slips[1])

    def _command_key(self) -> tuple[object, ...]:
        """The drive command standing now, whatever its mode."""
        return (self._mode, self._target, self._target_wheels, self._target_pwm, self._ramped)

    def _guard(self, counts: TakenCounts) -> None:
        """Both guards on one slot's counts (module docstring): the stall guard here, in
        a few comparisons a wheel (it runs every control tick)."""
        stamp = counts.stamp_s
        lw, rw = self._wheels
        left_step, right_step = lw.last_step, rw.last_step
        stall_s = self._stall_s
        if stall_s > 0.0:
            still = self._still_m
            low_pwm = self._stall_pwm
            low_sp = STALL_MIN_SETPOINT_MPS
            since = self._stall_since
            pwm = self._pwm
            stalled = None
            for index, sample, step in ((0, counts.left, left_step), (1, counts.right, right_step)):
                power = pwm[index]
                setpoint = 0.0 if step is None else step.setpoint
                if (
                    (-low_pwm < power < low_pwm and -low_sp < setpoint < low_sp)
                    or not -still < sample.delta_m < still
                    or since[index] == math.inf  # driven and still from its first tick on
                ):
                    since[index] = stamp
                elif stamp - since[index] >= stall_s:
                    stalled = [index] if stalled is None else [*stalled, index]
            if stalled is not None:
                self._stall(counts, stamp, stalled)
                return
        if self._slip_s > 0.0:
            if left_step is not None and right_step is not None:
                self._guard_slip(counts, stamp, left_step, right_step)
            elif self._slipping is not None:
                self._unslip("the wheels stand")
            else:
                self._slip_since = math.inf

    def _stall(self, counts: TakenCounts, stamp: float, wheels: list[int]) -> None:
        """A stall: the fault, the wheels held at zero, the brake at once, the goal told."""
        state = self._state
        steps = (self._wheels[0].last_step, self._wheels[1].last_step)
        measured = (counts.left.velocity_mps, counts.right.velocity_mps)
        fault = WheelFault(
            "stall",
            tuple(wheels),
            tuple(self._pwm[i] for i in wheels),
            tuple(0.0 if (step := steps[i]) is None else step.setpoint for i in wheels),
            tuple(measured[i] for i in wheels),
            max(stamp - self._stall_since[i] for i in wheels),
        )
        self._held = True
        self._held_command = self._command_key()
        for index in wheels:
            state.faults.add(f"wheel_stall:{index}")
            self.stalls[index] += 1
            self._stall_since[index] = math.inf
        self.stop_targets()
        self._limiter.reset()
        self._reset_pids()
        self._pwm = (0, 0)
        said = "; ".join(
            f"the {WHEEL_NAMES[i]} wheel (drive board {i}) driven at PWM {p}"
            + (f", setpoint {sp:+.2f} m/s," if sp else "")
            for i, p, sp in zip(wheels, fault.pwm, fault.setpoint_mps, strict=True)
        )
        state.publish(
            f"wheel_stall: {said} did not turn for {fault.duration_s:.2f} s: the wheels are "
            "stopped and held so until stop() or another drive command"
        )
        if self.on_wheel_fault is not None:
            self.on_wheel_fault(fault)
        self.write_early(force=True)

    def _release(self, why: str) -> None:
        """The stall's hold ends (``why``: what ended it); its faults clear."""
        self._held = False
        faults = self._state.faults
        for index in (0, 1):
            faults.discard(f"wheel_stall:{index}")
        self._state.publish(f"wheel_stall cleared by {why}")

    def _guard_slip(
        self, counts: TakenCounts, stamp: float, left_step: PidStep, right_step: PidStep
    ) -> None:
        left_sp, right_sp = left_step.setpoint, right_step.setpoint
        prev_left, prev_right = self._slip_prev
        self._slip_prev = (left_sp, right_sp)
        if not (
            -SLIP_STEADY_MPS < left_sp - prev_left < SLIP_STEADY_MPS
            and -SLIP_STEADY_MPS < right_sp - prev_right < SLIP_STEADY_MPS
        ):
            self._slip_since = math.inf  # a ramp: the PIDs trail it, both alike
            return
        left_v, right_v = counts.left.velocity_mps, counts.right.velocity_mps
        off = (right_v - left_v) - (right_sp - left_sp)
        top = left_sp if left_sp > right_sp else right_sp
        bottom = -left_sp if left_sp < right_sp else -right_sp
        allowed = SLIP_MIN_MPS + SLIP_SHARE * (top if top > bottom else bottom)
        if -allowed < off < allowed:
            self._slip_since = math.inf
            if self._slipping is not None and -allowed / 2 < off < allowed / 2:
                self._unslip("the wheels agree again")
            return
        if self._slip_since == math.inf:
            self._slip_since = stamp
        elif stamp - self._slip_since >= self._slip_s and self._slipping is None:
            self._slip(stamp, (left_sp, right_sp), (left_v, right_v))

    def _slip(
        self, stamp: float, setpoints: tuple[float, float], measured: tuple[float, float]
    ) -> None:
        """A slip: the fault on the wheel furthest off its setpoint, the goal told."""
        state = self._state
        index = 0 if abs(measured[0] - setpoints[0]) >= abs(measured[1] - setpoints[1]) else 1
        fault = WheelFault(
            "slip",
            (index,),
            (self._pwm[index],),
            (setpoints[index],),
            (measured[index],),
            stamp - self._slip_since,
        )
        self._slipping = index
        self.slips[index] += 1
        state.faults.add(f"wheel_slip:{index}")
        other = 1 - index
        state.publish(
            f"wheel_slip: the {WHEEL_NAMES[index]} wheel (drive board {index}) ran at "
            f"{measured[index]:+.3f} m/s, set to {setpoints[index]:+.3f} m/s, while the "
            f"{WHEEL_NAMES[other]} ran at {measured[other]:+.3f} m/s, set to "
            f"{setpoints[other]:+.3f} m/s, for {fault.duration_s:.2f} s: off the "
            "commanded curve (slipping, lifted or dragging?)"
        )
        if self.on_wheel_fault is not None:
            self.on_wheel_fault(fault)

    def _unslip(self, why: str) -> None:
        index = self._slipping
        self._slipping = None
        self._slip_since = math.inf
        self._state.faults.discard(f"wheel_slip:{index}")
        self._state.publish(f"wheel_slip cleared: {why}")
