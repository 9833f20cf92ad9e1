"""The Robot's contract: one API, whether the robot is on this process's port or served by
``ohmni serve``.

::

    from ohmni_tb import Robot

    async with Robot.open("sim://") as robot:           # or "/dev/ttyUSB0", or a daemon:
        ...                                               # Robot.open("ws://127.0.0.1:8766")

:class:`Robot` is an abstract base, as python-can's ``BusABC``: :meth:`Robot.open` picks
the implementation by the port — :class:`~ohmni_tb.robot.LocalRobot` runs the bus itself
(``sim://``, a device path, a :class:`~ohmni_tb.transport.Transport`);
:class:`~ohmni_tb.robot.RemoteRobot` talks to the daemon (``ws://``, ``wss://``). Both
answer every call below the same way: a call that is plain on one is plain on the other,
and a bad value raises the same error, with the same message, before anything is sent
(:mod:`ohmni_tb.robot.checks`). What only a local robot has (``bus``, ``ports()``,
``exit_error``) is on :class:`~ohmni_tb.robot.LocalRobot`.
"""

from __future__ import annotations

import abc
from contextlib import AbstractAsyncContextManager
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Protocol, TypeVar, overload

from ohmni_tb.errors import ConfigError
from ohmni_tb.protocol import Memory
from ohmni_tb.robot.streams import DEFAULT_QUEUE_SIZE

if TYPE_CHECKING:
    from ohmni_tb.config import RobotConfig
    from ohmni_tb.control.kinematics import LimitedTwist, WheelSpeeds
    from ohmni_tb.control.pid import PidGains
    from ohmni_tb.errors import MotionResult
    from ohmni_tb.herkulex import TorqueControl
    from ohmni_tb.herkulex.servo import ServoStatus
    from ohmni_tb.protocol.profile import BusProfile
    from ohmni_tb.robot.checks import Wheel
    from ohmni_tb.robot.samples import (
        DiagnosticsSample,
        PidDebugSample,
        RobotStateSample,
        ServoSample,
        TbcoreStatusSample,
        WheelEncoderSample,
        WheelOdomSample,
        WormNeckSample,
    )
    from ohmni_tb.robot.stats import RobotStats
    from ohmni_tb.transport import Transport

__all__ = ["HerkulexHandle", "NeckHandle", "Robot", "RobotStreams", "SampleStream"]

T_co = TypeVar("T_co", covariant=True)


class SampleStream(Protocol[T_co]):
    """One stream's samples from now on (:meth:`Robot.subscribe`): an async iterator that
    holds at most ``maxlen`` samples, dropping (and counting) the oldest when its reader
    falls behind; also an async context manager that closes it on exit."""

    @property
    def name(self) -> str:
        """The stream's name."""
        ...

    @property
    def dropped(self) -> int:
        """Samples it lost because its reader did not keep up."""
        ...

    @property
    def pending(self) -> int:
        """Samples waiting to be read."""
        ...

    @property
    def closed(self) -> bool:
        """Whether it was closed (queued samples can still be read)."""
        ...

    def close(self) -> None:
        """Stop receiving; a waiting reader's iteration ends."""
        ...

    def get_nowait(self) -> T_co | None:
        """The oldest queued sample, or ``None``."""
        ...

    def __aiter__(self) -> SampleStream[T_co]: ...

    async def __anext__(self) -> T_co: ...

    async def __aenter__(self) -> SampleStream[T_co]: ...

    async def __aexit__(self, *exc: object) -> None: ...


class NeckHandle(Protocol):
    """The neck, HerkuleX or worm gear (:attr:`Robot.neck`): what both kinds do."""

    @property
    def sid(self) -> int:
        """Its bus id (the HerkuleX neck's, or 4: the worm gear)."""
        ...

    @property
    def min_raw(self) -> int:
        """Lowest allowed position, raw counts."""
        ...

    @property
    def max_raw(self) -> int:
        """Highest allowed position, raw counts."""
        ...

    async def move(
        self,
        raw: int | None = None,
        *,
        rad: float | None = None,
        playtime_s: float = 1.0,
        wait: bool = False,
        timeout_s: float | None = None,
    ) -> ServoSample | WormNeckSample | None:
        """Move to ``raw`` counts, or ``rad`` (a HerkuleX servo), over ``playtime_s`` (a
        HerkuleX servo; the worm gear takes ``raw`` alone).

        With ``wait``, return once its feedback stream reads back at the target (a
        HerkuleX servo: within ``HERKULEX_TOLERANCE_RAW`` and done moving; the worm gear:
        within ``WORM_TOLERANCE_RAW``, at rest), within ``timeout_s`` (0..600 s; default
        the playtime + 1.5 s, the worm gear 15 s).

        Returns:
            With ``wait``, the sample that read back at the target; else ``None``.

        Raises:
            InvalidArgumentError: Neither or both of ``raw`` and ``rad``, not numbers, an
                argument the worm-gear neck does not take, or ``timeout_s`` without
                ``wait``.
            OutOfRangeError: Outside ``min_raw..max_raw``, a playtime outside
                0..2.8448 s (it goes to the nearest 11.2 ms tick) or a timeout outside
                0..600 s; nothing sent.
            StateError: The port is released (:meth:`Robot.release_port`), or ``wait``
                and the feedback stream is off; nothing sent.
            PositionError: ``wait``, and the worm gear stalled.
            PositionTimeoutError: ``wait``, and not there in time (or no sample came).
        """
        ...

    async def rest(self, *, free: bool = True) -> None:
        """Move to the rest position, then free it (a HerkuleX servo; the worm gear holds
        without power: nothing to do)."""
        ...


