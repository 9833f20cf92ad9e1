"""The Robot's serial link: a lost link stops the wheels and is reopened; the port can be
handed to another program and taken back (:meth:`LinkKeeper.release`,
:meth:`LinkKeeper.reclaim`); and the wheels are stopped, the neck rested or freed, before
the port goes (:meth:`LinkKeeper.stop_and_rest`).

Reopening is the transport's job (:meth:`~ohmni_tb.transport.Transport.reopen`, which
the bus calls): this part decides when, and what the Robot does around it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

from ohmni_tb.bus import Reopen
from ohmni_tb.errors import (
    BusClosedError,
    OhmniError,
    StateError,
    StopNotConfirmedError,
    TransportError,
)
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import wheel_command
from ohmni_tb.robot.control_loop import ControlLoop
from ohmni_tb.robot.devices import ServoHandle
from ohmni_tb.robot.discovery import Discovery
from ohmni_tb.robot.feedback import Feedback
from ohmni_tb.robot.samples import Link
from ohmni_tb.robot.state import RobotState
from ohmni_tb.safety import stop_wheels

__all__ = ["RECLAIM_BACKOFF_S", "LinkKeeper"]

_log = logging.getLogger(__name__)

#: The wait before the second attempt to reopen a port another program still holds
#: (then doubling, up to ``reconnect_max_backoff_s``).
RECLAIM_BACKOFF_S = 0.1


class LinkKeeper:
    """Watches the link, reopens it, and hands the port over and back (module docstring)."""

    def __init__(
        self,
        state: RobotState,
        control: ControlLoop,
        feedback: Feedback,
        discovery: Discovery,
    ) -> None:
        self._state = state
        self._control = control
        self._feedback = feedback
        self._discovery = discovery
        self._reclaim_timer: asyncio.TimerHandle | None = None
        self._lock = asyncio.Lock()

    def start(self) -> None:
        """Watch the link from now on."""
        self._state.spawn(self._watch(), "link watcher")

    async def close(self) -> StopNotConfirmedError | None:
        """Close the Robot (marked closed already): the schedule, the timers and the
        tasks stop, the wheels are stopped and the neck rested or freed while the port
        is there, the streams end, the port closes. The stop's error, if any."""
        state = self._state
        self._feedback.close()
        self._discovery.disarm()
        if self._reclaim_timer is not None:
            self._reclaim_timer.cancel()
        self._control.close()
        await state.cancel_tasks()
        stop = wheel_command(0, 0, state.profile.drive)
        error = None
        # Not when the port is released (or lost): there is nothing to send the stop on.
        if state.bus.connected:
            error = await self.stop_and_rest("closing")
        state.link = Link.CLOSED
        state.publish("closed")
        for topic in state.topics.values():
            topic.close()
        await state.bus.aclose(final=[stop])
        return error

    # -- before the port goes ------------------------------------------------------------

    async def stop_and_rest(self, why: str) -> StopNotConfirmedError | None:
        """Stop the wheels until their counts confirm it (``stop_timeout_s``) and rest or
        free the neck (``on_exit_neck``): what closing and releasing the port do before
        the port goes. Returns the stop's error when the counts did not confirm it."""
        state = self._state
        for periodic in state.periodic.values():
            periodic.cancel_in_flight()
        error: StopNotConfirmedError | None = None
        try:
            if state.present.isdisjoint((DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE)):
                # Neither drive board ever answered this Robot: it drove nothing, and no
                # count can confirm a stop (robot_state shows them absent). The stop still
                # goes, last, as the port closes.
                _log.info(
                    "%s: the drive boards never answered; the wheel stop is sent but cannot "
                    "be confirmed",
                    why,
                )
            else:
                await stop_wheels(
                    state.bus,
                    timeout_s=state.config.stop_timeout_s,
                    profile=state.profile.drive,
                )
        except StopNotConfirmedError as exc:
            error = exc
            _log.warning("%s: %s", why, exc)
        except OhmniError as exc:
            _log.warning("%s: stop not confirmed: %s", why, exc)
        await self._neck_on_exit(why)
        return error

    async def _neck_on_exit(self, why: str) -> None:
        config = self._state.config
        choice = config.on_exit_neck
        neck = self._state.neck
        if choice == "keep" or not isinstance(neck, ServoHandle):
            return
        try:
            async with asyncio.timeout(config.stop_timeout_s + 1.5):
                if choice == "rest":
                    await neck.rest()
                else:
                    await neck.free()
        except (OhmniError, TimeoutError) as exc:
            _log.warning(
                "%s: the neck was not %s: %s", why, "rested" if choice == "rest" else "freed", exc
            )

    # -- link loss -----------------------------------------------------------------------

    async def _watch(self) -> None:
        """Wait for a lost link; stop the targets and reopen it (``reconnect``).

        Not running while the port is released: :meth:`release` cancels it before it
        closes the port, and the reclaim becomes the watcher again.
        """
        state = self._state
        bus = state.bus
        while not state.closed:
            reason = await self._wait_lost()
            if reason is None:
                return
            self._feedback.stop()
            state.link = Link.LOST
            state.faults.add("link_lost")
            self._control.halt()
            state.publish(f"link lost: {reason}")
            if not state.config.reconnect:
                return
            try:
                await bus.reconnect(max_backoff_s=state.config.reconnect_max_backoff_s)
            except StateError as exc:  # a link its transport cannot reopen
                state.publish(f"not reconnecting: {exc}")
                return
            await self._back("link back: reconnected")

    async def _wait_lost(self) -> TransportError | None:
        """Why the link was lost, once it is; ``None`` if the Robot was closed meanwhile."""
        reason = await self._state.bus.wait_lost()
        return None if self._state.closed else reason

    async def _back(self, event: str) -> None:
        """The port is open again: a wheel stop first, then the schedule on a fresh phase
        (the control slot and the streams that are on)."""
        state = self._state
        with contextlib.suppress(OhmniError):
            await state.bus.send_now(wheel_command(0, 0, state.profile.drive))
        state.link = Link.CONNECTED
        state.faults.discard("link_lost")
        self._control.restart()
        self._feedback.restart()
        state.publish(event)

    # -- port hand-off -------------------------------------------------------------------

    async def release(self, duration_s: float | None, *, before: Callable[[], None]) -> None:
        """``Robot.release_port`` (``duration_s`` checked there); ``before`` is called once
        the release is sure to go ahead, before it begins."""
        state = self._state
        if not state.bus.can_reconnect:
            raise StateError(
                "this Robot cannot reopen its port, so it will not release it: it was opened "
                "on an injected transport that cannot reopen; open it by URL "
                "(Robot.open('/dev/ttyUSB0'))"
            )
        async with self._lock:
            state.check_open()
            before()
            error = await state.shielded(self._release(duration_s), "release port")
        if error is not None:
            raise error

    async def reclaim(self) -> None:
        """``Robot.reclaim_port``."""
        state = self._state
        async with self._lock:
            state.check_open()
            if state.link is not Link.RELEASED:
                return
            first = state.reclaim
            if first is None:
                first = self._start_reclaim()
            await asyncio.shield(first)
        state.check_open()

    async def disconnect(self, *, before: Callable[[], None]) -> None:
        """``Robot.disconnect``: close the port as a release does, until ``connect``."""
        state = self._state
        bus = state.bus
        if not bus.can_reconnect:
            raise StateError(
                "this Robot cannot reopen its port, so it will not close it: it was opened "
                "on an injected transport that cannot reopen; open it by URL"
            )
        error: StopNotConfirmedError | None = None
        async with self._lock:
            state.check_open()
            if state.link is Link.RELEASED:
                await state.cancel_tasks()  # a reclaim waiting for the port gives way
                self._arm_reclaim(None)
                if bus.connected:
                    await bus.release()
            else:
                before()
                error = await state.shielded(
                    self._release(None, why="disconnected from the port"), "disconnect"
                )
            state.disconnected = True
        if error is not None:
            raise error

    async def connect(
        self, reopen: Reopen | None, name: str, *, before: Callable[[], None]
    ) -> None:
        """``Robot.connect``: open the port ``reopen`` opens (``None``: the one the Robot
        had) in place of the one open now, which is closed first as a release closes it
        (the wheels stopped and confirmed, the neck rested or freed). ``before`` is called
        once it is sure to go ahead.

        Raises:
            StopNotConfirmedError: The old port's wheels were not confirmed stopped: not
                connected (disconnected; the other port is not opened).
            TransportError: The port cannot be opened: disconnected.
        """
        state = self._state
        bus = state.bus
        async with self._lock:
            state.check_open()
            if reopen is None and state.link is not Link.RELEASED:
                return  # connected to it already
            before()
            previous = bus.reopen
            if reopen is not None:
                bus.reopen = reopen
            try:
                if state.link is not Link.RELEASED:
                    error = await state.shielded(
                        self._release(None, why="disconnected from the port"), "disconnect"
                    )
                    state.disconnected = True
                    if error is not None:
                        raise error
                else:
                    # A reclaim waiting for the port, or a timed one, gives way.
                    await state.cancel_tasks()
                    self._arm_reclaim(None)
                await bus.reconnect(attempts=1)
            except (TransportError, StopNotConfirmedError) as exc:
                bus.reopen = previous
                state.disconnected = True
                state.publish(f"connecting to {name} failed: {exc}; disconnected")
                raise
            state.disconnected = False
            await self._back(f"connected to {name}")
            self._discovery.arm()
        state.spawn(self._watch(), "link watcher")

    async def _release(
        self, duration_s: float | None, *, why: str | None = None
    ) -> StopNotConfirmedError | None:
        """:meth:`release`'s work, under the port lock; the stop's error, if any."""
        state = self._state
        bus = state.bus
        if state.link is Link.RELEASED:
            # A reclaim waiting for the port, or a timed one due, stops: released again.
            await state.cancel_tasks()
            if bus.connected:
                # That reclaim had just reopened the port (nothing drove since the stop).
                await bus.release()
            self._arm_reclaim(duration_s)
            state.publish(f"port release renewed: {_released_for(duration_s)}")
            return None
        state.releasing = asyncio.current_task()
        try:
            self._feedback.stop()
            self._discovery.disarm()
            # Nothing of the Robot's may use the port from here: the link watcher (or it
            # would take the release for a loss), a reprobe, a guard (the neck is done
            # with below).
            await state.cancel_tasks()
            error: StopNotConfirmedError | None = None
            if bus.connected:
                error = await self.stop_and_rest("releasing the port")
                # The last word before the port goes, as closing's (the stop of a Robot
                # whose drive boards never answered, too).
                with contextlib.suppress(OhmniError):
                    await bus.send_now(wheel_command(0, 0, state.profile.drive))
            try:
                await bus.release()
            except BusClosedError as exc:  # close() ran meanwhile
                raise StateError("the robot was closed while releasing its port") from exc
            state.link = Link.RELEASED
            # Not lost any more: nobody tries to reopen it now.
            state.faults.discard("link_lost")
            self._control.halt()
        finally:
            state.releasing = None
        self._arm_reclaim(duration_s)
        unconfirmed = "" if error is None else f" (the wheel stop was not confirmed: {error})"
        why = why or f"port released to another program {_released_for(duration_s)}"
        state.publish(f"{why}{unconfirmed}")
        return error

    def _arm_reclaim(self, duration_s: float | None) -> None:
        if self._reclaim_timer is not None:
            self._reclaim_timer.cancel()
            self._reclaim_timer = None
        if duration_s is not None:
            self._reclaim_timer = self._state.loop.call_later(duration_s, self._reclaim_due)

    def _reclaim_due(self) -> None:
        self._reclaim_timer = None
        state = self._state
        if state.closed or state.link is not Link.RELEASED:
            return
        state.publish("port release time is up: reclaiming the port")
        state.spawn(self._timed_reclaim(), "timed reclaim")

    async def _timed_reclaim(self) -> None:
        self._state.check_open()
        await self.reclaim()

    def _start_reclaim(self) -> asyncio.Future[None]:
        """Start reopening the released port; the future is done after the first try."""
        if self._reclaim_timer is not None:
            self._reclaim_timer.cancel()
            self._reclaim_timer = None
        state = self._state
        first: asyncio.Future[None] = state.loop.create_future()
        state.reclaim = first
        state.spawn(self._reclaim_link(first), "reclaim port")
        return first

    async def _reclaim_link(self, first: asyncio.Future[None]) -> None:
        """Reopen the released port, retrying while another program holds it; then watch
        the link as before. ``first`` is done after the first attempt."""
        state = self._state
        bus = state.bus
        try:
            try:
                await bus.reconnect(attempts=1)
            except TransportError as exc:
                state.publish(
                    f"reclaiming the port: another program still holds it ({exc}); "
                    f"waiting for it, trying again every {RECLAIM_BACKOFF_S:g}.."
                    f"{state.config.reconnect_max_backoff_s:g} s"
                )
                if not first.done():
                    first.set_result(None)
                await asyncio.sleep(RECLAIM_BACKOFF_S)
                await bus.reconnect(
                    backoff_s=RECLAIM_BACKOFF_S * 2,
                    max_backoff_s=state.config.reconnect_max_backoff_s,
                )
            await self._back("port reclaimed")
            self._discovery.arm()
        finally:
            state.reclaim = None
            if not first.done():
                first.set_result(None)
        await self._watch()


def _released_for(duration_s: float | None) -> str:
    """How long a release lasts, in words for ``robot_state``."""
    if duration_s is None:
        return "until reclaim_port()"
    return f"for {duration_s:g} s"
