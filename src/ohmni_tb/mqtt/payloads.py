"""What the robot and the fleet say on the broker: topics, payloads, commands, Home
Assistant's discovery (sans-IO: no client, no clock — times come in as arguments).

The topic tree of one robot, under :data:`ROOT`::

    ohmni/<robot_id>/availability        online / offline        retained, QoS 1, the Will
    ohmni/<robot_id>/state               StatePayload (JSON)     retained, QoS 1
    ohmni/<robot_id>/stream/<name>       a sample (JSON)         QoS 0, at mqtt_rates
    ohmni/<robot_id>/cmd/<method>        the method's args  →    QoS 1, taken by the robot
    ohmni/<robot_id>/response[/...]      ←  ResultReply / ErrorReply
    ohmni/<robot_id>/ha/light/set        Home Assistant's light  →  light_ring

A stream's sample is the daemon's (:func:`ohmni_tb.robot.wire.sample_json`, whose schema
is ``samples`` in ``docs/daemon-schema.json``); a command's body is the daemon's ``args``
of that method, and its reply the daemon's result or error (:func:`fleet_schema` has
them all; ``docs/fleet-schema.json`` is it).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field

from ohmni_tb.robot.samples import STREAM_NAMES
from ohmni_tb.robot.wire import ERROR_CODES, METHOD_SPECS

__all__ = [
    "AVAILABILITY",
    "COMMANDS",
    "DRIVING",
    "ERROR_CODES_MQTT",
    "OFFLINE",
    "ONLINE",
    "RESPONSE",
    "ROOT",
    "STATE_PERIOD_S",
    "BatteryState",
    "BridgeFigures",
    "ErrorReply",
    "NeckState",
    "ResultReply",
    "StatePayload",
    "command_topic",
    "discovery_messages",
    "fleet_schema",
    "ha_light_args",
    "response_topic_allowed",
    "robot_topic",
    "state_key",
    "write_fleet_schema",
]

#: Every robot's topics are under ``ohmni/<robot_id>/``.
ROOT: Final = "ohmni"
#: The availability payloads (Home Assistant's defaults).
ONLINE: Final = "online"
OFFLINE: Final = "offline"
#: The sub-topics of a robot.
AVAILABILITY: Final = "availability"
STATE: Final = "state"
STREAM: Final = "stream"
COMMAND: Final = "cmd"
RESPONSE: Final = "response"
HA_LIGHT: Final = "ha/light/set"
#: The state is published on every change and at least this often (the fleet's "last
#: seen" is never older than this while the robot is online).
STATE_PERIOD_S: Final = 10.0

#: The daemon's methods a command topic takes, and what each needs beyond the daemon's
#: own rules: ``anyone`` (stopping), ``read`` (nothing changes), ``lease`` (the bridge takes
#: the control lease for it, refused when another client holds it), ``drive`` (as
#: ``lease``, and only with ``mqtt_drive``).
COMMANDS: Final[dict[str, Literal["anyone", "read", "lease", "drive"]]] = {
    "stop": "anyone",
    "estop": "anyone",
    "latest": "read",
    "info": "read",
    "lease": "read",
    "stats": "read",
    "light_ring": "lease",
    "move": "lease",
    "drive_distance": "drive",
    "rotate": "drive",
}
#: The commands that move the wheels.
DRIVING: Final = frozenset(name for name, kind in COMMANDS.items() if kind == "drive")
#: Refusals of the bridge itself, besides the daemon's codes.
ERROR_CODES_MQTT: Final = (
    "not_offered",  # not one of COMMANDS (or move for another target than the neck)
    "driving_off",  # a driving command without mqtt_drive
    "unauthenticated",  # a command that needs the lease, over a broker without credentials
    "busy",  # too many commands at once, or faster than the bridge takes them
    "retained",  # a retained command message: never run (it would run again at every connect)
)
_CODES = (*ERROR_CODES, *ERROR_CODES_MQTT)


class _Payload(BaseModel):
    model_config = ConfigDict(frozen=True, extra="ignore")


class BatteryState(_Payload):
    """The battery and the dock, from the robot's latest ``tbcore_status``."""

    percent: int = Field(description="The vendor's coarse state of charge (20, 50, 80, 100).")
    pack_v: float
    cell_v: list[float]
    current_a: float = Field(description="Positive while charging.")
    docked: bool
    charging: bool


