"""Which requests get a reply: one decider, checked against the reference's table."""

from __future__ import annotations

import dataclasses

import pytest

from ohmni_tb import herkulex, protocol
from ohmni_tb.herkulex import (
    AckPolicy,
    JogTarget,
    TorqueControl,
    eep_read,
    eep_write,
    i_jog,
    ram_read,
    ram_write,
    reboot,
    reply_expected,
    rollback,
    s_jog,
    stat,
)
from ohmni_tb.protocol import BROADCAST_ID, Command, Packet
from ohmni_tb.sim.servo import SimServo

SID = 3
# Replies to one servo under ACK policy (0, 1, 2), from the reference's command table.
TABLE: dict[Command, tuple[bool, bool, bool]] = {
    Command.EEP_WRITE: (False, False, True),
    Command.EEP_READ: (False, True, True),
    Command.RAM_WRITE: (False, False, True),
    Command.RAM_READ: (False, True, True),
    Command.I_JOG: (False, False, True),
    Command.S_JOG: (False, False, True),
    Command.STAT: (True, True, True),
    Command.ROLLBACK: (False, False, True),
    Command.REBOOT: (False, False, True),
}
CASES = [
    (cmd, policy, sid) for cmd in Command for policy in AckPolicy for sid in (SID, BROADCAST_ID)
]


def expected(cmd: Command, policy: AckPolicy, sid: int) -> bool:
    # To broadcast only STAT is answered (by every servo at once).
    if sid == BROADCAST_ID:
        return cmd == Command.STAT
    return TABLE[cmd][policy]


def test_herkulex_reexports_the_protocol_decider() -> None:
    assert herkulex.reply_expected is protocol.reply_expected


def test_table_covers_every_command() -> None:
    assert set(TABLE) == set(Command)


@pytest.mark.parametrize(("cmd", "policy", "sid"), CASES)
def test_reply_expected(cmd: Command, policy: AckPolicy, sid: int) -> None:
    assert reply_expected(cmd, sid, policy) is expected(cmd, policy, sid)


def test_default_policy_is_reads() -> None:
    assert reply_expected(Command.RAM_READ, SID)
    assert not reply_expected(Command.RAM_WRITE, SID)


def request(cmd: Command) -> Packet:
    """A well-formed request of each kind, addressed to SID."""
    return {
        Command.EEP_WRITE: lambda: eep_write(SID, "led_blink_period", 0x30),
        Command.EEP_READ: lambda: eep_read(SID, "id"),
        Command.RAM_WRITE: lambda: ram_write(SID, "led_control", 1),
        Command.RAM_READ: lambda: ram_read(SID, "temperature"),
        Command.I_JOG: lambda: i_jog(JogTarget(SID, 600, playtime_ticks=10)),
        Command.S_JOG: lambda: s_jog(10, JogTarget(SID, 600)),
        Command.STAT: lambda: stat(SID),
        Command.ROLLBACK: lambda: rollback(SID),
        Command.REBOOT: lambda: reboot(SID),
    }[cmd]()


@pytest.mark.parametrize(("cmd", "policy", "sid"), CASES)
def test_sim_servo_answers_exactly_when_expected(cmd: Command, policy: AckPolicy, sid: int) -> None:
    servo = SimServo(SID)
    servo.handle(ram_write(SID, "torque_control", TorqueControl.ON), 0.0)
    servo.handle(ram_write(SID, "ack_policy", policy), 0.0)
    # Builders refuse broadcast reads, so the broadcast ones are made by hand.
    packet = dataclasses.replace(request(cmd), sid=sid)
    reply = servo.handle(packet, 0.1)
    assert (reply is not None) is expected(cmd, policy, sid)
    if reply is not None:
        assert reply.sid == SID
        assert reply.cmd == cmd | 0x40
