"""The daemon's messages: versioned JSON, validated with pydantic at the edge (sans-IO).

Every message is one JSON object in one WebSocket text frame, with ``op`` naming it::

    client → server                          server → client
    subscribe   {id, topic, max_hz?, queue?}  hello   {protocol, version, topics, limits, …}
    unsubscribe {id, topic}                   sample  {topic, dropped, data}
    call        {id, method, args}            result  {id, data}
                                              error   {id | null, code, message}
                                              batch   {samples: [sample, …]}
                                              lease   {holder, you, reason}

``id`` is the client's (an integer or a short string); the ``result`` or ``error`` that
answers a request carries it back. A ``call`` names one of :data:`METHODS`; its ``args``
are checked against that method's model in :data:`METHOD_ARGS` (:func:`call_args`).
Methods in :data:`LEASE_METHODS` change the robot and need a control lease
(``acquire``): one lease per command source, each held by at most one client; the drive
commands and motion goals go as the command source of the lease (``source``), and the
daemon's Robot takes the highest source's. ``stop`` and ``estop`` are anyone's. A
sample's ``data`` is the Robot's sample dataclass as JSON (enums by value, tuples as
lists, nested dataclasses as objects): :func:`sample_json` and :func:`sample_from_json`
go both ways.
:func:`parse_client_message` turns one frame into a message or raises
:class:`RequestError` with the ``error`` to send back. :func:`json_schema` is the schema
of them all, checked in at ``docs/daemon-schema.json`` (regenerate it with
:func:`write_schema`: ``python -c 'import ohmni_tb.robot.wire as w; w.write_schema()'``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, field_validator

from ohmni_tb.control.pid import PidGains
from ohmni_tb.errors import (
    ConfigError,
    InvalidArgumentError,
    MotionAbortedError,
    MotionError,
    MotionPreemptedError,
    MotionResult,
    MotionTimeoutError,
    OhmniError,
    OutOfRangeError,
    PositionError,
    PositionTimeoutError,
    RobotClosedError,
    SourceOverriddenError,
    StateError,
    TransportError,
    WheelSlipError,
    WheelStallError,
)
from ohmni_tb.herkulex.servo import ServoStatus
from ohmni_tb.protocol import StatusDetail, StatusError
from ohmni_tb.robot.samples import (
    STREAM_NAMES,
    STREAMS,
    Sample,
)
from ohmni_tb.robot.stats import RobotStats

__all__ = [
    "CLIENT_OPS",
    "ERROR_CODES",
    "LEASE_METHODS",
    "MAX_QUEUE",
    "METHODS",
    "METHOD_SPECS",
    "PROTOCOL_VERSION",
    "TOKEN_ENV",
    "AcquireArgs",
    "BatchMessage",
    "BoardIdArgs",
    "Call",
    "ClientMessage",
    "ConnectArgs",
    "DriveArgs",
    "DriveDistanceArgs",
    "DrivePwmArgs",
    "DriveWheelsArgs",
    "EnabledArgs",
    "ErrorCode",
    "ErrorMessage",
    "GoToArgs",
    "Hello",
    "LatestArgs",
    "LeaseMessage",
    "LightArgs",
    "Limits",
    "MethodSpec",
    "Motion",
    "MoveArgs",
    "NoArgs",
    "OdometryArgs",
    "PidArgs",
    "PoseArgs",
    "RateArgs",
    "ReleaseArgs",
    "ReleasePortArgs",
    "RequestError",
    "RestArgs",
    "Result",
    "RotateArgs",
    "SampleMessage",
    "ServerMessage",
    "ServoArgs",
    "ServoCommand",
    "ServoIdArgs",
    "ServoWriteArgs",
    "SourceArgs",
    "SourceName",
    "StreamArgs",
    "Subscribe",
    "TorqueArgs",
    "Unsubscribe",
    "WheelArgs",
    "WheelName",
    "ZeroOffsetArgs",
    "call_args",
    "encode",
    "goal_from_json",
    "goal_json",
    "info_from_json",
    "json_schema",
    "parse_client_message",
    "parse_server_message",
    "pid_from_json",
    "pid_state_from_json",
    "pid_state_json",
    "raised_error",
    "result_json",
    "sample_from_json",
    "sample_json",
    "schedule_from_json",
    "schema_text",
    "servo_status_from_json",
    "servo_status_json",
    "stats_from_json",
    "stats_json",
    "write_schema",
]

#: Bumped on any change a peer of the previous version would misread (2: commands, lease;
#: 3: strict types, ``hello`` says what the daemon serves; 4: the motion goals, and the
#: Robot's own exception in ``error.raised``; 5: tb_control's sample fields, and the
#: frame settings in ``config``, which a client of 4 refuses as unknown; 6: the
#: ``diagnostics`` topic, ``set_odometry``, and ``wheel_odom``'s requested twist; 7: a
#: lease per command source, the drive commands' ``source``, ``robot_state``'s
#: ``active_source``).
PROTOCOL_VERSION: Final = 7
#: The environment variable a client takes the daemon's token from.
TOKEN_ENV: Final = "OHMNI_DAEMON_TOKEN"
#: What a client may ask (``op``).
CLIENT_OPS: Final = ("subscribe", "unsubscribe", "call")
#: Longest string ``id`` a client may use.
_MAX_ID_CHARS = 64
#: Longest error message: it quotes what was wrong, shortened (a frame is up to 16 KiB).
_MAX_ERROR_CHARS = 1000
#: Most samples a subscription's queue may hold (memory per client and topic).
MAX_QUEUE = 1024
#: Fastest rate cap a subscription may ask; no stream is faster than 100 Hz.
_MAX_HZ = 1000.0
#: Largest decimation a subscription may ask (one sample in 10,000).
_MAX_EVERY = 10_000

ErrorCode = Literal[
    "bad_json",  # not JSON (nested too deep included), or not one JSON object
    "bad_message",  # an object, but not a valid message (a field missing or wrong)
    "unknown_op",
    "unknown_method",
    "unknown_topic",
    "not_subscribed",  # unsubscribe from a topic the client is not subscribed to
    "too_large",  # over the message size limit
    "rate_limited",  # over the message rate limit (the connection is then closed)
    "no_lease",  # a command that needs the control lease, from a client without it
    "lease_held",  # acquire while another client holds the lease (steal to take it)
    "source_forbidden",  # a client beyond loopback claims a source of the robot's own computer
    "read_only",  # the daemon takes no commands (``ohmni serve --read-only``)
    "bad_value",  # the Robot refused a value (out of range, not finite): nothing sent
    "robot_state",  # the Robot cannot do it now (an emergency stop, no such device …)
    "robot_error",  # the Robot raised otherwise: the message says what
]
#: The ``code`` of an ``error``, for programs to act on.
ERROR_CODES: Final = ErrorCode.__args__  # type: ignore[attr-defined]  # Literal's members

MessageId = (
    Annotated[int, Field(ge=0, le=2**53 - 1, strict=True)]
    | Annotated[str, Field(min_length=1, max_length=_MAX_ID_CHARS, strict=True)]
)
Topic = Literal[STREAM_NAMES]  # type: ignore[valid-type]  # the tuple of names, for the schema
#: A finite number (JSON has no NaN, but Python's json module reads ``NaN``/``Infinity``);
#: an integer is one, ``true`` and ``"0.5"`` are not.
Number = Annotated[float, Field(allow_inf_nan=False, strict=True)]


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class _Request(_Message):
    """A client's message or a method's arguments: strict types (no ``true`` for 1, no
    ``"5"`` for 5), so that what reaches the Robot is what the client meant."""

    model_config = ConfigDict(strict=True)

    def call_kwargs(self) -> dict[str, Any]:
        """The arguments of the Robot method a call names (:attr:`MethodSpec.call`)."""
        return {name: getattr(self, name) for name in type(self).model_fields}


# -- the methods' arguments -----------------------------------------------------------------


class NoArgs(_Request):
    """No arguments."""


class LatestArgs(_Request):
    """``latest``: which stream."""

    topic: Topic

    def call_kwargs(self) -> dict[str, Any]:
        return {"name": self.topic}


#: A command source's name (the daemon's Robot's ``command_sources`` say which exist).
SourceName = Annotated[str, Field(min_length=1, max_length=32, pattern=r"^[a-z][a-z0-9_]*$")]


class AcquireArgs(_Request):
    """``acquire``: take the control lease of command source ``source``; ``steal`` takes it
    from its holder (told so). A client beyond loopback may not take ``local`` nor
    ``safety`` (nor a source above ``remote``)."""

    steal: bool = False
    source: SourceName = Field(
        "remote", description="The command source the lease is for (default remote)."
    )


class ReleaseArgs(_Request):
    """``release``: give back the lease of ``source``, or (``null``) every lease held."""

    source: SourceName | None = None


class SourceArgs(_Request):
    """``stop``, ``estop``: obeyed from anyone; ``source`` (one of this client's leases,
    default its highest) is the command source it comes from."""

    source: SourceName | None = None


#: A drive command's or goal's command source: one this client holds the lease of
#: (``null``: its highest).
_SOURCE_FIELD = Field(
    None, description="The command source (a lease this client holds; null: its highest)."
)


#: A wheel by name, or ``null`` for both (``set_pid``, ``get_pid``, ``enable_controllers``).
WheelName = Literal["left", "right"] | None


class DriveArgs(_Request):
    """``drive``: body velocity target, as :meth:`Robot.drive` (``ramped`` false: the
    pure velocity command, no acceleration limit)."""

    linear_mps: Number
    angular_radps: Number = 0.0
    ramped: bool = True
    source: SourceName | None = _SOURCE_FIELD


class DriveWheelsArgs(_Request):
    """``drive_wheels``: each wheel's rim speed target, as :meth:`Robot.drive_wheels`."""

    left_mps: Number
    right_mps: Number
    source: SourceName | None = _SOURCE_FIELD