class NeckState(_Payload):
    """The neck fitted, and where it is (raw units)."""

    kind: str = Field(description="herkulex, worm or none.")
    position_raw: int | None = Field(description="Its latest position; null: not read yet.")


class BridgeFigures(_Payload):
    """What the bridge did since the daemon started."""

    connects: int = Field(description="Connections to the broker made.")
    published: int = Field(description="Messages handed to the broker.")
    dropped: int = Field(
        description="Messages dropped: to the broker, oldest first, while it was away or "
        "slow; from it, commands beyond what the bridge holds unread."
    )
    commands: int = Field(description="Commands answered.")
    refused: int = Field(description="Commands refused (by the daemon or the bridge).")


class StatePayload(_Payload):
    """``ohmni/<robot_id>/state``: the robot at a glance (retained)."""

    robot_id: str
    time: float = Field(description="When it was published: Unix time, s (the 'last seen').")
    version: str = Field(description="ohmni_tb's version on the robot.")
    simulated: bool = Field(description="The robot is the built-in simulator.")
    link: str = Field(description="The serial link: connected, lost, released or closed.")
    estopped: bool
    faults: list[str] = Field(description="What is wrong now (robot_state's faults).")
    battery: BatteryState | None = Field(description="null until the battery is read.")
    neck: NeckState
    lease: str | None = Field(description="The client holding the control lease, or null.")
    firmware: dict[str, str] = Field(description="Each board's firmware tag.")
    drive: bool = Field(description="MQTT commands may drive the wheels (mqtt_drive).")
    uptime_s: float
    bridge: BridgeFigures


class ResultReply(_Payload):
    """The reply to a command that was carried out."""

    op: Literal["result"] = "result"
    method: str
    data: Any = Field(description="The daemon's result of that method (fleet-schema methods).")


class ErrorReply(_Payload):
    """The reply to a refused command: nothing was done."""

    op: Literal["error"] = "error"
    method: str
    code: Literal[_CODES]  # type: ignore[valid-type]  # the tuple of codes, for the schema
    message: str
    raised: dict[str, Any] | None = Field(
        None, description="The Robot's own exception, as in the daemon's error."
    )


def robot_topic(robot_id: str, *parts: str) -> str:
    """``ohmni/<robot_id>/<parts...>``."""
    return "/".join((ROOT, robot_id, *parts))


def command_topic(robot_id: str, method: str) -> str:
    """Where ``method`` is commanded: ``ohmni/<robot_id>/cmd/<method>``."""
    return robot_topic(robot_id, COMMAND, method)


def response_topic_allowed(robot_id: str, topic: str) -> bool:
    """Whether a command's response topic is one the robot answers on: its own
    ``ohmni/<robot_id>/response`` or below it. Anything else would let a commander make
    the robot publish elsewhere (as another robot, say); the reply then goes to the
    default response topic."""
    base = robot_topic(robot_id, RESPONSE)
    return (topic == base or topic.startswith(base + "/")) and not set(topic) & set("+#")


def state_key(state: StatePayload) -> tuple[Any, ...]:
    """What a change of the state is judged on: not the figures that move all the time
    (the pack voltage, the time, the bridge's counts) — those go out every
    :data:`STATE_PERIOD_S` and with every change."""
    battery = state.battery
    return (
        state.link,
        state.estopped,
        tuple(state.faults),
        None if battery is None else (battery.percent, battery.docked, battery.charging),
        state.neck.position_raw,
        state.lease,
        tuple(sorted(state.firmware.items())),
        state.drive,
    )


