"""The daemon's robot (``ohmni serve``) as a :class:`~ohmni_tb.robot.Robot`: the same calls,
over WebSocket.

::

    from ohmni_tb import Robot

    async with Robot.open("ws://127.0.0.1:8766") as robot:   # token=... beyond loopback
        robot.drive(0.3, 0.0)                                 # takes the control lease
        print(robot.latest("wheel_odom"), robot.stats())      # plain, as on a LocalRobot

A script written for ``Robot.open("sim://")`` runs unchanged against the daemon: what is
plain there is plain here, bad values raise the same errors before anything is sent, and
the samples are the same frozen dataclasses. How the plain calls are served:

- **Streams.** At connecting, the remote robot subscribes to every stream at its full
  rate and keeps the newest sample of each (:meth:`~RemoteRobot.latest`, a round trip
  old); :meth:`~RemoteRobot.subscribe` hands out the same :class:`Subscription` as a
  local robot, fed from those. The daemon pays for it as for any reader of every stream
  (docs/daemon.md, *Under load*: 64 of them cost it about a fifth of a core).
- **Figures.** :meth:`~RemoteRobot.stats` and :meth:`~RemoteRobot.get_pid` are copies
  refreshed in the background: every :data:`STATS_REFRESH_S` while a program reads them
  (never faster than the daemon computes its stats, ``STATS_INTERVAL_S``), every
  :data:`STATS_IDLE_REFRESH_S` after :data:`STATS_IDLE_S` without a read; two messages of
  the readers' budget per refresh. So a copy is at most 0.5 s and a round trip old while
  read, 5 s at the first read after a pause. The settings and the schedule are fetched
  at connecting, the schedule again after ``set_rate`` and ``enable_stream`` (and
  :meth:`~RemoteRobot.confirm` waits for that).
- **Commands.** Plain commands (``drive``, ``stop``, ``set_pid`` …) are checked here and
  sent in order without waiting; one the daemon still refuses is raised by the next
  command or :meth:`~RemoteRobot.confirm`. Awaited ones (``estop``, ``light_ring``, the
  neck, the motion goals) return the daemon's answer; the motion goals run inside the
  daemon and answer when they end.
- **The control lease** of the robot's command source (:attr:`RemoteRobot.source`, or a
  command's own ``source``) is taken by the first command that needs it, when nobody
  holds it (never stolen: while another client holds it, such a command raises
  :class:`~ohmni_tb.errors.LeaseError` naming the holder). The daemon keeps one lease per
  source, and its Robot takes the drive commands of the highest source that drives:
  while a higher one does, this robot's are refused
  (:class:`~ohmni_tb.errors.SourceOverriddenError`, raised by the next command or
  :meth:`~RemoteRobot.confirm`). ``stop`` and ``estop`` need none. Closing the
  connection gives the leases back, and the daemon stops the robot then (unless a
  higher source drives it).
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
from collections.abc import AsyncIterator, Coroutine
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any, ClassVar, Final, Self

from ohmni_tb._checks import integer, number, ws_address
from ohmni_tb.control.kinematics import (
    LimitedTwist,
    Twist,
    WheelSpeeds,
    limit_twist,
    saturate_wheel_speeds,
)
from ohmni_tb.control.sources import DEFAULT_SOURCE, SourceMux
from ohmni_tb.errors import (
    ConfigError,
    LeaseError,
    MotionResult,
    OhmniError,
    RobotClosedError,
    StateError,
    TransportClosedError,
)
from ohmni_tb.herkulex.registers import memory_of
from ohmni_tb.herkulex.units import check_zero_offset_raw
from ohmni_tb.protocol import Memory
from ohmni_tb.robot._connection import DEFAULT_TIMEOUT_S, DaemonConnection, open_websocket
from ohmni_tb.robot.api import Robot, SampleStream
from ohmni_tb.robot.checks import (
    WHEELS,
    Wheel,
    check_board_id,
    check_enabled,
    check_gains,
    check_port_name,
    check_pose,
    check_ramped,
    check_rate,
    check_release,
    check_servo_id,
    check_servo_write,
    check_stream,
    check_wheel,
    gains_of,
    pwm_command,
)
from ohmni_tb.robot.devices import torque_mode
from ohmni_tb.robot.samples import STREAM_NAMES
from ohmni_tb.robot.streams import DEFAULT_QUEUE_SIZE, Subscription, Topic
from ohmni_tb.robot.wire import (
    METHOD_SPECS,
    TOKEN_ENV,
    AcquireArgs,
    BoardIdArgs,
    ConnectArgs,
    DriveArgs,
    DriveDistanceArgs,
    DrivePwmArgs,
    DriveWheelsArgs,
    EnabledArgs,
    GoToArgs,
    Hello,
    LatestArgs,
    LightArgs,
    MoveArgs,
    OdometryArgs,
    PidArgs,
    PoseArgs,
    RateArgs,
    ReleasePortArgs,
    RestArgs,
    RotateArgs,
    SampleMessage,
    ServoArgs,
    ServoIdArgs,
    ServoWriteArgs,
    SourceArgs,
    StreamArgs,
    Subscribe,
    TorqueArgs,
    ZeroOffsetArgs,
    goal_from_json,
    info_from_json,
    pid_state_from_json,
    sample_from_json,
    schedule_from_json,
    servo_status_from_json,
    stats_from_json,
)

if TYPE_CHECKING:
    from pydantic import BaseModel

    from ohmni_tb.config import RobotConfig
    from ohmni_tb.control.pid import PidGains
    from ohmni_tb.herkulex import TorqueControl
    from ohmni_tb.herkulex.servo import ServoStatus
    from ohmni_tb.protocol.profile import BusProfile
    from ohmni_tb.robot.samples import RobotStateSample
    from ohmni_tb.robot.stats import RobotStats
    from ohmni_tb.transport import Transport

__all__ = [
    "DEFAULT_TIMEOUT_S",
    "DEFAULT_URL",
    "STATS_IDLE_REFRESH_S",
    "STATS_IDLE_S",
    "STATS_REFRESH_S",
    "RemoteRobot",
    "RemoteServo",
]

#: Where ``ohmni serve`` listens by default.
DEFAULT_URL: Final = "ws://127.0.0.1:8766"
#: How often the copies of ``stats()`` and ``get_pid()`` are refreshed while a program reads
#: them (one of them was called within :data:`STATS_IDLE_S`): no faster than the daemon
#: computes its stats (``STATS_INTERVAL_S``, 0.2 s); two messages of the daemon's
#: readers' budget (500 a second, shared) each time.
STATS_REFRESH_S: Final = 0.5
#: Without a read for this long, the copies are refreshed only every
#: :data:`STATS_IDLE_REFRESH_S`: a remote robot nobody asks for figures costs the daemon
#: 0.4 messages a second.
STATS_IDLE_S: Final = 10.0
STATS_IDLE_REFRESH_S: Final = 5.0
#: Samples the daemon holds for each stream of this connection before it drops the
#: oldest: half a second of the 50 Hz streams and more (the read loop takes them at once).
_MIRROR_QUEUE = 256
#: The methods after which the figures and the schedule are fetched again.
_CHANGES_SCHEDULE = frozenset(
    {"set_rate", "enable_stream", "release_port", "reclaim_port", "connect", "disconnect"}
)

_log = logging.getLogger("ohmni_tb.client")


class RemoteRobot(Robot):
    """The robot of a daemon (module docstring), opened with
    ``Robot.open("ws://HOST:PORT", token=...)``."""

    #: Whether a command takes the control lease by itself when nobody holds it.
    _auto_lease: ClassVar[bool] = True

    def __init__(
        self, connection: DaemonConnection, config: RobotConfig, source: str = DEFAULT_SOURCE
    ) -> None:
        self._connection = connection
        self.config = config
        # The daemon's robot's command sources, to check a source named here.
        self._sources = SourceMux(config.source_table())
        self._source = self._sources.check_name(source)
        connection.source = self._source
        self.sim = None  # the simulator runs in the daemon
        self._closed = False
        self._topics: dict[str, _Mirror] = {name: _Mirror(name) for name in STREAM_NAMES}
        self._figures = _Figures(connection)
        self._drive = config.drive()
        self._limits = config.velocity_limits()
        #: An ``acquire`` sent for a command source, not answered yet.
        self._acquiring: dict[str, asyncio.Future[Any]] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self._refetches: set[asyncio.Task[Any]] = set()
        self._port: str | None = None
        #: The zero offsets of the external servos set through this robot, by id.
        self._zero_offsets: dict[int, int] = {}
        #: Old id → new id of the servos given another id through this robot.
        self._moved: dict[int, int] = {}
        #: Samples the daemon dropped for this connection because it fell behind.
        self.lost_samples = 0
        connection.on_sample = self._on_sample
        connection.on_reconnected = self._on_reconnected
        connection.on_ended = self._on_ended

    # -- opening and closing -------------------------------------------------------------

    @classmethod
    def _opens(cls, port: str | Transport | None) -> bool:
        """A daemon's URL: ``ws://`` or ``wss://``."""
        return isinstance(port, str) and port.lower().startswith(("ws://", "wss://"))

    @classmethod
    @asynccontextmanager
    async def open(
        cls,
        port: str | Transport | None = None,
        *,
        token: str | None = None,
        config: RobotConfig | None = None,
        profile: BusProfile | None = None,
        source: str | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        reconnect: bool = False,
        **overrides: Any,
    ) -> AsyncIterator[Self]:
        """:meth:`Robot.open <ohmni_tb.robot.api.Robot.open>` on the daemon at ``port``
        (default :data:`DEFAULT_URL`).

        Args:
            port: ``ws://host:port`` or ``wss://host:port`` of ``ohmni serve``.
            token: The daemon's token (default ``$OHMNI_DAEMON_TOKEN``, else none).
            config: Not taken: the daemon's robot runs with the daemon's settings.
            profile: Not taken: the daemon's robot runs with the daemon's bus profile.
            source: The command source whose lease the commands take (default
                ``autonomy``); only a program on the daemon's computer may take ``local``
                or ``safety``.
            timeout_s: How long connecting, and each call, may take.
            reconnect: When the daemon goes away (restarted, its machine rebooted),
                connect again and again (backing off to one try every 2 s) instead of
                ending: the streams carry on once it is back, calls in between raise
                :class:`~ohmni_tb.errors.TransportClosedError`.
            overrides: Not taken (settings are the daemon's).

        Raises:
            ConfigError: Not a daemon's URL (``ws://HOST:PORT`` or ``wss://``, a port in
                1..65535), settings given, or a ``source`` the daemon's robot has not.
            TransportError: Nothing answers at the URL, it is not the daemon, or it
                refused the connection (no token or a wrong one: the message says).
        """
        url = DEFAULT_URL if port is None else port
        if not isinstance(url, str) or ws_address(url) is None:
            raise ConfigError(
                f"{url!r} is not a daemon URL: expected ws://HOST:PORT or wss://HOST:PORT "
                "(port 1..65535)"
            )
        if config is not None or profile is not None or overrides:
            given = ["config"] * (config is not None) + ["profile"] * (profile is not None)
            names = ", ".join(given + sorted(overrides))
            raise ConfigError(
                f"the daemon's robot runs with the daemon's settings: {names} cannot be "
                "given to a remote robot (set them for ohmni serve)"
            )
        token = token if token is not None else os.environ.get(TOKEN_ENV) or None
        headers = {"Authorization": f"Bearer {token}"} if token else None
        ws, hello = await open_websocket(url, headers, timeout_s)
        connection = DaemonConnection(
            ws, url, hello, timeout_s, headers=headers, reconnect=reconnect
        )
        connection.start()
        try:
            fetched = await _fetch_config(connection)
            known = [row.name for row in fetched.source_table()]
            if source is not None and source not in known:
                raise ConfigError(
                    f"source={source!r} is not a command source of the daemon's robot: "
                    f"allowed {', '.join(known)}"
                )
            robot = cls(connection, fetched, DEFAULT_SOURCE if source is None else source)
            await robot._start()
        except BaseException:
            await connection.aclose()
            raise
        try:
            yield robot
        finally:
            await robot._close()

    async def _start(self) -> None:
        """Subscribe to every stream, then fetch the newest samples, the schedule and the
        figures (a sample that came meanwhile is newer than the one fetched)."""
        connection = self._connection
        subscribed = [self._subscribe_daemon(name) for name in STREAM_NAMES]
        latest = [connection.call("latest", LatestArgs(topic=name)) for name in STREAM_NAMES]
        *answers, _, self._port = await asyncio.gather(
            *subscribed, *latest, self._figures.fetch(), connection.call("port")
        )
        for name, data in zip(STREAM_NAMES, answers[len(STREAM_NAMES) :], strict=True):
            topic = self._topics[name]
            if data is not None and topic.latest is None:
                topic.latest = sample_from_json(name, data)
        self._spawn(self._figures.refresh_loop(), "figures")

    def _subscribe_daemon(self, name: str) -> asyncio.Future[Any]:
        return self._connection.send_request(
            lambda id: Subscribe(id=id, topic=name, max_hz=None, queue=_MIRROR_QUEUE),
            f"subscribe {name}",
        )

    async def _close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._connection.aclose()
        for topic in self._topics.values():
            topic.close()

    @property
    def closed(self) -> bool:
        """Whether the robot was closed."""
        return self._closed

    @property
    def url(self) -> str:
        """The daemon's address."""
        return self._connection.url

    @property
    def connected(self) -> bool:
        """Whether the connection is up (``False`` while connecting again)."""
        return self._connection.connected

    @property
    def reconnects(self) -> int:
        """Times the connection was made again after the daemon went away."""
        return self._connection.reconnects

    @property
    def lease_holder(self) -> str | None:
        """Who holds the control lease of this robot's command source (``host:port`` as
        the daemon names it), as last told by the daemon; ``None``: nobody."""
        return self._connection.holder

    @property
    def leases(self) -> dict[str, str]:
        """Each command source's lease held at the daemon and its holder, as last told."""
        return dict(self._connection.holders)

    @property
    def source(self) -> str:
        """:attr:`Robot.source <ohmni_tb.robot.api.Robot.source>`: the command source of the
        commands that name none, and of the lease they take."""
        return self._source

    @property
    def simulated(self) -> bool:
        """Whether the daemon serves the built-in simulator (its ``hello`` says)."""
        return self._connection.hello.simulated

    async def confirm(self) -> None:
        """:meth:`Robot.confirm <ohmni_tb.robot.api.Robot.confirm>`: the daemon's answers,
        and the schedule and figures fetched again after a change of rates or streams."""
        self._check_open()
        await self._connection.confirm()
        refetches, self._refetches = self._refetches, set()
        await asyncio.gather(*refetches, return_exceptions=True)

    # -- streams -----------------------------------------------------------------------------

    def _latest(self, name: str) -> Any:
        check_stream(name)
        return self._topics[name].latest

    def _subscribe(self, name: str, maxlen: int) -> SampleStream[Any]:
        check_stream(name)
        return self._topics[name].subscribe(maxlen)

    def stats(self) -> RobotStats:
        """The daemon's figures, as last fetched (module docstring: how old)."""
        return self._figures.read().stats

    def schedule(self) -> list[tuple[str, float, float, float]]:
        """The daemon's schedule, as last fetched."""
        return list(self._figures.schedule)

    @property
    def state(self) -> RobotStateSample:
        """The newest ``robot_state`` sample."""
        state: RobotStateSample | None = self._topics["robot_state"].latest
        if state is None:
            raise StateError("the daemon has not sent the robot's state yet")
        return state

    def enable_stream(self, name: str, enabled: bool = True) -> None:
        """:meth:`Robot.enable_stream <ohmni_tb.robot.api.Robot.enable_stream>`."""
        check_stream(name)
        check_enabled(enabled)
        self._command("enable_stream", StreamArgs(topic=name, enabled=enabled))

    def set_rate(self, name: str, hz: float) -> None:
        """:meth:`Robot.set_rate <ohmni_tb.robot.api.Robot.set_rate>`."""
        self._command("set_rate", RateArgs(topic=name, hz=check_rate(name, hz)))

    # -- motion ------------------------------------------------------------------------------

    def drive(
        self,
        linear_mps: float,
        angular_radps: float = 0.0,
        *,
        ramped: bool = True,
        source: str | None = None,
    ) -> LimitedTwist:
        """:meth:`Robot.drive <ohmni_tb.robot.api.Robot.drive>`, scaled here as the daemon's
        robot will scale it."""
        twist = Twist(number("linear_mps", linear_mps), number("angular_radps", angular_radps))
        check_ramped(ramped)
        name = self._source_name(source)
        self._command(
            "drive",
            DriveArgs(
                linear_mps=twist.linear_mps,
                angular_radps=twist.angular_radps,
                ramped=ramped,
                source=name,
            ),
            source=name,
        )
        return limit_twist(twist, self._limits, self._drive)

    def drive_wheels(
        self, left_mps: float, right_mps: float, *, source: str | None = None
    ) -> WheelSpeeds:
        """:meth:`Robot.drive_wheels <ohmni_tb.robot.api.Robot.drive_wheels>`."""
        asked = WheelSpeeds(number("left_mps", left_mps), number("right_mps", right_mps))
        name = self._source_name(source)
        self._command(
            "drive_wheels",
            DriveWheelsArgs(left_mps=asked.left_mps, right_mps=asked.right_mps, source=name),
            source=name,
        )
        return saturate_wheel_speeds(asked, self._limits.max_wheel_mps)

    def drive_pwm(
        self,
        left: float,
        right: float,
        *,
        left_enabled: bool = True,
        right_enabled: bool = True,
        source: str | None = None,
    ) -> tuple[int, int]:
        """:meth:`Robot.drive_pwm <ohmni_tb.robot.api.Robot.drive_pwm>` (converted here as
        the daemon's robot converts it)."""
        pwm = pwm_command(left, right, left_enabled, right_enabled)
        name = self._source_name(source)
        self._command(
            "drive_pwm",
            DrivePwmArgs(
                left=left,
                right=right,
                left_enabled=left_enabled,
                right_enabled=right_enabled,
                source=name,
            ),
            source=name,
        )
        return pwm

    def stop(self, *, source: str | None = None) -> None:
        """:meth:`Robot.stop <ohmni_tb.robot.api.Robot.stop>` (while the connection is down
        there is nothing to send: the daemon stopped the robot when it went)."""
        name = self._source_name(source)
        self._check_open()
        if self._connection.connected:
            self._command("stop", SourceArgs(source=name))

    async def estop(self, *, source: str | None = None) -> None:
        """:meth:`Robot.estop <ohmni_tb.robot.api.Robot.estop>`."""
        await self._call("estop", SourceArgs(source=self._source_name(source)))

    def clear_estop(self) -> None:
        """:meth:`Robot.clear_estop <ohmni_tb.robot.api.Robot.clear_estop>`."""
        self._command("clear_estop")

    def enable_controllers(self, enabled: bool = True, wheel: Wheel | None = None) -> None:
        """:meth:`Robot.enable_controllers <ohmni_tb.robot.api.Robot.enable_controllers>`."""
        self._check_open()
        check_enabled(enabled)
        checked = check_wheel(wheel)
        future = self._command("enable_controllers", EnabledArgs(enabled=enabled, wheel=checked))
        future.add_done_callback(lambda done: self._enabled_done(done, enabled, checked))

    def controllers_enabled(self) -> dict[str, bool]:
        """Whether each of the daemon's wheel PIDs runs, as last fetched or set."""
        return dict(zip(WHEELS, self._figures.read().enabled, strict=True))

    def get_pid(self, wheel: Wheel | None = None) -> PidGains:
        """The daemon's wheel PID gains, as last fetched or set."""
        left, right = self._figures.read().pid
        return gains_of(check_wheel(wheel), left, right)

    def set_pid(self, gains: PidGains, wheel: Wheel | None = None) -> None:
        """:meth:`Robot.set_pid <ohmni_tb.robot.api.Robot.set_pid>`."""
        self._check_open()
        checked = check_gains(gains)
        which = check_wheel(wheel)
        future = self._command("set_pid", PidArgs.of(checked, which))
        future.add_done_callback(
            lambda done: self._set_pid_done(done, checked, which),
        )

    def _set_pid_done(
        self, future: asyncio.Future[Any], gains: PidGains, wheel: Wheel | None
    ) -> None:
        if not future.cancelled() and future.exception() is None:
            left, right = self._figures.pid
            self._figures.pid = (
                gains if wheel != "right" else left,
                gains if wheel != "left" else right,
            )

    def _enabled_done(
        self, future: asyncio.Future[Any], enabled: bool, wheel: Wheel | None
    ) -> None:
        if not future.cancelled() and future.exception() is None:
            left, right = self._figures.enabled
            self._figures.enabled = (
                enabled if wheel != "right" else left,
                enabled if wheel != "left" else right,
            )

    def reset_odometry(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """:meth:`Robot.reset_odometry <ohmni_tb.robot.api.Robot.reset_odometry>`."""
        self._check_open()
        x, y, yaw = check_pose(x_m, y_m, yaw_rad)
        self._command("reset_odometry", PoseArgs(x_m=x, y_m=y, yaw_rad=yaw))

    def set_odometry(self, x_m: float, y_m: float, yaw_rad: float) -> None:
        """:meth:`Robot.set_odometry <ohmni_tb.robot.api.Robot.set_odometry>`."""
        self._check_open()
        x, y, yaw = check_pose(x_m, y_m, yaw_rad)
        self._command("set_odometry", OdometryArgs(x_m=x, y_m=y, yaw_rad=yaw))

    async def drive_distance(
        self,
        distance_m: float,
        *,
        speed_mps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """:meth:`Robot.drive_distance <ohmni_tb.robot.api.Robot.drive_distance>`, run by
        the daemon's robot."""
        name = self._source_name(source)
        args = DriveDistanceArgs(
            distance_m=distance_m, speed_mps=speed_mps, timeout_s=timeout_s, source=name
        )
        return await self._goal("drive_distance", args, name)

    async def rotate(
        self,
        angle_rad: float,
        *,
        speed_radps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """:meth:`Robot.rotate <ohmni_tb.robot.api.Robot.rotate>`, run by the daemon's robot."""
        name = self._source_name(source)
        args = RotateArgs(
            angle_rad=angle_rad, speed_radps=speed_radps, timeout_s=timeout_s, source=name
        )
        return await self._goal("rotate", args, name)

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
        """:meth:`Robot.go_to <ohmni_tb.robot.api.Robot.go_to>`, run by the daemon's robot."""
        name = self._source_name(source)
        args = GoToArgs(
            x_m=x_m,
            y_m=y_m,
            yaw_rad=yaw_rad,
            speed_mps=speed_mps,
            timeout_s=timeout_s,
            source=name,
        )
        return await self._goal("go_to", args, name)

    async def _goal(self, method: str, args: BaseModel, source: str) -> MotionResult:
        """A motion goal in the daemon: its result, or its error as the daemon's robot
        raised it; cancelled, the robot is told to stop (the goal ends there)."""
        try:
            data = await self._call(method, args, until_done=True, source=source)
        except asyncio.CancelledError:
            if not self._closed and self._connection.connected:
                self._command("stop", SourceArgs(source=source))
            raise
        return goal_from_json(data)

    # -- devices -----------------------------------------------------------------------------

    @property
    def neck_kind(self) -> str:
        """``herkulex``, ``worm`` or ``none``: which neck the daemon's robot found."""
        return self.state.neck

    @property
    def neck(self) -> RemoteServo:
        """The neck, through the daemon (:attr:`Robot.neck <ohmni_tb.robot.api.Robot.neck>`)."""
        config = self.config
        kind = self.neck_kind
        if kind == "herkulex":
            return self._servo_handle("neck", config.neck_id, neck=True)
        if kind == "worm":
            return RemoteServo(
                self, "neck", 4, config.worm_min_raw, config.worm_max_raw, stream="new_neck"
            )
        raise StateError(
            f"no neck answered (looked for {config.neck}: HerkuleX at "
            f"{config.neck_id}, worm gear at 4)"
        )

    def servo(self, sid: int) -> RemoteServo:
        """The HerkuleX servo ``sid``, through the daemon."""
        found = self._servo_ids()
        if sid not in found:
            shown = ", ".join(map(str, found)) or "none"
            moved = self._moved.get(sid) if isinstance(sid, int) else None
            if moved is not None and moved in found:
                raise StateError(
                    f"no HerkuleX servo {sid!r} on this robot: it was given id {moved} "
                    f"(robot.servo({moved})); found: {shown}"
                )
            raise StateError(f"no HerkuleX servo {sid!r} on this robot (found: {shown})")
        return self._servo_handle(sid, sid, neck=sid == self.config.neck_id)

    def _servo_ids(self) -> list[int]:
        """The HerkuleX servos the daemon's robot found: the neck and the external ones."""
        config = self.config
        state = self.state
        ids = [sid for sid in config.ext_servo_ids[:2] if sid in state.present]
        if state.neck == "herkulex":
            ids.append(config.neck_id)
        return sorted(ids)

    def _servo_handle(self, target: str | int, sid: int, *, neck: bool) -> RemoteServo:
        config = self.config
        if neck:
            return RemoteServo(
                self,
                target,
                sid,
                config.neck_min_raw,
                config.neck_max_raw,
                rest_raw=config.neck_rest_raw,
                zero_offset_raw=config.neck_zero_offset_raw,
            )
        return RemoteServo(
            self, target, sid, 21, 1002, zero_offset_raw=self._zero_offsets.get(sid, 0)
        )

    async def _follow(self) -> None:
        """The daemon's settings and state again, after a change its robot follows (a
        servo's id, the neck's zero offset): ``servo(new_sid)`` works at once."""
        self.config = await _fetch_config(self._connection)
        data = await self._connection.call("latest", LatestArgs(topic="robot_state"))
        if data is not None:
            sample = sample_from_json("robot_state", data)
            topic = self._topics["robot_state"]
            latest = topic.latest
            if latest is None or latest.stamp_s <= sample.stamp_s:
                topic.latest = sample

    async def reset_board_id(self, sid: int, new_sid: int, *, confirm: bool = False) -> None:
        """:meth:`Robot.reset_board_id <ohmni_tb.robot.api.Robot.reset_board_id>`, by the
        daemon's robot."""
        check_board_id(sid, new_sid, confirm)
        await self._call("reset_board_id", BoardIdArgs(sid=sid, new_sid=new_sid, confirm=confirm))
        await self._follow()

    async def light_ring(self, hue: int, saturation: int, value: int) -> None:
        """:meth:`Robot.light_ring <ohmni_tb.robot.api.Robot.light_ring>`."""
        for name, component in (("hue", hue), ("saturation", saturation), ("value", value)):
            integer(name, component, 0, 255)
        await self._call("light_ring", LightArgs(hue=hue, saturation=saturation, value=value))

    async def info(self) -> dict[str, Any]:
        """:meth:`Robot.info <ohmni_tb.robot.api.Robot.info>`, asked of the daemon's robot."""
        return info_from_json(await self._call("info"))

    async def list_ports(self) -> list[dict[str, Any]]:
        """:meth:`Robot.list_ports <ohmni_tb.robot.api.Robot.list_ports>`: the daemon's
        computer's serial ports."""
        listed: list[dict[str, Any]] = await self._call("list_ports")
        return listed

    async def release_port(self, duration_s: float | None = None) -> None:
        """:meth:`Robot.release_port <ohmni_tb.robot.api.Robot.release_port>`, by the
        daemon's robot."""
        await self._call("release_port", ReleasePortArgs(duration_s=check_release(duration_s)))

    async def reclaim_port(self) -> None:
        """:meth:`Robot.reclaim_port <ohmni_tb.robot.api.Robot.reclaim_port>`."""
        await self._call("reclaim_port")
        self._port = await self._connection.call("port")

    @property
    def port(self) -> str | None:
        """The daemon's robot's port, as last fetched (:attr:`Robot.port
        <ohmni_tb.robot.api.Robot.port>`)."""
        return self._port

    async def connect(self, port: str | None = None) -> None:
        """:meth:`Robot.connect <ohmni_tb.robot.api.Robot.connect>`, by the daemon's robot
        (``port`` is opened on the daemon's machine)."""
        check_port_name(port)
        try:
            await self._call("connect", ConnectArgs(port=port))
        finally:
            self._port = await self._connection.call("port")

    async def disconnect(self) -> None:
        """:meth:`Robot.disconnect <ohmni_tb.robot.api.Robot.disconnect>`, by the daemon's
        robot."""
        try:
            await self._call("disconnect")
        finally:
            self._port = await self._connection.call("port")

    # -- the command path --------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise RobotClosedError

    def _source_name(self, source: str | None) -> str:
        """A command's source: the robot's for ``None``, else one of the daemon's robot's.

        Raises:
            InvalidArgumentError: Not a command source; the message lists them.
        """
        return self._source if source is None else self._sources.check_name(source)

    def _command(
        self, method: str, args: BaseModel | None = None, *, source: str | None = None
    ) -> asyncio.Future[Any]:
        """Send ``method`` without waiting (module docstring), after the lease it needs."""
        self._check_open()
        self._connection.check()
        self._lease_for(method, source)
        future = self._connection.command(method, args)
        if method in _CHANGES_SCHEDULE:
            future.add_done_callback(self._refetch_after)
        return future

    async def _call(
        self,
        method: str,
        args: BaseModel | None = None,
        *,
        until_done: bool = False,
        source: str | None = None,
    ) -> Any:
        """Call ``method`` and wait for its answer, after the lease it needs."""
        self._check_open()
        self._connection.check()
        self._lease_for(method, source)
        data = await self._connection.call(method, args, until_done=until_done)
        if method in _CHANGES_SCHEDULE:
            await self._figures.fetch()
        return data

    def _lease_for(self, method: str, source: str | None = None) -> None:
        """Take the control lease for ``method`` when it needs it and nobody holds it: an
        ``acquire`` goes just before it (the daemon answers in order). A drive command or
        goal needs the lease of its ``source``; another command any lease of this
        connection (else this robot's source's).

        Raises:
            LeaseError: Another client holds it (or, without the automatic lease, this
                connection does not); nothing sent.
        """
        connection = self._connection
        if not METHOD_SPECS[method].lease:
            return
        if source is None:
            if any(connection.holds(name) for name in connection.holders):
                return
            source = self._source
        if connection.holds(source):
            return
        acquiring = self._acquiring.get(source)
        if acquiring is not None and not acquiring.done():
            return
        holder = connection.holders.get(source)
        if holder is not None or not self._auto_lease:
            raise LeaseError(self._lease_refusal(method, holder, source), holder=holder)
        self._acquiring[source] = connection.command("acquire", AcquireArgs(source=source))

    def _lease_refusal(self, method: str, holder: str | None, source: str) -> str:
        whose = "" if source == self._source else f" of command source {source}"
        return (
            f"{method} needs the control lease{whose}: {holder} holds it (another client "
            "drives the robot)"
        )

    # -- what the daemon sends ---------------------------------------------------------------

    def _on_sample(self, message: SampleMessage) -> None:
        if message.dropped:
            if not self.lost_samples:
                _log.warning(
                    "the daemon at %s dropped %s samples for this connection: it fell behind "
                    "(counted in lost_samples)",
                    self.url,
                    message.dropped,
                )
            self.lost_samples += message.dropped
        sample = sample_from_json(message.topic, message.data)
        self._topics[message.topic].publish(sample, sample.stamp_s)

    def _on_reconnected(self, hello: Hello) -> None:
        """Connected again: the streams again, then fresh copies of the figures."""
        for name in STREAM_NAMES:
            self._subscribe_daemon(name).add_done_callback(_told_if_refused)
        self._spawn(self._figures.fetch(), "figures after reconnecting")

    def _on_ended(self, error: TransportClosedError | None) -> None:
        """The connection ended for good: the subscriptions end (with its error)."""
        for topic in self._topics.values():
            topic.end(error)

    def _refetch_after(self, future: asyncio.Future[Any]) -> None:
        if not self._closed and not future.cancelled() and future.exception() is None:
            self._refetches.add(self._spawn(self._figures.fetch(), "schedule"))

    def _spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        task = asyncio.get_running_loop().create_task(coro, name=f"ohmni remote robot: {name}")
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            _log.warning("%s: %s", task.get_name(), task.exception())


class RemoteServo:
    """The neck or a HerkuleX servo of the daemon's robot (:attr:`RemoteRobot.neck`,
    :meth:`RemoteRobot.servo`): the local handles' commands, each answered by the daemon
    (the same checks, the same errors); they need the control lease, taken as for any
    command."""

    def __init__(
        self,
        robot: RemoteRobot,
        target: str | int,
        sid: int,
        min_raw: int,
        max_raw: int,
        *,
        rest_raw: int = 512,
        zero_offset_raw: int = 0,
        stream: str = "servo_neck",
    ) -> None:
        self._robot = robot
        self.target = target
        self.sid = sid
        self.min_raw = min_raw
        self.max_raw = max_raw
        self.rest_raw = rest_raw
        self.zero_offset_raw = zero_offset_raw
        # Which sample a wait answers with: the worm gear's, or a HerkuleX servo's.
        self._stream = stream

    def __repr__(self) -> str:
        return f"<RemoteServo {self.target!r} at {self._robot.url}>"

    async def move(
        self,
        raw: int | None = None,
        *,
        rad: float | None = None,
        playtime_s: float | None = None,
        wait: bool = False,
        timeout_s: float | None = None,
    ) -> Any:
        """:meth:`NeckHandle.move <ohmni_tb.robot.api.NeckHandle.move>`: answered when the
        daemon's robot has sent it, or with ``wait`` when it read back at the target."""
        args = MoveArgs(
            target=self.target,
            raw=raw,
            rad=rad,
            playtime_s=playtime_s,
            wait=wait,
            timeout_s=timeout_s,
        )
        data = await self._robot._call("move", args, until_done=wait)
        return None if data is None else sample_from_json(self._stream, data)

    async def torque(self, mode: TorqueControl | str) -> None:
        """``"on"``, ``"brake"`` or ``"free"`` (a HerkuleX servo)."""
        args = {"target": self.target, "mode": torque_mode(mode).name.lower()}
        await self._robot._call("torque", TorqueArgs.model_validate(args))

    async def free(self) -> None:
        """Torque off."""
        await self.torque("free")

    async def rest(self, *, free: bool = True) -> None:
        """Move to the rest position, then (by default) free it; returns when done."""
        await self._robot._call("rest", RestArgs(target=self.target, free=free))

    async def info(self) -> dict[str, dict[str, int]]:
        """:meth:`HerkulexHandle.info <ohmni_tb.robot.api.HerkulexHandle.info>`: read by
        the daemon's robot (no lease needed)."""
        data: dict[str, dict[str, int]] = await self._robot._call(
            "servo_info", ServoArgs(target=self.target)
        )
        return data

    async def write(
        self,
        register: str | int,
        value: int,
        *,
        persist: bool = False,
        memory: Memory | str = Memory.RAM,
    ) -> None:
        """:meth:`HerkulexHandle.write <ohmni_tb.robot.api.HerkulexHandle.write>`, checked
        and sent by the daemon's robot."""
        check_servo_write(self.sid, register, value, persist, memory)
        args = ServoWriteArgs(
            target=self.target,
            reg=register,
            value=value,
            persist=persist,
            memory=memory_of(memory).value,
        )
        await self._robot._call("servo_write", args)

    async def set_id(self, new_sid: int) -> None:
        """:meth:`HerkulexHandle.set_id <ohmni_tb.robot.api.HerkulexHandle.set_id>`: the
        daemon's robot follows, and so does this handle and ``servo(new_sid)``."""
        check_servo_id(new_sid)
        await self._robot._call("servo_set_id", ServoIdArgs(target=self.target, new_sid=new_sid))
        if self.target != "neck":
            self.target = new_sid
        old, self.sid = self.sid, new_sid
        self._robot._moved[old] = new_sid
        self._robot._moved.pop(new_sid, None)
        offsets = self._robot._zero_offsets
        if old in offsets:
            offsets[new_sid] = offsets.pop(old)
        await self._robot._follow()

    async def set_zero_offset(self, raw: int) -> None:
        """:meth:`HerkulexHandle.set_zero_offset
        <ohmni_tb.robot.api.HerkulexHandle.set_zero_offset>`, in the daemon's robot."""
        check_zero_offset_raw(raw)
        await self._robot._call("servo_zero_offset", ZeroOffsetArgs(target=self.target, raw=raw))
        self.zero_offset_raw = raw
        robot = self._robot
        if self.sid == robot.config.neck_id:
            await robot._follow()
        else:
            robot._zero_offsets[self.sid] = raw

    async def status(self) -> ServoStatus:
        """:meth:`HerkulexHandle.status <ohmni_tb.robot.api.HerkulexHandle.status>`: asked
        by the daemon's robot (no lease needed)."""
        data = await self._robot._call("servo_status", ServoArgs(target=self.target))
        return servo_status_from_json(data)

    async def clear_errors(self) -> ServoStatus:
        """:meth:`HerkulexHandle.clear_errors
        <ohmni_tb.robot.api.HerkulexHandle.clear_errors>`, by the daemon's robot (with the
        control lease)."""
        data = await self._robot._call("servo_clear", ServoArgs(target=self.target))
        return servo_status_from_json(data)


class _Figures:
    """The daemon's schedule, figures and gains, as last fetched: on connecting, after a
    change of rates or streams, and (the figures and gains) every :data:`STATS_REFRESH_S`
    while they are read, else every :data:`STATS_IDLE_REFRESH_S`."""

    stats: RobotStats
    #: Each wheel's gains (left, right), and whether each wheel's PID runs.
    pid: tuple[PidGains, PidGains]
    enabled: tuple[bool, bool]

    def __init__(self, connection: DaemonConnection) -> None:
        self._connection = connection
        self.schedule: list[tuple[str, float, float, float]] = []
        self._read_s = -math.inf

    def read(self) -> _Figures:
        """These figures, noted as read now (they are refreshed often while read)."""
        self._read_s = asyncio.get_running_loop().time()
        return self

    async def fetch(self) -> None:
        """The schedule, figures and gains, now."""
        schedule, stats, pid = await asyncio.gather(
            self._connection.call("schedule"),
            self._connection.call("stats"),
            self._connection.call("pid_state"),
        )
        self.schedule = schedule_from_json(schedule)
        self.stats = stats_from_json(stats)
        self._take_pid(pid)

    def _take_pid(self, data: Any) -> None:
        left, right, self.enabled = pid_state_from_json(data)
        self.pid = (left, right)

    async def refresh_loop(self) -> None:
        """The figures and the gains again every :data:`STATS_REFRESH_S` while read, else
        every :data:`STATS_IDLE_REFRESH_S`."""
        connection = self._connection
        loop = asyncio.get_running_loop()
        fetched_s = loop.time()
        while True:
            await asyncio.sleep(STATS_REFRESH_S)
            now = loop.time()
            idle = now - self._read_s > STATS_IDLE_S
            if not connection.connected or (idle and now - fetched_s < STATS_IDLE_REFRESH_S):
                continue
            fetched_s = now
            try:
                stats, pid = await asyncio.gather(
                    connection.call("stats"), connection.call("pid_state")
                )
            except OhmniError:
                continue  # the connection's trouble: the next call says
            self.stats = stats_from_json(stats)
            self._take_pid(pid)


class _Mirror(Topic[Any]):
    """One stream of the daemon's robot: the Robot's own fan-out, whose subscriptions end
    with the connection's error when it ends for good."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.error: TransportClosedError | None = None

    def subscribe(self, maxlen: int = DEFAULT_QUEUE_SIZE) -> Subscription[Any]:
        integer("maxlen", maxlen, 1, 100_000)
        subscription = _Ending(self, maxlen)
        if self._closed:
            subscription.close()  # the stream has ended: iteration ends at once
        else:
            self._subscriptions.add(subscription)
        return subscription

    def end(self, error: TransportClosedError | None) -> None:
        """End every subscription; with ``error``, their iteration raises it."""
        self.error = error
        self.close()


class _Ending(Subscription[Any]):
    """A subscription whose iteration raises the connection's error when it ended."""

    def __init__(self, mirror: _Mirror, maxlen: int) -> None:
        super().__init__(mirror, maxlen)
        self._mirror = mirror

    async def __anext__(self) -> Any:
        try:
            return await super().__anext__()
        except StopAsyncIteration:
            if self._mirror.error is not None:
                raise self._mirror.error from None
            raise


async def _fetch_config(connection: DaemonConnection) -> RobotConfig:
    """The daemon's robot's settings."""
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # pydantic-settings: when opened

    data: dict[str, Any] = await connection.call("config")
    return RobotConfig(**data)


def _told_if_refused(future: asyncio.Future[Any]) -> None:
    if not future.cancelled() and future.exception() is not None:
        _log.warning("renewing a stream: %s", future.exception())