class HerkulexHandle(NeckHandle, Protocol):
    """A HerkuleX servo (:meth:`Robot.servo`, and the neck when it is one): torque modes too."""

    @property
    def rest_raw(self) -> int:
        """Where :meth:`rest` moves it."""
        ...

    @property
    def zero_offset_raw(self) -> int:
        """Raw counts added to 512 to define 0 rad."""
        ...

    async def move(
        self,
        raw: int | None = None,
        *,
        rad: float | None = None,
        playtime_s: float = 1.0,
        wait: bool = False,
        timeout_s: float | None = None,
    ) -> ServoSample | None:
        """As :meth:`NeckHandle.move`: the sample a HerkuleX servo's stream carries."""
        ...

    async def torque(self, mode: TorqueControl | str) -> None:
        """Set the torque mode: ``"on"``, ``"brake"`` or ``"free"``.

        Raises:
            InvalidArgumentError: Another mode.
        """
        ...

    async def free(self) -> None:
        """Torque off: the servo can be turned by hand and draws no holding current."""
        ...

    # -- maintenance (tb_control's get_servo_info, servo_write_eep, reset_servo_id,
    # set_servo_zero_offset); through the daemon all but info need the control lease.

    async def info(self) -> dict[str, dict[str, int]]:
        """Every register of the servo, ``{"eep": {name: value}, "ram": {...}}``
        (tb_control's ``get_servo_info``). Read-only: no lease needed through the daemon.

        Raises:
            StateError: The port is released (:meth:`Robot.release_port`).
            BusTimeoutError: The servo did not answer.
        """
        ...

    async def write(
        self,
        register: str | int,
        value: int,
        *,
        persist: bool = False,
        memory: Memory | str = Memory.RAM,
    ) -> None:
        """Write a register by name or address: RAM (acts now; with ``persist`` its EEP
        copy too, which survives a reboot), or with ``memory="eep"`` the EEP register
        alone (acts after a reboot: tb_control's ``servo_write_eep``, e.g.
        ``write(30, 200, memory="eep")``, EEP 30 being ``position_kp``). Checked against
        the register map first.

        Raises:
            InvalidArgumentError: Unknown register or memory, no register at that address,
                a read-only one, ``persist`` with an EEP write or of a register with no EEP
                copy, or the id (:meth:`set_id` changes it); nothing sent.
            OutOfRangeError: The value is outside the register's range; nothing sent.
            StateError: The port is released; nothing sent.
        """
        ...

    async def set_id(self, new_sid: int) -> None:
        """Give the servo a new id, in EEP and RAM (tb_control's ``reset_servo_id``).

        The robot follows: this handle and ``robot.servo(new_sid)`` speak to it, its
        stream (``servo_neck``, ``servo_ext1``…) goes on from the new id without a missed
        cycle, ``robot.servo(old)`` raises :class:`~ohmni_tb.errors.StateError` naming
        the new id, and ``config.ext_servo_ids`` (or ``config.neck_id``) holds the new id.

        Raises:
            OutOfRangeError: ``new_sid`` is not 0..253; nothing sent.
            StateError: Another device the robot knows has that id (a board, the neck, an
                external servo), or the port is released; nothing sent.
        """
        ...

    async def set_zero_offset(self, raw: int) -> None:
        """Set :attr:`zero_offset_raw`, the raw counts added to 512 to define 0 rad
        (tb_control's ``set_servo_zero_offset``): angles read and commanded from now on
        use it (the neck's ``neck_zero_offset_raw`` setting follows). Nothing is sent to
        the servo.

        Raises:
            InvalidArgumentError: Not an int.
            OutOfRangeError: Outside −512..511.
        """
        ...

    # -- status (tb_control reports it in every servo sample; these ask the servo now).

    async def status(self) -> ServoStatus:
        """The servo's two status bytes, asked now (STAT): its latched errors (RAM 48) and
        torque on, moving, in position… (RAM 49). Read-only: no lease needed through the
        daemon.

        Raises:
            StateError: The port is released (:meth:`Robot.release_port`); nothing sent.
            BusTimeoutError: The servo did not answer.
        """
        ...

    async def clear_errors(self) -> ServoStatus:
        """Clear the servo's latched errors (RAM 48/49 ← 0) and return its status after.

        The torque stays as the fault left it: a fault that released it leaves it off,
        and :meth:`torque` ``"on"`` (or the next :meth:`move`) turns it on again. An
        error whose cause remains (still too hot) comes back at once: check
        ``ServoStatus.ok``. Through the daemon it needs the control lease.

        Raises:
            StateError: The port is released; nothing sent.
            BusTimeoutError: The servo did not answer.
        """
        ...


