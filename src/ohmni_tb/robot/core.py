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

The Robot is a façade: it opens and closes, checks arguments and hands the work to
parts of one job each, which share one :class:`~ohmni_tb.robot.state.RobotState`:
:mod:`~ohmni_tb.robot.discovery`, :mod:`~ohmni_tb.robot.control_loop`,
:mod:`~ohmni_tb.robot.wheels`, :mod:`~ohmni_tb.robot.feedback`,
:mod:`~ohmni_tb.robot.guards` and :mod:`~ohmni_tb.robot.link`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, Any, Literal, overload

from ohmni_tb._checks import check_seconds, host_port, number
from ohmni_tb.bus import Bus
from ohmni_tb.config import RobotConfig
from ohmni_tb.control.defaults import CONTROL_HZ_RANGE
from ohmni_tb.control.kinematics import LimitedTwist, Twist, WheelSpeeds
from ohmni_tb.control.pid import PidGains
from ohmni_tb.errors import (
    ConfigError,
    InvalidArgumentError,
    OutOfRangeError,
    StopNotConfirmedError,
)
from ohmni_tb.eventloop import MILLISECOND_S, timer_resolution_s
from ohmni_tb.protocol.core import set_light_ring
from ohmni_tb.protocol.drive import PWM_LIMIT, wheel_command
from ohmni_tb.robot.control_loop import ControlLoop
from ohmni_tb.robot.devices import COMMAND_PRIORITY, ServoHandle, WormNeckHandle
from ohmni_tb.robot.discovery import Discovery
from ohmni_tb.robot.feedback import Feedback
from ohmni_tb.robot.guards import Guards
from ohmni_tb.robot.link import RELEASE_MAX_S, RELEASE_MIN_S, LinkKeeper
from ohmni_tb.robot.samples import (
    PidDebugSample,
    RobotStateSample,
    ServoSample,
    TbcoreStatusSample,
    WheelEncoderSample,
    WheelOdomSample,
    WormNeckSample,
)
from ohmni_tb.robot.state import RobotState
from ohmni_tb.robot.stats import BusFigures, RobotStats
from ohmni_tb.robot.streams import DEFAULT_QUEUE_SIZE, Subscription
from ohmni_tb.robot.wheels import WheelCounts
from ohmni_tb.transport import SerialTransport, Transport, open_transport

if TYPE_CHECKING:
    from ohmni_tb.foxglove import FoxgloveBridge

__all__ = ["BusFigures", "Robot", "RobotStats"]

_log = logging.getLogger(__name__)
#: A feedback stream's rate range, Hz (the control tick's is ``CONTROL_HZ_RANGE``).
FEEDBACK_HZ_RANGE = (0.1, 100.0)


