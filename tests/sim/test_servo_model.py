"""SimServo: the virtual DRS-0101/0201 seen through its packets and registers only."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError
from ohmni_tb.herkulex import (
    EEP,
    RAM,
    AckPolicy,
    JogMode,
    JogTarget,
    Led,
    Model,
    Reply,
    StatusDetail,
    StatusError,
    TorqueControl,
    clear_status,
    eep_read,
    eep_write,
    i_jog,
    parse_reply,
    playtime_ticks_from_s,
    ram_read,
    ram_write,
    ram_write_many,
    reboot,
    rollback,
    s_jog,
    stat,
)
from ohmni_tb.protocol import (
    BROADCAST_ID,
    Command,
    Memory,
    Packet,
    PacketDecoder,
    RejectReason,
    encode_packet,
    write_request,
)
from ohmni_tb.sim.servo import RESTART_S, SimServo

NECK = 3
GOLDEN_EEP_KP_KD_REPLY = bytes.fromhex("FF FF 0F FD 42 4C B2 1E 04 B8 01 40 1F 00 00")


class Bench:
    """One servo on a byte-accurate line: requests and replies go through the wire codec."""

    def __init__(self, servo: SimServo) -> None:
        self.servo = servo
        self.now_s = 0.0
        self._device_side = PacketDecoder(on_reject=self._rejected)
        self._host_side = PacketDecoder()

    def _rejected(self, reason: RejectReason, frame: bytes) -> None:
        self.servo.on_rejected(reason, frame, self.now_s)

    def send(self, packet: Packet | bytes, at_s: float | None = None) -> Reply | None:
        """Send a request (or raw bytes) at ``at_s``; return the parsed reply, if any."""
        if at_s is not None:
            self.now_s = at_s
        wire = packet if isinstance(packet, bytes) else encode_packet(packet)
        reply: Reply | None = None
        for request in self._device_side.feed(wire):
            self.servo.advance(self.now_s)
            answer = self.servo.handle(request, self.now_s)
            if answer is not None:
                (back,) = self._host_side.feed(encode_packet(answer))
                reply = parse_reply(back)
        return reply

    def ask(self, packet: Packet, at_s: float | None = None) -> Reply:
        reply = self.send(packet, at_s)
        assert reply is not None, f"no reply to {packet!r}"
        return reply

    def ram(self, name: str, at_s: float | None = None) -> int:
        return self.ask(ram_read(self.servo.sid, name), at_s).value(name)

    def eep(self, name: str) -> int:
        return self.ask(eep_read(self.servo.sid, name)).value(name)

    def status(self, at_s: float | None = None) -> Reply:
        return self.ask(stat(self.servo.sid), at_s)

    def power_cycle(self, at_s: float) -> None:
        self.now_s = at_s
        self.servo.power_cycle(at_s)

    def torque_on(self) -> None:
        self.send(ram_write(self.servo.sid, "torque_control", TorqueControl.ON))


@pytest.fixture
def neck() -> Bench:
    return Bench(SimServo(NECK, pos_raw=280))


# -- registers by packet ------------------------------------------------------------


def test_fresh_servo_answers_the_manuals_reply_byte_for_byte() -> None:
    servo = SimServo()  # factory id 0xFD
    answer = servo.handle(eep_read(0xFD, "position_kp", through="position_kd"), 0.0)
    assert answer is not None
    assert encode_packet(answer) == GOLDEN_EEP_KP_KD_REPLY


@pytest.mark.parametrize("model", list(Model))
def test_eep_holds_defaults_and_is_copied_to_ram(model: Model) -> None:
    bench = Bench(SimServo(NECK, model=model))
    eep = bench.ask(eep_read(NECK, "model_no1", through="calibration_difference"))
    ram = bench.ask(ram_read(NECK, "id", through="calibration_difference"))
    assert eep.data[:2] == bytes((model, 0x01))
    assert ram.data == eep.data[6:]
    for reg in EEP:
        if reg.default is not None and reg.name != "id":
            assert eep.value(reg) == reg.default, reg.name
    assert ram.value("id") == NECK
    assert ram.value("position_kp") == 440


def test_write_then_read_back(neck: Bench) -> None:
    neck.send(ram_write(NECK, "led_control", Led.GREEN | Led.RED))
    neck.send(ram_write_many(NECK, {"min_position": 280, "max_position": 650}))
    assert neck.ram("led_control") == Led.GREEN | Led.RED
    reply = neck.ask(ram_read(NECK, "min_position", through="max_position"))
    assert (reply.value("min_position"), reply.value("max_position")) == (280, 650)


def test_eep_write_waits_for_reboot(neck: Bench) -> None:
    neck.send(eep_write(NECK, "max_position", 650))
    assert neck.eep("max_position") == 650
    assert neck.ram("max_position") == 1002


def test_new_id_takes_effect_at_once(neck: Bench) -> None:
    neck.send(ram_write(NECK, "id", 11))
    assert neck.send(stat(NECK)) is None
    assert neck.ask(stat(11)).sid == 11


def test_packets_for_another_id_are_ignored(neck: Bench) -> None:
    assert neck.send(ram_write(4, "led_control", Led.BLUE)) is None
    assert neck.send(ram_read(4, "led_control")) is None
    assert neck.ram("led_control") == Led.NONE


@pytest.mark.parametrize(
    ("policy", "read", "write"),
    [
        (AckPolicy.STAT_ONLY, False, False),
        (AckPolicy.READS, True, False),
        (AckPolicy.ALL, True, True),
    ],
)
def test_ack_policy(neck: Bench, policy: AckPolicy, read: bool, write: bool) -> None:
    neck.send(ram_write(NECK, "ack_policy", policy))
    assert (neck.send(ram_read(NECK, "led_control")) is not None) is read
    assert (neck.send(ram_write(NECK, "led_control", 1)) is not None) is write
    assert (neck.send(i_jog(JogTarget(NECK, 300))) is not None) is write
    assert neck.status().status_error == StatusError.NONE  # STAT answers under every policy


def test_write_ack_is_the_two_status_bytes(neck: Bench) -> None:
    neck.send(ram_write(NECK, "ack_policy", AckPolicy.ALL))
    answer = neck.servo.handle(ram_write(NECK, "torque_control", TorqueControl.ON), 0.0)
    assert answer == Packet(NECK, Command.RAM_WRITE | 0x40, bytes((0x00, 0x42)))


def test_stat_to_broadcast_is_answered_with_the_servos_id(neck: Bench) -> None:
    assert neck.ask(stat(BROADCAST_ID)).sid == NECK


def test_broadcast_write_acts_but_is_not_answered(neck: Bench) -> None:
    neck.send(ram_write(NECK, "ack_policy", AckPolicy.ALL))
    assert neck.send(ram_write(BROADCAST_ID, "led_control", Led.BLUE)) is None
    assert neck.ram("led_control") == Led.BLUE


def test_tick_counts_11_2_ms_and_wraps(neck: Bench) -> None:
    assert neck.ram("tick", at_s=1.12) == 100
    assert neck.ram("tick", at_s=256 * 0.0112 + 0.001) == 0


def test_time_cannot_go_backwards() -> None:
    servo = SimServo(NECK, now_s=5.0)
    with pytest.raises(InvalidArgumentError, match="backwards"):
        servo.advance(4.0)


def test_constructor_checks_its_arguments() -> None:
    with pytest.raises(OutOfRangeError):
        SimServo(BROADCAST_ID)
    with pytest.raises(OutOfRangeError):
        SimServo(NECK, pos_raw=1024)


# -- faults in packets --------------------------------------------------------------


def test_read_only_write_is_flagged_and_changes_nothing(neck: Bench) -> None:
    neck.send(ram_write(NECK, "ack_policy", AckPolicy.ALL))
    # The builders refuse this, so it is made with the raw protocol helper.
    ack = neck.ask(write_request(NECK, RAM["absolute_position"].addr, b"\x00\x02"))
    assert ack.status_error == StatusError.INVALID_PACKET
    assert ack.status_detail & StatusDetail.EXCEED_REG_RANGE
    assert neck.ram("absolute_position") == 280
    # The flags stay until cleared.
    assert neck.status().status_detail & StatusDetail.EXCEED_REG_RANGE
    neck.send(clear_status(NECK))
    assert neck.status().status_error == StatusError.NONE


def test_read_only_eep_write_is_flagged(neck: Bench) -> None:
    neck.send(write_request(NECK, EEP["model_no1"].addr, b"\x02", Memory.EEP))
    assert neck.eep("model_no1") == Model.DRS_0101
    assert neck.status().status_detail & StatusDetail.EXCEED_REG_RANGE


def test_read_past_the_map_is_flagged_and_unanswered(neck: Bench) -> None:
    assert neck.send(Packet(NECK, Command.RAM_READ, bytes((RAM.size - 1, 2)))) is None
    status = neck.status()
    assert status.status_error == StatusError.INVALID_PACKET
    assert status.status_detail == StatusDetail.EXCEED_REG_RANGE


def test_bad_checksum_is_flagged_only_by_the_addressed_servo(neck: Bench) -> None:
    for sid, flagged in ((4, False), (NECK, True)):
        wire = bytearray(encode_packet(ram_write(sid, "led_control", Led.RED)))
        wire[-1] ^= 0x02  # breaks the checksum, keeps the header plausible
        assert neck.send(bytes(wire)) is None
        detail = neck.status().status_detail
        assert bool(detail & StatusDetail.CHECKSUM_ERROR) is flagged
    assert neck.ram("led_control") == Led.NONE


def test_unknown_command_is_flagged(neck: Bench) -> None:
    # The line's decoder rejects the unknown code and tells the servo.
    wire = bytes((0xFF, 0xFF, 0x07, NECK, 0x0A, 0x0A, 0xF4))
    assert neck.send(wire) is None
    status = neck.status()
    assert status.status_error == StatusError.INVALID_PACKET
    assert status.status_detail == StatusDetail.UNKNOWN_COMMAND
    # A line that lets the code through reaches the same verdict in the servo.
    other = Bench(SimServo(NECK))
    assert other.servo.handle(Packet(NECK, 0x0A), 0.0) is None
    assert other.status().status_detail == StatusDetail.UNKNOWN_COMMAND


def test_malformed_jog_is_garbage(neck: Bench) -> None:
    assert neck.send(Packet(NECK, Command.I_JOG, b"\x00\x02\x00")) is None
    assert neck.status().status_detail == StatusDetail.GARBAGE_DETECTED


# -- motion ---------------------------------------------------------------------------


def test_neck_move_280_to_650_over_the_playtime(neck: Bench) -> None:
    neck.torque_on()
    start_s = 0.5
    playtime_ticks = playtime_ticks_from_s(1.5)
    playtime_s = playtime_ticks * 0.0112
    neck.send(i_jog(JogTarget(NECK, 650, led=Led.GREEN, playtime_ticks=playtime_ticks)), start_s)
    positions: list[int] = []
    t = start_s
    while t < start_s + playtime_s - 0.1:
        reply = neck.ask(ram_read(NECK, "status_error", through="calibrated_position"), t)
        pos = reply.value("calibrated_position")
        assert reply.status_detail & StatusDetail.MOVING, t
        # In position only within the margin (3 counts by default) of the goal.
        assert bool(reply.status_detail & StatusDetail.INPOSITION) is (650 - pos <= 3), t
        positions.append(pos)
        t += 0.02
    assert positions == sorted(positions)
    assert positions[0] == 280
    assert positions[-1] < 650  # not there before the playtime is over
    end = neck.ask(
        ram_read(NECK, "status_error", through="calibrated_position"), start_s + playtime_s
    )
    assert end.value("calibrated_position") == 650
    assert end.status_detail == StatusDetail.INPOSITION | StatusDetail.MOTOR_ON
    assert end.value("led_control") == Led.GREEN
    assert neck.ram("absolute_goal_position") == 650


def test_in_position_margin(neck: Bench) -> None:
    neck.torque_on()
    neck.send(ram_write(NECK, "inposition_margin", 50))
    neck.send(i_jog(JogTarget(NECK, 650, playtime_ticks=100)), 0.0)
    t = 0.0
    while (pos := neck.ram("calibrated_position", at_s=t)) < 600:
        assert not neck.status().status_detail & StatusDetail.INPOSITION
        t += 0.01
    # Within 50 counts of the goal but still on the way: both bits.
    assert pos < 650
    detail = neck.status().status_detail
    assert detail & StatusDetail.INPOSITION
    assert detail & StatusDetail.MOVING


def test_trajectory_is_trapezoidal(neck: Bench) -> None:
    neck.torque_on()
    neck.send(ram_write(NECK, "acceleration_ratio", 25))
    neck.send(i_jog(JogTarget(NECK, 650, playtime_ticks=200)), 0.0)
    playtime_s = 200 * 0.0112
    mean_speed = (650 - 280) / playtime_s * 0.325 / 29.09  # in RAM 62 units

    def speed_at(fraction: float) -> int:
        return neck.ram("differential_position", at_s=fraction * playtime_s)

    accel, cruise = speed_at(0.1), speed_at(0.5)
    assert neck.ram("desired_velocity") == cruise
    decel = speed_at(0.9)
    assert accel < cruise
    assert decel < cruise
    # Peak speed = distance / (playtime × (1 - ratio)): 4/3 of the mean for 25 %.
    assert cruise == round(mean_speed * 4 / 3)


def test_goal_is_clamped_to_min_and_max_position(neck: Bench) -> None:
    neck.torque_on()
    neck.send(ram_write_many(NECK, {"min_position": 280, "max_position": 650}))
    neck.send(i_jog(JogTarget(NECK, 900, playtime_ticks=50)), 0.0)
    assert neck.ram("calibrated_position", at_s=2.0) == 650
    neck.send(i_jog(JogTarget(NECK, 10, playtime_ticks=50)), 2.0)
    assert neck.ram("calibrated_position", at_s=4.0) == 280


def test_playtime_zero_moves_at_motor_speed(neck: Bench) -> None:
    neck.torque_on()
    neck.send(i_jog(JogTarget(NECK, 650)), 0.0)
    # DRS-0101: 0.166 s / 60°; 370 counts = 120 deg, so about a third of a second.
    assert neck.ram("calibrated_position", at_s=0.2) < 650
    assert neck.ram("calibrated_position", at_s=0.6) == 650


def test_stop_holds_where_the_servo_is(neck: Bench) -> None:
    neck.torque_on()
    neck.send(i_jog(JogTarget(NECK, 650, playtime_ticks=200)), 0.0)
    neck.send(i_jog(JogTarget(NECK, 650, stop=True)), 1.0)
    held = neck.ram("calibrated_position", at_s=1.0)
    assert 280 < held < 650
    assert neck.ram("calibrated_position", at_s=5.0) == held
    assert neck.status().status_detail & StatusDetail.INPOSITION


def test_turn_mode_spins_and_reports_speed(neck: Bench) -> None:
    neck.torque_on()
    neck.send(i_jog(JogTarget(NECK, 1023, mode=JogMode.TURN)), 0.0)
    assert neck.ram("current_control_mode") == JogMode.TURN
    expected_diff = round((60 / 0.166) / 29.09)
    assert neck.ram("differential_position", at_s=0.1) == expected_diff
    assert neck.ram("pwm") == 1023
    assert neck.status().status_detail & StatusDetail.MOVING
    neck.send(i_jog(JogTarget(NECK, 0, mode=JogMode.TURN, stop=True)), 0.2)
    assert neck.ram("differential_position", at_s=0.3) == 0


def test_turn_mode_needs_torque_off_first(neck: Bench) -> None:
    neck.torque_on()
    neck.send(i_jog(JogTarget(NECK, 500, playtime_ticks=10)), 0.0)
    neck.send(i_jog(JogTarget(NECK, 300, mode=JogMode.TURN)), 0.5)  # ignored
    assert neck.ram("current_control_mode", at_s=0.6) == JogMode.POSITION
    assert neck.ram("calibrated_position") == 500
    # Torque off first: then the turn JOG is obeyed, even sent after torque is on again.
    neck.send(ram_write(NECK, "torque_control", TorqueControl.FREE))
    neck.torque_on()
    neck.send(i_jog(JogTarget(NECK, 300, mode=JogMode.TURN)), 0.6)
    assert neck.ram("current_control_mode") == JogMode.TURN
    assert neck.ram("differential_position", at_s=0.7) > 0


@pytest.mark.parametrize("torque", [TorqueControl.BRAKE, TorqueControl.FREE])
def test_jogs_are_ignored_without_torque_on(neck: Bench, torque: TorqueControl) -> None:
    neck.send(ram_write(NECK, "torque_control", torque))
    neck.send(i_jog(JogTarget(NECK, 650, led=Led.RED, playtime_ticks=20)), 0.0)
    assert neck.ram("calibrated_position", at_s=1.0) == 280
    assert neck.ram("led_control") == Led.NONE
    assert neck.status().status_detail == StatusDetail.NONE


def test_brake_during_a_move_stops_it(neck: Bench) -> None:
    neck.torque_on()
    neck.send(i_jog(JogTarget(NECK, 650, playtime_ticks=200)), 0.0)
    neck.send(ram_write(NECK, "torque_control", TorqueControl.BRAKE), 1.0)
    held = neck.ram("calibrated_position")
    assert neck.ram("calibrated_position", at_s=3.0) == held < 650
    assert not neck.status().status_detail & StatusDetail.MOVING


def test_broadcast_jog_moves_the_servos_named_in_its_tags() -> None:
    servos = {sid: SimServo(sid, pos_raw=512) for sid in (NECK, 11, 12)}
    for sid, servo in servos.items():
        servo.handle(ram_write(sid, "ack_policy", AckPolicy.ALL), 0.0)
        servo.handle(ram_write(sid, "torque_control", TorqueControl.ON), 0.0)
    jog = s_jog(20, JogTarget(NECK, 600), JogTarget(11, 400))
    assert jog.sid == BROADCAST_ID
    assert all(servo.handle(jog, 0.0) is None for servo in servos.values())
    positions = {}
    for sid, servo in servos.items():
        reply = servo.handle(ram_read(sid, "calibrated_position"), 1.0)
        assert reply is not None
        positions[sid] = parse_reply(reply).value("calibrated_position")
    assert positions == {NECK: 600, 11: 400, 12: 512}


def test_jog_tag_for_another_servo_in_a_packet_to_this_one_is_ignored(neck: Bench) -> None:
    neck.torque_on()
    # Addressed to the neck but naming servo 4: only servo 4 may act on its tag.
    neck.send(Packet(NECK, Command.I_JOG, i_jog(JogTarget(4, 650, playtime_ticks=10)).data), 0.0)
    assert neck.ram("calibrated_position", at_s=1.0) == 280


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 1023), st.integers(0, 254), st.floats(0.0, 3.0)),
        min_size=1,
        max_size=6,
    ),
)
def test_any_jog_sequence_stays_within_limits_and_settles(
    jogs: list[tuple[int, int, float]],
) -> None:
    bench = Bench(SimServo(NECK, pos_raw=280))
    bench.torque_on()
    bench.send(ram_write_many(NECK, {"min_position": 280, "max_position": 650}))
    t = 0.0
    goal = 280
    for pos_raw, ticks, wait_s in jogs:
        bench.send(i_jog(JogTarget(NECK, pos_raw, playtime_ticks=ticks)), t)
        goal = min(650, max(280, pos_raw))
        t += wait_s
        assert 280 <= bench.ram("calibrated_position", at_s=t) <= 650
    assert bench.ram("calibrated_position", at_s=t + 3.0) == goal
    assert bench.status().status_detail == StatusDetail.INPOSITION | StatusDetail.MOTOR_ON


# -- temperature, voltage and the torque policy ----------------------------------------


def test_temperature_rises_under_load_and_falls_when_free(neck: Bench) -> None:
    neck.torque_on()
    neck.servo.set_load(0.5)
    temps = [neck.ram("temperature", at_s=t) for t in range(0, 300, 30)]
    assert temps == sorted(temps)
    assert temps[-1] > temps[0]
    assert neck.ram("pwm") == round(0.5 * 1023)
    neck.send(ram_write(NECK, "torque_control", TorqueControl.FREE))
    cooling = [neck.ram("temperature", at_s=t) for t in range(300, 600, 30)]
    assert cooling == sorted(cooling, reverse=True)
    assert cooling[-1] < temps[-1]
    assert neck.ram("pwm") == 0


def test_no_load_no_heat(neck: Bench) -> None:
    neck.torque_on()
    before = neck.ram("temperature")
    assert neck.ram("temperature", at_s=3600.0) == before


def test_over_temperature_releases_torque_latches_and_recovers(neck: Bench) -> None:
    neck.torque_on()
    neck.send(i_jog(JogTarget(NECK, 500, playtime_ticks=50)), 0.0)
    neck.servo.set_load(1.0)
    limit = neck.ram("max_temperature")
    t = 1.0
    while not (status := neck.status(t)).status_error & StatusError.TEMPERATURE:
        assert status.status_detail & StatusDetail.MOTOR_ON
        t += 5.0
        assert t < 1000, "never overheated"
    # Released by the default torque policy (0x35 includes TEMPERATURE).
    assert status.status_detail == StatusDetail.NONE
    assert neck.ram("torque_control") == TorqueControl.FREE
    # Sampled within 5 s of the crossing, it has only just started to cool.
    assert limit - 5 <= neck.ram("temperature") < limit
    # Latched: torque cannot come back, and jogs do nothing.
    neck.torque_on()
    assert neck.ram("torque_control") == TorqueControl.FREE
    neck.send(i_jog(JogTarget(NECK, 600, playtime_ticks=10)), t + 1)
    assert neck.ram("calibrated_position", at_s=t + 3) == 500
    # Cooled down, cleared, torque on again: it works.
    t += 120.0
    assert neck.ram("temperature", at_s=t) < limit
    assert neck.status().status_error & StatusError.TEMPERATURE  # still latched
    neck.send(clear_status(NECK))
    assert neck.status().status_error == StatusError.NONE
    neck.servo.set_load(0.0)
    neck.torque_on()
    assert neck.ram("torque_control") == TorqueControl.ON
    neck.send(i_jog(JogTarget(NECK, 600, playtime_ticks=10)), t)
    assert neck.ram("calibrated_position", at_s=t + 1) == 600


def test_clearing_while_still_hot_does_not_clear(neck: Bench) -> None:
    # A torque policy without TEMPERATURE keeps holding, so the servo stays hot.
    neck.send(ram_write(NECK, "torque_policy", 0x31))
    neck.torque_on()
    neck.servo.set_load(1.0)
    assert neck.status(600.0).status_error == StatusError.TEMPERATURE
    assert neck.ram("torque_control") == TorqueControl.ON
    neck.send(clear_status(NECK))
    assert neck.status().status_error == StatusError.TEMPERATURE


def test_over_temperature_is_found_inside_one_long_advance(neck: Bench) -> None:
    # One read an hour later: the release happened when the limit was crossed, so the
    # servo has been cooling since, not heating for the whole hour.
    neck.torque_on()
    neck.servo.set_load(1.0)
    status = neck.status(3600.0)
    assert status.status_error == StatusError.TEMPERATURE
    assert neck.ram("temperature") < neck.ram("max_temperature") - 20


def test_low_supply_voltage_releases_torque(neck: Bench) -> None:
    neck.torque_on()
    assert neck.ram("voltage") == 100  # 7.4 V
    neck.servo.set_supply_voltage(6.0)
    assert neck.status().status_error == StatusError.INPUT_VOLTAGE
    assert neck.ram("torque_control") == TorqueControl.FREE


def test_set_load_checks_its_argument(neck: Bench) -> None:
    with pytest.raises(OutOfRangeError):
        neck.servo.set_load(1.5)
    with pytest.raises(InvalidArgumentError, match="finite"):
        neck.servo.set_load(float("nan"))


# -- reboot, rollback, power cycle ----------------------------------------------------


def test_reboot_restores_eep_values_to_ram(neck: Bench) -> None:
    neck.send(ram_write(NECK, "max_position", 700))
    neck.send(eep_write(NECK, "min_position", 300))
    neck.send(ram_write(NECK, "led_control", Led.BLUE))
    neck.torque_on()
    neck.send(reboot(NECK), 1.0)
    neck.now_s = 1.0 + RESTART_S  # it answers again once restarted
    assert neck.ram("max_position") == 1002
    assert neck.ram("min_position") == 300
    assert neck.ram("led_control") == Led.NONE
    assert neck.ram("torque_control") == TorqueControl.FREE
    assert neck.ram("tick") == 0


def test_reboot_ack_under_policy_2_then_policy_from_eep(neck: Bench) -> None:
    neck.send(ram_write(NECK, "ack_policy", AckPolicy.ALL))
    assert neck.send(reboot(NECK), 1.0) is not None
    # RAM 1 came back from EEP 7 (policy 1): writes are silent again, reads are not.
    assert neck.send(ram_write(NECK, "led_control", 1), 1.0 + RESTART_S) is None
    assert neck.ram("led_control") == 1


def test_rollback_restores_factory_eep(neck: Bench) -> None:
    neck.send(eep_write(NECK, "position_kp", 100))
    neck.send(eep_write(NECK, "baud_rate", 0x22))
    neck.send(rollback(NECK, keep_id=True, keep_baud=True), 1.0)
    neck.now_s = 1.0 + RESTART_S
    assert neck.eep("position_kp") == 440
    assert neck.eep("baud_rate") == 0x22
    assert neck.servo.sid == NECK
    neck.send(rollback(NECK, keep_id=False, keep_baud=False), 2.0)
    assert neck.servo.sid == 0xFD
    neck.now_s = 2.0 + RESTART_S
    assert neck.eep("baud_rate") == 0x10


def test_power_cycle_clears_faults_and_reloads_eep(neck: Bench) -> None:
    neck.send(ram_write(NECK, "max_position", 700))
    neck.send(Packet(NECK, Command.RAM_READ, bytes((200, 1))))
    assert neck.status().status_error == StatusError.INVALID_PACKET
    neck.power_cycle(2.0)
    assert neck.status().status_error == StatusError.NONE
    assert neck.ram("max_position") == 1002
    assert neck.ram("calibrated_position") == 280  # the horn did not move


def test_a_lower_max_pwm_makes_the_fastest_move_slower(neck: Bench) -> None:
    # 280 → 650 at playtime 0 (as fast as it can): at full PWM the no-load speed sets the
    # time; at max PWM 511 (half the drive) it takes about twice as long.
    neck.torque_on()
    neck.send(i_jog(JogTarget(NECK, 650, playtime_ticks=0)), 0.0)
    full_s = next(t / 100 for t in range(1, 300) if neck.ram("calibrated_position", t / 100) == 650)
    neck.send(ram_write(NECK, "max_pwm", 511))
    neck.send(i_jog(JogTarget(NECK, 280, playtime_ticks=0)), 4.0)
    half_s = next(
        t / 100 - 4.0 for t in range(401, 900) if neck.ram("calibrated_position", t / 100) == 280
    )
    assert half_s == pytest.approx(2 * full_s, rel=0.1)
    # No drive at all: a move does not start.
    neck.send(ram_write(NECK, "max_pwm", 0))
    neck.send(i_jog(JogTarget(NECK, 650, playtime_ticks=0)), 10.0)
    assert neck.ram("calibrated_position", 12.0) == 280
