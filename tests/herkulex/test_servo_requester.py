"""Servo over a minimal Requester (not a Bus), and the cached status that spares a STAT."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable

import pytest

from ohmni_tb.bus import Bus
from ohmni_tb.errors import DeviceStatusError, InvalidArgumentError, OutOfRangeError
from ohmni_tb.herkulex import StatusDetail, StatusError, TorqueControl
from ohmni_tb.herkulex.servo import Requester, Servo, ServoStatus, move_group
from ohmni_tb.protocol import REPLY_FLAG, Command, Packet
from ohmni_tb.sim.clock import run_virtual

SID = 3
GOOD = ServoStatus(StatusError.NONE, StatusDetail.MOTOR_ON | StatusDetail.INPOSITION)
HOT = ServoStatus(StatusError.TEMPERATURE, StatusDetail.NONE)


class FakeRequester:
    """Answers like one HerkuleX servo under ACK policy 1, records every packet; no Bus."""

    def __init__(self) -> None:
        self.sent: list[Packet] = []
        self.ram: dict[int, int] = {}
        self.error = StatusError.NONE
        self.detail = StatusDetail.INPOSITION
        self.policies: dict[int, int] = {}

    async def request(
        self,
        packet: Packet,
        *,
        expect_reply: bool | None = None,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> Packet | None:
        self.sent.append(packet)
        status = bytes((self.error, self.detail))
        reply_cmd = packet.cmd | REPLY_FLAG
        if packet.cmd == Command.STAT:
            return Packet(packet.sid, reply_cmd, status)
        if packet.cmd == Command.RAM_READ:
            addr, length = packet.data
            body = bytes(self.ram.get(addr + i, 0) for i in range(length))
            return Packet(packet.sid, reply_cmd, bytes((addr, length)) + body + status)
        if packet.cmd == Command.RAM_WRITE:
            addr, _, *values = packet.data
            for i, value in enumerate(values):
                self.ram[addr + i] = value
            if addr == 52:
                on = values[0] == TorqueControl.ON
                self.detail = (
                    (self.detail | StatusDetail.MOTOR_ON)
                    if on
                    else (self.detail & ~StatusDetail.MOTOR_ON)
                )
        return None

    async def send(self, packet: Packet) -> None:
        self.sent.append(packet)

    def ack_policy(self, sid: int) -> int:
        return self.policies.get(sid, 1)

    def set_ack_policy(self, sid: int, policy: int) -> None:
        self.policies[sid] = policy

    def count(self, cmd: Command) -> int:
        return sum(p.cmd == cmd for p in self.sent)


def run(body: Callable[[FakeRequester], Awaitable[None]]) -> None:
    """Run ``body`` on a fresh fake, in virtual time (sleeps jump the loop's clock)."""

    async def main() -> None:
        await body(FakeRequester())

    run_virtual(main())


def now() -> float:
    return asyncio.get_running_loop().time()


# -- the Requester protocol ---------------------------------------------------------------


def test_a_servo_works_over_a_requester_that_is_not_a_bus() -> None:
    async def body(fake: FakeRequester) -> None:
        servo = Servo(fake, SID, min_raw=280, max_raw=650)
        await servo.torque(TorqueControl.ON)
        await servo.move_to(400, playtime_ticks=10)
        assert [Command(p.cmd) for p in fake.sent] == [
            Command.RAM_WRITE,
            Command.STAT,
            Command.S_JOG,
        ]
        assert fake.sent[-1].data == bytes((10, 400 & 0xFF, 400 >> 8, 0x00, SID))
        assert await servo.read("torque_control") == TorqueControl.ON
        await servo.write("ack_policy", 2)
        assert fake.ack_policy(SID) == 2
        await move_group([(servo, 300)], playtime_ticks=5)
        assert fake.sent[-1] == Packet(SID, Command.S_JOG, bytes((5, 300 & 0xFF, 300 >> 8, 0, SID)))

    run(body)


def test_the_bus_is_a_requester() -> None:
    assert issubclass(Bus, Requester)
    assert isinstance(FakeRequester(), Requester)


def _bus_carries_a_servo(bus: Bus) -> Requester:
    return bus  # mypy checks this: the Bus has every call a Servo makes


@pytest.mark.parametrize("thing", [object(), None, "sim://"])
def test_a_servo_refuses_what_cannot_carry_it(thing: object) -> None:
    with pytest.raises(InvalidArgumentError, match="Requester"):
        Servo(thing, SID)  # type: ignore[arg-type]  # what a caller might pass


# -- the cached status --------------------------------------------------------------------


def test_two_moves_in_a_row_send_one_stat() -> None:
    async def body(fake: FakeRequester) -> None:
        servo = Servo(fake, SID)
        await servo.torque(TorqueControl.ON)
        await servo.move_to(400)
        await asyncio.sleep(0.05)
        await servo.move_to(500)
        assert fake.count(Command.STAT) == 1
        assert fake.count(Command.S_JOG) == 2
        assert servo.last_status == GOOD
        assert servo.last_status_at is not None
        assert now() - servo.last_status_at == pytest.approx(0.05)

    run(body)


def test_a_stale_status_forces_a_stat() -> None:
    async def body(fake: FakeRequester) -> None:
        servo = Servo(fake, SID)
        await servo.torque(TorqueControl.ON)
        await servo.move_to(400)
        await asyncio.sleep(0.15)  # older than the default 0.1 s
        await servo.move_to(500)
        assert fake.count(Command.STAT) == 2

    run(body)


def test_the_age_limit_is_the_servos_own() -> None:
    async def body(fake: FakeRequester) -> None:
        patient = Servo(fake, SID, status_max_age_s=0.5)
        await patient.torque(TorqueControl.ON)
        await patient.move_to(400)
        await asyncio.sleep(0.3)
        await patient.move_to(500)
        assert fake.count(Command.STAT) == 1

        fake.sent.clear()
        always_asks = Servo(fake, 4, status_max_age_s=0)
        for _ in range(3):
            await always_asks.move_to(500)
        assert fake.count(Command.STAT) == 3

    run(body)


def test_a_status_fed_by_a_poller_spares_the_stat() -> None:
    async def body(fake: FakeRequester) -> None:
        fake.detail |= StatusDetail.MOTOR_ON
        servo = Servo(fake, SID)
        at = now()
        servo.note_status(GOOD, at)
        await asyncio.sleep(0.02)
        await servo.move_to(400)
        assert [Command(p.cmd) for p in fake.sent] == [Command.S_JOG]
        assert (servo.last_status, servo.last_status_at) == (GOOD, at)

    run(body)


def test_a_cached_fault_still_refuses_the_move() -> None:
    async def body(fake: FakeRequester) -> None:
        fake.error, fake.detail = StatusError.TEMPERATURE, StatusDetail.NONE
        servo = Servo(fake, SID)
        servo.note_status(HOT, now())
        with pytest.raises(DeviceStatusError, match="TEMPERATURE"):
            await servo.move_to(400)
        assert fake.count(Command.S_JOG) == 0

    run(body)


def test_a_refusal_rests_on_the_servos_answer_not_on_the_cache() -> None:
    # The cache only ever spares a STAT: a cached fault is asked about again, so a fault
    # cleared since (by another owner) does not block the move.
    async def body(fake: FakeRequester) -> None:
        fake.detail |= StatusDetail.MOTOR_ON
        servo = Servo(fake, SID)
        servo.note_status(HOT, now())
        await servo.move_to(400)
        assert [Command(p.cmd) for p in fake.sent] == [Command.STAT, Command.S_JOG]

    run(body)


def test_a_torque_write_makes_the_cached_status_untrusted() -> None:
    async def body(fake: FakeRequester) -> None:
        servo = Servo(fake, SID)
        await servo.torque(TorqueControl.ON)
        await servo.move_to(400)
        await servo.torque(TorqueControl.FREE)  # no reply under ACK policy 1
        with pytest.raises(DeviceStatusError, match="torque off"):
            await servo.move_to(500)
        assert fake.count(Command.STAT) == 2
        assert fake.count(Command.S_JOG) == 1

    run(body)


def test_clearing_errors_makes_the_cached_status_untrusted() -> None:
    async def body(fake: FakeRequester) -> None:
        fake.detail |= StatusDetail.MOTOR_ON
        servo = Servo(fake, SID)
        servo.note_status(GOOD, now())
        await servo.write("status_error", 0)  # a write the servo does not answer
        await servo.move_to(400)
        assert fake.count(Command.STAT) == 1

    run(body)


def test_an_older_fed_status_does_not_replace_a_newer_one() -> None:
    async def body(fake: FakeRequester) -> None:
        servo = Servo(fake, SID)
        await asyncio.sleep(1.0)
        servo.note_status(GOOD, now())
        servo.note_status(HOT, now() - 0.5)
        assert servo.last_status == GOOD

    run(body)


def test_a_fed_status_must_carry_a_past_loop_time() -> None:
    async def body(fake: FakeRequester) -> None:
        servo = Servo(fake, SID)
        with pytest.raises(InvalidArgumentError, match="after the loop's time"):
            servo.note_status(GOOD, now() + 10.0)
        with pytest.raises(InvalidArgumentError, match="at_s"):
            servo.note_status(GOOD, math.nan)
        with pytest.raises(InvalidArgumentError, match="ServoStatus"):
            servo.note_status((0, 0), now())  # type: ignore[arg-type]  # what a caller might pass
        assert servo.last_status is None

    run(body)


@pytest.mark.parametrize("age", [-0.01, 1.5, math.nan, math.inf])
def test_status_max_age_out_of_range_is_refused(age: float) -> None:
    with pytest.raises(OutOfRangeError, match=r"status_max_age_s=.* allowed 0\.0\.\.1\.0 s"):
        Servo(FakeRequester(), SID, status_max_age_s=age)


@pytest.mark.parametrize("age", ["0.1", True, None])
def test_status_max_age_must_be_seconds(age: object) -> None:
    with pytest.raises(InvalidArgumentError, match="status_max_age_s"):
        Servo(FakeRequester(), SID, status_max_age_s=age)  # type: ignore[arg-type]  # a caller's mistake