class Robot:
    """One Ohmni robot on its bus (module docstring). Create it with :meth:`open`."""

    def __init__(self, bus: Bus, config: RobotConfig, *, sim: Any = None) -> None:
        self._bus = bus
        self.config = config
        #: The simulated robot (ground truth) on ``sim://``, else ``None``.
        self.sim = sim
        self._loop = asyncio.get_running_loop()
        self._opened_at = self._loop.time()
        # One state shared by the parts, each part one job (each module's docstring).
        self._state = state = RobotState(bus, config, self._loop)
        self._counts = WheelCounts(state)
        self._control = ControlLoop(state, self._counts)
        self._feedback = Feedback(state, self._control, self._counts, Guards(state))
        self._discovery = Discovery(state, self._feedback.found)
        self._link = LinkKeeper(state, self._control, self._feedback, self._discovery)
        #: Why the stop on the way out was not confirmed, if it was not (also raised
        #: from ``async with`` when the block itself ended without an error).
        self.exit_error: StopNotConfirmedError | None = None
        #: The Foxglove view ``Robot.open(foxglove=...)`` serves (its ``url``), else None.
        self.foxglove: FoxgloveBridge | None = None

    # -- opening and closing -----------------------------------------------------------

    @classmethod
    @contextlib.asynccontextmanager
    async def open(
        cls,
        port: str | Transport | None = None,
        *,
        config: RobotConfig | None = None,
        foxglove: str | int | None = None,
        **overrides: Any,
    ) -> AsyncIterator[Robot]:
        """Open the robot on ``port`` (a URL: ``sim://``, ``/dev/ttyUSB0`` …) and run it.

        An async context manager. Leaving it stops the wheels (confirmed by their counts,
        within ``stop_timeout_s``) and rests or frees the neck (``on_exit_neck``), even on
        an error or a cancellation; then the port closes. When the block ended cleanly
        but the counts did not confirm the stop, leaving it raises
        :class:`~ohmni_tb.errors.StopNotConfirmedError` (the robot may be moving); after
        an error, that error goes on and :attr:`exit_error` holds the stop's.

        Args:
            port: The port's URL (default ``config.port``), or an open
                :class:`~ohmni_tb.transport.Transport` (reopened after a loss when it
                can be: :meth:`~ohmni_tb.transport.Transport.reopen`).
            config: The settings (default: :class:`RobotConfig` from the environment).
            foxglove: Serve the streams to the Foxglove app as well, on ``"HOST:PORT"``
                or a port on loopback (``0``: a free one): a read-only
                :class:`~ohmni_tb.foxglove.FoxgloveBridge`, at :attr:`foxglove` while
                open, closed before the Robot stops the wheels. Needs the ``foxglove``
                extra.
            overrides: Settings that replace the config's, by field name.

        Raises:
            ConfigError: A setting is invalid; the message names it (``foxglove`` too,
                and when the extra is not installed).
            TransportError: The port cannot be opened, nor the Foxglove address bound.
        """
        view = None if foxglove is None else _foxglove_address(foxglove)
        if config is None:
            config = RobotConfig(**overrides)
        elif overrides:
            config = config.replace(**overrides)
        if isinstance(port, Transport):
            transport = port  # an open link, injected (a test's, a tap's)
        else:
            transport = await open_transport(port if port is not None else config.port)
        _warn_if_coarse_timers(transport)
        reopen = transport.reopen if transport.can_reopen else None
        bus = Bus(transport, timeout_s=config.bus_timeout_s(), reopen=reopen)
        bus.start()
        robot: Robot | None = None
        try:
            robot = cls(bus, config, sim=transport.simulated)
            await robot._start()
        except BaseException:
            await bus.aclose(final=[wheel_command(0, 0)])
            raise
        try:
            if view is not None:
                robot.foxglove = await _serve_foxglove(robot, *view)
            yield robot
        except BaseException:
            await robot._close_view()
            await robot._close_shielded()
            raise
        await robot._close_view()
        # A clean exit whose stop the wheel counts did not confirm raises: the robot may
        # be moving and nobody else would say so.
        await robot._close_shielded()
        if robot.exit_error is not None:
            raise robot.exit_error

    async def _start(self) -> None:
        await self._discovery.discover()
        self._feedback.build()
        self._feedback.start()
        self._link.start()
        self._discovery.arm()
        self._state.publish("opened")

    async def _close_view(self) -> None:
        """Close the Foxglove view ``open(foxglove=...)`` started, if any."""
        view, self.foxglove = self.foxglove, None
        if view is not None:
            await asyncio.shield(view.aclose())

    async def _close_shielded(self) -> None:
        """Close, and finish closing even if the caller is cancelled meanwhile."""
        await self._state.shielded(self._close(), "close")

    async def _close(self) -> None:
        state = self._state
        if state.closed:
            return
        state.closed = True
        state.closing = asyncio.current_task()
        self.exit_error = await self._link.close()

    @property
    def closed(self) -> bool:
        """Whether the Robot was closed."""
        return self._state.closed

    @property
    def bus(self) -> Bus:
        """The bus the Robot schedules (for figures and raw access; mind the schedule)."""
        return self._bus

    def schedule(self) -> list[tuple[str, float, float, float]]:
        """The schedule: per stream its rate (Hz), phase (s) and line time per cycle (s).

        The control slot is always in it (it runs whether its samples are wanted or not);
        a feedback stream only while it is enabled.
        """
        return self._feedback.rows()

    # -- port hand-off (public) ----------------------------------------------------------

    async def release_port(self, duration_s: float | None = None) -> None:
        """Hand the serial port to another program (tb-node, a flashing tool) for a while.

        The wheels are stopped first, as leaving ``async with`` stops them: the stop
        jumps the queue and is repeated until the wheel counts confirm it (within
        ``stop_timeout_s``). The HerkuleX neck is then rested or freed as on exit
        (``on_exit_neck``, default ``free``): while the port is released nobody watches
        its temperature, and a neck left holding torque overheats; ``keep`` leaves it
        holding. The worm-gear neck holds without power and is left as it is. Then the
        streams stop and the port closes (its file descriptor and exclusive lock are
        free); ``robot_state`` says ``released`` with an event, and ``link`` is
        :attr:`Link.RELEASED` in :attr:`state` and every later sample.

        While released, :meth:`drive`, :meth:`drive_wheels`, :meth:`drive_pwm`, the neck
        and servo commands, :meth:`light_ring` and :meth:`info` raise
        :class:`~ohmni_tb.errors.StateError` and send nothing; :meth:`latest`,
        :meth:`subscribe` and :meth:`stats` keep working (the streams just pause), and
        the link watcher does not take the release for a lost link. Closing the Robot
        while released sends nothing and returns at once.

        Releasing again while released replaces the timer (``duration_s`` counts from
        the new call; ``None`` cancels it) and stops a reclaim that waits for the port.
        It runs to its end even if the caller is cancelled (then the cancellation goes on).

        Args:
            duration_s: Take the port back by itself after this many seconds,
                0.1..3600 (:meth:`reclaim_port` is called for you); ``None``: keep it
                released until :meth:`reclaim_port`.

        Raises:
            OutOfRangeError: ``duration_s`` is not a number of seconds in 0.1..3600;
                nothing changed.
            StateError: The Robot is closed, or it cannot reopen its port (it was opened
                on an injected transport that cannot reopen); nothing changed.
            StopNotConfirmedError: The wheel counts did not confirm the stop: the robot
                may be moving. The port was released all the same, as closing would
                have closed it (the other program may be what is needed to stop it).
        """
        if duration_s is not None:
            check_seconds("duration_s", duration_s, RELEASE_MIN_S, RELEASE_MAX_S)
            duration_s = float(duration_s)
        self._state.check_open()
        await self._link.release(duration_s)

    async def reclaim_port(self) -> None:
        """Take the serial port back after :meth:`release_port`. A no-op when not released.

        The port is reopened, a zero wheel command goes out first, the streams restart
        on a fresh phase, ``link`` is :attr:`Link.CONNECTED` again and ``robot_state``
        says ``port reclaimed``; then it returns. Absent devices are asked again.

        If the port cannot be opened now (the other program still holds it), it does
        not raise: ``robot_state`` says the Robot is waiting for the port, the link
        stays :attr:`Link.RELEASED`, and this returns after that first attempt while the
        Robot keeps trying in the background with a doubling backoff (up to
        ``reconnect_max_backoff_s``), as after a lost link; ``port reclaimed`` follows
        once it opens. Check :attr:`state` (``link``) or watch ``robot_state`` to know;
        drive commands raise :class:`~ohmni_tb.errors.StateError` until then. A
        :meth:`release_port` meanwhile stops the waiting. Cancelling the call does not
        cancel the reclaim.

        Raises:
            StateError: The Robot is closed (or closed while this waited).
        """
        self._state.check_open()
        await self._link.reclaim()

    # -- streams (public) --------------------------------------------------------------------

    @overload
    def latest(self, name: Literal["wheel_encoder"]) -> WheelEncoderSample | None: ...
    @overload
    def latest(self, name: Literal["wheel_odom"]) -> WheelOdomSample | None: ...
    @overload
    def latest(self, name: Literal["tbcore_status"]) -> TbcoreStatusSample | None: ...
    @overload
    def latest(
        self, name: Literal["servo_neck", "servo_ext1", "servo_ext2"]
    ) -> ServoSample | None: ...
    @overload
    def latest(self, name: Literal["new_neck"]) -> WormNeckSample | None: ...
    @overload
    def latest(self, name: Literal["robot_state"]) -> RobotStateSample | None: ...
    @overload
    def latest(self, name: Literal["pid_debug"]) -> PidDebugSample | None: ...
    @overload
    def latest(self, name: str) -> Any: ...
    def latest(self, name: str) -> Any:
        """The newest sample of stream ``name``, or ``None`` before the first.

        Raises:
            InvalidArgumentError: No such stream; the message lists them.
        """
        return self._state.topic(name).latest

    @overload
    def subscribe(
        self, name: Literal["wheel_encoder"], *, maxlen: int = ...
    ) -> Subscription[WheelEncoderSample]: ...
    @overload
    def subscribe(
        self, name: Literal["wheel_odom"], *, maxlen: int = ...
    ) -> Subscription[WheelOdomSample]: ...
    @overload
    def subscribe(
        self, name: Literal["tbcore_status"], *, maxlen: int = ...
    ) -> Subscription[TbcoreStatusSample]: ...
    @overload
    def subscribe(
        self, name: Literal["servo_neck", "servo_ext1", "servo_ext2"], *, maxlen: int = ...
    ) -> Subscription[ServoSample]: ...
    @overload
    def subscribe(
        self, name: Literal["new_neck"], *, maxlen: int = ...
    ) -> Subscription[WormNeckSample]: ...
    @overload
    def subscribe(
        self, name: Literal["robot_state"], *, maxlen: int = ...
    ) -> Subscription[RobotStateSample]: ...
    @overload
    def subscribe(
        self, name: Literal["pid_debug"], *, maxlen: int = ...
    ) -> Subscription[PidDebugSample]: ...
    @overload
    def subscribe(self, name: str, *, maxlen: int = ...) -> Subscription[Any]: ...
    def subscribe(self, name: str, *, maxlen: int = DEFAULT_QUEUE_SIZE) -> Subscription[Any]:
        """An async iterator over stream ``name``'s samples from now on.

        It keeps at most ``maxlen`` samples; a reader that falls behind loses the oldest
        (counted in the subscription's ``dropped`` and the stream's stats), and the
        schedule never waits for it. Iteration ends when the Robot closes (at once for
        a subscription taken after).

        Raises:
            InvalidArgumentError: No such stream.
            OutOfRangeError: ``maxlen`` is not 1..100000.
        """
        return self._state.topic(name).subscribe(maxlen)

    def enable_stream(self, name: str, enabled: bool = True) -> None:
        """Turn a stream on or off at run time (tb_control's ``enable_sensor_stream``).

        Turning off ``wheel_encoder`` stops only its samples: the control slot keeps
        running while the wheels are driven. Off streams stop their bus reads.

        Raises:
            InvalidArgumentError: No such stream.
            StateError: The stream's device is absent (it cannot be turned on).
            RobotClosedError: The Robot is closed.
        """
        self._state.check_open()
        topic = self._state.topic(name)
        if not isinstance(enabled, bool):
            raise InvalidArgumentError(f"enabled must be True or False, not {enabled!r}")
        self._feedback.enable(name, topic, enabled)

    def set_rate(self, name: str, hz: float) -> None:
        """Change a polled stream's rate (the control tick's too, ``wheel_encoder``).

        The control tick (``wheel_encoder``, which ``wheel_odom`` and ``pid_debug``
        follow) takes 10..100 Hz (:data:`~ohmni_tb.control.defaults.CONTROL_HZ_RANGE`, as
        ``wheel_hz``); a feedback stream 0.1..100 Hz.

        Raises:
            InvalidArgumentError: No such stream, or it is not polled.
            OutOfRangeError: ``hz`` is outside the stream's range; nothing changes.
            RobotClosedError: The Robot is closed.
        """
        self._state.check_open()
        self._state.topic(name)
        low, high = CONTROL_HZ_RANGE if name == "wheel_encoder" else FEEDBACK_HZ_RANGE
        if not low <= number("hz", hz) <= high:
            raise OutOfRangeError(f"{name} rate", hz, low, high, "Hz")
        self._feedback.set_rate(name, hz)

    def stats(self) -> RobotStats:
        """Per-stream rates, jitter, missed/skipped cycles and the bus's figures."""
        return self._feedback.stats(self._opened_at)

    @property
    def state(self) -> RobotStateSample:
        """The Robot's state now (as ``robot_state`` would publish it)."""
        return self._state.sample(None)

    # -- motion commands (public) ----------------------------------------------------------

    def drive(self, linear_mps: float, angular_radps: float = 0.0) -> LimitedTwist:
        """Set the body velocity target (m/s forward, rad/s counter-clockwise).

        Not a coroutine: the control tick drives toward the target, within the speed
        limits (scaled keeping the curvature; the return value says by how much) and the
        acceleration limits. The watchdog stops the wheels ``watchdog_s`` after the last
        call: repeat it (at 5..20 Hz) to keep moving.

        Raises:
            InvalidArgumentError: A value is not a finite number.
            StateError: An emergency stop is latched, the port is released
                (:meth:`release_port`), or the robot is closed.
        """
        twist = Twist(number("linear_mps", linear_mps), number("angular_radps", angular_radps))
        self._control.check_can_drive()
        return self._control.drive(twist)

    def drive_wheels(self, left_mps: float, right_mps: float) -> WheelSpeeds:
        """Set each wheel's rim speed target (m/s, forward positive), no ramp.

        Both are scaled by one factor into ``max_wheel_mps``; the return value is what
        is driven.

        Raises:
            InvalidArgumentError: A value is not a finite number.
            StateError: An emergency stop is latched, the port is released
                (:meth:`release_port`), or the robot is closed.
        """
        asked = WheelSpeeds(number("left_mps", left_mps), number("right_mps", right_mps))
        self._control.check_can_drive()
        return self._control.drive_wheels(asked)

    def drive_pwm(self, left: int, right: int) -> None:
        """Drive the wheels open loop with raw PWM −1000..1000 (the controllers step aside).

        Forward positive for both wheels (the right board's mirror is handled in the
        packet). The watchdog still applies.

        Raises:
            InvalidArgumentError: Not ints.
            OutOfRangeError: Outside −1000..1000; nothing changes.
            StateError: An emergency stop is latched, the port is released
                (:meth:`release_port`), or the robot is closed.
        """
        for name, value in (("left", left), ("right", right)):
            if isinstance(value, bool) or not isinstance(value, int):
                raise InvalidArgumentError(f"{name} PWM must be an int, not {value!r}")
            if not -PWM_LIMIT <= value <= PWM_LIMIT:
                raise OutOfRangeError(f"{name} PWM", value, -PWM_LIMIT, PWM_LIMIT)
        self._control.check_can_drive()
        self._control.drive_pwm(left, right)

    def stop(self) -> None:
        """Target zero: the wheels ramp down at the deceleration limits.

        The first braking command goes on the wire at once (in the next free slot), not
        at the next control tick.

        Raises:
            RobotClosedError: The Robot is closed (closing stopped the wheels).
        """
        self._state.check_open()
        self._control.stop()

    async def estop(self) -> None:
        """Emergency stop: zero PWM ahead of everything queued, latched until cleared.

        Drive commands are refused until :meth:`clear_estop`.

        Raises:
            RobotClosedError: The Robot is closed (closing stopped the wheels).
        """
        self._state.check_open()
        await self._control.estop()

    def clear_estop(self) -> None:
        """Release a latched emergency stop (the robot stays still until commanded).

        Raises:
            RobotClosedError: The Robot is closed.
        """
        self._state.check_open()
        self._control.clear_estop()

    def enable_controllers(self, enabled: bool = True) -> None:
        """Run the wheel PIDs (default), or not: then only :meth:`drive_pwm` moves.

        Raises:
            InvalidArgumentError: ``enabled`` is not a bool.
            RobotClosedError: The Robot is closed.
        """
        self._state.check_open()
        self._control.enable_controllers(enabled)

    def get_pid(self) -> PidGains:
        """The wheel PIDs' gains (both wheels share them)."""
        return self._control.gains

    def set_pid(self, gains: PidGains) -> None:
        """Change the wheel PIDs' gains, bumplessly (the output does not jump).

        Each gain has one allowed range, the same as the ``pid_*`` settings'
        (:data:`~ohmni_tb.control.defaults.WHEEL_GAIN_RANGES`). Whatever the gains, a
        wheel measured faster than ``max_wheel_mps`` gets no drive power.

        Raises:
            InvalidArgumentError: Not a :class:`PidGains`.
            OutOfRangeError: A gain is outside its range; nothing changes.
            RobotClosedError: The Robot is closed.
        """
        self._state.check_open()
        self._control.set_gains(gains)

    def reset_odometry(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """Set the odometry pose (tb_control's ``reset_odom``).

        Raises:
            InvalidArgumentError: A value is not a finite number.
            OutOfRangeError: A value is beyond ±1e6 (m or rad: :data:`MAX_POSE_M`).
            RobotClosedError: The Robot is closed.
        """
        self._state.check_open()
        self._counts.reset_odometry(x_m, y_m, yaw_rad)

    # -- devices (public) --------------------------------------------------------------------

    @property
    def neck_kind(self) -> str:
        """``herkulex``, ``worm`` or ``none``: which neck answered at open."""
        return self._state.neck_kind

    @property
    def neck(self) -> ServoHandle | WormNeckHandle:
        """The neck: a HerkuleX servo handle or the worm-gear neck's.

        Raises:
            StateError: No neck answered at open.
        """
        return self._discovery.neck()

    def servo(self, sid: int) -> ServoHandle:
        """The HerkuleX servo ``sid`` (the neck or an external one found at open).

        Raises:
            StateError: No such servo answered.
        """
        return self._discovery.servo(sid)

    async def light_ring(self, hue: int, saturation: int, value: int) -> None:
        """Set the light ring's colour (0..255 each).

        Raises:
            OutOfRangeError: A component is outside 0..255; nothing sent.
            StateError: The port is released (:meth:`release_port`); nothing sent.
        """
        packet = set_light_ring(hue, saturation, value)
        self._state.check_port()
        await self._bus.request(packet, expect_reply=False, priority=COMMAND_PRIORITY)

    async def info(self) -> dict[str, Any]:
        """Firmware tags, servo models and the neck kind.

        Raises:
            StateError: The port is released (:meth:`release_port`).
        """
        self._state.check_port()
        return await self._discovery.info()

    @staticmethod
    def ports() -> list[dict[str, Any]]:
        """Serial ports on this machine with their USB ids, the likely bus adapter first
        (``likely_bus``; :func:`ohmni_tb.transport.ports.list_ports`)."""
        from ohmni_tb.transport.ports import list_ports  # noqa: PLC0415  # slow: when asked

        return [port.as_dict() for port in list_ports()]


def _foxglove_address(value: str | int) -> tuple[str, int]:
    """``Robot.open(foxglove=...)``: ``"HOST:PORT"``, ``"PORT"`` or a port number.

    Raises:
        ConfigError: Not such an address, or a port outside 0..65535.
    """
    text = str(value) if isinstance(value, int) and not isinstance(value, bool) else value
    address = host_port(text, default_host="127.0.0.1") if isinstance(text, str) else None
    if address is None:
        raise ConfigError(f"foxglove must be 'HOST:PORT' or a port 0..65535, not {value!r}")
    return address


async def _serve_foxglove(robot: Robot, host: str, port: int) -> FoxgloveBridge:
    try:
        from ohmni_tb.foxglove import FoxgloveBridge  # noqa: PLC0415  # the optional extra
    except ImportError as exc:
        raise ConfigError(
            "Robot.open(foxglove=...) needs the foxglove extra: pip install 'ohmni_tb[foxglove]'"
        ) from exc
    bridge = FoxgloveBridge(robot, host=host, port=port)
    await bridge.start()
    _log.info("serving the Foxglove app on %s", bridge.url)
    return bridge


_coarse_timers_told = False


def _warn_if_coarse_timers(transport: Transport) -> None:
    """Tell once per process when a serial port runs on a loop with millisecond timers.

    Behind an adapter that holds replies, every request of the schedule goes out on a
    timer, and each one late by up to a millisecond does not fit a line booked to 81 %
    (ohmni_tb.eventloop). The simulator in this process delivers at once: not told.
    """
    global _coarse_timers_told  # noqa: PLW0603  # once per process, not per Robot
    if _coarse_timers_told or not isinstance(transport, SerialTransport):
        return
    if timer_resolution_s() < MILLISECOND_S:
        return
    _coarse_timers_told = True
    _log.warning(
        "this event loop's timers fire up to 1 ms late (asyncio's epoll waits in whole "
        "milliseconds): behind a USB adapter that holds replies the servo streams can miss "
        "their rates; run the program with ohmni_tb.run(main()) instead of asyncio.run"
    )