class DrivePwmArgs(_Request):
    """``drive_pwm``: open-loop PWM −1000..1000 (numbers, rounded to whole steps), and
    whether each motor is enabled (a disabled one gets 0), as :meth:`Robot.drive_pwm`."""

    left: Number
    right: Number
    left_enabled: bool = True
    right_enabled: bool = True
    source: SourceName | None = _SOURCE_FIELD


class EnabledArgs(_Request):
    """``enable_controllers``: on or off, for one ``wheel`` or (``null``) both."""

    enabled: bool = True
    wheel: WheelName = None


class WheelArgs(_Request):
    """``get_pid``: one ``wheel``'s gains, or (``null``) the gains both share."""

    wheel: WheelName = None


class PidArgs(_Request):
    """``set_pid``: the wheel PIDs' gains, as :class:`PidGains`, each within its range
    (the ``pid_*`` settings': ``ohmni_tb.control.defaults.WHEEL_GAIN_RANGES``)."""

    kp: Number
    ki: Number
    kd: Number
    kff: Number = 0.0
    ff_offset: Number = 0.0
    wheel: WheelName = None

    def call_kwargs(self) -> dict[str, Any]:
        return {
            "gains": PidGains(self.kp, self.ki, self.kd, self.kff, self.ff_offset),
            "wheel": self.wheel,
        }

    @classmethod
    def of(cls, gains: PidGains, wheel: Literal["left", "right"] | None = None) -> PidArgs:
        """The arguments that set ``gains`` (for ``wheel``, or both)."""
        return cls(
            kp=gains.kp,
            ki=gains.ki,
            kd=gains.kd,
            kff=gains.kff,
            ff_offset=gains.ff_offset,
            wheel=wheel,
        )


