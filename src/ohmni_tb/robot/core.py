"""The asyncio Robot: tb_control's job on one bus — streams, commands and safety.

::

    from ohmni_tb import Robot

    async with Robot.open("sim://") as robot:
        robot.drive(0.3, 0.0)                        # m/s, rad/s: sets the target
        await asyncio.sleep(1.0)
        print(robot.latest("wheel_odom"))
        async for status in robot.subscribe("tbcore_status"):
            print(status.pack_v)
            break

The Robot owns one schedule on the bus (:mod:`ohmni_tb.robot.schedule`): the control
slot every 20 ms at top priority (the wheel command computed at send time, then both
wheel counts, in one atomic slot), each HerkuleX servo's feedback at 30 Hz, the
worm-gear neck at 30 Hz, the core board at 10 Hz, on absolute deadlines with staggered
phases. Commands (neck moves, light ring, PID writes) go in the free time at a priority
between the control slot and the feedback reads.

:meth:`Robot.release_port` hands the serial port to another program for a while (the
vendor's tb-node, a flashing tool) and :meth:`Robot.reclaim_port` takes it back, on the
same Robot: its streams, statistics and subscriptions carry on.

:class:`LocalRobot` implements the contract (:class:`~ohmni_tb.robot.api.Robot`, where the
API is documented) in this process. It is a façade: it opens and closes, checks arguments
(with the checks the remote robot makes: :mod:`ohmni_tb.robot.checks`), makes every
motion command preempt a motion goal under way (:mod:`~ohmni_tb.robot.motion`), and hands
the work to parts of one job each, which share one
:class:`~ohmni_tb.robot.state.RobotState`: :mod:`~ohmni_tb.robot.discovery`,
:mod:`~ohmni_tb.robot.control_loop`, :mod:`~ohmni_tb.robot.wheels`,
:mod:`~ohmni_tb.robot.feedback`, :mod:`~ohmni_tb.robot.guards`,
:mod:`~ohmni_tb.robot.diagnostics`, :mod:`~ohmni_tb.robot.link` and
:mod:`~ohmni_tb.robot.sources` (which command source drives).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Any

from ohmni_tb._checks import number
from ohmni_tb.bus import Bus, Reopen
from ohmni_tb.config import RobotConfig
from ohmni_tb.control.kinematics import LimitedTwist, Twist, WheelSpeeds
from ohmni_tb.control.pid import PidGains
from ohmni_tb.errors import ConfigError, StopNotConfirmedError
from ohmni_tb.eventloop import MILLISECOND_S, timer_resolution_s
from ohmni_tb.protocol.core import set_light_ring
from ohmni_tb.protocol.drive import wheel_command
from ohmni_tb.protocol.profile import PROFILE_SETTINGS, BusProfile
from ohmni_tb.robot.api import Robot, SampleStream
from ohmni_tb.robot.checks import (
    WHEELS,
    Wheel,
    check_enabled,
    check_gains,
    check_port_name,
    check_pose,
    check_ramped,
    check_rate,
    check_release,
    check_wheel,
    gains_of,
    pwm_command,
    wheel_index,
)
from ohmni_tb.robot.control_loop import ControlLoop
from ohmni_tb.robot.devices import COMMAND_PRIORITY, ServoHandle, WormNeckHandle
from ohmni_tb.robot.diagnostics import Diagnostics
from ohmni_tb.robot.discovery import Discovery
from ohmni_tb.robot.feedback import Feedback
from ohmni_tb.robot.guards import Guards
from ohmni_tb.robot.link import LinkKeeper
from ohmni_tb.robot.motion import MotionGoals, MotionResult
from ohmni_tb.robot.renumber import Renumbering
from ohmni_tb.robot.samples import Link, RobotStateSample
from ohmni_tb.robot.servo_settings import NeckSettings
from ohmni_tb.robot.sources import CommandSources
from ohmni_tb.robot.state import RobotState
from ohmni_tb.robot.stats import BusFigures, RobotStats
from ohmni_tb.robot.wheels import WheelCounts
from ohmni_tb.transport import SerialTransport, Transport, open_transport

__all__ = ["BusFigures", "LocalRobot", "RobotStats"]

_log = logging.getLogger(__name__)


class LocalRobot(Robot):
    """One Ohmni robot on its bus, run by this process (module docstring); the API is
    :class:`~ohmni_tb.robot.api.Robot`'s. Create it with :meth:`open`."""

    def __init__(self, bus: Bus, config: RobotConfig, *, sim: Any = None) -> None:
        self._bus = bus
        #: The simulated robot (ground truth) on ``sim://``, else ``None``.
        self.sim = sim
        self._loop = asyncio.get_running_loop()
        self._opened_at = self._loop.time()
        # One state shared by the parts, each part one job (each module's docstring).
        self._state = state = RobotState(bus, config, self._loop)
        self._counts = WheelCounts(state)
        self._control = ControlLoop(state, self._counts)
        # The neck servo's own settings: loaded at open, checked after a silence.
        self._settings = NeckSettings(state)
        self._feedback = Feedback(state, self._control, self._counts, Guards(state, self._settings))
        self._discovery = Discovery(state, self._found)
        self._link = LinkKeeper(state, self._control, self._feedback, self._discovery)
        self._renumbering = Renumbering(state, self._feedback, self._reconfigure)
        counts = self._counts
        self._diagnostics = Diagnostics(
            state,
            self._control.saturated_steps,
            lambda: (counts.wheels[0].rejected, counts.wheels[1].rejected),
            self._control.guard_trips,
        )
        self._discovery.renumber = self._renumbering.servo
        self._discovery.zero_offset = self._zero_offset_set
        self._discovery.moved = self._renumbering.moved
        # Which command source drives; a motion goal holds its own live while it runs.
        self._sources = CommandSources(state, self._control)
        # Motion goals: every other motion command preempts the one under way.
        self._motion = MotionGoals(self, check=self._check_goal, sources=self._sources)
        # The control loop's stall and slip guards end the goal under way.
        self._control.on_wheel_fault = self._motion.wheel_fault
        self._port = config.port
        #: Why the stop on the way out was not confirmed, if it was not (also raised
        #: from ``async with`` when the block itself ended without an error).
        self.exit_error: StopNotConfirmedError | None = None

    # -- opening and closing -----------------------------------------------------------

    @classmethod
    def _opens(cls, port: str | Transport | None) -> bool:
        """Every port but a daemon's URL."""
        return not (isinstance(port, str) and port.lower().startswith(("ws://", "wss://")))

    @classmethod
    @contextlib.asynccontextmanager
    async def open(
        cls,
        port: str | Transport | None = None,
        *,
        token: str | None = None,
        config: RobotConfig | None = None,
        profile: BusProfile | None = None,
        source: str | None = None,
        **overrides: Any,
    ) -> AsyncIterator[LocalRobot]:
        """:meth:`Robot.open <ohmni_tb.robot.api.Robot.open>` on a port this process opens;
        after an error in the block, that error goes on and :attr:`exit_error` holds the
        stop's. A :class:`~ohmni_tb.transport.Transport` given is reopened after a loss
        when it can be (:meth:`~ohmni_tb.transport.Transport.reopen`)."""
        if not cls._opens(port):
            raise ConfigError(
                f"{port!r} is a daemon's URL: open it with Robot.open({port!r}) "
                "(LocalRobot opens a serial port or sim://)"
            )
        if token is not None:
            raise ConfigError("a token is for a daemon's URL (ws://, wss://), not for a port")
        if profile is not None:
            if not isinstance(profile, BusProfile):
                raise ConfigError(f"profile must be a BusProfile, not {profile!r}")
            clash = sorted(set(overrides) & set(PROFILE_SETTINGS))
            if clash:
                raise ConfigError(
                    f"{', '.join(clash)} given both alone and in profile: give one or the other"
                )
            overrides = {**overrides, **profile.settings()}
        if config is None:
            config = RobotConfig(**overrides)
        elif overrides:
            config = config.replace(**overrides)
        if source is not None and source not in {row.name for row in config.source_table()}:
            names = ", ".join(row.name for row in config.source_table())
            raise ConfigError(
                f"source={source!r} is not a command source of command_sources: allowed {names}"
            )
        if isinstance(port, Transport):
            transport = port  # an open link, injected (a test's, a tap's)
        else:
            transport = await open_transport(port if port is not None else config.port)
        _warn_if_coarse_timers(transport)
        reopen = transport.reopen if transport.can_reopen else None
        bus = Bus(
            transport,
            timeout_s=config.bus_timeout_s(),
            reply_guard_s=_reply_guard_s(transport.baudrate),
            reopen=reopen,
        )
        bus.start()
        robot: LocalRobot | None = None
        try:
            robot = cls(bus, config, sim=transport.simulated)
            if source is not None:
                robot._sources.set_default(source)
            asked = config.port if port is None else port if isinstance(port, str) else repr(port)
            robot._port = _port_name(transport, asked)
            await robot._start()
        except BaseException:
            await bus.aclose(final=[wheel_command(0, 0, config.profile().drive)])
            raise
        try:
            yield robot
        except BaseException:
            await robot._close_shielded()
            raise
        # A clean exit whose stop the wheel counts did not confirm raises: the robot may
        # be moving and nobody else would say so.
        await robot._close_shielded()
        if robot.exit_error is not None:
            raise robot.exit_error

    async def _start(self) -> None:
        await self._discovery.discover()
        await self._settings.load("the Robot opened")
        self._feedback.build()
        self._feedback.start()
        self._diagnostics.start()
        self._link.start()
        self._discovery.arm()
        self._state.publish("opened")

    def _found(self, sid: int) -> None:
        """A device answered after open: its stream, and the neck servo its settings."""
        self._feedback.found(sid)
        neck = self._settings.handle()
        if neck is not None and sid == neck.sid:
            self._state.spawn(self._settings.load("the neck answered"), "neck settings")

    async def _close_shielded(self) -> None:
        """Close, and finish closing even if the caller is cancelled meanwhile."""
        await self._state.shielded(self._close(), "close")

    async def _close(self) -> None:
        state = self._state
        if state.closed:
            return
        state.closed = True
        state.closing = asyncio.current_task()
        self._motion.close()
        self._sources.close()
        self._diagnostics.close()
        self.exit_error = await self._link.close()

    @property
    def closed(self) -> bool:
        """Whether the Robot was closed."""
        return self._state.closed

    @property
    def config(self) -> RobotConfig:
        """The settings the Robot runs with (the servo ids and the neck's zero offset follow
        their changes at run time)."""
        return self._state.config

    @config.setter
    def config(self, config: RobotConfig) -> None:
        profile = config.profile()
        fixed = self._state.profile
        if (profile.drive, profile.core, profile.worm) != (fixed.drive, fixed.core, fixed.worm):
            changed = [
                name
                for name, value in profile.settings().items()
                if name != "ext_servo_ids" and fixed.settings()[name] != value
            ]
            raise ConfigError(
                f"the bus profile ({', '.join(changed)}) is fixed while the Robot is open: "
                "open it again with the new settings"
            )
        self._state.config = config

    def _reconfigure(self, **changes: Any) -> None:
        """The settings with ``changes`` (ids and offsets the Robot follows)."""
        self._state.config = self._state.config.replace(**changes)

    def _zero_offset_set(self, sid: int, raw: int) -> None:
        if sid == self._state.config.neck_id:
            self._reconfigure(neck_zero_offset_raw=raw)

    @property
    def bus(self) -> Bus:
        """The bus the Robot schedules (for figures and raw access; mind the schedule)."""
        return self._bus

    def schedule(self) -> list[tuple[str, float, float, float]]:
        """The schedule (:meth:`Robot.schedule <ohmni_tb.robot.api.Robot.schedule>`)."""
        return self._feedback.rows()

    # -- port hand-off (public) ----------------------------------------------------------

    async def release_port(self, duration_s: float | None = None) -> None:
        """Hand the port to another program (the contract: ohmni_tb.robot.api.Robot)."""
        duration_s = check_release(duration_s)
        self._state.check_open()
        self._state.disconnected = False
        await self._link.release(duration_s, before=lambda: self._motion.preempt("release_port"))

    async def reclaim_port(self) -> None:
        """Take the port back (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        self._state.disconnected = False
        await self._link.reclaim()

    # -- switching the port (public) ---------------------------------------------------

    @property
    def port(self) -> str | None:
        """The port open now (the contract: ohmni_tb.robot.api.Robot)."""
        state = self._state
        if state.closed or state.link is Link.RELEASED:
            return None
        return self._port

    async def connect(self, port: str | None = None) -> None:
        """Open ``port`` in place of the one open now (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        reopen = None
        check_port_name(port)
        if port is not None:
            if port == self._port and self.port is not None:
                return  # open already
            reopen = _reopener(port)
        name = port if port is not None else self._port
        await self._link.connect(reopen, name, before=lambda: self._motion.preempt("connect"))
        transport = self._bus.transport
        if port is not None:
            self._port = _port_name(transport, port)
            self.sim = transport.simulated

    async def disconnect(self) -> None:
        """Close the port until :meth:`connect` (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        await self._link.disconnect(before=lambda: self._motion.preempt("disconnect"))

    # -- streams (public) --------------------------------------------------------------------

    def _latest(self, name: str) -> Any:
        return self._state.topic(name).latest

    def _subscribe(self, name: str, maxlen: int) -> SampleStream[Any]:
        return self._state.topic(name).subscribe(maxlen)

    def enable_stream(self, name: str, enabled: bool = True) -> None:
        """A stream on or off (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        topic = self._state.topic(name)
        check_enabled(enabled)
        self._feedback.enable(name, topic, enabled)

    def set_rate(self, name: str, hz: float) -> None:
        """A polled stream's rate (:meth:`Robot.set_rate <ohmni_tb.robot.api.Robot.set_rate>`)."""
        self._state.check_open()
        self._state.topic(name)
        self._feedback.set_rate(name, check_rate(name, hz))

    def stats(self) -> RobotStats:
        """Per-stream rates, jitter, missed/skipped cycles and the bus's figures."""
        return self._feedback.stats(self._opened_at)

    @property
    def state(self) -> RobotStateSample:
        """The Robot's state now (as ``robot_state`` would publish it)."""
        return self._state.sample(None)

    # -- motion commands (public) ----------------------------------------------------------

    @property
    def source(self) -> str:
        """The command source of the commands that name none (the contract)."""
        return self._sources.default

    def drive(
        self,
        linear_mps: float,
        angular_radps: float = 0.0,
        *,
        ramped: bool = True,
        source: str | None = None,
    ) -> LimitedTwist:
        """The body velocity target (:meth:`Robot.drive <ohmni_tb.robot.api.Robot.drive>`)."""
        twist = Twist(number("linear_mps", linear_mps), number("angular_radps", angular_radps))
        check_ramped(ramped)
        name = self._sources.name(source)
        self._control.check_can_drive()
        self._control.check_closed_loop("drive()")
        self._sources.take(name, "drive()")
        self._motion.preempt("drive", source=name)
        # A motion goal's own command follows the goal's braking curve, not the jerk limit.
        return self._control.drive(twist, ramped=ramped, jerk_limited=not self._motion.owning)

    def drive_wheels(
        self, left_mps: float, right_mps: float, *, source: str | None = None
    ) -> WheelSpeeds:
        """Each wheel's speed target (the contract: ohmni_tb.robot.api.Robot)."""
        asked = WheelSpeeds(number("left_mps", left_mps), number("right_mps", right_mps))
        name = self._sources.name(source)
        self._control.check_can_drive()
        self._control.check_closed_loop("drive_wheels()")
        self._sources.take(name, "drive_wheels()")
        self._motion.preempt("drive_wheels", source=name)
        return self._control.drive_wheels(asked)

    def drive_pwm(
        self,
        left: float,
        right: float,
        *,
        left_enabled: bool = True,
        right_enabled: bool = True,
        source: str | None = None,
    ) -> tuple[int, int]:
        """Open-loop PWM (:meth:`Robot.drive_pwm <ohmni_tb.robot.api.Robot.drive_pwm>`)."""
        pwm = pwm_command(left, right, left_enabled, right_enabled)
        name = self._sources.name(source)
        self._control.check_can_drive()
        self._sources.take(name, "drive_pwm()")
        self._motion.preempt("drive_pwm", source=name)
        self._control.drive_pwm(*pwm)
        return pwm

    def stop(self, *, source: str | None = None) -> None:
        """Target zero, the first braking command at once, from any source."""
        name = self._sources.name(source)
        self._state.check_open()
        self._sources.stop(name)
        self._motion.preempt("stop", source=name)
        self._control.stop()

    async def estop(self, *, source: str | None = None) -> None:
        """Zero PWM ahead of everything, latched (the contract: ohmni_tb.robot.api.Robot)."""
        name = self._sources.name(source)
        self._state.check_open()
        self._sources.stop(name)
        self._motion.preempt("estop", source=name)
        await self._control.estop()

    def clear_estop(self) -> None:
        """Release a latched emergency stop (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        self._control.clear_estop()

    def enable_controllers(self, enabled: bool = True, wheel: Wheel | None = None) -> None:
        """The wheel PIDs on or off (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        check_enabled(enabled)
        index = wheel_index(check_wheel(wheel))
        if not enabled:
            self._motion.preempt("enable_controllers")
        self._control.enable_controllers(enabled, index)

    def controllers_enabled(self) -> dict[str, bool]:
        """Whether each wheel's PID runs (the contract: ohmni_tb.robot.api.Robot)."""
        return dict(zip(WHEELS, self._control.controllers(), strict=True))

    def get_pid(self, wheel: Wheel | None = None) -> PidGains:
        """The wheel PIDs' gains (the contract: ohmni_tb.robot.api.Robot)."""
        return gains_of(check_wheel(wheel), self._control.gains_of(0), self._control.gains_of(1))

    def set_pid(self, gains: PidGains, wheel: Wheel | None = None) -> None:
        """New wheel PID gains, bumplessly (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        checked = check_gains(gains)
        self._control.set_gains(checked, wheel_index(check_wheel(wheel)))

    def reset_odometry(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """Set the odometry pose (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        pose = check_pose(x_m, y_m, yaw_rad)
        # A goal steering by the odometry cannot go on in a new frame.
        self._motion.preempt("reset_odometry", stop=True)
        self._counts.reset_odometry(*pose)

    def set_odometry(self, x_m: float, y_m: float, yaw_rad: float) -> None:
        """Set the odometry pose to the one given (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        pose = check_pose(x_m, y_m, yaw_rad)
        # A goal steering by the odometry cannot go on in a new frame.
        self._motion.preempt("set_odometry", stop=True)
        self._counts.reset_odometry(*pose)

    def _check_goal(self) -> None:
        """A motion goal may start: the robot can drive, closed loop."""
        self._control.check_can_drive()
        self._control.check_closed_loop("a motion goal")

    # -- motion goals (public): ohmni_tb.robot.motion ---------------------------------------

    async def drive_distance(
        self,
        distance_m: float,
        *,
        speed_mps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """Drive straight by odometry (the contract: ohmni_tb.robot.api.Robot)."""
        return await self._motion.drive_distance(
            distance_m, speed_mps=speed_mps, timeout_s=timeout_s, source=self._sources.name(source)
        )

    async def rotate(
        self,
        angle_rad: float,
        *,
        speed_radps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """Turn on the spot by odometry (the contract: ohmni_tb.robot.api.Robot)."""
        return await self._motion.rotate(
            angle_rad,
            speed_radps=speed_radps,
            timeout_s=timeout_s,
            source=self._sources.name(source),
        )

    async def go_to(
        self,
        x_m: float,
        y_m: float,
        yaw_rad: float | None = None,
        *,
        speed_mps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """Go to a point of the odometry frame (the contract: ohmni_tb.robot.api.Robot)."""
        return await self._motion.go_to(
            x_m,
            y_m,
            yaw_rad,
            speed_mps=speed_mps,
            timeout_s=timeout_s,
            source=self._sources.name(source),
        )

    # -- devices (public) --------------------------------------------------------------------

    @property
    def neck_kind(self) -> str:
        """``herkulex``, ``worm`` or ``none``: which neck answered at open."""
        return self._state.neck_kind

    @property
    def neck(self) -> ServoHandle | WormNeckHandle:
        """The neck's handle (:attr:`Robot.neck <ohmni_tb.robot.api.Robot.neck>`)."""
        return self._discovery.neck()

    def servo(self, sid: int) -> ServoHandle:
        """A HerkuleX servo's handle (:meth:`Robot.servo <ohmni_tb.robot.api.Robot.servo>`)."""
        return self._discovery.servo(sid)

    async def reset_board_id(self, sid: int, new_sid: int, *, confirm: bool = False) -> None:
        """A drive board's new id (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_open()
        await self._renumbering.board(sid, new_sid, confirm=confirm, stop=self._board_stop)

    def _board_stop(self) -> None:
        self._motion.preempt("reset_board_id")
        self._control.stop()

    async def light_ring(self, hue: int, saturation: int, value: int) -> None:
        """The light ring's colour (the contract: ohmni_tb.robot.api.Robot)."""
        packet = set_light_ring(hue, saturation, value, self._state.profile.core)
        self._state.check_port()
        await self._bus.request(packet, expect_reply=False, priority=COMMAND_PRIORITY)

    async def info(self) -> dict[str, Any]:
        """Firmware tags, servo models, the neck kind (the contract: ohmni_tb.robot.api.Robot)."""
        self._state.check_port()
        info = await self._discovery.info()
        info["neck_settings"] = self._settings.report
        info["profile"] = self._state.config.profile().as_json()
        return info

    async def list_ports(self) -> list[dict[str, Any]]:
        """This computer's serial ports (the contract: ohmni_tb.robot.api.Robot), listed in
        a thread: reading the USB descriptors may block."""
        return await asyncio.to_thread(self.ports)

    @staticmethod
    def ports() -> list[dict[str, Any]]:
        """Serial ports of the computer it runs on, with their USB ids, the likely adapter first
        (``likely_bus``; :func:`ohmni_tb.transport.ports.list_ports`)."""
        from ohmni_tb.transport.ports import list_ports  # noqa: PLC0415  # slow: when asked

        return [port.as_dict() for port in list_ports()]


def _port_name(transport: Transport, asked: str) -> str:
    """What ``robot.port`` says: a serial port's device (``auto`` found), else the URL."""
    if isinstance(transport, SerialTransport):
        return transport.port
    return asked


def _reopener(url: str) -> Reopen:
    """Opens ``url`` the first time, and that transport again after (a simulator's robot
    stays the same, as a serial device does)."""
    opened: Transport | None = None

    async def reopen() -> Transport:
        nonlocal opened
        if opened is None or not opened.can_reopen:
            opened = await open_transport(url)
        else:
            opened = await opened.reopen()
        return opened

    return reopen


_coarse_timers_told = False

#: After a reply it has seen, the Robot's bus sends the next request once the reply's
#: sender can have turned its line driver around: a few bit times after its stop bit
#: (the cost model keeps its 0.2 ms guard). The reply's own callback then sends it.
_REPLY_GUARD_BITS = 3


def _reply_guard_s(baudrate: int | None) -> float | None:
    """The quiet the Robot's bus keeps after a reply it has seen (``None``: the guard)."""
    return None if not baudrate else _REPLY_GUARD_BITS / baudrate


def _warn_if_coarse_timers(transport: Transport) -> None:
    """Tell once per process when a serial port runs on a loop with millisecond timers.

    Behind an adapter that holds replies, every request of the schedule goes out on a
    timer, and each one late by up to a millisecond does not fit a line booked to 81 %
    (ohmni_tb.eventloop): the bus sleeps the last millisecond of those waits in the loop
    instead. The simulator in this process delivers at once: not told.
    """
    global _coarse_timers_told  # noqa: PLW0603  # once per process, not per Robot
    if _coarse_timers_told or not isinstance(transport, SerialTransport):
        return
    if timer_resolution_s() < MILLISECOND_S:
        return
    _coarse_timers_told = True
    _log.warning(
        "this event loop's timers fire up to 1 ms late (asyncio's epoll waits, and uvloop "
        "counts its timers, in whole milliseconds): the bus sleeps the last millisecond of "
        "its waits for the line in the loop, which the program's other work waits for; run "
        "the program with ohmni_tb.run(main()) instead of asyncio.run to give it back"
    )
