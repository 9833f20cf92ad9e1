"""``ohmni neck`` against the simulator: the moves checked against its ground truth, the
refusals, the JSON schema, and a neck that stays where it was sent between commands."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest

from ohmni_tb.cli import neck as neck_cli
from ohmni_tb.herkulex import TorqueControl, parse_reply, ram_read, ram_write
from ohmni_tb.protocol import Command, Packet
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import SimServo
from ohmni_tb.sim.worm_neck import SimWormNeck

from ._helpers import Opened, invoke, needs_pty, sim_on_pty, spy_on_ports, words

SIM = ["--port", "sim://"]
WORM = ["--port", "sim://?neck=worm"]
#: How close the read-back and the truth must be to the target (the command's own rule).
TOLERANCE_RAW = 5
WORM_TOLERANCE_RAW = 1000
#: The documented JSON object: every key, none more.
KEYS = {
    "neck",
    "sid",
    "action",
    "target_raw",
    "target_deg",
    "playtime_s",
    "position_raw",
    "position_deg",
    "torque",
    "moving",
    "stalled",
    "elapsed_s",
    "range_raw",
    "positions_raw",
    "notes",
}


@pytest.fixture
def opened(monkeypatch: pytest.MonkeyPatch) -> Opened:
    return spy_on_ports(monkeypatch)


def herkulex(opened: Opened) -> SimServo:
    """The simulated HerkuleX neck of the last command."""
    assert opened.sims
    neck = opened.sims[-1].neck
    assert isinstance(neck, SimServo)
    return neck


def worm(opened: Opened) -> SimWormNeck:
    """The simulated worm-gear neck of the last command."""
    assert opened.sims
    neck = opened.sims[-1].neck
    assert isinstance(neck, SimWormNeck)
    return neck


def register(sim: SimRobot, servo: SimServo, name: str) -> int:
    """A register's true value now, asked of the simulated servo, not over the wire."""
    reply = servo.handle(ram_read(servo.sid, name), sim.sync())
    assert reply is not None
    return int(parse_reply(reply).value(name))


def truth(opened: Opened) -> tuple[int, TorqueControl]:
    """The last command's simulated HerkuleX neck: its true position and torque now."""
    sim, neck = opened.sims[-1], herkulex(opened)
    return register(sim, neck, "calibrated_position"), TorqueControl(
        register(sim, neck, "torque_control")
    )


def run_json(*args: str) -> dict[str, Any]:
    result = invoke("neck", *args, "--json")
    assert result.code == 0, result.out
    data: dict[str, Any] = json.loads(result.stdout)
    return data


# -- the HerkuleX neck ------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize(("name", "target"), [("up", 650), ("down", 280), ("center", 465)])
def test_named_positions_move_the_herkulex_neck_there_and_it_stays(
    opened: Opened, name: str, target: int
) -> None:
    data = run_json(name, *SIM, "--playtime", "0.3")
    assert data["neck"] == "herkulex"
    assert data["sid"] == 3
    assert data["action"] == name
    assert data["target_raw"] == target
    assert data["target_deg"] == pytest.approx((target - 512) * 0.325, abs=0.01)
    assert data["positions_raw"] == {"up": 650, "down": 280, "center": 465}
    # The read-back the user sees and the simulator's truth agree, at the target.
    assert abs(data["position_raw"] - target) <= TOLERANCE_RAW
    assert data["position_deg"] == pytest.approx((data["position_raw"] - 512) * 0.325, abs=0.01)
    position, torque = truth(opened)
    assert abs(position - target) <= TOLERANCE_RAW
    assert abs(position - data["position_raw"]) <= TOLERANCE_RAW
    # The Robot closed with on_exit_neck=keep: the neck still holds there, torque on.
    assert torque is TorqueControl.ON
    assert data["torque"] == "on"