class RobotStreams(abc.ABC):
    """The streams half of the Robot's contract (:class:`Robot` is the whole): the newest
    sample of a stream, subscriptions, the figures, and turning streams on and off."""

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
    def latest(self, name: Literal["diagnostics"]) -> DiagnosticsSample | None: ...
    @overload
    def latest(self, name: str) -> Any: ...
    def latest(self, name: str) -> Any:
        """The newest sample of stream ``name``, or ``None`` before the first.

        Not awaited. A remote robot keeps the newest sample of every stream as the
        daemon sends it (a round trip late).

        Raises:
            InvalidArgumentError: No such stream; the message lists them.
        """
        return self._latest(name)

    @overload
    def subscribe(
        self, name: Literal["wheel_encoder"], *, maxlen: int = ...
    ) -> SampleStream[WheelEncoderSample]: ...
    @overload
    def subscribe(
        self, name: Literal["wheel_odom"], *, maxlen: int = ...
    ) -> SampleStream[WheelOdomSample]: ...
    @overload
    def subscribe(
        self, name: Literal["tbcore_status"], *, maxlen: int = ...
    ) -> SampleStream[TbcoreStatusSample]: ...
    @overload
    def subscribe(
        self, name: Literal["servo_neck", "servo_ext1", "servo_ext2"], *, maxlen: int = ...
    ) -> SampleStream[ServoSample]: ...
    @overload
    def subscribe(
        self, name: Literal["new_neck"], *, maxlen: int = ...
    ) -> SampleStream[WormNeckSample]: ...
    @overload
    def subscribe(
        self, name: Literal["robot_state"], *, maxlen: int = ...
    ) -> SampleStream[RobotStateSample]: ...
    @overload
    def subscribe(
        self, name: Literal["pid_debug"], *, maxlen: int = ...
    ) -> SampleStream[PidDebugSample]: ...
    @overload
    def subscribe(
        self, name: Literal["diagnostics"], *, maxlen: int = ...
    ) -> SampleStream[DiagnosticsSample]: ...
    @overload
    def subscribe(self, name: str, *, maxlen: int = ...) -> SampleStream[Any]: ...
    def subscribe(self, name: str, *, maxlen: int = DEFAULT_QUEUE_SIZE) -> SampleStream[Any]:
        """An async iterator over stream ``name``'s samples from now on.

        It keeps at most ``maxlen`` samples; a reader that falls behind loses the oldest
        (counted in the subscription's ``dropped`` and the stream's stats), and the
        schedule never waits for it. Iteration ends when the robot closes (at once for
        a subscription taken after).

        Raises:
            InvalidArgumentError: No such stream.
            OutOfRangeError: ``maxlen`` is not 1..100000.
        """
        return self._subscribe(name, maxlen)

    @abc.abstractmethod
    def _latest(self, name: str) -> Any:
        """:meth:`latest`'s work."""

    @abc.abstractmethod
    def _subscribe(self, name: str, maxlen: int) -> SampleStream[Any]:
        """:meth:`subscribe`'s work."""

    @abc.abstractmethod
    def stats(self) -> RobotStats:
        """Per-stream rates, jitter, missed/skipped cycles and the bus's figures.

        Not awaited. A remote robot's are the daemon's (stamps on the daemon's clock), as
        a copy it refreshes in the background (:mod:`ohmni_tb.robot.remote`: at most
        0.5 s and a round trip old while read, up to 5 s at the first read after a pause).
        """

    @abc.abstractmethod
    def schedule(self) -> list[tuple[str, float, float, float]]:
        """The schedule: per stream its rate (Hz), phase (s) and line time per cycle (s).

        The control slot is always in it (it runs whether its samples are wanted or not);
        a feedback stream only while it is enabled. Not awaited (a remote robot's is the
        daemon's, fetched at connecting and again after each ``set_rate`` and
        ``enable_stream``).
        """

    @property
    @abc.abstractmethod
    def state(self) -> RobotStateSample:
        """The robot's state (as ``robot_state`` publishes it): link, emergency stop,
        watchdog, faults, neck, devices present and absent, the command source that
        drives (``active_source``)."""

    @abc.abstractmethod
    def enable_stream(self, name: str, enabled: bool = True) -> None:
        """Turn a stream on or off at run time (tb_control's ``enable_sensor_stream``).

        Turning off ``wheel_encoder`` stops only its samples: the control slot keeps
        running while the wheels are driven. Off streams stop their bus reads.

        Raises:
            InvalidArgumentError: No such stream, or ``enabled`` is not a bool.
            StateError: The stream's device is absent (it cannot be turned on).
            RobotClosedError: The robot is closed.
        """

    @abc.abstractmethod
    def set_rate(self, name: str, hz: float) -> None:
        """Change a polled stream's rate (the control tick's too, ``wheel_encoder``).

        The control tick (``wheel_encoder``, which ``wheel_odom`` and ``pid_debug``
        follow) takes 10..100 Hz (:data:`~ohmni_tb.control.defaults.CONTROL_HZ_RANGE`, as
        ``wheel_hz``); a feedback stream 0.1 Hz up to the top of its setting's range
        (:attr:`StreamSpec.rate_range_hz <ohmni_tb.robot.samples.StreamSpec>`).

        Raises:
            InvalidArgumentError: No such stream, or it is not polled.
            OutOfRangeError: ``hz`` is outside the stream's range; nothing changes.
            RobotClosedError: The robot is closed.
        """