class PoseArgs(_Request):
    """``reset_odometry``: the pose to set."""

    x_m: Number = 0.0
    y_m: Number = 0.0
    yaw_rad: Number = 0.0


class OdometryArgs(_Request):
    """``set_odometry``: the pose to set, every part of it."""

    x_m: Number
    y_m: Number
    yaw_rad: Number


class LightArgs(_Request):
    """``light_ring``: hue, saturation, value, 0..255 each."""

    hue: int
    saturation: int
    value: int


class StreamArgs(_Request):
    """``enable_stream``: a stream on or off."""

    topic: Topic
    enabled: bool = True

    def call_kwargs(self) -> dict[str, Any]:
        return {"name": self.topic, "enabled": self.enabled}


class RateArgs(_Request):
    """``set_rate``: a polled stream's rate, within its ``rate_range_hz`` (the streams table,
    :data:`~ohmni_tb.robot.STREAMS`): 10..100 Hz for ``wheel_encoder`` (the control tick)."""

    topic: Topic
    hz: Number

    def call_kwargs(self) -> dict[str, Any]:
        return {"name": self.topic, "hz": self.hz}


class ReleasePortArgs(_Request):
    """``release_port``: hand the serial port to another program for ``duration_s``
    (0.1..3600 s; ``null``: until ``reclaim_port``)."""

    duration_s: Number | None = None


class _ServoCommand(_Request):
    target: str | int = Field(description='"neck", or a HerkuleX servo id 0..253.')

    @field_validator("target", mode="before")
    @classmethod
    def _neck_or_id(cls, value: object) -> object:
        if value == "neck" or (
            isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 253
        ):
            return value
        raise ValueError(f'target must be "neck" or a servo id 0..253, not {_shown(value)}')

    def call_kwargs(self) -> dict[str, Any]:
        # The target picks the handle; what is not given keeps the handle's default.
        return {
            name: getattr(self, name)
            for name in type(self).model_fields
            if name != "target" and getattr(self, name) is not None
        }


class MoveArgs(_ServoCommand):
    """``move``: the neck or servo ``target`` to ``raw`` counts or ``rad`` over ``playtime_s``
    (a worm-gear neck takes ``raw`` only); with ``wait``, answered once it reads back at
    the target (within ``timeout_s``)."""

    raw: int | None = None
    rad: Number | None = None
    playtime_s: Number | None = None
    wait: bool = False
    timeout_s: Number | None = None


class TorqueArgs(_ServoCommand):
    """``torque``: ``on``, ``brake`` or ``free`` for a HerkuleX neck or servo."""

    mode: Literal["on", "brake", "free"]


class RestArgs(_ServoCommand):
    """``rest``: move the neck or servo to its rest position (then free it, by default)."""

    free: bool = True


#: The arguments of every command to the neck or a servo (``target`` picks the handle).
ServoCommand = _ServoCommand


class ServoArgs(_ServoCommand):
    """``servo_info``: every register of the neck or servo ``target``."""


class ServoWriteArgs(_ServoCommand):
    """``servo_write``: register ``reg`` (a name or an address) of ``target``, in RAM
    (``persist``: its EEP copy too) or EEP alone, checked against the register map before
    anything is sent."""

    reg: str | int = Field(
        description="The register: its name, or its address in ``memory`` (the register map)."
    )
    value: int
    persist: bool = False
    memory: Literal["ram", "eep"] = "ram"

    def call_kwargs(self) -> dict[str, Any]:
        return {
            "register": self.reg,
            "value": self.value,
            "persist": self.persist,
            "memory": self.memory,
        }


class ServoIdArgs(_ServoCommand):
    """``servo_set_id``: give ``target`` the id ``new_sid`` (0..253); the robot follows."""

    new_sid: int


class ZeroOffsetArgs(_ServoCommand):
    """``servo_zero_offset``: ``target``'s zero offset, raw counts (−512..511)."""

    raw: int


class BoardIdArgs(_Request):
    """``reset_board_id``: give drive board ``sid`` (0, 1) the id ``new_sid``; refused
    without ``confirm``."""

    sid: int
    new_sid: int
    confirm: bool = False


class ConnectArgs(_Request):
    """``connect``: open ``port`` (a serial device or URL on the daemon's machine) in place
    of the one open now; ``null``: the one it had, again."""

    port: str | None = None


class DriveDistanceArgs(_Request):
    """``drive_distance``: as :meth:`Robot.drive_distance` (``null``: its default)."""

    distance_m: Number
    speed_mps: Number | None = None
    timeout_s: Number | None = None
    source: SourceName | None = _SOURCE_FIELD


class RotateArgs(_Request):
    """``rotate``: as :meth:`Robot.rotate` (``null``: its default)."""

    angle_rad: Number
    speed_radps: Number | None = None
    timeout_s: Number | None = None
    source: SourceName | None = _SOURCE_FIELD


class GoToArgs(_Request):
    """``go_to``: as :meth:`Robot.go_to` (``null``: its default; ``yaw_rad`` null: keep the
    heading it arrives with)."""

    x_m: Number
    y_m: Number
    yaw_rad: Number | None = None
    speed_mps: Number | None = None
    timeout_s: Number | None = None
    source: SourceName | None = _SOURCE_FIELD


@dataclass(frozen=True, slots=True)
class MethodSpec:
    """One service of the daemon.

    Attributes:
        args: Its arguments' model (:meth:`~_Request.call_kwargs` gives the call's).
        lease: Whether it needs the control lease.
        result: What its ``result`` carries (for the docs and the schema).
        call: The :class:`~ohmni_tb.robot.Robot` method it calls (on the neck's or
            servo's handle for ``move``, ``torque``, ``rest``), or ``None``: the
            server's own (the lease, the shared stats, the settings).
        awaited: Whether that method is a coroutine (the answer comes when it ends).
        sourced: Whether it goes as a command source (``source``: the drive commands,
            the goals, the stops).
    """

    args: type[_Request]
    lease: bool
    result: str
    call: str | None = None
    awaited: bool = False
    sourced: bool = False


