"""The MQTT parts without a broker: settings, the broker's address, the back-off, Home
Assistant's light command, where replies may go, what counts as a change of state, and
the checked-in schema."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest
from pydantic import SecretStr

from ohmni_tb import Robot, RobotConfig
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import ConfigError
from ohmni_tb.mqtt import Backoff, Broker, MqttBridge, default_robot_id
from ohmni_tb.mqtt.payloads import (
    BatteryState,
    BridgeFigures,
    NeckState,
    StatePayload,
    fleet_schema,
    ha_light_args,
    response_topic_allowed,
    state_key,
    write_fleet_schema,
)

ROOT = Path(__file__).resolve().parents[2]


# -- settings -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"mqtt_url": "http://broker"}, "mqtt_url='http://broker' is not a broker URL: allowed"),
        ({"mqtt_url": "mqtt://u:p@broker"}, "without a user or path"),
        ({"mqtt_url": "mqtt://broker:0"}, "is not a broker URL"),
        ({"robot_id": "a/b"}, "robot_id='a/b' is not a name: allowed empty, or 1..64"),
        ({"robot_id": "x" * 65}, "is not a name"),
        ({"mqtt_rates": "wheel_odom=0"}, "'wheel_odom=0' is not NAME=HZ with a rate >0..100 Hz"),
        ({"mqtt_rates": "wheel_odom"}, "is not NAME=HZ"),
        ({"mqtt_rates": "a=1,a=2"}, "names a twice"),
        ({"mqtt_keepalive_s": 0}, "mqtt_keepalive_s=0 is out of range: allowed 1..3600 s"),
        ({"mqtt_discovery_prefix": "home/#"}, "is not a topic"),
        ({"mqtt_cert_file": "c.pem"}, "mqtt_cert_file is set but mqtt_key_file is not"),
        (
            {"mqtt_url": "mqtt://broker", "mqtt_ca_file": "ca.pem"},
            "mqtt_ca_file='ca.pem' needs TLS: mqtt_url must be mqtts://",
        ),
        ({"mqtt_password": "secret"}, "mqtt_password is set but mqtt_username is not"),
    ],
)
def test_a_bad_mqtt_setting_is_one_clear_error(settings: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=_escaped(message)):
        RobotConfig(**settings)  # type: ignore[arg-type]  # values of the wrong kind


def _escaped(text: str) -> str:
    import re

    return re.escape(text)


def test_the_password_is_never_shown() -> None:
    config = RobotConfig(
        mqtt_url="mqtts://broker", mqtt_username="a", mqtt_password=SecretStr("s3cret")
    )
    assert "s3cret" not in json.dumps(config.model_dump(mode="json"))
    assert "s3cret" not in repr(config)
    assert config.mqtt_password.get_secret_value() == "s3cret"
    # A copy with a change keeps it (the daemon's own overrides are applied so).
    assert config.replace(robot_id="x").mqtt_password.get_secret_value() == "s3cret"


def test_the_rates_setting_reads_as_streams() -> None:
    assert RobotConfig().mqtt_streams() == {"wheel_odom": 5.0, "tbcore_status": 1.0}
    assert RobotConfig(mqtt_rates="none").mqtt_streams() == {}
    assert RobotConfig(mqtt_rates=" diagnostics = 0.5 ").mqtt_streams() == {"diagnostics": 0.5}


async def test_the_bridge_refuses_a_rate_for_no_stream() -> None:
    async with (
        Robot.open("sim://", mqtt_url="mqtt://127.0.0.1:1", mqtt_rates="odometry=5") as robot,
        RobotServer(robot, port=0) as server,
    ):
        with pytest.raises(ConfigError, match="names no stream odometry: the streams are wheel_"):
            MqttBridge(robot, server)


def test_the_default_robot_id_is_the_host_name_made_a_name(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr("socket.gethostname", lambda: "Robot #7.ward.example")
    assert default_robot_id() == "Robot--7"
    monkeypatch.setattr("socket.gethostname", lambda: "")
    assert default_robot_id() == "ohmni"


# -- the broker ---------------------------------------------------------------------------


def test_a_broker_url_gives_its_address_and_tls() -> None:
    assert Broker.from_url("mqtt://broker").url == "mqtt://broker:1883"
    assert Broker.from_url("mqtts://broker").port == 8883
    assert Broker.from_url("mqtts://[::1]:9000").url == "mqtts://[::1]:9000"
    with pytest.raises(ConfigError, match="'ws://x' is not a broker URL"):
        Broker.from_url("ws://x")


def test_who_the_broker_is_told_and_where_it_is() -> None:
    assert not Broker.from_url("mqtt://broker").authenticated
    assert Broker.from_url("mqtt://broker", username="a").authenticated
    assert Broker.from_url("mqtts://b", cert_file="c", key_file="k").authenticated
    assert Broker.from_url("mqtt://127.0.0.1").local
    assert Broker.from_url("mqtt://localhost").local
    assert not Broker.from_url("mqtt://10.0.0.5").local


def test_the_broker_of_the_settings_carries_its_credentials() -> None:
    config = RobotConfig(mqtt_url="mqtt://h:1884", mqtt_username="a", mqtt_password=SecretStr("pw"))
    broker = Broker.from_config(config)
    assert (broker.host, broker.port, broker.username, broker.password) == ("h", 1884, "a", "pw")
    with pytest.raises(ConfigError, match="no broker: give --mqtt URL"):
        Broker.from_config(RobotConfig())


def test_a_missing_tls_file_is_named() -> None:
    broker = Broker.from_url("mqtts://h", ca_file="/nowhere/ca.pem")
    with pytest.raises(ConfigError, match=r"mqtt_ca_file='/nowhere/ca\.pem': no such file"):
        broker._tls_context()


def test_the_backoff_doubles_to_its_cap_spread_and_resets() -> None:
    backoff = Backoff(0.5, 4.0, random.Random(1))
    waits = [backoff.next_s() for _ in range(6)]
    for wait, nominal in zip(waits, [0.5, 1, 2, 4, 4, 4], strict=True):
        assert 0.8 * nominal <= wait <= 1.2 * nominal
    backoff.reset()
    assert backoff.next_s() <= 0.6


# -- payloads -----------------------------------------------------------------------------


def test_home_assistants_light_command_is_the_rings_hsv() -> None:
    last = (10, 20, 30)
    assert ha_light_args({"state": "ON"}, last) == last
    assert ha_light_args({"state": "ON", "brightness": 255}, last) == (10, 20, 255)
    assert ha_light_args({"state": "ON", "color": {"h": 360, "s": 50}}, last) == (255, 128, 30)
    assert ha_light_args({"state": "OFF"}, last) == (10, 20, 0)
    assert ha_light_args({"state": "ON"}, (1, 2, 0)) == (1, 2, 255)  # on again: lit
    with pytest.raises(ValueError, match='"state": "ON" or "OFF"'):
        ha_light_args({"brightness": 3}, last)
    with pytest.raises(ValueError, match=r"color.h=400 is out of range: allowed 0..360"):
        ha_light_args({"state": "ON", "color": {"h": 400, "s": 1}}, last)
    with pytest.raises(ValueError, match="brightness=True is out of range"):
        ha_light_args({"state": "ON", "brightness": True}, last)


def test_replies_go_only_under_the_robots_own_response_topic() -> None:
    assert response_topic_allowed("a", "ohmni/a/response")
    assert response_topic_allowed("a", "ohmni/a/response/fleet-1")
    assert not response_topic_allowed("a", "ohmni/b/response")
    assert not response_topic_allowed("a", "ohmni/a/state")
    assert not response_topic_allowed("a", "ohmni/a/responses")
    assert not response_topic_allowed("a", "ohmni/a/response/#")


def _state(**changes: object) -> StatePayload:
    base = StatePayload(
        robot_id="a",
        time=1.0,
        version="1",
        simulated=True,
        link="connected",
        estopped=False,
        faults=[],
        battery=BatteryState(
            percent=80,
            pack_v=16.4,
            cell_v=[3.3] * 5,
            current_a=-1.0,
            docked=False,
            charging=False,
        ),
        neck=NeckState(kind="herkulex", position_raw=512),
        lease=None,
        firmware={},
        drive=False,
        uptime_s=1.0,
        bridge=BridgeFigures(connects=1, published=0, dropped=0, commands=0, refused=0),
    )
    return base.model_copy(update=changes)


def test_a_change_of_state_is_what_a_fleet_watches_not_the_moving_figures() -> None:
    key = state_key(_state())
    battery = _state().battery
    assert battery is not None
    assert state_key(_state(time=99.0, uptime_s=50.0)) == key
    assert state_key(_state(battery=battery.model_copy(update={"pack_v": 16.1}))) == key
    assert state_key(_state(battery=battery.model_copy(update={"docked": True}))) != key
    assert state_key(_state(faults=["link_lost"])) != key
    assert state_key(_state(lease="mqtt:a")) != key
    assert state_key(_state(neck=NeckState(kind="herkulex", position_raw=400))) != key


def test_the_checked_in_schema_is_the_codes(tmp_path: Path) -> None:
    write_fleet_schema(tmp_path / "fleet-schema.json")
    written = (tmp_path / "fleet-schema.json").read_text(encoding="utf-8")
    shipped = (ROOT / "docs" / "fleet-schema.json").read_text(encoding="utf-8")
    assert written == shipped, (
        "regenerate: python -c 'import ohmni_tb.mqtt.payloads as p; p.write_fleet_schema()'"
    )
    schema = fleet_schema()
    assert set(schema["commands"]) >= {"stop", "estop", "light_ring", "move", "rotate"}
    assert "battery" in schema["state"]["properties"]