@pytest.mark.usefixtures("virtual_time")
def test_up_prints_the_target_and_the_read_back(opened: Opened) -> None:
    result = invoke("neck", "up", *SIM, "--playtime", "0.2")
    assert result.code == 0, result.out
    text = words(result.out)
    assert "neck: HerkuleX (sid 3), up → 650 raw (+44.85°) over 0.2016 s" in text
    assert "read back: 650 raw (+44.85°), torque on" in text
    assert truth(opened) == (650, TorqueControl.ON)


@pytest.mark.usefixtures("virtual_time")
def test_raw_and_deg_targets(opened: Opened) -> None:
    data = run_json("--raw", "0x190", *SIM, "--playtime", "0.2")  # 400
    assert (data["action"], data["target_raw"]) == ("raw", 400)
    assert data["playtime_s"] == pytest.approx(0.2016)  # 18 ticks of 11.2 ms
    assert abs(truth(opened)[0] - 400) <= TOLERANCE_RAW
    # -10° is 30.8 counts below the level head (512): raw 481.
    data = run_json("--deg", "-10", *SIM, "--playtime", "0.2")
    assert (data["action"], data["target_raw"]) == ("deg", 481)
    assert data["target_deg"] == pytest.approx(-10.08, abs=0.01)
    assert abs(data["position_deg"] - -10) <= TOLERANCE_RAW * 0.325
    assert abs(truth(opened)[0] - 481) <= TOLERANCE_RAW


@pytest.mark.usefixtures("virtual_time")
def test_the_longest_playtime_is_taken_as_the_servo_command_takes_it(opened: Opened) -> None:
    # 254 ticks of 11.2 ms: the longest playtime, as neck.move() and `ohmni servo move`.
    data = run_json("--raw", "400", *SIM, "--playtime", "2.8448")
    assert data["playtime_s"] == 2.8448
    assert abs(truth(opened)[0] - 400) <= TOLERANCE_RAW
    # 2.84 s goes to the nearest tick, 254: the same seconds are printed.
    data = run_json("--raw", "600", *SIM, "--playtime", "2.84")
    assert data["playtime_s"] == 2.8448
    result = invoke("neck", "--raw", "400", *SIM, "--playtime", "2.85")
    assert result.code == 2
    assert "--playtime=2.85 is out of range: allowed 0..2.8448 s" in words(result.out)


@pytest.mark.usefixtures("virtual_time")
def test_rest_moves_to_the_rest_position_then_frees(opened: Opened) -> None:
    data = run_json("rest", *SIM)
    assert data["action"] == "rest"
    assert data["target_raw"] == 465
    assert (data["position_raw"], data["torque"]) == (465, "free")
    assert truth(opened) == (465, TorqueControl.FREE)


@pytest.mark.usefixtures("virtual_time")
def test_free_releases_the_torque(monkeypatch: pytest.MonkeyPatch) -> None:
    def holding(sim: SimRobot) -> None:
        neck = sim.neck
        assert isinstance(neck, SimServo)
        neck.handle(ram_write(3, "torque_control", TorqueControl.ON), sim.sync())

    opened = spy_on_ports(monkeypatch, setup=holding)
    result = invoke("neck", "free", *SIM)
    assert result.code == 0, result.out
    assert "torque free" in result.out
    assert truth(opened) == (512, TorqueControl.FREE)


@pytest.mark.usefixtures("virtual_time")
def test_no_target_prints_where_the_neck_is_and_moves_nothing(opened: Opened) -> None:
    data = run_json(*SIM)
    assert set(data) == KEYS
    assert data["action"] == "read"
    assert (data["position_raw"], data["position_deg"], data["torque"]) == (512, 0.0, "free")
    assert data["target_raw"] is None
    assert data["range_raw"] == [280, 650]
    assert truth(opened) == (512, TorqueControl.FREE)


@pytest.mark.usefixtures("virtual_time")
def test_the_json_schema(opened: Opened) -> None:
    data = run_json("down", *SIM, "--playtime", "0")
    assert set(data) == KEYS
    assert isinstance(data["target_raw"], int)
    assert isinstance(data["position_raw"], int)
    for key in ("target_deg", "playtime_s", "position_deg", "elapsed_s"):
        assert isinstance(data[key], float | int), key
    assert data["moving"] is False
    assert data["stalled"] is None  # a worm-gear flag
    assert data["notes"] == []