class Robot(RobotStreams):
    """One Ohmni robot: open it with :meth:`open` (module docstring).

    Attributes:
        config: The settings the robot runs with (a remote robot's: the daemon's).
        sim: The simulated robot (its ground truth: ``pose``, ``wheel_speeds_mps()``…)
            when this process runs the simulator behind a ``sim://`` port, else ``None``
            (a remote robot's simulator runs in the daemon).
    """

    config: RobotConfig
    sim: Any
    #: The implementations, each with the ports it opens (``_opens``).
    _implementations: ClassVar[list[type[Robot]]] = []

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "_opens" in cls.__dict__:
            Robot._implementations.append(cls)

    @classmethod
    def _opens(cls, port: str | Transport | None) -> bool:
        """Whether this implementation opens ``port`` (each implementation says)."""
        return False

    # -- opening -----------------------------------------------------------------------------

    @classmethod
    def open(
        cls,
        port: str | Transport | None = None,
        *,
        token: str | None = None,
        config: RobotConfig | None = None,
        profile: BusProfile | None = None,
        source: str | None = None,
        **overrides: Any,
    ) -> AbstractAsyncContextManager[Robot]:
        """Open the robot on ``port`` and run it: ``async with Robot.open(port) as robot:``.

        The port picks the implementation: ``ws://host:port`` or ``wss://…`` is a daemon
        (``ohmni serve``) and gives a :class:`~ohmni_tb.robot.RemoteRobot`; anything else
        (``sim://``, ``/dev/ttyUSB0``, ``serial://…``, ``auto``, an open
        :class:`~ohmni_tb.transport.Transport`, ``None`` for ``config.port``) gives a
        :class:`~ohmni_tb.robot.LocalRobot`, which runs the bus in this process.

        Leaving the block stops the robot. A local robot stops the wheels (confirmed by
        their counts, within ``stop_timeout_s``) and rests or frees the neck
        (``on_exit_neck``), even on an error or a cancellation, then closes the port;
        when the block ended cleanly but the counts did not confirm the stop, leaving
        raises :class:`~ohmni_tb.errors.StopNotConfirmedError`. A remote robot closes its
        connection: the daemon stops the robot if this connection held the control lease.

        Args:
            port: Where the robot is (see above; default ``config.port``).
            token: The daemon's token (its token file's content), needed beyond loopback;
                default ``$OHMNI_DAEMON_TOKEN``. A local robot takes none.
            config: The settings of a local robot (default: :class:`RobotConfig` from the
                environment and the config file). A remote robot runs with the daemon's.
            profile: The bus profile of a local robot (wheel command form, battery block,
                worm neck registers, external servo ids): a
                :class:`~ohmni_tb.protocol.profile.BusProfile`, e.g. what ``ohmni probe``
                found; it replaces the config's profile settings. A remote robot runs with
                the daemon's.
            source: The command source of this robot's drive commands and motion goals
                that name none (:attr:`source`): ``"local"`` for a person at the robot,
                ``"remote"`` for an operator elsewhere…, one of ``command_sources``;
                default ``"autonomy"``, a script's. Through the daemon it is the lease
                this robot takes (only a program on the daemon's computer may take
                ``local`` or ``safety``).
            overrides: Settings that replace the config's, by field name (a local robot);
                a remote robot takes ``timeout_s`` (each call, 5 s) and ``reconnect``.

        Raises:
            ConfigError: A setting is invalid (the message names it), a token for a local
                robot, settings for a remote one, a ``source`` not in the robot's
                ``command_sources``, or a malformed daemon URL.
            TransportError: The port cannot be opened, or the daemon does not answer or
                refused the connection.
        """
        for implementation in Robot._implementations:
            if implementation._opens(port):
                return implementation.open(
                    port, token=token, config=config, profile=profile, source=source, **overrides
                )
        raise ConfigError(f"no Robot implementation opens {port!r}")

    @property
    @abc.abstractmethod
    def closed(self) -> bool:
        """Whether the robot was closed: every call then raises
        :class:`~ohmni_tb.errors.RobotClosedError` (the plain reads excepted)."""

    async def confirm(self) -> None:  # a no-op here, on purpose: see the docstring
        """Wait until every command so far has taken effect.

        A local robot applies each command as it is called (this returns at once); a
        remote robot sends plain commands without waiting, and this waits for the
        daemon's answers to all of them.

        Raises:
            OhmniError: The first of them that was refused (the lease taken by another
                client, an emergency stop latched meanwhile …), if not raised already.
            TransportError: The daemon did not answer in time, or went away.
        """

    # -- motion --------------------------------------------------------------------------------

    @property
    @abc.abstractmethod
    def source(self) -> str:
        """The command source of this robot's drive commands and motion goals that name
        none: ``Robot.open(..., source=…)``, default ``"autonomy"``.

        Command sources (the ``command_sources`` setting; docs/robot.md, *Command
        sources*): each has a priority, its place in the table — by default ``safety``,
        ``local`` (a person at the robot), ``remote`` (an operator elsewhere),
        ``autonomy`` (a script) — and a timeout. A source is live from a drive command
        of it that was taken until its timeout passes without another, and all the
        while one of its motion goals runs. The highest live source drives
        (``robot_state``'s ``active_source``): a drive command or goal from a lower one
        raises :class:`~ohmni_tb.errors.SourceOverriddenError` and sends nothing, and
        its commands are taken again once the higher one lapses. :meth:`stop` and
        :meth:`estop` are obeyed from any source.
        """

    @abc.abstractmethod
    def drive(
        self,
        linear_mps: float,
        angular_radps: float = 0.0,
        *,
        ramped: bool = True,
        source: str | None = None,
    ) -> LimitedTwist:
        """Set the body velocity target (m/s forward, rad/s counter-clockwise).

        Not a coroutine: the control tick drives toward the target, within the speed
        limits (scaled keeping the curvature; the return value says by how much). With
        ``ramped`` (default; tb_control's ``/cmd_vel_accel``) the wheel setpoints get
        there through the acceleration and braking limits (and the jerk limits, when
        set: ``linear_jerk_mps3``, ``angular_jerk_radps3``); ``ramped=False`` is the
        pure velocity command (tb_control's ``/tb_cmd_vel``): the setpoints jump to the
        target at the next control tick, and the wheel PIDs take it from there. Either
        way the watchdog stops the wheels ``watchdog_s`` after the last call (repeat it
        at 5..20 Hz to keep moving), and a stop, the watchdog's included, ramps down at
        the deceleration limits, never held back by a jerk limit.

        It comes from command source ``source`` (default :attr:`source`): taken, it
        makes that source live; it ends a motion goal under way (``MotionPreemptedError``).

        Raises:
            InvalidArgumentError: A value is not a finite number, ``ramped`` not a bool, or
                ``source`` not a command source.
            SourceOverriddenError: A source of higher priority drives (named, with when
                it lapses); nothing sent, a goal under way goes on.
            StateError: An emergency stop is latched, a wheel's controller is off
                (:meth:`enable_controllers`), the port is released (:meth:`release_port`),
                or the robot is closed.
        """

    @abc.abstractmethod
    def drive_wheels(
        self, left_mps: float, right_mps: float, *, source: str | None = None
    ) -> WheelSpeeds:
        """Set each wheel's rim speed target (m/s, forward positive), no ramp.

        Both are scaled by one factor into ``max_wheel_mps``; the return value is what
        is driven. From command source ``source``, as :meth:`drive`.

        Raises:
            InvalidArgumentError: A value is not a finite number, or ``source`` not a
                command source.
            SourceOverriddenError: A source of higher priority drives; nothing sent.
            StateError: An emergency stop is latched, a wheel's controller is off
                (:meth:`enable_controllers`), the port is released (:meth:`release_port`),
                or the robot is closed.
        """

    @abc.abstractmethod
    def drive_pwm(
        self,
        left: float,
        right: float,
        *,
        left_enabled: bool = True,
        right_enabled: bool = True,
        source: str | None = None,
    ) -> tuple[int, int]:
        """Drive the wheels open loop with PWM −1000..1000 (the controllers step aside),
        as tb_control's ``/tb_cmd_motor_pwm`` takes it; from command source ``source``,
        as :meth:`drive`.

        Forward positive for both wheels (the right board's mirror is handled in the
        packet). A value may be a float: it is rounded once to the whole PWM step the
        wire carries (:func:`round`: a half goes to the even step, 2.5 → 2). A motor
        not enabled (tb_control's ``motor_1_enable`` false) gets PWM 0. The watchdog
        and the speed governor still apply.

        Returns:
            The PWM sent for (left, right), before the governor.

        Raises:
            InvalidArgumentError: A value is not a finite number, a flag not a bool, or
                ``source`` not a command source.
            OutOfRangeError: A value outside −1000..1000 (a disabled motor's too);
                nothing changes.
            SourceOverriddenError: A source of higher priority drives; nothing sent.
            StateError: An emergency stop is latched, the port is released
                (:meth:`release_port`), or the robot is closed.
        """

    @abc.abstractmethod
    def stop(self, *, source: str | None = None) -> None:
        """Target zero: the wheels ramp down at the deceleration limits.

        The first braking command goes on the wire at once (in the next free slot), not
        at the next control tick. A stop is obeyed from any command source, and ends a
        motion goal under way whatever its source; from a source no higher one
        overrides, it also takes over as a drive command does (the robot stays
        stopped until that source lapses or drives again). Through the daemon anyone
        may stop the robot, without the control lease.

        Raises:
            InvalidArgumentError: ``source`` is not a command source.
            RobotClosedError: The robot is closed (closing stopped the wheels).
        """

    @abc.abstractmethod
    async def estop(self, *, source: str | None = None) -> None:
        """Emergency stop: zero PWM ahead of everything queued, latched until cleared.

        Drive commands are refused until :meth:`clear_estop`. Obeyed from any command
        source, as :meth:`stop`. Through the daemon anyone may, without the control
        lease.

        Raises:
            InvalidArgumentError: ``source`` is not a command source.
            RobotClosedError: The robot is closed (closing stopped the wheels).
        """

    @abc.abstractmethod
    def clear_estop(self) -> None:
        """Release a latched emergency stop (the robot stays still until commanded).

        Raises:
            RobotClosedError: The robot is closed.
        """

    @abc.abstractmethod
    def enable_controllers(self, enabled: bool = True, wheel: Wheel | None = None) -> None:
        """Run the wheel PIDs (default), or not: ``wheel`` ``"left"`` or ``"right"`` for
        one of them, ``None`` for both (tb_control's ``enable_controllers``).

        While a wheel's controller is off, :meth:`drive`, :meth:`drive_wheels` and the
        motion goals are refused (:class:`~ohmni_tb.errors.StateError`) and only
        :meth:`drive_pwm` moves the wheels. Turning one off ends a motion goal and drops
        a :meth:`drive` or :meth:`drive_wheels` target: the robot stands until commanded
        again.

        Raises:
            InvalidArgumentError: ``enabled`` is not a bool, or ``wheel`` is not
                ``"left"``, ``"right"`` or ``None``.
            RobotClosedError: The robot is closed.
        """

    @abc.abstractmethod
    def controllers_enabled(self) -> dict[str, bool]:
        """Whether each wheel's PID runs: ``{"left": bool, "right": bool}``. Not awaited
        (a remote robot's copy is refreshed as :meth:`get_pid`'s)."""

    @abc.abstractmethod
    def get_pid(self, wheel: Wheel | None = None) -> PidGains:
        """A wheel PID's gains: ``wheel`` ``"left"`` or ``"right"``; ``None`` (default)
        for the gains both wheels share.

        Not awaited (a remote robot's copy is fetched at connecting, after its own
        :meth:`set_pid` and with the stats).

        Raises:
            InvalidArgumentError: ``wheel`` is not ``"left"``, ``"right"`` or ``None``.
            StateError: ``wheel`` is ``None`` and the two wheels' gains differ (after a
                :meth:`set_pid` of one wheel): the message shows both; name a wheel.
        """

    @abc.abstractmethod
    def set_pid(self, gains: PidGains, wheel: Wheel | None = None) -> None:
        """Change a wheel PID's gains, bumplessly (the output does not jump): ``wheel``
        ``"left"`` or ``"right"``, ``None`` (default) for both.

        Each gain has one allowed range, the same as the ``pid_*`` settings'
        (:data:`~ohmni_tb.control.defaults.WHEEL_GAIN_RANGES`). Whatever the gains, a
        wheel measured faster than ``max_wheel_mps`` gets no drive power.

        Raises:
            InvalidArgumentError: Not a :class:`PidGains`, or ``wheel`` is not
                ``"left"``, ``"right"`` or ``None``.
            OutOfRangeError: A gain is outside its range; nothing changes.
            RobotClosedError: The robot is closed.
        """

    @abc.abstractmethod
    def reset_odometry(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """Set the odometry pose: back to the origin, or to the pose given (tb_control's
        ``reset_wheel_odom``); as :meth:`set_odometry` otherwise.

        Raises:
            InvalidArgumentError: A value is not a finite number.
            OutOfRangeError: A value is beyond ±1e6 (m or rad: ``MAX_POSE_M``).
            RobotClosedError: The robot is closed.
        """

    @abc.abstractmethod
    def set_odometry(self, x_m: float, y_m: float, yaw_rad: float) -> None:
        """Set the odometry pose to (``x_m``, ``y_m``, ``yaw_rad``): diff_drive_controller's
        ``~/set_odometry``, e.g. to put the robot where a map says it is.

        ``wheel_odom`` goes on from that pose with its next sample (its covariance starts
        again from zero, its speeds as they were). A motion goal under way ends
        (:class:`~ohmni_tb.errors.MotionPreemptedError`, ``by="set_odometry"``: it steered
        in the old frame) and the target goes to zero; a ``drive`` goes on. Through the
        daemon it needs the control lease.

        Args:
            x_m: The position, m.
            y_m: The position, m.
            yaw_rad: The heading, rad (any angle: ``heading_rad`` takes it unwrapped,
                ``yaw_rad`` wrapped into (−π, π]).

        Raises:
            InvalidArgumentError: A value is not a finite number; nothing changes.
            OutOfRangeError: A value is beyond ±1e6 (m or rad: ``MAX_POSE_M``); nothing
                changes.
            RobotClosedError: The robot is closed.
        """

    @abc.abstractmethod
    async def drive_distance(
        self,
        distance_m: float,
        *,
        speed_mps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """Drive straight ``distance_m`` by odometry and stop there, at rest.

        Cruises at ``speed_mps``, slows on a braking curve near the goal and ends within
        about 1 mm of it by odometry (the wheel counts), then waits until the counts show
        the robot at rest. It runs where the robot runs: inside the daemon for a remote
        robot, so the connection's delays cannot spoil it. Another motion command
        meanwhile (``drive``, ``stop``, ``estop``, another goal…, from any client) ends it
        and stands; cancelling the awaiting task sets the target to zero (the wheels ramp
        down) and the cancellation goes on.

        It runs under command source ``source`` (default :attr:`source`), which stays
        live while it runs: a drive command of a lower source is refused meanwhile and
        leaves it alone; one of a higher source ends it (``MotionPreemptedError``, its
        ``.source`` naming that source).

        Args:
            distance_m: How far, m, −100..100 (negative: backward).
            speed_mps: The cruising speed, m/s, from 0.03 up to ``max_linear_mps`` (and
                ``max_wheel_mps``); default 0.3 within them.
            timeout_s: The time it may take, 0..3600 s; default twice the plan's + 2 s.
            source: The command source it runs under (see :attr:`source`).

        Returns:
            What it did (:class:`~ohmni_tb.errors.MotionResult`): distance and heading
            change by odometry, the pose, what is left, the time taken, and
            ``reason="arrived"``.

        Raises:
            InvalidArgumentError: A value is not a finite number, or ``source`` not a
                command source; nothing sent.
            OutOfRangeError: A value is outside its range (named with it); nothing sent.
            SourceOverriddenError: A source of higher priority drives; nothing sent.
            StateError: An emergency stop is latched, the port is released, the robot
                is closed, or the wheel_encoder or wheel_odom stream is off.
            MotionPreemptedError: Another motion command took over (``.by``, and
                ``.source``: its command source).
            WheelStallError: A wheel driven did not turn for ``stall_s`` (the fault
                ``wheel_stall:<sid>``): the wheels' power is cut and held so until
                ``stop()`` or another drive command (``.wheels``, ``.pwm``,
                ``.stalled_s``).
            WheelSlipError: The wheels ran off the commanded curve for ``slip_s`` (the
                fault ``wheel_slip:<sid>``); stopped (``.wheel``, ``.setpoint_mps``,
                ``.measured_mps``, ``.slipped_s``).
            MotionTimeoutError: Not there in time; stopped.
            MotionAbortedError: The watchdog tripped, the link was lost, no wheel counts
                came for 0.5 s, or the robot closed.
            StopNotConfirmedError: The counts did not show the robot at rest after the
                stop: it may be moving.
        """

    @abc.abstractmethod
    async def rotate(
        self,
        angle_rad: float,
        *,
        speed_radps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """Turn on the spot ``angle_rad`` by odometry (positive: counter-clockwise, as
        ``wheel_odom``'s heading) and stop there, at rest: within about 0.1° by odometry.

        As :meth:`drive_distance` (where it runs, its command source, preemption,
        cancellation, the errors).

        Args:
            angle_rad: How far, rad, −20π..20π (ten turns either way).
            speed_radps: The turning rate, rad/s, from 0.2 up to ``max_angular_radps``
                (and what ``max_wheel_mps`` allows); default 1.0 within them.
            timeout_s: The time it may take, 0..3600 s; default twice the plan's + 2 s.
            source: The command source it runs under (see :attr:`source`).

        Returns:
            What it did (:class:`~ohmni_tb.errors.MotionResult`).
        """

    @abc.abstractmethod
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
        """Go to the point (``x_m``, ``y_m``) of the odometry frame (``wheel_odom``), then
        turn to ``yaw_rad`` if given; stop there, at rest.

        It turns on the spot to face the point, drives there steering toward it and
        slowing on the braking curve, and faces and drives again while the point is more
        than 1 cm away; then turns to ``yaw_rad`` (within about 0.1°). As
        :meth:`drive_distance` otherwise (where it runs, its command source, preemption,
        cancellation, the errors).

        Args:
            x_m: The point, m (±1e6; at most 100 m from where the robot is).
            y_m: The point, m.
            yaw_rad: The heading to end with, rad, or ``None`` to keep the one it
                arrives with.
            speed_mps: The cruising speed, m/s, as :meth:`drive_distance`'s; the turns
                go at 1.0 rad/s within the limits.
            timeout_s: The time it may take, 0..3600 s; default twice the plan's + 2 s
                for each part.
            source: The command source it runs under (see :attr:`source`).

        Returns:
            What it did (:class:`~ohmni_tb.errors.MotionResult`); ``remaining_m`` is the
            distance left to the point.
        """

    # -- devices -------------------------------------------------------------------------------

    @property
    @abc.abstractmethod
    def neck_kind(self) -> str:
        """``herkulex``, ``worm`` or ``none``: which neck answered."""

    @property
    @abc.abstractmethod
    def neck(self) -> NeckHandle:
        """The neck: a HerkuleX servo's handle (:class:`HerkulexHandle`) or the worm-gear
        neck's (:class:`NeckHandle`). Its commands need the control lease through the
        daemon.

        Raises:
            StateError: No neck answered.
        """

    @abc.abstractmethod
    def servo(self, sid: int) -> HerkulexHandle:
        """The HerkuleX servo ``sid`` (the neck or an external one that answered).

        Raises:
            StateError: No such servo answered.
        """

    @abc.abstractmethod
    async def reset_board_id(self, sid: int, new_sid: int, *, confirm: bool = False) -> None:
        """Give drive board ``sid`` (0 left, 1 right) the bus id ``new_sid``, in EEP and RAM
        (tb_control's ``reset_servo_id`` on a motor board, for new hardware).

        The robot drives its wheels by ids 0 and 1: a board given another id no longer
        takes the wheel command, and ``robot_state`` shows it absent until it is given
        its id back (``reset_board_id(new_sid, sid, confirm=True)``: the robot remembers
        where it sent it). So it is done only with ``confirm=True``, after the wheels are
        stopped (confirmed by their counts). The id change's bytes are an assumption of
        the profile (:class:`~ohmni_tb.protocol.drive.DriveProfile`). Through the daemon
        it needs the control lease.

        Raises:
            InvalidArgumentError: ``sid`` is not a drive board's, or ``confirm`` is not
                ``True``; nothing sent.
            OutOfRangeError: An id is not 0..253; nothing sent.
            StateError: Another device the robot knows answers to ``new_sid``, the board
                does not answer, or the port is released; nothing sent.
            StopNotConfirmedError: The wheels were not confirmed stopped; nothing sent.
        """

    @abc.abstractmethod
    async def light_ring(self, hue: int, saturation: int, value: int) -> None:
        """Set the light ring's colour (0..255 each).

        Raises:
            OutOfRangeError: A component is outside 0..255; nothing sent.
            StateError: The port is released (:meth:`release_port`); nothing sent.
        """

    @abc.abstractmethod
    async def info(self) -> dict[str, Any]:
        """Firmware tags, servo models and the neck kind (``firmware``, ``servos``,
        ``neck``, ``present``, ``absent``), and the bus profile the robot runs with
        (``profile``: its settings, e.g. ``{"wheel_form": "s_jog", "battery_addr": 160,
        ...}``).

        Raises:
            StateError: The port is released (:meth:`release_port`).
        """

    @abc.abstractmethod
    async def list_ports(self) -> list[dict[str, Any]]:
        """The serial ports of the computer the robot runs on (through a daemon, the
        daemon's computer), with their USB ids, the likely bus adapter first
        (``likely_bus``): tb_control's ``get_connect_ports``. Opens none of them, and
        works while the port is released or disconnected."""

    # -- the port ------------------------------------------------------------------------------

    @abc.abstractmethod
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
        the link watcher does not take the release for a lost link. Closing the robot
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
            StateError: The robot is closed, or it cannot reopen its port (it was opened
                on an injected transport that cannot reopen); nothing changed.
            StopNotConfirmedError: The wheel counts did not confirm the stop: the robot
                may be moving. The port was released all the same, as closing would
                have closed it (the other program may be what is needed to stop it).
        """

    @property
    @abc.abstractmethod
    def port(self) -> str | None:
        """The port open now: a serial device (``/dev/ttyUSB0``; ``auto`` as found),
        ``sim://…`` or the URL it was opened with; ``None`` while disconnected, released
        or closed. A remote robot's is its daemon's robot's, as last fetched (at
        connecting, and after its own :meth:`connect` and :meth:`disconnect`)."""

    @abc.abstractmethod
    async def connect(self, port: str | None = None) -> None:
        """Switch to ``port`` at run time (tb_control's ``connect`` service: the wrong port
        of several serial devices, a robot on another adapter), or open the port again
        after :meth:`disconnect` (``None``: the one it had).

        The port open now is closed first as :meth:`release_port` closes it: the wheels
        stopped and confirmed by their counts, the neck rested or freed
        (``on_exit_neck``). Then ``port`` opens, a zero wheel command goes out first and
        the streams restart; devices that do not answer there are asked again every few
        seconds (``robot_state``: ``present``, ``absent``). :attr:`port` then says
        ``port``, and ``robot_state`` says ``connected to …``. Through the daemon it
        needs the control lease, and ``port`` is opened on the daemon's machine.

        Raises:
            InvalidArgumentError: ``port`` is not a port's name or URL.
            StopNotConfirmedError: The wheels on the old port were not confirmed stopped:
                it is closed all the same, and ``port`` is not opened (disconnected).
            TransportError: ``port`` cannot be opened (another program holds it, no such
                device): disconnected, :meth:`connect` again.
            StateError: The robot is closed.
        """

    @abc.abstractmethod
    async def disconnect(self) -> None:
        """Close the port until :meth:`connect`, as :meth:`release_port` does (the wheels
        stopped and confirmed first, the neck rested or freed); :attr:`port` is then
        ``None`` and commands raise :class:`~ohmni_tb.errors.StateError` (disconnected).
        Through the daemon it needs the control lease.

        Raises:
            StopNotConfirmedError: The wheel counts did not confirm the stop: the robot
                may be moving (the port is closed all the same).
            StateError: The robot is closed, or it cannot reopen its port (an injected
                transport that cannot reopen).
        """

    @abc.abstractmethod
    async def reclaim_port(self) -> None:
        """Take the serial port back after :meth:`release_port`. A no-op when not released.

        The port is reopened, a zero wheel command goes out first, the streams restart
        on a fresh phase, ``link`` is :attr:`Link.CONNECTED` again and ``robot_state``
        says ``port reclaimed``; then it returns. Absent devices are asked again.

        If the port cannot be opened now (the other program still holds it), it does
        not raise: ``robot_state`` says the robot is waiting for the port, the link
        stays :attr:`Link.RELEASED`, and this returns after that first attempt while the
        robot keeps trying in the background with a doubling backoff (up to
        ``reconnect_max_backoff_s``), as after a lost link; ``port reclaimed`` follows
        once it opens. Check :attr:`state` (``link``) or watch ``robot_state`` to know;
        drive commands raise :class:`~ohmni_tb.errors.StateError` until then. A
        :meth:`release_port` meanwhile stops the waiting. Cancelling the call does not
        cancel the reclaim.

        Raises:
            StateError: The robot is closed (or closed while this waited).
        """
