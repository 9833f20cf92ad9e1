"""Command sources through the daemon: one lease per source, who may claim which (a
client beyond loopback never a source of the robot's own computer, and never without the
token), and a client leaving stops the robot only when its source drives it.

On the simulator's virtual clock; the simulator's ground truth says whether it moved.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator

import pytest

from ohmni_tb import Robot
from ohmni_tb.client import RobotClient
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import ConfigError, LeaseError, SourceOverriddenError, TransportError
from ohmni_tb.robot import SampleStream, WheelOdomSample

from .test_control import drive_for, speed, until

TOKEN = "s" * 20 + "-a-sources-token"


async def drive_confirmed(robot: Robot) -> None:
    """Drive as a teleop does for half a second, and wait for the daemon's answers."""
    for _ in range(10):
        robot.drive(0.3, 0.0)
        await asyncio.sleep(0.05)
    await robot.confirm()


def drain(stream: SampleStream[WheelOdomSample]) -> list[WheelOdomSample]:
    """The samples queued in ``stream``."""
    got = []
    while (sample := stream.get_nowait()) is not None:
        got.append(sample)
    return got


def this_computers_address() -> str | None:
    """An address of this computer beyond loopback (no packet is sent), or ``None``."""
    with contextlib.suppress(OSError), socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect(("192.0.2.1", 9))  # TEST-NET-1: a route out, never reached
        address: str = probe.getsockname()[0]
        if not address.startswith("127."):
            return address
    return None


@contextlib.asynccontextmanager
async def beyond_loopback(robot: Robot) -> AsyncIterator[tuple[str, str]]:
    """The daemon on every address with its token: its URL through this computer's
    address beyond loopback, and through loopback."""
    address = this_computers_address()
    if address is None:
        pytest.skip("this computer has no address beyond loopback")
    async with RobotServer(robot, host="0.0.0.0", port=0, token=TOKEN) as server:
        port = server.url.rsplit(":", 1)[1]
        yield f"ws://{address}:{port}", f"ws://127.0.0.1:{port}"


async def test_beyond_loopback_a_client_cannot_claim_local_and_nothing_moves(robot: Robot) -> None:
    async with beyond_loopback(robot) as (far, near):
        with pytest.raises(TransportError, match="HTTP 401"):  # the token, as always
            async with RobotClient.connect(far, source="remote"):
                pass
        async with RobotClient.connect(far, token=TOKEN) as client:
            for source in ("local", "safety"):
                with pytest.raises(LeaseError) as refused:
                    await client.acquire(source=source)
                assert f"command source {source!r} is for programs on the robot's own" in str(
                    refused.value
                )
                assert "may take remote, autonomy" in str(refused.value)
            assert client.leases == {}
        # A script opened as local from beyond loopback: its drive takes no lease, and
        # nothing reaches the wheels.
        async with Robot.open(far, token=TOKEN, source="local") as script:
            with pytest.raises(LeaseError, match="is for programs on the robot's own computer"):
                await drive_confirmed(script)
            assert speed(robot) == 0.0
        # remote and autonomy it may take; on loopback, local too.
        async with RobotClient.connect(far, token=TOKEN, source="remote") as client:
            assert await client.acquire() is None
            assert client.has_lease
        async with RobotClient.connect(near, token=TOKEN, source="local") as client:
            assert await client.acquire() is None
            await drive_for(client, 0.5)
            await client.confirm()
            assert speed(robot) > 0.1


async def test_one_lease_per_source_and_the_highest_drives(
    robot: Robot, server: RobotServer
) -> None:
    async with (
        RobotClient.connect(server.url) as script,  # autonomy
        RobotClient.connect(server.url, source="local") as person,
        RobotClient.connect(server.url) as other_script,
    ):
        await script.acquire()
        await person.acquire()
        assert server.leases == {"local": person.peer, "autonomy": script.peer}
        assert server.lease_holder == person.peer  # the highest source's
        with pytest.raises(LeaseError, match="control lease of command source autonomy is held"):
            await other_script.acquire()
        await drive_for(script, 0.5)
        await script.confirm()
        await until(lambda: speed(robot) > 0.1)
        # The person takes over; the script's commands are refused meanwhile.
        await drive_for(person, 0.3, 0.0)
        with pytest.raises(SourceOverriddenError, match="source 'local'"):
            await drive_confirmed(script)
        await until(lambda: speed(robot) == 0.0, 1.0)
        assert robot.state.active_source == "local"


async def test_a_client_leaving_stops_the_robot_only_if_its_source_drives(
    robot: Robot, server: RobotServer
) -> None:
    async with RobotClient.connect(server.url, source="local") as person:
        await person.acquire()
        async with RobotClient.connect(server.url) as script:
            await script.acquire()
            driving = asyncio.create_task(drive_for(person, 1.5))
            await until(lambda: speed(robot) > 0.29)  # at the speed asked
            odom = robot.subscribe("wheel_odom", maxlen=1000)
        # The script left while the person drives: the robot goes on, never stopped for
        # a tick (a stop would show as a request of 0 until the person's next command).
        await asyncio.sleep(0.3)
        requested = [sample.requested_linear_mps for sample in drain(odom)]
        assert len(requested) > 10
        assert set(requested) == {0.3}
        assert speed(robot) > 0.28
        await driving
        await person.confirm()
        driving = asyncio.create_task(drive_for(person, 0.5))
        await until(lambda: speed(robot) > 0.25)
        await person.release()  # the source that drives gives its lease back: stopped
        driving.cancel()
        with contextlib.suppress(asyncio.CancelledError, LeaseError):
            await driving
        await until(lambda: speed(robot) == 0.0, 0.45)  # before the watchdog would


async def test_a_source_the_daemons_robot_has_not_is_refused_at_open(server: RobotServer) -> None:
    with pytest.raises(ConfigError) as caught:
        async with Robot.open(server.url, source="operator"):
            pass
    assert str(caught.value) == (
        "source='operator' is not a command source of the daemon's robot: allowed safety, "
        "local, remote, autonomy"
    )
    assert server.leases == {}