#: What a motion goal's ``result`` carries: it ended short of its goal when ``error`` is
#: not null (``type`` is the ``MotionError``'s class, with its fields).
_GOAL_RESULT = (
    "{result: MotionResult, error: null or {type, message, by?, source?, timeout_s?, wheels?}}"
)
#: Every service a ``call`` may name.
METHOD_SPECS: Final[dict[str, MethodSpec]] = {
    # Read-only: anyone.
    "stats": MethodSpec(NoArgs, False, "Robot.stats() (see results.stats)"),
    "info": MethodSpec(
        NoArgs,
        False,
        "firmware tags, servo models (keys: ids), neck, present, absent",
        "info",
        awaited=True,
    ),
    "latest": MethodSpec(LatestArgs, False, "the topic's sample (see samples), or null", "latest"),
    "schedule": MethodSpec(NoArgs, False, "[[stream, hz, phase_s, line_time_s], ...]", "schedule"),
    "get_pid": MethodSpec(
        WheelArgs,
        False,
        "{kp, ki, kd, kff, ff_offset}: the wheel's, or the gains both share (an error "
        "when they differ)",
        "get_pid",
    ),
    "pid_state": MethodSpec(
        NoArgs,
        False,
        "{left: {kp, ki, kd, kff, ff_offset}, right: {…}, enabled: {left: bool, right: bool}}",
    ),
    "config": MethodSpec(NoArgs, False, "the daemon's RobotConfig: every setting by name"),
    "lease": MethodSpec(
        NoArgs,
        False,
        "{holder: peer or null, you: bool, leases: {source: peer}, yours: [source]}",
    ),
    # The leases themselves: one per command source.
    "acquire": MethodSpec(
        AcquireArgs, False, "{holder, you: true, stolen_from: peer or null, source}"
    ),
    "release": MethodSpec(ReleaseArgs, True, "{holder: null, you: false, released: [source]}"),
    # Stopping: anyone may.
    "stop": MethodSpec(SourceArgs, False, "null", "stop", sourced=True),
    "estop": MethodSpec(SourceArgs, False, "null", "estop", awaited=True, sourced=True),
    # Commands: the lease holders only.
    "drive": MethodSpec(
        DriveArgs,
        True,
        "{requested: [m/s, rad/s], twist: [m/s, rad/s], scale}",
        "drive",
        sourced=True,
    ),
    "drive_wheels": MethodSpec(
        DriveWheelsArgs, True, "{left_mps, right_mps} driven", "drive_wheels", sourced=True
    ),
    "drive_pwm": MethodSpec(
        DrivePwmArgs, True, "[left, right]: the PWM sent", "drive_pwm", sourced=True
    ),
    "clear_estop": MethodSpec(NoArgs, True, "null", "clear_estop"),
    "enable_controllers": MethodSpec(EnabledArgs, True, "null", "enable_controllers"),
    "set_pid": MethodSpec(PidArgs, True, "null", "set_pid"),
    "reset_odometry": MethodSpec(PoseArgs, True, "null", "reset_odometry"),
    "set_odometry": MethodSpec(OdometryArgs, True, "null", "set_odometry"),
    "light_ring": MethodSpec(LightArgs, True, "null", "light_ring", awaited=True),
    "enable_stream": MethodSpec(StreamArgs, True, "null", "enable_stream"),
    "set_rate": MethodSpec(RateArgs, True, "null", "set_rate"),
    "move": MethodSpec(
        MoveArgs,
        True,
        "null (sent; the servo's stream shows it moving), or with wait the sample at the target",
        "move",
        awaited=True,
    ),
    "torque": MethodSpec(TorqueArgs, True, "null", "torque", awaited=True),
    "rest": MethodSpec(
        RestArgs, True, "null (after the rest move, and the free)", "rest", awaited=True
    ),
    "servo_info": MethodSpec(
        ServoArgs, False, "{eep: {register: value}, ram: {register: value}}", "info", awaited=True
    ),
    "servo_write": MethodSpec(ServoWriteArgs, True, "null", "write", awaited=True),
    "servo_set_id": MethodSpec(
        ServoIdArgs, True, "null (the robot's stream and handle follow)", "set_id", awaited=True
    ),
    "servo_zero_offset": MethodSpec(ZeroOffsetArgs, True, "null", "set_zero_offset", awaited=True),
    "servo_status": MethodSpec(
        ServoArgs, False, "{error: RAM 48, detail: RAM 49}, asked now", "status", awaited=True
    ),
    "servo_clear": MethodSpec(
        ServoArgs,
        True,
        "{error, detail}: the status after clearing (the torque stays as the fault left it)",
        "clear_errors",
        awaited=True,
    ),
    "reset_board_id": MethodSpec(BoardIdArgs, True, "null", "reset_board_id", awaited=True),
    "port": MethodSpec(NoArgs, False, "the port open now, or null (disconnected, released)"),
    "list_ports": MethodSpec(
        NoArgs,
        False,
        "[{device, vid, pid, …, usb_id, likely_bus}]: the serial ports of the daemon's computer",
        "list_ports",
        awaited=True,
    ),
    "connect": MethodSpec(
        ConnectArgs,
        True,
        "null, once the port is open (robot_state: connected to …)",
        "connect",
        awaited=True,
    ),
    "disconnect": MethodSpec(
        NoArgs,
        True,
        "null, once the wheels stopped and the port is closed",
        "disconnect",
        awaited=True,
    ),
    "release_port": MethodSpec(
        ReleasePortArgs,
        True,
        "null, once the wheels stopped and the port is closed",
        "release_port",
        awaited=True,
    ),
    "reclaim_port": MethodSpec(
        NoArgs, True, "null (robot_state says when it is back)", "reclaim_port", awaited=True
    ),
    # Motion goals: they run in the daemon; the answer comes when the goal ends.
    "drive_distance": MethodSpec(
        DriveDistanceArgs, True, _GOAL_RESULT, "drive_distance", awaited=True, sourced=True
    ),
    "rotate": MethodSpec(RotateArgs, True, _GOAL_RESULT, "rotate", awaited=True, sourced=True),
    "go_to": MethodSpec(GoToArgs, True, _GOAL_RESULT, "go_to", awaited=True, sourced=True),
}
#: The services a ``call`` may name.
METHODS: Final = tuple(METHOD_SPECS)
#: The services that need the control lease.
LEASE_METHODS: Final = tuple(name for name, spec in METHOD_SPECS.items() if spec.lease)
Method = Literal[METHODS]  # type: ignore[valid-type]  # the tuple of names, for the schema


