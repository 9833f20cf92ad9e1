"""A client and a daemon of different protocol versions are told apart, both numbers named."""

from __future__ import annotations

import json

import pytest
from websockets.asyncio.server import ServerConnection, serve

from ohmni_tb import Robot
from ohmni_tb._version import __version__
from ohmni_tb.errors import TransportError
from ohmni_tb.robot.wire import PROTOCOL_VERSION

pytestmark = pytest.mark.real_time  # a real socket


async def _greet_with(protocol: object) -> str:
    """Open a robot on a server that greets with ``protocol``; the error it raises."""

    async def hello(ws: ServerConnection) -> None:
        await ws.send(json.dumps({"op": "hello", "protocol": protocol, "version": "9.9.9"}))
        await ws.wait_closed()

    async with serve(hello, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        with pytest.raises(TransportError) as caught:
            async with Robot.open(f"ws://127.0.0.1:{port}", timeout_s=2.0):
                pass
    return str(caught.value)


async def test_a_daemon_of_another_protocol_is_refused_naming_both() -> None:
    older = PROTOCOL_VERSION - 1
    said = await _greet_with(older)
    assert f"speaks protocol {older} (ohmni_tb 9.9.9)" in said
    assert f"this client protocol {PROTOCOL_VERSION} (ohmni_tb {__version__})" in said
    assert "run the same ohmni_tb version on both sides" in said


async def test_a_hello_without_a_protocol_is_refused_too() -> None:
    assert "speaks protocol None" in await _greet_with(None)
