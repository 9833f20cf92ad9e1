"""The control loop: drive targets, watchdog, emergency stop, wheel PIDs, speed governor.

Its slot on the bus runs every control period at top priority: the wheel command is
computed when the slot is sent (:meth:`ControlLoop.packets`), then both wheel counts are
read in the same atomic slot and handed to :mod:`ohmni_tb.robot.wheels` (encoders and
odometry); the PIDs' terms go out as ``pid_debug``. Too many slots without the counts
stop the wheels (``stale_ticks``). A changed command does not wait for the next slot
when that is far off (:meth:`ControlLoop.write_early`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
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
from ohmni_tb.robot.wheels import WheelCounts

__all__ = [
    "CONTROL_PRIORITY",
    "CONTROL_SLACK",
    "OVERSPEED_MARGIN_MPS",
    "OVERSPEED_SHARE",
    "ControlLoop",
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

    def drive(self, twist: Twist, *, ramped: bool = True) -> LimitedTwist:
        """Make ``twist``, within the speed limits, the target (``Robot.drive``): through
        the acceleration limiter, or (``ramped=False``) at once."""
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
        """Target zero; the first braking command goes at once (``Robot.stop``)."""
        self.stop_targets()
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
        if self._mode == "pwm":
            self._mode = "twist"

    def _commanded(self, changed: bool) -> None:
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
        if state.estopped or state.link is not Link.CONNECTED or "stale_feedback" in state.faults:
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
            twist = self._limiter.step(self._target, dt)
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
            return self._target_wheels != WheelSpeeds(0.0, 0.0)
        return self._target != Twist()

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
        self._counts.publish(counts, self._limiter.current, self._requested)
        debug = state.topics["pid_debug"]
        lw, rw = self._wheels
        if debug.enabled and lw.last_step is not None and rw.last_step is not None:
            stamp_s = counts.stamp_s
            debug.publish(PidDebugSample(stamp_s, lw.last_step, rw.last_step), stamp_s)