# -- client → server -----------------------------------------------------------------------


class Subscribe(_Request):
    """Send me ``topic``'s samples from now on (again: replaces the options)."""

    op: Literal["subscribe"] = "subscribe"
    id: MessageId
    topic: Topic
    max_hz: Annotated[float, Field(gt=0, le=_MAX_HZ)] | None = Field(
        None, description="Rate cap: at most this many samples a second, the newest each time."
    )
    every: Annotated[int, Field(ge=1, le=_MAX_EVERY)] | None = Field(
        default=None,
        description="Decimation: only every Nth sample of the stream (before max_hz).",
    )
    queue: Annotated[int, Field(ge=1, le=MAX_QUEUE)] = Field(
        64, description="Samples held for this client; when full the oldest is dropped."
    )


class Unsubscribe(_Request):
    """Stop sending ``topic``."""

    op: Literal["unsubscribe"] = "unsubscribe"
    id: MessageId
    topic: Topic


class Call(_Request):
    """Call a service: ``method`` with ``args`` (each method's are under ``methods``)."""

    op: Literal["call"] = "call"
    id: MessageId
    method: Method
    args: dict[str, Any] = Field(
        default_factory=dict, description="The method's arguments (see 'methods')."
    )


ClientMessage = Annotated[Subscribe | Unsubscribe | Call, Field(discriminator="op")]


# -- server → client -----------------------------------------------------------------------


class Limits(_Message):
    """The server's limits, told in ``hello``."""

    max_message_bytes: int = Field(description="Longer client messages are refused.")
    max_messages_per_s: float = Field(description="Sustained client message rate allowed.")
    burst_messages: int = Field(description="Messages allowed at once above that rate.")
    max_queue: int = Field(MAX_QUEUE, description="Largest queue a subscription may ask.")


class Motion(_Message):
    """The Robot's geometry and speed limits, told in ``hello``: a client scales a drive
    command as the Robot will (``null``: no limit)."""

    wheel_radius_m: float
    wheel_separation_m: float
    max_linear_mps: float | None
    max_angular_radps: float | None
    max_wheel_mps: float | None
    watchdog_s: float = Field(
        description="The wheels stop this long after the last drive command (0: off)."
    )


class Hello(_Message):
    """The first message on every connection."""

    op: Literal["hello"] = "hello"
    protocol: int = Field(description="PROTOCOL_VERSION of the server.")
    version: str = Field(description="ohmni_tb's version.")
    read_only: bool = Field(description="Commands are refused (stop and estop excepted).")
    serves: str | None = Field(
        None, description="The port the daemon's Robot opened (sim://, /dev/ttyUSB0 …), if told."
    )
    simulated: bool = Field(
        False, description="The Robot is the built-in simulator: nothing physical moves."
    )
    peer: str = Field(description="This connection as the server names it (host:port).")
    lease: str | None = Field(
        description="Who holds the control lease of the highest command source held (peer), "
        "or null: nobody holds one."
    )
    leases: dict[str, str] = Field(
        default_factory=dict, description="Each command source's lease and its holder (peer)."
    )
    topics: dict[str, float] = Field(description="Each stream and its rate (Hz; 0: on events).")
    motion: Motion
    limits: Limits


class LeaseMessage(_Message):
    """The control lease changed hands: sent to every client."""

    op: Literal["lease"] = "lease"
    holder: str | None = Field(description="The new holder (peer), or null: nobody.")
    you: bool = Field(description="This connection holds it now.")
    reason: str = Field(description="What happened, for people: acquired, stolen by …")
    source: str = Field("remote", description="The command source whose lease it is.")


class SampleMessage(_Message):
    """One sample of a subscribed topic."""

    op: Literal["sample"] = "sample"
    topic: Topic
    dropped: int = Field(
        ge=0, description="Samples of this topic this client lost since the previous one."
    )
    data: dict[str, Any] = Field(description="The sample; its schema is under 'samples'.")


class BatchMessage(_Message):
    """Several samples in one frame: what waited for this client since the last flush
    (``SAMPLE_FLUSH_S``), oldest first within each topic."""

    op: Literal["batch"] = "batch"
    samples: list[SampleMessage]


class Result(_Message):
    """The answer to a request."""

    op: Literal["result"] = "result"
    id: MessageId
    data: Any


class ErrorMessage(_Message):
    """A refused request: ``id`` is ``null`` when the request had none readable."""

    op: Literal["error"] = "error"
    id: MessageId | None
    code: ErrorCode
    message: str
    raised: dict[str, Any] | None = Field(
        None,
        description="A refusal of the daemon's Robot: its exception's class (type) and, "
        "for an OutOfRangeError, the value and its range (name, value, low, high, unit); "
        "for a SourceOverriddenError, source, active and lapses_in_s.",
    )


