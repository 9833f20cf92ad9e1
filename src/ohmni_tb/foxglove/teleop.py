"""The Foxglove Teleop panel through the daemon: Twists coalesced, driven under its lease.

``ohmni serve --foxglove-control`` hands the Twists of unlocked Foxglove clients to a
:class:`FoxgloveTeleop` over a :class:`~ohmni_tb.client.RobotClient` of its own daemon::

    async with RobotClient.connect(url, reconnect=True) as client, FoxgloveTeleop(
        client
    ) as teleop:
        bridge = FoxgloveBridge(robot, teleop=teleop, token=token, ...)

A panel, or a client flooding the topic, may publish far faster than the robot is
controlled; the daemon closes a connection that sends more than its message rate limit.
So a Twist is not sent when it arrives: it replaces the one waiting (latest wins,
counted), and the waiting one goes to the daemon at most :data:`DEFAULT_RATE_HZ` times a
second, the control tick's rate. The first Twist takes the control lease when nobody
holds it (never steals: while another client drives, the Twists are refused, counted and
logged once per holder); it is given back, which stops the robot, :data:`TELEOP_IDLE_S`
after the last Twist or change. The Robot's watchdog stops the wheels sooner when the
panel goes quiet. Made with ``reconnect=True``, the client connects again when the daemon
closes its connection; the lease is then taken anew by the next Twist.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from ohmni_tb._checks import number
from ohmni_tb.control.defaults import PID_RATE_HZ
from ohmni_tb.errors import OhmniError, OutOfRangeError

if TYPE_CHECKING:
    from ohmni_tb.client import RobotClient

__all__ = ["DEFAULT_RATE_HZ", "MAX_RATE_HZ", "TELEOP_IDLE_S", "FoxgloveTeleop", "TeleopStats"]

_log = logging.getLogger("ohmni_tb.daemon")

#: The lease is given back this long after the last Twist, parameter change or call.
TELEOP_IDLE_S: Final = 1.0
#: Twists sent to the daemon a second, at most: the control tick's rate (a newer Twist
#: than that replaces the one waiting).
DEFAULT_RATE_HZ: Final = PID_RATE_HZ
#: The fastest allowed: half the daemon's sustained message rate limit (100 a second),
#: leaving the rest to the parameter changes and service calls on the same connection.
MAX_RATE_HZ: Final = 50.0
#: After the lease was refused (another client drives), Twists wait this long before
#: asking again: they are refused meanwhile, without a message to the daemon.
_LEASE_RETRY_S: Final = 0.25


@dataclass(frozen=True, slots=True)
class TeleopStats:
    """What became of the Twists.

    Attributes:
        received: Twists handed to the teleop.
        sent: Drive commands sent to the daemon.
        coalesced: Twists replaced by a newer one before they were sent.
        refused: Twists not sent: the lease held by another client, the daemon's
            connection down, a command refused.
    """

    received: int
    sent: int
    coalesced: int
    refused: int


class FoxgloveTeleop:
    """Twists driven through the daemon's control lease, coalesced (module docstring).

    An async context manager: its one task sends the Twists and gives the lease back.
    Call it on the event loop with each Twist (``linear_mps``, ``angular_radps``, and
    ``ramped``: whether it goes through the acceleration limits, as ``Robot.drive``'s): it
    never waits.

    Args:
        client: A connection to the daemon (``reconnect=True`` to outlive its closing).
        rate_hz: Twists sent a second at most (1..:data:`MAX_RATE_HZ`).
        idle_s: The lease is given back this long after the last use.

    Raises:
        OutOfRangeError: ``rate_hz`` not 1..50, or ``idle_s`` not 0.1..60.
    """

    def __init__(
        self,
        client: RobotClient,
        *,
        rate_hz: float = DEFAULT_RATE_HZ,
        idle_s: float = TELEOP_IDLE_S,
    ) -> None:
        if not 1.0 <= number("rate_hz", rate_hz) <= MAX_RATE_HZ:
            raise OutOfRangeError("rate_hz", rate_hz, 1.0, MAX_RATE_HZ, "Hz")
        if not 0.1 <= number("idle_s", idle_s) <= 60.0:
            raise OutOfRangeError("idle_s", idle_s, 0.1, 60.0, "s")
        self._client = client
        self._period_s = 1.0 / rate_hz
        self._idle_s = idle_s
        self._twist: tuple[float, float, bool] | None = None
        self._wake = asyncio.Event()
        self._idle_at: float | None = None
        self._retry_at = -float("inf")
        self._taking = asyncio.Lock()
        self._told: str | None = None
        self._runner: asyncio.Task[None] | None = None
        self._received = self._sent = self._coalesced = self._refused = 0

    def __call__(self, linear_mps: float, angular_radps: float, ramped: bool = True) -> None:
        self._received += 1
        if self._twist is not None:
            self._coalesced += 1
        self._twist = (linear_mps, angular_radps, ramped)
        self._wake.set()

    async def hold(self) -> None:
        """Hold the lease for a parameter change or a service call: take it when nobody
        holds it (never steals), and give it back :data:`TELEOP_IDLE_S` after the last use.

        Raises:
            LeaseError: Another client holds it (the message names it).
            TransportError: The daemon's connection is down (it is being made again).
        """
        await self._take()
        self._rearm()

    def stats(self) -> TeleopStats:
        """The counts so far."""
        return TeleopStats(self._received, self._sent, self._coalesced, self._refused)

    async def start(self) -> None:
        """Start sending."""
        self._runner = asyncio.get_running_loop().create_task(
            self._run(), name="ohmni-foxglove-teleop"
        )

    async def aclose(self) -> None:
        """Stop sending (the lease goes with the client's connection). Idempotent."""
        runner, self._runner = self._runner, None
        if runner is not None:
            runner.cancel()
            await asyncio.gather(runner, return_exceptions=True)

    async def __aenter__(self) -> FoxgloveTeleop:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        due = loop.time()
        while True:
            if self._twist is None:
                await self._idle(loop)
                continue
            wait_s = due - loop.time()
            if wait_s > 0:
                await asyncio.sleep(wait_s)  # newer Twists replace the waiting one
            twist, self._twist = self._twist, None
            if twist is not None:
                await self._send(*twist)
            # Late (a slow acquire): the next goes at once, never a burst to catch up.
            due = max(due + self._period_s, loop.time())

    async def _idle(self, loop: asyncio.AbstractEventLoop) -> None:
        """Until a Twist arrives, or the lease is due back (then give it)."""
        idle_at = self._idle_at
        wait_s = None if idle_at is None else idle_at - loop.time()
        if wait_s is None or wait_s > 0:
            self._wake.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(wait_s):
                    await self._wake.wait()
            return
        self._idle_at = None
        try:
            await self._client.release()  # the robot stops
        except OhmniError as exc:
            _log.warning("foxglove teleop: giving the control lease back: %s", exc)

    async def _take(self) -> None:
        async with self._taking:
            if not self._client.has_lease:
                await self._client.acquire()
                _log.info("foxglove took the control lease")

    def _rearm(self) -> None:
        self._idle_at = asyncio.get_running_loop().time() + self._idle_s
        self._wake.set()  # the idle wait is measured anew

    async def _send(self, linear_mps: float, angular_radps: float, ramped: bool) -> None:
        loop = asyncio.get_running_loop()
        if not self._client.has_lease and loop.time() < self._retry_at:
            self._refused += 1
            return
        try:
            await self._take()
            self._client.drive(linear_mps, angular_radps, ramped=ramped)
        except OhmniError as exc:
            self._refused += 1
            self._retry_at = loop.time() + _LEASE_RETRY_S
            told = str(exc)
            if told != self._told:  # once per reason (per holder), not once per Twist
                _log.warning("foxglove teleop refused: %s", exc)
                self._told = told
            return
        self._told = None
        self._sent += 1
        self._rearm()