def ha_light_args(payload: dict[str, Any], last: tuple[int, int, int]) -> tuple[int, int, int]:
    """Home Assistant's JSON light command (``{"state": "ON", "brightness": 0..255,
    "color": {"h": 0..360, "s": 0..100}}``, parts left out keep ``last``) as the light
    ring's hue, saturation and value, 0..255 each; ``OFF`` is value 0.

    Raises:
        ValueError: Not such a command; the message names what is wrong.
    """
    state = payload.get("state")
    if state not in ("ON", "OFF"):
        raise ValueError(f'a light command has "state": "ON" or "OFF", not {state!r}')
    hue, saturation, value = last
    color = payload.get("color")
    if color is not None:
        if not isinstance(color, dict):
            raise ValueError(f'"color" is an object {{"h": 0..360, "s": 0..100}}, not {color!r}')
        if "h" in color:
            hue = _scaled("color.h", color["h"], 360)
        if "s" in color:
            saturation = _scaled("color.s", color["s"], 100)
    if "brightness" in payload:
        value = _scaled("brightness", payload["brightness"], 255)
    elif state == "ON" and value == 0:
        value = 255
    if state == "OFF":
        value = 0
    return hue, saturation, value


def discovery_messages(
    robot_id: str,
    *,
    prefix: str,
    version: str,
    neck_kind: str,
    neck_range_raw: tuple[int, int] | None,
) -> list[tuple[str, dict[str, Any]]]:
    """Home Assistant's MQTT discovery: ``(topic, config)`` for each entity of the robot's
    device — sensors (battery %, pack voltage, link, faults), binary sensors (docked,
    charging, a fault), the light ring (a JSON-schema light), the neck (a number, raw
    units within ``neck_range_raw``; none without a neck) and a stop button. Each topic is
    ``<prefix>/<component>/<robot_id>/<object>/config``; publish them retained."""
    state = robot_topic(robot_id, STATE)
    device = {
        "identifiers": [f"ohmni_{robot_id}"],
        "name": f"Ohmni {robot_id}",
        "manufacturer": "OhmniLabs",
        "model": "Ohmni Developer Edition",
        "sw_version": version,
    }
    common = {
        "device": device,
        "availability": [{"topic": robot_topic(robot_id, AVAILABILITY)}],
        "origin": {"name": "ohmni_tb", "sw_version": version},
    }
    battery = "value_json.battery"
    entities: list[tuple[str, str, dict[str, Any]]] = [
        (
            "sensor",
            "battery",
            {
                "name": "Battery",
                "device_class": "battery",
                "state_class": "measurement",
                "unit_of_measurement": "%",
                "state_topic": state,
                "value_template": f"{{{{ {battery}.percent if {battery} else None }}}}",
            },
        ),
        (
            "sensor",
            "pack_voltage",
            {
                "name": "Pack voltage",
                "device_class": "voltage",
                "state_class": "measurement",
                "unit_of_measurement": "V",
                "suggested_display_precision": 2,
                "state_topic": state,
                "value_template": f"{{{{ {battery}.pack_v if {battery} else None }}}}",
            },
        ),
        (
            "binary_sensor",
            "docked",
            {
                "name": "Docked",
                "device_class": "plug",
                "state_topic": state,
                "value_template": f"{{{{ 'ON' if {battery} and {battery}.docked else 'OFF' }}}}",
            },
        ),
        (
            "binary_sensor",
            "charging",
            {
                "name": "Charging",
                "device_class": "battery_charging",
                "state_topic": state,
                "value_template": f"{{{{ 'ON' if {battery} and {battery}.charging else 'OFF' }}}}",
            },
        ),
        (
            "sensor",
            "link",
            {
                "name": "Link",
                "device_class": "enum",
                "options": ["connected", "lost", "released", "closed"],
                "state_topic": state,
                "value_template": "{{ value_json.link }}",
            },
        ),
        (
            "sensor",
            "faults",
            {
                "name": "Faults",
                "icon": "mdi:alert-circle-outline",
                "state_topic": state,
                # A state holds 255 characters at most.
                "value_template": "{{ (value_json.faults | join(', ') or 'none')[:255] }}",
            },
        ),
        (
            "binary_sensor",
            "problem",
            {
                "name": "Problem",
                "device_class": "problem",
                "state_topic": state,
                "value_template": "{{ 'ON' if value_json.faults or value_json.estopped "
                "else 'OFF' }}",
            },
        ),
        (
            "light",
            "light_ring",
            {
                "name": "Light ring",
                "schema": "json",
                "command_topic": robot_topic(robot_id, HA_LIGHT),
                "supported_color_modes": ["hs"],
                "brightness": True,
                "brightness_scale": 255,
                "optimistic": True,
            },
        ),
        (
            "button",
            "stop",
            {
                "name": "Stop",
                "icon": "mdi:stop-circle-outline",
                "command_topic": command_topic(robot_id, "stop"),
                "payload_press": "{}",
            },
        ),
    ]
    if neck_range_raw is not None and neck_kind != "none":
        low, high = neck_range_raw
        entities.append(
            (
                "number",
                "neck",
                {
                    "name": "Neck",
                    "icon": "mdi:head-cog-outline",
                    "command_topic": command_topic(robot_id, "move"),
                    "command_template": '{"target": "neck", "raw": {{ value | int }}}',
                    "state_topic": state,
                    "value_template": "{{ value_json.neck.position_raw }}",
                    "min": low,
                    "max": high,
                    "step": 1,
                    "mode": "slider",
                },
            )
        )
    return [
        (
            f"{prefix}/{component}/{robot_id}/{name}/config",
            {**config, "unique_id": f"ohmni_{robot_id}_{name}", **common},
        )
        for component, name, config in entities
    ]


