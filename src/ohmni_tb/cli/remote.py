"""The commands' Robot when ``ohmni serve`` runs: the part of the Robot's API they use, over
the daemon (:class:`~ohmni_tb.client.RobotClient`).

A command opens the port itself unless a daemon answers (then the port is the daemon's:
a second opener would only get "port busy"): ``common.daemon_for`` decides; :func:`open_remote`
connects, takes the daemon's settings, subscribes to every stream (so ``latest`` needs no
round trip, as on the Robot) and, for a command that moves the robot, takes the control
lease — refused, with who holds it, when another client drives. Leaving gives the lease
back, which stops the robot at the daemon.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any

from ohmni_tb.errors import LeaseError, OhmniError, StateError
from ohmni_tb.robot.streams import Subscription, Topic

if TYPE_CHECKING:
    from ohmni_tb.client import ClientSubscription, RemoteServo, RobotClient
    from ohmni_tb.config import RobotConfig
    from ohmni_tb.control.kinematics import LimitedTwist
    from ohmni_tb.control.pid import PidGains
    from ohmni_tb.robot import RobotStateSample, RobotStats

__all__ = ["DaemonRobot", "open_remote", "serves_simulator"]

#: How often the daemon's figures are fetched for ``stats()``.
_STATS_EVERY_S = 0.25


class _RemoteHandle:
    """The neck or a servo through the daemon, with the Robot's handle's attributes."""

    def __init__(
        self,
        remote: RemoteServo,
        sid: int,
        *,
        min_raw: int,
        max_raw: int,
        rest_raw: int = 512,
        zero_offset_raw: int = 0,
    ) -> None:
        self._remote = remote
        self.sid = sid
        self.min_raw = min_raw
        self.max_raw = max_raw
        self.rest_raw = rest_raw
        self.zero_offset_raw = zero_offset_raw

    async def move(
        self, raw: int | None = None, *, rad: float | None = None, playtime_s: float | None = None
    ) -> None:
        await self._remote.move(raw, rad=rad, playtime_s=playtime_s)

    async def torque(self, mode: str) -> None:
        await self._remote.torque(mode)

    async def free(self) -> None:
        await self._remote.free()

    async def rest(self, *, free: bool = True) -> None:
        await self._remote.rest(free=free)


class DaemonRobot:
    """What the commands use of a Robot, served by the daemon (see :func:`open_remote`)."""

    #: The simulator's ground truth is the daemon's: not here.
    sim = None

    def __init__(
        self,
        client: RobotClient,
        config: RobotConfig,
        info: dict[str, Any],
        stats: RobotStats,
        pid: PidGains,
        state: RobotStateSample | None,
    ) -> None:
        self.client = client
        self.config = config
        self._info = info
        self._stats = stats
        self._pid = pid
        self._state = state
        # The Robot's own stream objects, fed from the daemon: subscriptions behave alike.
        self._topics: dict[str, Topic[Any]] = {}
        self._tasks: list[asyncio.Task[None]] = []

    @property
    def url(self) -> str:
        """The daemon's address."""
        return self.client.url

    @property
    def neck_kind(self) -> str:
        kind: str = self._info["neck"]
        return kind

    @property
    def neck(self) -> _RemoteHandle:
        config = self.config
        if self.neck_kind == "herkulex":
            return _RemoteHandle(
                self.client.neck,
                config.neck_id,
                min_raw=config.neck_min_raw,
                max_raw=config.neck_max_raw,
                rest_raw=config.neck_rest_raw,
                zero_offset_raw=config.neck_zero_offset_raw,
            )
        if self.neck_kind == "worm":
            return _RemoteHandle(
                self.client.neck, 4, min_raw=config.worm_min_raw, max_raw=config.worm_max_raw
            )
        raise StateError(
            f"no neck answered at the daemon's robot (looked for {config.neck}: HerkuleX at "
            f"{config.neck_id}, worm gear at 4)"
        )

    @property
    def state(self) -> RobotStateSample:
        if self._state is None:
            raise StateError("the daemon has not sent the robot's state yet")
        return self._state

    def latest(self, name: str) -> Any:
        return self.client.latest_received(name)

    def subscribe(self, name: str, *, maxlen: int = 64) -> Subscription[Any]:
        return self._topic(name).subscribe(maxlen)

    def _topic(self, name: str) -> Topic[Any]:
        topic = self._topics.get(name)
        if topic is None:
            topic = self._topics[name] = Topic(name)
        return topic

    def stats(self) -> RobotStats:
        return self._stats

    def get_pid(self) -> PidGains:
        return self._pid

    async def info(self) -> dict[str, Any]:
        return dict(self._info)

    def drive(self, linear_mps: float, angular_radps: float = 0.0) -> LimitedTwist:
        return self.client.drive(linear_mps, angular_radps)

    def drive_pwm(self, left: int, right: int) -> None:
        self.client.drive_pwm(left, right)

    def stop(self) -> None:
        if self.client.connected:
            self.client.stop()

    def reset_odometry(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        self.client.reset_odometry(x_m, y_m, yaw_rad)

    async def light_ring(self, hue: int, saturation: int, value: int) -> None:
        await self.client.light_ring(hue, saturation, value)

    # -- feeding ------------------------------------------------------------------------

    async def _pump(self, subscription: ClientSubscription[Any]) -> None:
        name = subscription.name
        topic = self._topic(name)
        try:
            async for sample in subscription:
                if name == "robot_state":
                    self._state = sample
                topic.publish(sample, sample.stamp_s)
        finally:
            topic.close()  # the commands' subscriptions end with the connection

    async def _poll_stats(self) -> None:
        while True:
            await asyncio.sleep(_STATS_EVERY_S)
            with contextlib.suppress(OhmniError):  # gone: the command hears it otherwise
                self._stats = await self.client.stats()


@asynccontextmanager
async def open_remote(url: str, *, control: bool) -> AsyncIterator[DaemonRobot]:
    """Connect to the daemon at ``url`` as a command's Robot; with ``control``, hold the
    control lease for the command (given back on leaving, which stops the robot).

    Raises:
        TransportError: The daemon does not answer or refused the connection.
        LeaseError: ``control`` and another client drives; the message names it.
    """
    from ohmni_tb.client import RobotClient  # noqa: PLC0415
    from ohmni_tb.robot.samples import STREAM_NAMES  # noqa: PLC0415

    async with RobotClient.connect(url) as client, contextlib.AsyncExitStack() as stack:
        config = await client.config()
        state = await client.latest("robot_state")
        try:
            info = await client.info()
        except StateError:
            # The port is handed to another program: no device can be asked. What the
            # daemon's Robot found when it had the port is in its state.
            info = _info_from_state(config, state)
        remote = DaemonRobot(
            client, config, info, await client.stats(), await client.get_pid(), state
        )
        for name in STREAM_NAMES:
            subscription = await stack.enter_async_context(client.subscribe(name, maxlen=256))
            remote._tasks.append(asyncio.create_task(remote._pump(subscription)))
        remote._tasks.append(asyncio.create_task(remote._poll_stats()))
        if control:
            try:
                await client.acquire()
            except LeaseError as exc:
                raise LeaseError(
                    f"another client of the daemon at {url} drives the robot ({exc.holder}): "
                    "this command needs the control lease",
                    holder=exc.holder,
                ) from None
        try:
            yield remote
        finally:
            for task in remote._tasks:
                task.cancel()
            await asyncio.gather(*remote._tasks, return_exceptions=True)
            if control and client.connected:
                # Shielded: a cancelled command still hands the lease back, which stops the
                # robot at the daemon (nothing else here could).
                with contextlib.suppress(Exception):
                    await asyncio.shield(client.release())


async def serves_simulator(url: str) -> bool:
    """Whether the daemon at ``url`` serves the built-in simulator, as its ``hello`` says
    (a command's motion then needs no consent, as on ``sim://``).

    Raises:
        TransportError: The daemon does not answer or refused the connection.
    """
    from ohmni_tb.client import RobotClient  # noqa: PLC0415

    async with RobotClient.connect(url) as client:
        return client.hello.simulated


def _info_from_state(config: RobotConfig, state: RobotStateSample | None) -> dict[str, Any]:
    """``Robot.info()``'s shape from the Robot's state, without asking the devices: the
    firmware tags and servo models unknown (``None``)."""
    neck = state.neck if state is not None else "none"
    servos = [sid for sid in config.ext_servo_ids if state is None or sid in state.present]
    if neck == "herkulex":
        servos.insert(0, config.neck_id)
    return {
        "firmware": {"left_drive": None, "right_drive": None, "core": None},
        "servos": dict.fromkeys(servos),
        "neck": neck,
        "present": list(state.present) if state is not None else [],
        "absent": list(state.absent) if state is not None else [],
    }