ServerMessage = Annotated[
    Hello | SampleMessage | BatchMessage | Result | ErrorMessage | LeaseMessage,
    Field(discriminator="op"),
]

_CLIENT: TypeAdapter[Subscribe | Unsubscribe | Call] = TypeAdapter(ClientMessage)
_SERVER: TypeAdapter[
    Hello | SampleMessage | BatchMessage | Result | ErrorMessage | LeaseMessage
] = TypeAdapter(ServerMessage)
_SAMPLES: dict[type[Any], TypeAdapter[Any]] = {
    cls: TypeAdapter(cls) for cls in dict.fromkeys(spec.sample_type for spec in STREAMS.values())
}
_STATS: TypeAdapter[RobotStats] = TypeAdapter(RobotStats)
_MOTION: TypeAdapter[MotionResult] = TypeAdapter(MotionResult)


class RequestError(Exception):
    """A client message that cannot be served: the ``error`` to send back."""

    def __init__(
        self,
        code: ErrorCode,
        message: str,
        id: int | str | None = None,
        *,
        raised: OhmniError | None = None,
    ) -> None:
        # What the client sent may be quoted (a key, a value): as UTF-8 text, and short.
        message = message.encode("utf-8", "backslashreplace").decode("utf-8")
        if len(message) > _MAX_ERROR_CHARS:
            message = f"{message[: _MAX_ERROR_CHARS - 1]}…"
        super().__init__(message)
        self.code: ErrorCode = code
        self.message = message
        self.id = id
        self.raised = None if raised is None else _raised_json(raised)

    def reply(self) -> ErrorMessage:
        """The ``error`` message for the client."""
        return ErrorMessage(id=self.id, code=self.code, message=self.message, raised=self.raised)


#: The Robot's refusals a client raises as the Robot did (the class: the message alone).
_RAISED: Final[dict[str, type[OhmniError]]] = {
    cls.__name__: cls
    for cls in (
        InvalidArgumentError,
        StateError,
        ConfigError,
        RobotClosedError,
        TransportError,  # the daemon's robot cannot open a port (connect)
    )
}


def raised_error(raised: dict[str, Any] | None, message: str) -> OhmniError | None:
    """The daemon's Robot's refusal (``error.raised``, with its ``message``) as the exception
    the Robot raised — the same class, the same message — or ``None`` when it is not one a
    client can make again."""
    if raised is None:
        return None
    kind = raised.get("type")
    if kind == "OutOfRangeError":
        try:
            return OutOfRangeError(
                str(raised["name"]),
                raised["value"],
                raised["low"],
                raised["high"],
                str(raised.get("unit") or ""),
            )
        except (KeyError, TypeError):
            return None
    if kind == "SourceOverriddenError":
        try:
            lapses = raised.get("lapses_in_s")
            return SourceOverriddenError(
                message,
                source=str(raised["source"]),
                active=str(raised["active"]),
                lapses_in_s=None if lapses is None else float(lapses),
            )
        except (KeyError, TypeError, ValueError):
            return None
    if kind in ("PositionError", "PositionTimeoutError"):
        position = PositionTimeoutError if kind == "PositionTimeoutError" else PositionError
        try:
            return position(
                message, sid=int(raised["sid"]), target_raw=int(raised["target_raw"]), sample=None
            )
        except (KeyError, TypeError, ValueError):
            return None
    cls = _RAISED.get(str(kind))
    return None if cls is None else cls(message)


def _raised_json(exc: OhmniError) -> dict[str, Any]:
    raised: dict[str, Any] = {"type": type(exc).__name__}
    if isinstance(exc, OutOfRangeError):
        value = exc.value
        if not isinstance(value, int | float | str) or isinstance(value, bool):
            value = repr(value)
        raised.update(name=exc.name, value=value, low=exc.low, high=exc.high, unit=exc.unit)
    elif isinstance(exc, PositionError):
        raised.update(sid=exc.sid, target_raw=exc.target_raw)
    elif isinstance(exc, SourceOverriddenError):
        raised.update(source=exc.source, active=exc.active, lapses_in_s=exc.lapses_in_s)
    return raised


def parse_client_message(frame: str | bytes) -> Subscribe | Unsubscribe | Call:
    """One client frame as a message.

    Raises:
        RequestError: Not JSON, not an object, an unknown ``op``, ``method`` or ``topic``,
            or a field missing or wrong; the message names the value and what is allowed.
    """
    try:
        raw = json.loads(frame)
    except (ValueError, UnicodeDecodeError) as exc:
        raise RequestError("bad_json", f"not JSON: {exc}") from None
    except RecursionError:
        # Python's JSON reader refuses nesting deeper than the interpreter's recursion
        # limit (about 1,000): no message nests more than three levels.
        raise RequestError("bad_json", "JSON nested too deep: a message nests 3 levels") from None
    if not isinstance(raw, dict):
        raise RequestError("bad_json", f"a message is a JSON object, not {type(raw).__name__}")
    ident = _readable_id(raw.get("id"))
    op = raw.get("op")
    if op not in CLIENT_OPS:
        raise RequestError(
            "unknown_op", f"unknown op {_shown(op)}: allowed {_listed(CLIENT_OPS)}", ident
        )
    method = raw.get("method")
    if op == "call" and method not in METHODS:
        raise RequestError(
            "unknown_method", f"unknown method {_shown(method)}: allowed {_listed(METHODS)}", ident
        )
    topic = raw.get("topic") if op != "call" else _args(raw).get("topic")
    if isinstance(topic, str) and topic not in STREAM_NAMES:
        raise RequestError(
            "unknown_topic",
            f"unknown topic {_shown(topic)}: the topics are {_listed(STREAM_NAMES)}",
            ident,
        )
    try:
        message = _CLIENT.validate_python(raw)
    except ValidationError as exc:
        raise RequestError("bad_message", f"bad {op}: {_problems(exc, op)}", ident) from None
    if isinstance(message, Call):
        call_args(message)  # the arguments are checked here, at the edge, too
    return message


