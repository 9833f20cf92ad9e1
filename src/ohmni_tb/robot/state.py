"""What the Robot's parts share: one state object, its ``robot_state`` sample, its tasks.

The façade (:mod:`ohmni_tb.robot.core`) makes one :class:`RobotState` and hands it to
every part (discovery, the control loop, the guards, the link, the feedback streams);
each part keeps its own working state and reads or changes only what is here when
another part must see it.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from ohmni_tb.bus import Bus
from ohmni_tb.config import RobotConfig
from ohmni_tb.control.sources import SourceMux
from ohmni_tb.errors import InvalidArgumentError, RobotClosedError, StateError
from ohmni_tb.protocol import Packet
from ohmni_tb.robot.devices import ServoHandle, WormNeckHandle
from ohmni_tb.robot.samples import STREAM_NAMES, Link, RobotStateSample, ServoSample
from ohmni_tb.robot.schedule import Periodic
from ohmni_tb.robot.streams import Topic

__all__ = ["RobotState", "ServoWatch", "shielded"]

_log = logging.getLogger(__name__)
#: What a shielded coroutine returns.
_R = TypeVar("_R")


@dataclass(eq=False)
class ServoWatch:
    """What the thermal and hold guards know of one HerkuleX servo."""

    handle: ServoHandle
    stream: str
    last_command_s: float = -math.inf
    tripped: bool = False
    guard: asyncio.Task[None] | None = None
    sample: ServoSample | None = None


@dataclass(eq=False)
class RobotState:
    """The Robot's shared state: its bus, settings, streams, devices, link and faults."""

    bus: Bus
    config: RobotConfig
    loop: asyncio.AbstractEventLoop
    #: Every stream's topic, by name.
    topics: dict[str, Topic[Any]] = field(init=False)
    #: The schedule: the control slot (``wheel_encoder``) and each polled stream.
    periodic: dict[str, Periodic] = field(default_factory=dict)
    #: Each polled stream's packets of one cycle (the control slot's with a stop).
    packets: dict[str, Sequence[Packet]] = field(default_factory=dict)
    link: Link = Link.CONNECTED
    estopped: bool = False
    watchdog_tripped: bool = False
    #: Times the motion watchdog stopped the wheels since the Robot opened.
    watchdog_trips: int = 0
    faults: set[str] = field(default_factory=set)
    #: ``herkulex``, ``worm`` or ``none``; the handle of the one found.
    neck_kind: str = "none"
    neck: ServoHandle | WormNeckHandle | None = None
    #: Every HerkuleX servo found (the neck included), by id.
    servos: dict[int, ServoWatch] = field(default_factory=dict)
    #: Device ids looked for, and those that answered.
    expected: set[int] = field(default_factory=set)
    present: set[int] = field(default_factory=set)
    #: The boards' firmware tags (EEP 0xF1) as read, by id (``None``: no answer, or empty).
    firmware: dict[int, str | None] = field(default_factory=dict)
    closed: bool = False
    #: The task closing the Robot, and the one releasing its port (their own commands
    #: still go: the neck is rested or freed on the way).
    closing: asyncio.Task[Any] | None = None
    releasing: asyncio.Task[Any] | None = None
    #: The first attempt of a reclaim under way (done once it was tried).
    reclaim: asyncio.Future[None] | None = None
    #: The port was closed by ``disconnect()`` (released, waiting for ``connect()``).
    disconnected: bool = False
    #: Drive commands clamped into the limits, and wheel PWM the governor capped or cut.
    clamped: int = 0
    #: Every background task (the link watcher, reprobes, guards).
    tasks: set[asyncio.Task[Any]] = field(default_factory=set)

    def __post_init__(self) -> None:
        #: The bus profile, fixed while the Robot is open (its packets are built once).
        self.profile = self.config.profile()
        #: Which command source drives (``command_sources``, fixed while open):
        #: :mod:`ohmni_tb.robot.sources` feeds it.
        self.sources = SourceMux(self.config.source_table())
        self.topics = {name: Topic(name) for name in STREAM_NAMES}
        self.topics["pid_debug"].enabled = self.config.pid_debug

    def topic(self, name: str) -> Topic[Any]:
        """Stream ``name``'s topic.

        Raises:
            InvalidArgumentError: No such stream; the message lists them.
        """
        topic = self.topics.get(name)
        if topic is None:
            raise InvalidArgumentError(
                f"no stream {name!r}: the streams are {', '.join(STREAM_NAMES)}"
            )
        return topic

    # -- robot_state -------------------------------------------------------------------

    def sample(self, event: str | None) -> RobotStateSample:
        """The state now, as ``robot_state`` publishes it."""
        now = self.loop.time()
        return RobotStateSample(
            stamp_s=now,
            link=self.link,
            estopped=self.estopped,
            watchdog_tripped=self.watchdog_tripped,
            faults=tuple(sorted(self.faults)),
            neck=self.neck_kind,
            present=tuple(sorted(self.present)),
            absent=tuple(sorted(self.expected - self.present)),
            event=event,
            active_source=self.sources.active(now),
        )

    def publish(self, event: str | None) -> None:
        """Publish ``robot_state`` now (with ``event``: what changed, also logged)."""
        sample = self.sample(event)
        if event is not None:
            _log.info("robot: %s", event)
        self.topics["robot_state"].publish(sample, sample.stamp_s)

    # -- refusals ----------------------------------------------------------------------

    def check_open(self) -> None:
        """Refuse a command to a closed Robot (but for the closing's own: the neck is
        rested or freed on the way)."""
        if self.closed and asyncio.current_task() is not self.closing:
            raise RobotClosedError

    def check_port(self) -> None:
        """Refuse a command while the port is released, or being released (but for the
        release's own: the neck is rested or freed on the way), or to a closed Robot."""
        self.check_open()
        if self.releasing is not None and asyncio.current_task() is not self.releasing:
            raise StateError("the port is being released to another program (release_port())")
        if self.link is not Link.RELEASED:
            return
        if self.disconnected:
            raise StateError("the robot is disconnected from its port; connect() first")
        if self.reclaim is not None and self.reclaim.done():
            raise StateError(
                "the port is released and another program still holds it: the robot is "
                "waiting for it (robot_state says 'port reclaimed' when it is back)"
            )
        raise StateError("the port is released to another program; reclaim_port() first")

    # -- tasks -------------------------------------------------------------------------

    def spawn(self, coro: Coroutine[Any, Any, Any], name: str) -> asyncio.Task[Any]:
        """Run ``coro`` in the background; a failure is logged and published."""
        task = self.loop.create_task(coro, name=f"ohmni robot: {name}")
        self.tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self.tasks.discard(task)
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            _log.error("%s failed", task.get_name(), exc_info=exc)
            self.publish(f"{task.get_name()} failed: {exc}")

    async def cancel_tasks(self) -> None:
        """Cancel every background task; wait for them to end."""
        for task in list(self.tasks):
            task.cancel()
        if self.tasks:
            await asyncio.gather(*self.tasks, return_exceptions=True)

    async def shielded(self, work: Coroutine[Any, Any, _R], name: str) -> _R:
        """:func:`shielded` on this Robot's loop."""
        return await shielded(self.loop, work, name)


async def shielded(loop: asyncio.AbstractEventLoop, work: Coroutine[Any, Any, _R], name: str) -> _R:
    """Run ``work`` to its end even if the caller is cancelled meanwhile (the cancellation
    is raised afterwards): a stop must never be cut short."""
    task = loop.create_task(work, name=f"ohmni robot {name}")
    cancelled: asyncio.CancelledError | None = None
    while not task.done():
        try:
            await asyncio.shield(task)
        except asyncio.CancelledError as exc:
            cancelled = exc
    result = task.result()
    if cancelled is not None:
        raise cancelled
    return result
