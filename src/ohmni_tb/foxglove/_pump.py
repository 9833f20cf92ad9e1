"""Every stream of a Robot onto its Foxglove channels, in one SDK context (internal).

One task per stream reads the Robot's own bounded subscription, so the schedule never
waits for it (a pump that falls behind loses the oldest samples, counted). Each sample is
encoded only for the channels someone listens to (``has_sinks``: a WebSocket client
subscribed, or an MCAP writer attached), and handed to the SDK, which copies it to its
sinks without waiting. All the tasks belong to one TaskGroup, run by one task.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import foxglove

from ohmni_tb.foxglove.channels import (
    CHANNELS,
    TF_TOPIC,
    ChannelSpec,
    Encoder,
    WallClock,
    channel_schema,
    encoder_for,
)

if TYPE_CHECKING:
    from ohmni_tb.robot import Robot

__all__ = ["ChannelStats", "Pump", "robot_channels"]

_log = logging.getLogger("ohmni_tb.foxglove")

#: Samples a stream's subscription holds (5 s of the 50 Hz streams): it only fills when
#: the event loop itself falls that far behind.
DEFAULT_QUEUE = 256


@dataclass(frozen=True, slots=True)
class ChannelStats:
    """One channel's figures.

    Attributes:
        topic: The channel's topic.
        schema_name: Its schema.
        messages: Messages handed to the SDK (while anyone listened).
        dropped: Samples of its stream lost before they were encoded: the pump fell
            behind the Robot, or a recorder's disk fell behind the pump.
    """

    topic: str
    schema_name: str
    messages: int
    dropped: int


def robot_channels(robot: Robot) -> tuple[ChannelSpec, ...]:
    """The channels a robot's streams go to: :data:`CHANNELS`, without the transform on
    ``/tf`` when its config turns it off (``enable_broadcast_transform``, tb_control's
    ``~enable_broadcast_transform``)."""
    if robot.config.enable_broadcast_transform:
        return CHANNELS
    return tuple(spec for spec in CHANNELS if spec.topic != TF_TOPIC)


class Pump:
    """Publishes a Robot's streams on :data:`CHANNELS` in ``context`` while it runs.

    Args:
        source: An open Robot, on a port or a daemon's.
        context: The SDK context the channels are made in; its sinks get the messages.
        specs: The channels (default: all of them, ``/tf`` only when the robot's
            ``enable_broadcast_transform`` is on).
        admit: Asked before each sample is encoded; ``False`` drops it (counted). A
            recorder's bound on its backlog.
        window: Only samples stamped in ``[start, end)`` (loop clock) are published.
        queue: Each stream subscription's bound.
    """

    def __init__(
        self,
        source: Robot,
        context: foxglove.Context,
        *,
        specs: Sequence[ChannelSpec] | None = None,
        admit: Callable[[], bool] | None = None,
        window: tuple[float, float] | None = None,
        queue: int = DEFAULT_QUEUE,
    ) -> None:
        self._source = source
        self._specs = tuple(specs) if specs is not None else robot_channels(source)
        self._admit = admit
        self._window = window
        self._queue = queue
        self._channels = [
            foxglove.Channel(
                spec.topic,
                schema=channel_schema(spec),
                message_encoding=spec.message_encoding,
                context=context,
            )
            for spec in self._specs
        ]
        self._messages = [0] * len(self._specs)
        self._lost: dict[str, int] = {}
        self._subscriptions: dict[str, Any] = {}
        self._runner: asyncio.Task[None] | None = None
        #: What ended the pump early (the daemon went away …), if anything did.
        self.error: BaseException | None = None
        self.clock: WallClock | None = None

    @property
    def channel_ids(self) -> dict[str, int]:
        """Each topic's channel id in the SDK context."""
        return {spec.topic: ch.id() for spec, ch in zip(self._specs, self._channels, strict=True)}

    def start(self) -> None:
        """Take the wall-clock offset and start reading the streams."""
        loop = asyncio.get_running_loop()
        self.clock = WallClock.at(loop.time())
        self._runner = loop.create_task(self._run(), name="ohmni-foxglove-pump")

    @property
    def running(self) -> bool:
        """Whether the streams are still read (they end with the Robot, or an error)."""
        return self._runner is not None and not self._runner.done()

    async def wait(self) -> None:
        """Until every stream has ended (the Robot closed) or one failed."""
        if self._runner is not None:
            await asyncio.shield(self._runner)

    async def aclose(self) -> None:
        """Stop reading; the channels are closed. Idempotent."""
        runner, self._runner = self._runner, None
        if runner is not None:
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)
        for channel in self._channels:
            channel.close()

    def stats(self) -> dict[str, ChannelStats]:
        """Every channel's figures, by topic."""
        lost = {
            stream: self._lost.get(stream, 0) + getattr(sub, "dropped", 0)
            for stream, sub in self._subscriptions.items()
        }
        return {
            spec.topic: ChannelStats(
                spec.topic, spec.schema_name, self._messages[i], lost.get(spec.stream, 0)
            )
            for i, spec in enumerate(self._specs)
        }

    async def _run(self) -> None:
        streams = list(dict.fromkeys(spec.stream for spec in self._specs))
        try:
            async with asyncio.TaskGroup() as group:
                for stream in streams:
                    group.create_task(self._pump(stream), name=f"ohmni-foxglove {stream}")
        except Exception as exc:  # kept for the owner to raise (wait, the CLI)
            failures = exc.exceptions if isinstance(exc, BaseExceptionGroup) else (exc,)
            self.error = failures[0]
            _log.warning("publishing stopped: %s", self.error)

    async def _pump(self, stream: str) -> None:
        indices = [i for i, spec in enumerate(self._specs) if spec.stream == stream]
        channels = [self._channels[i] for i in indices]
        encoders: list[Encoder] = [encoder_for(self._specs[i]) for i in indices]
        messages = self._messages
        admit = self._admit
        start, end = self._window or (float("-inf"), float("inf"))
        clock = self.clock
        assert clock is not None
        lost = 0
        async with self._source.subscribe(stream, maxlen=self._queue) as subscription:
            self._subscriptions[stream] = subscription
            async for sample in subscription:
                stamp: float = sample.stamp_s
                if not start <= stamp < end:
                    continue
                if admit is not None and not admit():
                    lost += 1
                    self._lost[stream] = lost
                    continue
                ns = clock.ns(stamp)
                for index, channel, encode in zip(indices, channels, encoders, strict=True):
                    if not channel.has_sinks():
                        continue  # nobody listens: encode nothing
                    payload = encode(sample, ns)
                    if payload is not None:
                        channel.log(payload, log_time=ns)
                        messages[index] += 1