def call_args(call: Call) -> _Request:
    """``call``'s arguments as its method's model (:data:`METHOD_SPECS`).

    Raises:
        RequestError: An argument missing, extra or of the wrong type (``bad_message``);
            the message names it, the value and what is allowed.
    """
    model = METHOD_SPECS[call.method].args
    try:
        return model.model_validate(call.args)
    except ValidationError as exc:
        raise RequestError(
            "bad_message", f"bad {call.method} args: {_problems(exc, 'args', 'args')}", call.id
        ) from None


def parse_server_message(
    frame: str | bytes,
) -> Hello | SampleMessage | BatchMessage | Result | ErrorMessage | LeaseMessage:
    """One server frame as a message (the client's edge).

    Raises:
        ValueError: Not a valid server message (a pydantic ``ValidationError``).
    """
    return _SERVER.validate_json(frame)


def encode(message: BaseModel) -> str:
    """A message as its JSON frame."""
    return message.model_dump_json()


def sample_json(sample: Sample) -> dict[str, Any]:
    """A sample as JSON-ready data: enums by value, tuples as lists."""
    data: dict[str, Any] = _SAMPLES[type(sample)].dump_python(sample, mode="json")
    return data


def sample_from_json(topic: str, data: Any) -> Sample:
    """The sample dataclass of ``topic`` rebuilt from :func:`sample_json`'s data.

    Raises:
        KeyError: No such topic.
        ValueError: The data does not fit the topic's sample (a ``ValidationError``).
    """
    sample: Sample = _SAMPLES[STREAMS[topic].sample_type].validate_python(data)
    return sample


def result_json(method: str, value: Any) -> Any:
    """What the Robot method of ``method`` (:attr:`MethodSpec.call`) returned, as the data
    of its ``result``."""
    encode = _RESULTS.get(method)
    return value if encode is None else encode(value)


def pid_from_json(data: Any) -> PidGains:
    """``get_pid``'s data as :class:`PidGains`."""
    return PidGains(**data)


def pid_state_json(left: PidGains, right: PidGains, enabled: tuple[bool, bool]) -> dict[str, Any]:
    """``pid_state``'s data: each wheel's gains, and whether each wheel's PID runs."""
    return {
        "left": _gains_json(left),
        "right": _gains_json(right),
        "enabled": {"left": enabled[0], "right": enabled[1]},
    }


def pid_state_from_json(data: Any) -> tuple[PidGains, PidGains, tuple[bool, bool]]:
    """``pid_state``'s data as (left gains, right gains, (left on, right on))."""
    enabled = data["enabled"]
    return (
        PidGains(**data["left"]),
        PidGains(**data["right"]),
        (bool(enabled["left"]), bool(enabled["right"])),
    )


def servo_status_json(status: ServoStatus) -> dict[str, int]:
    """``servo_status``'s and ``servo_clear``'s data: the two status bytes."""
    return {"error": int(status.error), "detail": int(status.detail)}


def servo_status_from_json(data: Any) -> ServoStatus:
    """``servo_status``'s and ``servo_clear``'s data as a :class:`ServoStatus`."""
    return ServoStatus(StatusError(data["error"]), StatusDetail(data["detail"]))


def schedule_from_json(data: Any) -> list[tuple[str, float, float, float]]:
    """``schedule``'s data as :meth:`Robot.schedule`'s rows."""
    return [(str(name), float(hz), float(phase), float(cost)) for name, hz, phase, cost in data]


def info_from_json(data: Any) -> dict[str, Any]:
    """``info``'s data as :meth:`Robot.info`'s (servo models by int id: JSON keys are text)."""
    info: dict[str, Any] = dict(data)
    info["servos"] = {int(sid): model for sid, model in info.get("servos", {}).items()}
    return info


def goal_json(outcome: MotionResult | MotionError) -> dict[str, Any]:
    """A motion goal's end as its ``result``'s data: what it did, and the error when it
    ended short of its goal (its class and fields)."""
    if isinstance(outcome, MotionResult):
        return {"result": _MOTION.dump_python(outcome, mode="json"), "error": None}
    error: dict[str, Any] = {"type": type(outcome).__name__, "message": str(outcome)}
    if isinstance(outcome, MotionPreemptedError):
        error["by"] = outcome.by
        error["source"] = outcome.source
    elif isinstance(outcome, MotionTimeoutError):
        error["timeout_s"] = outcome.timeout_s
    elif isinstance(outcome, WheelStallError):
        error["wheels"] = list(outcome.wheels)
        error["pwm"] = list(outcome.pwm)
        error["stalled_s"] = _finite_or_none(outcome.stalled_s)
    elif isinstance(outcome, WheelSlipError):
        error["wheel"] = outcome.wheel
        error["setpoint_mps"] = _finite_or_none(outcome.setpoint_mps)
        error["measured_mps"] = _finite_or_none(outcome.measured_mps)
        error["slipped_s"] = _finite_or_none(outcome.slipped_s)
    return {"result": _MOTION.dump_python(outcome.result, mode="json"), "error": error}