# -- the worm-gear neck ------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_the_worm_gear_neck_goes_up_and_to_its_center(opened: Opened) -> None:
    data = run_json("up", *WORM)
    assert (data["neck"], data["sid"], data["target_raw"]) == ("worm", 4, -127_000)
    assert data["positions_raw"] == {"up": -127_000, "down": 120_000, "center": -3500}
    assert abs(data["position_raw"] - -127_000) <= WORM_TOLERANCE_RAW
    assert (data["moving"], data["stalled"]) == (False, False)
    assert data["position_deg"] is None  # no angle is known for the worm gear
    neck = worm(opened)
    opened.sims[-1].sync()
    assert abs(neck.feedback().position - -127_000) <= WORM_TOLERANCE_RAW
    assert neck.target == -127_000

    result = invoke("neck", "center", *WORM, "--playtime", "2")
    assert result.code == 0, result.out
    assert "center → -3500 raw" in result.out
    assert "--playtime ignored" in words(result.out)
    neck = worm(opened)
    opened.sims[-1].sync()
    assert abs(neck.feedback().position - -3500) <= WORM_TOLERANCE_RAW


@pytest.mark.usefixtures("virtual_time")
def test_the_worm_gear_neck_refuses_what_only_a_herkulex_takes(opened: Opened) -> None:
    result = invoke("neck", "--deg", "10", *WORM)
    assert result.code == 1, result.out
    assert result.out.startswith("error: --deg is for the HerkuleX neck")
    assert "nothing was sent to the neck" in words(result.out)
    assert worm(opened).target == 0
    data = run_json("rest", *WORM)
    assert "nothing to rest" in data["notes"][0]
    assert data["position_raw"] == 0


