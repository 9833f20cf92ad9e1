"""A client inside the daemon's process (a bridge to MQTT) goes through the same dispatch
as a WebSocket client: the same control lease, the same checks, the same ``read_only``."""

from __future__ import annotations

import pytest

from ohmni_tb import Robot
from ohmni_tb.client import RobotClient
from ohmni_tb.daemon.local import LocalClient
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import LeaseError
from ohmni_tb.robot.wire import LeaseMessage, RequestError


async def test_a_command_needs_the_lease_and_another_client_holding_it_refuses_it(
    server: RobotServer,
) -> None:
    local = LocalClient(server, "mqtt:test")
    try:
        with pytest.raises(RequestError) as refused:
            await local.call("light_ring", {"hue": 1, "saturation": 2, "value": 3})
        assert refused.value.code == "no_lease"
        async with RobotClient.connect(server.url) as other:
            await other.acquire(source="remote")  # the local client's source
            with pytest.raises(RequestError) as held:
                await local.call("acquire")
            assert held.value.code == "lease_held"
            assert other.peer in held.value.message
            assert local.refused == 2
            # Stopping is anyone's.
            assert await local.call("stop") is None
    finally:
        local.close()


def lease_of(server: RobotServer, local: LocalClient) -> tuple[str | None, bool]:
    """Who holds the lease, and whether the local client does (read again each time)."""
    return server.lease_holder, local.holds_lease


async def test_holding_the_lease_it_commands_and_others_are_told(
    server: RobotServer, robot: Robot
) -> None:
    local = LocalClient(server, "mqtt:test")
    told: list[LeaseMessage] = []
    local.on_lease = told.append
    async with RobotClient.connect(server.url) as other:
        await local.call("acquire")
        assert local.holds_lease
        assert server.lease_holder == "mqtt:test"
        assert "mqtt:test" in [c.peer for c in server.clients]
        await local.call("light_ring", {"hue": 10, "saturation": 20, "value": 30})
        assert robot.sim is not None
        assert bytes(robot.sim.core.light_ring) == bytes((10, 20, 30))
        with pytest.raises(LeaseError, match="mqtt:test"):
            await other.acquire(source="remote")
        local.close()  # leaving releases the lease
        assert lease_of(server, local) == (None, False)
        await other.acquire(source="remote")
    assert [(m.holder, m.you) for m in told] == [("mqtt:test", True)]


async def test_bad_arguments_are_refused_with_the_daemons_words(server: RobotServer) -> None:
    local = LocalClient(server, "mqtt:test")
    try:
        await local.call("acquire")
        with pytest.raises(RequestError) as bad:
            await local.call("light_ring", {"hue": "red", "saturation": 2, "value": 3})
        assert bad.value.code == "bad_message"
        assert "hue" in bad.value.message
        with pytest.raises(RequestError) as out:
            await local.call("light_ring", {"hue": 300, "saturation": 2, "value": 3})
        assert out.value.code == "bad_value"
        assert out.value.raised is not None
        assert out.value.raised["type"] == "OutOfRangeError"
        with pytest.raises(RequestError) as unknown:
            await local.call("fly")
        assert unknown.value.code == "unknown_method"
    finally:
        local.close()


async def test_a_read_only_daemon_refuses_it_the_lease(robot: Robot) -> None:
    async with RobotServer(robot, port=0, read_only=True) as server:
        local = LocalClient(server, "mqtt:test")
        with pytest.raises(RequestError) as refused:
            await local.call("acquire")
        assert refused.value.code == "read_only"
        stats = await local.call("stats")
        assert "wheel_encoder" in stats["streams"]
        local.close()