def goal_from_json(data: Any) -> MotionResult:
    """A motion goal's ``result`` data as what the goal returned.

    Raises:
        MotionError: The goal ended short of its goal: the same class as the daemon's
            Robot raised (:class:`MotionPreemptedError` …), with its fields and result.
        ValueError: The data is not a goal's result.
    """
    result = _MOTION.validate_python(data["result"])
    error = data.get("error")
    if error is None:
        return result
    kind, message = error.get("type"), str(error.get("message", ""))
    if kind == "MotionPreemptedError":
        source = error.get("source")
        raise MotionPreemptedError(
            message,
            result=result,
            by=str(error.get("by")),
            source=None if source is None else str(source),
        )
    if kind == "MotionTimeoutError":
        raise MotionTimeoutError(message, result=result, timeout_s=float(error["timeout_s"]))
    if kind == "WheelStallError":
        raise WheelStallError(
            message,
            result=result,
            wheels=tuple(error.get("wheels", ())),
            pwm=tuple(int(p) for p in error.get("pwm", ())),
            stalled_s=_float_or_nan(error.get("stalled_s")),
        )
    if kind == "WheelSlipError":
        raise WheelSlipError(
            message,
            result=result,
            wheel=str(error.get("wheel")),
            setpoint_mps=_float_or_nan(error.get("setpoint_mps")),
            measured_mps=_float_or_nan(error.get("measured_mps")),
            slipped_s=_float_or_nan(error.get("slipped_s")),
        )
    if kind == "MotionAbortedError":
        raise MotionAbortedError(message, result=result)
    raise MotionError(message, result=result)


def _finite_or_none(value: float) -> float | None:
    """A float as JSON carries it: NaN (not known) as ``null``."""
    return None if math.isnan(value) else value


def _float_or_nan(value: Any) -> float:
    """A JSON number back as a float; ``null`` (not known) as NaN."""
    return math.nan if value is None else float(value)


def stats_json(stats: RobotStats) -> dict[str, Any]:
    """:meth:`Robot.stats` as JSON-ready data."""
    data: dict[str, Any] = _STATS.dump_python(stats, mode="json")
    return data


def stats_from_json(data: Any) -> RobotStats:
    """:class:`RobotStats` rebuilt from :func:`stats_json`'s data."""
    return _STATS.validate_python(data)


def json_schema() -> dict[str, Any]:
    """The JSON Schema of every message, and of each topic's sample (``samples``)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"ohmni_tb daemon protocol {PROTOCOL_VERSION}",
        "protocol": PROTOCOL_VERSION,
        "client_to_server": _CLIENT.json_schema(),
        "server_to_client": _SERVER.json_schema(),
        "samples": {
            topic: _SAMPLES[spec.sample_type].json_schema() for topic, spec in STREAMS.items()
        },
        "methods": {
            name: {
                "lease": spec.lease,
                "args": spec.args.model_json_schema(),
                "result": spec.result,
            }
            for name, spec in METHOD_SPECS.items()
        },
        "results": {
            "stats": _STATS.json_schema(),
            "subscribe": "{topic, max_hz, every, queue, hz}",
            "unsubscribe": "{topic}",
        },
    }


def write_schema(path: str | os.PathLike[str] = "docs/daemon-schema.json") -> None:
    """Write :func:`json_schema` to ``path`` (``docs/daemon-schema.json``), as the repo keeps it."""
    Path(path).write_text(schema_text(), encoding="utf-8")


def schema_text() -> str:
    """:func:`json_schema` as the checked-in file's text."""
    return json.dumps(json_schema(), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


_ID: TypeAdapter[int | str] = TypeAdapter(MessageId)


def _gains_json(gains: PidGains) -> dict[str, float]:
    return {name: getattr(gains, name) for name in ("kp", "ki", "kd", "kff", "ff_offset")}


#: The results that are not JSON as the Robot returns them.
_RESULTS: dict[str, Any] = {
    "latest": lambda sample: None if sample is None else sample_json(sample),
    "move": lambda sample: None if sample is None else sample_json(sample),
    "schedule": lambda rows: [list(row) for row in rows],
    "get_pid": _gains_json,
    "drive": lambda limited: {
        "requested": [limited.requested.linear_mps, limited.requested.angular_radps],
        "twist": [limited.twist.linear_mps, limited.twist.angular_radps],
        "scale": limited.scale,
    },
    "drive_wheels": lambda wheels: {"left_mps": wheels.left_mps, "right_mps": wheels.right_mps},
    "drive_pwm": list,
    "servo_status": servo_status_json,
    "servo_clear": servo_status_json,
    "drive_distance": goal_json,
    "rotate": goal_json,
    "go_to": goal_json,
}


def _readable_id(value: object) -> int | str | None:
    """``value`` if it is a valid ``id`` to send back, else ``None`` (a negative number,
    a string too long or not UTF-8 text, a bool …)."""
    if isinstance(value, bool) or not isinstance(value, int | str):
        return None
    try:
        return _ID.validate_python(value)
    except ValidationError:
        return None


def _args(raw: dict[str, Any]) -> dict[str, Any]:
    args = raw.get("args")
    return args if isinstance(args, dict) else {}


def _shown(value: object) -> str:
    try:
        text = json.dumps(value) if not isinstance(value, str) else repr(value)
    except (RecursionError, ValueError, TypeError):
        text = f"a {type(value).__name__} nested too deep"  # deeper than JSON can show
    return text if len(text) <= 40 else f"{text[:30]}…({len(text)} chars)"


def _listed(names: tuple[str, ...]) -> str:
    return ", ".join(names)


def _problems(exc: ValidationError, op: str, whole: str = "message") -> str:
    """pydantic's errors, one short clause each: where (``whole`` for the object itself),
    what, and the value given."""
    parts = []
    for error in exc.errors(include_url=False):
        loc = error["loc"][1:] if error["loc"][:1] == (op,) else error["loc"]
        where = ".".join(str(p) for p in loc)
        if error["type"] == "value_error":
            # Our own validator's message, which names the value already.
            parts.append(f"{where}: {error['msg'].removeprefix('Value error, ')}")
            continue
        given = "" if error["type"] == "missing" else f" (got {_shown(error.get('input'))})"
        parts.append(f"{where or whole}: {error['msg']}{given}")
    return "; ".join(parts)
