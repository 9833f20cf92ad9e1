"""The daemon's messages: what a client gets back for each bad frame, samples both ways,
and the checked-in schema."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from ohmni_tb import Robot
from ohmni_tb.errors import (
    InvalidArgumentError,
    MotionAbortedError,
    MotionEnd,
    MotionError,
    MotionPreemptedError,
    MotionResult,
    MotionTimeoutError,
    OhmniError,
    OutOfRangeError,
    StateError,
    WheelStallError,
)
from ohmni_tb.robot import STREAM_NAMES
from ohmni_tb.robot import wire as protocol
from ohmni_tb.robot.wire import (
    Call,
    LatestArgs,
    RequestError,
    SampleMessage,
    Subscribe,
    parse_client_message,
    parse_server_message,
    sample_from_json,
    sample_json,
)
from ohmni_tb.sim.clock import run_virtual

SCHEMA = Path(__file__).resolve().parents[2] / "docs" / "daemon-schema.json"


def refused(frame: str | bytes) -> RequestError:
    with pytest.raises(RequestError) as caught:
        parse_client_message(frame)
    return caught.value


def test_a_subscribe_and_a_call_parse() -> None:
    assert parse_client_message(
        '{"op": "subscribe", "id": 1, "topic": "wheel_odom", "max_hz": 5, "queue": 8}'
    ) == Subscribe(id=1, topic="wheel_odom", max_hz=5, queue=8)
    call = parse_client_message(
        '{"op": "call", "id": "a", "method": "latest", "args": {"topic": "tbcore_status"}}'
    )
    assert call == Call(id="a", method="latest", args={"topic": "tbcore_status"})
    assert isinstance(call, Call)
    assert protocol.call_args(call) == LatestArgs(topic="tbcore_status")


def test_a_command_parses_with_its_defaults_filled_by_its_model() -> None:
    call = parse_client_message(
        '{"op": "call", "id": 2, "method": "drive", "args": {"linear_mps": 0.3}}'
    )
    assert isinstance(call, Call)
    assert protocol.call_args(call) == protocol.DriveArgs(linear_mps=0.3, angular_radps=0.0)
    move = parse_client_message(
        '{"op": "call", "id": 3, "method": "move", "args": {"target": 11, "raw": 512}}'
    )
    assert isinstance(move, Call)
    assert protocol.call_args(move) == protocol.MoveArgs(target=11, raw=512)


@pytest.mark.parametrize(
    ("frame", "code", "said"),
    [
        ("{", "bad_json", "not JSON"),
        (b"\xff\xfe", "bad_json", "not JSON"),
        ("[1, 2]", "bad_json", "JSON object, not list"),
        ('{"op": "drive", "id": 1}', "unknown_op", "'drive': allowed subscribe, unsubscribe, call"),
        ('{"op": "subscribe", "id": 1, "topic": "odom"}', "unknown_topic", "'odom': the topics"),
        ('{"op": "call", "id": 1, "method": "fly"}', "unknown_method",
         "'fly': allowed stats, info"),
        ('{"op": "subscribe", "id": 1, "topic": "wheel_odom", "max_hz": 0}', "bad_message",
         "max_hz: Input should be greater than 0 (got 0)"),
        ('{"op": "subscribe", "id": 1, "topic": "wheel_odom", "queue": 5000}', "bad_message",
         "queue: Input should be less than or equal to 1024 (got 5000)"),
        ('{"op": "subscribe", "topic": "wheel_odom"}', "bad_message", "id: Field required"),
        ('{"op": "subscribe", "id": 1, "topic": "wheel_odom", "rate": 3}', "bad_message",
         "rate: Extra inputs are not permitted"),
        ('{"op": "call", "id": 1, "method": "latest"}', "bad_message",
         "bad latest args: topic: Field required"),
        ('{"op": "call", "id": 1, "method": "latest", "args": {"topic": "odom"}}', "unknown_topic",
         "'odom': the topics"),
        ('{"op": "call", "id": 1, "method": "stats", "args": {"x": 1}}', "bad_message",
         "bad stats args: x: Extra inputs are not permitted (got 1)"),
        ('{"op": "call", "id": 1, "method": "drive", "args": {"linear_mps": NaN}}', "bad_message",
         "linear_mps: Input should be a finite number (got NaN)"),
        ('{"op": "call", "id": 1, "method": "drive", "args": {"linear_mps": Infinity}}',
         "bad_message", "linear_mps: Input should be a finite number"),
        ('{"op": "call", "id": 1, "method": "drive", "args": {}}', "bad_message",
         "bad drive args: linear_mps: Field required"),
        ('{"op": "call", "id": 1, "method": "drive_pwm", "args": {"left": "1.5", "right": 0}}',
         "bad_message", "left: Input should be a valid number"),
        ('{"op": "call", "id": 1, "method": "get_pid", "args": {"wheel": "both"}}',
         "bad_message", "wheel: Input should be 'left' or 'right'"),
        ('{"op": "call", "id": 1, "method": "move", "args": {"target": "nek", "raw": 5}}',
         "bad_message", 'target: target must be "neck" or a servo id 0..253, not \'nek\''),
        ('{"op": "call", "id": 1, "method": "move", "args": {"target": 300}}', "bad_message",
         "servo id 0..253, not 300"),
        ('{"op": "call", "id": 1, "method": "torque", "args": {"target": "neck", "mode": "x"}}',
         "bad_message", "mode: Input should be 'on', 'brake' or 'free' (got 'x')"),
        ('{"op": "call", "id": 1, "method": "acquire", "args": {"steal": "yes please"}}',
         "bad_message", "steal: Input should be a valid boolean"),
    ],
)  # fmt: skip
def test_a_bad_frame_says_what_was_wrong_and_what_is_allowed(
    frame: str | bytes, code: str, said: str
) -> None:
    error = refused(frame)
    assert error.code == code
    assert said in error.message
    reply = error.reply()
    assert reply.code == code


def test_the_error_carries_the_request_id_when_one_was_readable() -> None:
    assert refused('{"op": "subscribe", "id": 7, "topic": "odom"}').reply().id == 7
    assert refused('{"op": "nope", "id": "x"}').id == "x"
    assert refused("{").id is None
    assert refused('{"op": "nope", "id": true}').id is None  # a bool is not an id


def test_every_error_code_is_in_the_schema() -> None:
    schema = json.dumps(protocol.json_schema())
    for code in protocol.ERROR_CODES:
        assert f'"{code}"' in schema


def test_the_schema_documents_every_method_its_arguments_and_whether_it_needs_the_lease() -> None:
    methods = protocol.json_schema()["methods"]
    assert set(methods) == set(protocol.METHODS)
    assert methods["drive"]["lease"] is True
    assert methods["drive"]["args"]["required"] == ["linear_mps"]
    # Anyone may stop the robot; reading needs no lease either.
    for name in ("stop", "estop", "stats", "latest", "acquire"):
        assert methods[name]["lease"] is False, name
    assert set(protocol.LEASE_METHODS) >= {"drive", "drive_pwm", "move", "set_pid", "release"}


def test_the_checked_in_schema_matches_the_code() -> None:
    assert SCHEMA.read_text(encoding="utf-8") == protocol.schema_text(), (
        "docs/daemon-schema.json is out of date: regenerate it with "
        "`.venv/bin/python -c 'import ohmni_tb.robot.wire as w; w.write_schema()'`"
    )


def test_every_stream_sample_goes_to_json_and_back_unchanged() -> None:
    async def main() -> None:
        seen: dict[str, object] = {}
        for url, pid_debug in (("sim://", True), ("sim://?neck=worm", False)):
            async with Robot.open(url, pid_debug=pid_debug) as robot:
                for _ in range(20):
                    robot.drive(0.2, 0.3)  # pid_debug publishes while driving
                    await asyncio.sleep(0.05)
                for name in STREAM_NAMES:
                    sample = robot.latest(name)
                    if sample is not None:
                        seen[name] = sample
        assert set(seen) == set(STREAM_NAMES)
        for name, sample in seen.items():
            data = json.loads(json.dumps(sample_json(sample)))  # type: ignore[arg-type]  # Sample
            assert sample_from_json(name, data) == sample, name

    run_virtual(main())


def test_the_servers_sample_frame_is_a_valid_sample_message() -> None:
    data = {
        "stamp_s": 1.0,
        "link": "connected",
        "estopped": False,
        "watchdog_tripped": False,
        "faults": [],
        "neck": "herkulex",
        "present": [0, 1],
        "absent": [],
        "event": None,
    }
    frame = '{"op":"sample","topic":"robot_state","dropped":3,"data":' + json.dumps(data) + "}"
    message = parse_server_message(frame)
    assert isinstance(message, SampleMessage)
    assert message.dropped == 3
    state = sample_from_json(message.topic, message.data)
    assert state.link.value == "connected"  # type: ignore[union-attr]  # a RobotStateSample


def _motion_result(reason: MotionEnd) -> MotionResult:
    return MotionResult(
        kind="drive_distance",
        reason=reason,
        distance_m=0.25,
        heading_change_rad=0.01,
        x_m=0.25,
        y_m=0.0,
        yaw_rad=0.01,
        remaining_m=0.25,
        remaining_rad=0.0,
        elapsed_s=1.5,
    )


@pytest.mark.parametrize(
    "error",
    [
        MotionPreemptedError("preempted by stop", result=_motion_result("preempted"), by="stop"),
        MotionTimeoutError("not there in 3 s", result=_motion_result("timeout"), timeout_s=3.0),
        WheelStallError(
            "the left wheel stalled", result=_motion_result("stalled"), wheels=("left",)
        ),
        MotionAbortedError("the watchdog tripped", result=_motion_result("watchdog")),
    ],
)
def test_a_goals_error_goes_to_json_and_back_as_the_same_error(error: MotionError) -> None:
    data = json.loads(json.dumps(protocol.goal_json(error)))
    with pytest.raises(type(error)) as raised:
        protocol.goal_from_json(data)
    assert str(raised.value) == str(error)
    assert raised.value.result == error.result
    assert vars(raised.value) == vars(error)


def test_a_goal_that_arrived_is_its_result() -> None:
    result = _motion_result("arrived")
    assert protocol.goal_from_json(json.loads(json.dumps(protocol.goal_json(result)))) == result


@pytest.mark.parametrize(
    "error",
    [
        OutOfRangeError("servo 3 position", 2000, 280, 650, "count"),
        OutOfRangeError("pid kp", 1e9, 0.0, 10000.0),
        InvalidArgumentError("give exactly one of pos_raw or angle_rad"),
        StateError("an emergency stop is latched: call robot.clear_estop() first"),
    ],
)
def test_the_robots_refusal_comes_back_as_the_robot_raised_it(error: OhmniError) -> None:
    reply = RequestError("bad_value", f"move: {error}", 7, raised=error).reply()
    message = protocol.parse_server_message(protocol.encode(reply))
    assert isinstance(message, protocol.ErrorMessage)
    again = protocol.raised_error(message.raised, message.message.removeprefix("move: "))
    assert type(again) is type(error)
    assert str(again) == str(error)
