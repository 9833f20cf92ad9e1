"""``RobotClient`` (the daemon's robot, with explicit lease control) against a served
Robot: the same values and the same dataclasses, plain reads as on the Robot."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import signal
import socket
from collections.abc import Callable

import pytest

from ohmni_tb import Robot
from ohmni_tb.client import RobotClient
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import InvalidArgumentError, LeaseError, TransportError
from ohmni_tb.robot import TbcoreStatusSample, WheelOdomSample

from ._serving import free_port, start_serving, stop_serving


async def test_info_schedule_and_stats_match_the_robots(robot: Robot, server: RobotServer) -> None:
    async with RobotClient.connect(server.url) as client:
        assert await client.info() == await robot.info()
        assert client.schedule() == robot.schedule()
        stats = client.stats()
        local = robot.stats()
        assert set(stats.streams) == set(local.streams)
        for name, figures in stats.streams.items():
            assert figures.requested_hz == local.streams[name].requested_hz
            assert figures.samples <= local.streams[name].samples
        assert stats.bus.budget_share == local.bus.budget_share
        assert client.topics == {n: s.requested_hz for n, s in local.streams.items()}


async def test_latest_is_plain_and_follows_the_daemons_samples(
    robot: Robot, server: RobotServer
) -> None:
    async with robot.subscribe("tbcore_status") as status:
        await anext(status)  # the Robot has one now
    async with RobotClient.connect(server.url) as client:
        # Fetched on connecting: there at once, though the next comes in 0.1 s.
        first = client.latest("tbcore_status")
        assert isinstance(first, TbcoreStatusSample)
        assert first.pack_v > 10
        async with client.subscribe("wheel_odom") as odom:
            sample = await anext(odom)
            assert isinstance(sample, WheelOdomSample)
            kept = client.latest("wheel_odom")
            assert kept is not None
            assert kept.stamp_s >= sample.stamp_s  # the newest the daemon sent
        async with client.subscribe("tbcore_status") as status:
            await anext(status)
            newer = client.latest("tbcore_status")
            assert newer is not None
            assert newer.stamp_s > first.stamp_s
        assert client.latest("new_neck") is None  # no worm neck on this robot


async def test_subscribed_samples_are_the_robots_own(robot: Robot, server: RobotServer) -> None:
    async with RobotClient.connect(server.url) as client:
        async with client.subscribe("wheel_odom") as remote:
            await anext(remote)
            async with robot.subscribe("wheel_odom") as local:
                robot_side = [await anext(local) for _ in range(10)]
            client_side = [await anext(remote) for _ in range(12)]
        by_stamp = {s.stamp_s: s for s in client_side}
        matched = [s for s in robot_side if s.stamp_s in by_stamp]
        assert len(matched) >= 8
        for sample in matched:
            assert by_stamp[sample.stamp_s] == sample
            assert dataclasses.is_dataclass(by_stamp[sample.stamp_s])


async def test_bad_names_are_refused_here_and_one_stream_takes_many_subscriptions(
    server: RobotServer,
) -> None:
    async with RobotClient.connect(server.url) as client:
        with pytest.raises(InvalidArgumentError, match="no stream 'odom'"):
            client.latest("odom")
        with pytest.raises(InvalidArgumentError, match="no stream"):
            client.subscribe("odom")
        with pytest.raises(InvalidArgumentError, match="maxlen=0"):
            client.subscribe("wheel_odom", maxlen=0)
        async with client.subscribe("wheel_odom") as one, client.subscribe("wheel_odom") as two:
            assert (await anext(one)).stamp_s == (await anext(two)).stamp_s


async def test_nothing_listening_is_a_transport_error_naming_the_url() -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # free, and nobody listens once closed
    url = f"ws://127.0.0.1:{port}"
    with pytest.raises(TransportError, match=f"cannot connect to the daemon at {url}"):
        async with RobotClient.connect(url, timeout_s=2.0):
            pass


def test_ohmni_serve_serves_sim_and_exits_cleanly_on_ctrl_c() -> None:
    proc, url = start_serving("--listen", "127.0.0.1:0", "--foreground")
    try:
        assert url.startswith("ws://127.0.0.1:")

        async def use() -> float:
            async with RobotClient.connect(url) as client:
                async with client.subscribe("tbcore_status") as status:
                    sample = await anext(status)
                    odom = client.latest("wheel_odom")  # the newest the daemon sent
                    assert odom is not None
                    proc.send_signal(signal.SIGINT)
                    with pytest.raises(TransportError, match="1001"):
                        async for _ in status:
                            pass
                pack_v: float = sample.pack_v
                return pack_v

        assert asyncio.run(use()) > 10
    finally:
        log = stop_serving(proc)
    assert "Traceback" not in log
    assert 'level=info logger=ohmni_tb.daemon msg="client 127.0.0.1:' in log
    assert "stopped serving" in log


def test_clients_that_reconnect_ride_out_a_daemon_restart() -> None:
    """The daemon killed outright (no closing handshake) and started again on its port:
    reconnecting clients get their streams back; the lease is not handed back by itself."""
    listen = f"127.0.0.1:{free_port()}"
    first, url = start_serving("--listen", listen)

    async def use() -> None:
        nonlocal first
        async with contextlib.AsyncExitStack() as stack:
            readers = [
                await stack.enter_async_context(RobotClient.connect(url, reconnect=True))
                for _ in range(4)
            ]
            streams = [
                await stack.enter_async_context(reader.subscribe("tbcore_status"))
                for reader in readers
            ]
            driver = await stack.enter_async_context(RobotClient.connect(url, reconnect=True))
            await driver.acquire()
            for stream in streams:
                await anext(stream)
            once = await stack.enter_async_context(RobotClient.connect(url))
            first.kill()
            first.communicate()
            async with asyncio.timeout(5):
                while driver.connected or any(r.connected for r in readers):  # noqa: ASYNC110  # no event for it
                    await asyncio.sleep(0.02)
            # Down: calls say so at once; a client without reconnect has ended.
            with pytest.raises(TransportError, match="closed the connection"):
                driver.drive(0.1, 0.0)
            with pytest.raises(TransportError):
                await readers[0].info()
            assert not once.connected
            second, url2 = start_serving("--listen", listen)
            first = second
            assert url2 == url
            async with asyncio.timeout(15):
                for stream in streams:
                    while stream.pending:  # samples from before the restart
                        await anext(stream)
                    sample = await anext(stream)
                    assert sample.pack_v > 10
            assert all(client.connected for client in (driver, *readers))
            assert [client.reconnects for client in (driver, *readers)] == [1] * 5
            assert not driver.has_lease
            with pytest.raises(LeaseError, match="acquire"):
                driver.drive(0.1, 0.0)
            await driver.acquire()
            driver.drive(0.1, 0.0)
            await driver.confirm()

    try:
        asyncio.run(use())
    finally:
        stop_serving(first)


async def test_a_closed_client_refuses_every_command_with_one_error(server: RobotServer) -> None:
    from ohmni_tb.errors import RobotClosedError

    async with RobotClient.connect(server.url) as client:
        await client.acquire()
    commands: list[Callable[[], object]] = [
        lambda: client.drive(0.1, 0.0),
        client.stop,
        lambda: client.set_rate("tbcore_status", 5.0),
    ]
    for command in commands:
        with pytest.raises(RobotClosedError, match="the robot is closed"):
            command()
    with pytest.raises(RobotClosedError, match="the robot is closed"):
        await client.info()
    with pytest.raises(RobotClosedError, match="the robot is closed"):
        await client.estop()
