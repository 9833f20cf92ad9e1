"""The daemon's robot with explicit control of the lease: :class:`RobotClient`.

``Robot.open("ws://127.0.0.1:8766")`` gives the daemon's robot
(:class:`~ohmni_tb.robot.RemoteRobot`), which takes the control lease by itself on the
first command that needs it. A program that decides when it drives — an operator's tool
taking over from a misbehaving script, a teleop that gives the lease back when idle —
uses :class:`RobotClient`: the same robot, whose commands need the lease taken with
:meth:`RobotClient.acquire` (or ``async with client.lease():``)::

    from ohmni_tb.client import RobotClient

    async with RobotClient.connect("ws://127.0.0.1:8766") as client:
        odom = client.latest("wheel_odom")            # plain, as on any Robot
        async with client.lease():                    # one driver at a time
            client.drive(0.3, 0.0)
            await client.neck.move(raw=400, playtime_s=1.0)
            await client.confirm()                    # every command so far accepted
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import AsyncIterator, Coroutine
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from typing import Any, ClassVar, Protocol, overload

from ohmni_tb.errors import LeaseError, TransportError
from ohmni_tb.robot.remote import DEFAULT_TIMEOUT_S, DEFAULT_URL, RemoteRobot
from ohmni_tb.robot.wire import AcquireArgs, Hello, ReleaseArgs

__all__ = ["DEFAULT_TIMEOUT_S", "DEFAULT_URL", "RobotClient"]


class _Opener(Protocol):
    def __call__(
        self,
        url: str = DEFAULT_URL,
        *,
        token: str | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        reconnect: bool = False,
        source: str | None = None,
    ) -> AbstractAsyncContextManager[RobotClient]: ...


class _Connector(Protocol):
    def __call__(self, port: str | None = None) -> Coroutine[Any, Any, None]: ...


class _OpenOrConnect:
    """``RobotClient.connect``: on the class, connect to the daemon at ``url`` (leaving the
    block closes the connection and gives the lease back, which stops the robot; with
    ``reconnect`` the lease is **not** taken again after the daemon came back: a driver
    must :meth:`RobotClient.acquire` anew); on a client, :meth:`Robot.connect
    <ohmni_tb.robot.api.Robot.connect>` (switch the daemon's robot to another port)."""

    @overload
    def __get__(self, instance: None, owner: type[RobotClient]) -> _Opener: ...
    @overload
    def __get__(self, instance: RobotClient, owner: type[RobotClient]) -> _Connector: ...
    def __get__(self, instance: RobotClient | None, owner: type[RobotClient]) -> Any:
        if instance is None:

            def opener(
                url: str = DEFAULT_URL,
                *,
                token: str | None = None,
                timeout_s: float = DEFAULT_TIMEOUT_S,
                reconnect: bool = False,
                source: str | None = None,
            ) -> AbstractAsyncContextManager[RobotClient]:
                return owner.open(
                    url, token=token, timeout_s=timeout_s, reconnect=reconnect, source=source
                )

            return opener
        return functools.partial(RemoteRobot.connect, instance)


class RobotClient(RemoteRobot):
    """The daemon's robot whose commands need the lease taken explicitly (module
    docstring). Open it with ``async with RobotClient.connect(url) as client:``."""

    _auto_lease: ClassVar[bool] = False

    #: ``RobotClient.connect(url)`` opens a client (as :meth:`RemoteRobot.open`);
    #: ``client.connect(port)`` is the Robot's: switch the daemon's robot to ``port``.
    connect = _OpenOrConnect()

    @property
    def hello(self) -> Hello:
        """What the daemon said on connecting: protocol, version, topics and rates, limits."""
        return self._connection.hello

    @property
    def topics(self) -> dict[str, float]:
        """Every stream and its rate in Hz (0: on events), as the daemon said on connecting."""
        return dict(self._connection.hello.topics)

    @property
    def peer(self) -> str:
        """This connection as the daemon names it (``host:port``)."""
        return self._connection.peer

    @property
    def has_lease(self) -> bool:
        """Whether this connection holds the control lease of its command source
        (:attr:`source`)."""
        return self._connection.has_lease

    async def acquire(self, *, steal: bool = False, source: str | None = None) -> str | None:
        """Take the control lease of command source ``source`` (default :attr:`source`):
        from now on this connection's commands move the robot as that source.

        One client at most holds each source's lease; the daemon's Robot takes the drive
        commands of the highest source that drives. ``steal`` takes it from the holder
        (an operator taking over a misbehaving script); the loser is told, and the robot
        stops whenever the lease changes hands while its source drives. Closing the
        connection releases it (and so stops the robot). Only a program on the daemon's
        computer may take ``local`` or ``safety``.

        Returns:
            The peer it was stolen from, or ``None``.

        Raises:
            LeaseError: Another client holds it and ``steal`` is not set (``.holder``
                names it), or a source this client may not take (beyond loopback).
            InvalidArgumentError: ``source`` is not a command source of the daemon's robot.
            StateError: The daemon takes no commands (started read-only).
        """
        name = self._source_name(source)
        data = await self._call("acquire", AcquireArgs(steal=bool(steal), source=name))
        self._connection.holders[name] = data["holder"]
        stolen_from: str | None = data["stolen_from"]
        return stolen_from

    async def release(self, *, source: str | None = None) -> None:
        """Give the control lease of ``source`` (default :attr:`source`) back: the robot
        stops unless a higher source drives it. Without that lease: nothing."""
        name = self._source_name(source)
        if not self._connection.holds(name):
            return
        self._check_open()
        # Before the daemon's lease message: ours, not a loss.
        self._connection.holders.pop(name, None)
        await self._connection.call("release", ReleaseArgs(source=name))

    @asynccontextmanager
    async def lease(
        self, *, steal: bool = False, source: str | None = None
    ) -> AsyncIterator[RobotClient]:
        """``async with client.lease():`` — hold the control lease (of ``source``) for the
        block."""
        await self.acquire(steal=steal, source=source)
        try:
            yield self
        finally:
            if self.connected and not self.closed:
                with contextlib.suppress(TransportError, LeaseError):
                    await self.release(source=source)

    def _lease_refusal(self, method: str, holder: str | None, source: str) -> str:
        whose = "" if source == self.source else f" of command source {source}"
        return f"{method} needs the control lease{whose}: " + (
            f"{holder} holds it (acquire(steal=True) takes it)"
            if holder
            else f"call await client.acquire({'' if not whose else f'source={source!r}'}) first"
        )