def fleet_schema() -> dict[str, Any]:
    """The JSON Schema of what the robot publishes and takes on the broker: the state,
    the replies, each command's body (the daemon's ``args``); the streams' samples are the
    daemon's (``docs/daemon-schema.json``, ``samples``)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "ohmni_tb on MQTT",
        "topics": {
            f"{ROOT}/<robot_id>/{AVAILABILITY}": f"{ONLINE} or {OFFLINE} (retained)",
            f"{ROOT}/<robot_id>/{STATE}": "state (retained)",
            f"{ROOT}/<robot_id>/{STREAM}/<name>": "daemon-schema.json samples.<name>",
            f"{ROOT}/<robot_id>/{COMMAND}/<method>": "commands.<method>",
            f"{ROOT}/<robot_id>/{RESPONSE}": "reply",
            f"{ROOT}/<robot_id>/{HA_LIGHT}": "Home Assistant's JSON light command",
        },
        "streams": list(STREAM_NAMES),
        "state": StatePayload.model_json_schema(),
        "reply": {"oneOf": [ResultReply.model_json_schema(), ErrorReply.model_json_schema()]},
        "commands": {
            name: {
                "needs": kind,
                "args": METHOD_SPECS[name].args.model_json_schema(),
                "result": METHOD_SPECS[name].result,
            }
            for name, kind in COMMANDS.items()
        },
    }


def write_fleet_schema(path: str | os.PathLike[str] = "docs/fleet-schema.json") -> None:
    """Write :func:`fleet_schema` to ``path``, as the repository keeps it."""
    text = json.dumps(fleet_schema(), indent=2, sort_keys=True, ensure_ascii=False) + "\n"
    Path(path).write_text(text, encoding="utf-8")


def _scaled(name: str, value: object, top: float) -> int:
    """``value`` in 0..``top`` as 0..255."""
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or not 0 <= value <= top
    ):
        raise ValueError(f"{name}={value!r} is out of range: allowed 0..{top:g}")
    return round(value * 255 / top)