# -- refusals ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--raw", "200000"],
            "--raw=200000 is out of range: allowed 280..650 (HerkuleX neck) or "
            "-127000..120000 (worm-gear neck)",
        ),
        (["--raw=-127001"], "--raw=-127001 is out of range: allowed 280..650"),
        (["--raw", "4OO"], "--raw must be an integer (decimal or 0x..), not '4OO'"),
        (["--deg", "90"], "--deg=90.0 is out of range: allowed -75.40..+44.85° (raw 280..650)"),
        (["--deg", "nan"], "--deg=nan is not a finite number"),
        (["up", "--playtime", "inf"], "--playtime=inf is out of range: allowed 0..2.8448 s"),
        (["up", "--playtime", "3"], "--playtime=3.0 is out of range: allowed 0..2.8448 s"),
        (["rest", "--playtime", "1"], "--playtime is for moves"),
        (["up", "--raw", "400"], "give one target, not 2: POSITION 'up', --raw=400"),
        (["--raw", "400", "--deg", "1"], "give one target, not 2"),
        (["sideways"], "POSITION must be up, down, center, rest or free, not 'sideways'"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_bad_targets_are_refused_before_the_port_opens(
    opened: Opened, args: list[str], message: str
) -> None:
    result = invoke("neck", *args, *SIM)
    assert result.code == 2, result.out
    assert message in words(result.out)
    assert opened.urls == []


@pytest.mark.usefixtures("virtual_time")
def test_a_target_outside_the_answering_necks_range_is_refused_with_nothing_sent(
    opened: Opened,
) -> None:
    # 700 is a worm-gear position, so only the neck that answers can refuse it: exit 1.
    result = invoke("neck", "--raw", "700", *SIM)
    assert result.code == 1, result.out
    assert result.out.strip().splitlines() == [
        "error: --raw=700 is out of range for the HerkuleX neck (sid 3): allowed 280..650; "
        "nothing was sent to the neck"
    ]
    assert truth(opened) == (512, TorqueControl.FREE)  # a move would have turned torque on


@pytest.mark.usefixtures("virtual_time")
def test_a_real_port_asks_first(opened: Opened) -> None:
    result = invoke("neck", "up", "--port", "/dev/no-such-ohmni")
    assert result.code == 1, result.out
    assert "pass --yes" in words(result.out)
    assert opened.urls == []


# -- between commands: ohmni sim --pty ---------------------------------------------------------


@needs_pty
def test_the_neck_stays_where_it_was_sent_between_commands() -> None:
    with sim_on_pty() as (path, _):
        port = ["--port", path]
        result = invoke("neck", "up", *port, "--playtime", "0.3", "--json")
        assert result.code == 1  # a real port: no --yes, no motion
        assert "pass --yes" in words(result.out)
        sent = invoke("neck", "up", *port, "--playtime", "0.3", "--json", "--yes")
        assert sent.code == 0, sent.out
        assert abs(json.loads(sent.stdout)["position_raw"] - 650) <= TOLERANCE_RAW
        # Other commands (other Robots) find it still there, holding: neither the first
        # command's exit nor their opening rested or freed it, nor a second of streaming.
        streamed = invoke("odom", *port, "--duration", "1", "--json")
        assert streamed.code == 0, streamed.out
        again = invoke("neck", *port, "--json")
        assert again.code == 0, again.out
        seen = json.loads(again.stdout)
        assert abs(seen["position_raw"] - 650) <= TOLERANCE_RAW
        assert seen["torque"] == "on"
        # And the raw servo read, without the Robot, says the same.
        stat = invoke("servo", "read", "torque_control", *port, "--json")
        assert json.loads(stat.stdout)["value"] == TorqueControl.ON
        position = invoke("servo", "read", "calibrated_position", *port, "--json")
        assert abs(json.loads(position.stdout)["value"] - 650) <= TOLERANCE_RAW
        rest = invoke("neck", "rest", *port, "--yes", "--json")
        assert rest.code == 0, rest.out
        assert json.loads(rest.stdout)["torque"] == "free"


def _silence_neck_after_the_move(monkeypatch: pytest.MonkeyPatch, sid: int, after_s: float) -> None:
    """The simulated neck stops answering ``after_s`` after its move command arrives."""
    opened: Opened

    def setup(sim: SimRobot) -> None:
        neck = sim.neck
        real = neck.handle

        def handle(packet: Packet, now_s: float) -> Packet | None:
            moves = packet.cmd in (Command.S_JOG, Command.I_JOG) or (
                sid == 4 and packet.cmd == Command.RAM_WRITE
            )
            if packet.sid == sid and moves:
                faults = opened.transports[-1].line.faults  # type: ignore[attr-defined]
                asyncio.get_running_loop().call_later(after_s, faults.silent.add, sid)
            return real(packet, now_s)

        monkeypatch.setattr(neck, "handle", handle)

    opened = spy_on_ports(monkeypatch, setup=setup)


@pytest.mark.usefixtures("virtual_time")
def test_a_herkulex_neck_silent_after_the_move_says_how_long_it_waited(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _silence_neck_after_the_move(monkeypatch, 3, 0.0)
    result = invoke("neck", "--raw", "300", "--playtime", "0.2", *SIM)
    assert result.code == 1, result.out
    # It waited the playtime + 1.5 s (not the 1 s a single sample may take).
    assert result.out.strip() == (
        "error: no servo_neck sample came within 1.7 s: is the neck still answering?"
    )


@pytest.mark.usefixtures("virtual_time")
def test_a_worm_neck_silent_mid_move_is_not_reported_as_still_moving_now(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(neck_cli, "WORM_TIMEOUT_S", 2.5)
    _silence_neck_after_the_move(monkeypatch, 4, 0.3)
    result = invoke("neck", "up", *WORM)
    assert result.code == 1, result.out
    text = words(result.out)
    assert text.startswith("error: the worm-gear neck did not reach -127000 within 2.5 s: ")
    # The last sample is over 2 s old: the neck stopped answering, it does not "read back".
    assert "it stopped answering" in text
    assert "it reads back" not in text
