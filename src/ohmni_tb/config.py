"""Robot settings: one frozen, validated :class:`RobotConfig` from arguments, env and TOML.

Where a setting comes from, highest first::

    keyword arguments   RobotConfig.load(port="sim://")  or  RobotConfig(port="sim://")
    environment         OHMNI_PORT=sim://  OHMNI_WATCHDOG_S=0.3   (names in any case)
    one TOML file       only RobotConfig.load() reads one, the first of:
                          load(config_file)                 must exist
                          $OHMNI_CONFIG                     must exist
                          ./ohmni.toml                      if it exists
                          $XDG_CONFIG_HOME/ohmni/ohmni.toml if it exists (~/.config/...)
    defaults            ohmni_tb.control.defaults and ohmni_tb.protocol

The TOML file holds the settings at top level, or in a ``[robot]`` table::

    port = "/dev/ttyUSB0"
    watchdog_s = 0.3
    ext_servo_ids = [11, 12]

Every bad value is a :class:`~ohmni_tb.errors.ConfigError` (a ``ValueError``), one line
per problem, naming the setting, the value, what is allowed and where it came from::

    watchdog_s=-1.0 is out of range: allowed 0 (off) or 0.05..60 s (from OHMNI_WATCHDOG_S)

pydantic stays at this edge: the Robot asks the config for the control layer's own
frozen objects (:meth:`RobotConfig.drive`, :meth:`RobotConfig.pid_gains`, ...).
"""

from __future__ import annotations

import difflib
import json
import logging
import math
import os
import tomllib
from collections.abc import Mapping
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, Self, cast

from pydantic import (
    Field,
    SecretStr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError
from pydantic_settings import (
    BaseSettings,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)
from pydantic_settings.exceptions import SettingsError

from ohmni_tb._checks import mqtt_address, show
from ohmni_tb.control.defaults import (
    CONTROL_HZ_RANGE,
    DEFAULT_BASE_FRAME,
    DEFAULT_MAX_ANGULAR_RADPS,
    DEFAULT_MAX_LINEAR_MPS,
    DEFAULT_ODOM_FRAME,
    DEFAULT_TICKS_PER_REV,
    DEFAULT_WHEEL_RADIUS_M,
    DEFAULT_WHEEL_SEPARATION_M,
    PID_RATE_HZ,
    WHEEL_GAIN_RANGES,
)
from ohmni_tb.control.encoder import EncoderConfig
from ohmni_tb.control.kinematics import DiffDrive, VelocityLimits
from ohmni_tb.control.limiter import AccelLimits, TwistLimiter
from ohmni_tb.control.pid import PidGains
from ohmni_tb.control.sources import (
    DEFAULT_SOURCES,
    REQUIRED_SOURCES,
    TIMEOUT_RANGE_S,
    CommandSource,
    format_sources,
    parse_sources,
)
from ohmni_tb.errors import ConfigError, OhmniError
from ohmni_tb.herkulex.registers import RAM as SERVO_RAM
from ohmni_tb.protocol.connection import DEFAULT_TIMEOUT_S
from ohmni_tb.protocol.core import BatteryLayout
from ohmni_tb.protocol.devices import DEFAULT_EXT_SERVO_IDS, NECK_RAW_RANGE, DeviceId
from ohmni_tb.protocol.messages import MAX_READ_LENGTH
from ohmni_tb.protocol.profile import (
    PROFILE_SETTINGS,
    BusProfile,
    check_ext_servo_ids,
    parse_ext_servo_ids,
)
from ohmni_tb.protocol.worm_neck import WORM_MAX, WORM_MIN

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

__all__ = [
    "CONFIG_ENV",
    "CONFIG_FILE_NAME",
    "ENV_PREFIX",
    "RobotConfig",
    "config_paths",
    "user_config_dir",
]

#: Prefix of the environment variables that set a field (``OHMNI_PORT``), any case.
ENV_PREFIX = "OHMNI_"
#: Environment variable naming the TOML file to load (below an explicit ``config_file``).
CONFIG_ENV = "OHMNI_CONFIG"
#: Name of the TOML file looked for in the working directory and the user's config dir.
CONFIG_FILE_NAME = "ohmni.toml"

#: The other ``OHMNI_*`` variables the package reads, exactly so spelled: the config file,
#: and where ``ohmni`` finds the daemon and its token (ohmni_tb.cli.common.DAEMON_URL_ENV,
#: ohmni_tb.daemon.auth.TOKEN_ENV). Any other ``OHMNI_*`` name is warned about once.
_OTHER_ENV = frozenset({CONFIG_ENV, "OHMNI_DAEMON_URL", "OHMNI_DAEMON_TOKEN"})

_log = logging.getLogger(__name__)

#: Highest bus id a HerkuleX servo may have (0xFE is the broadcast id).
_MAX_SERVO_ID = 253
#: The vendor API addresses two external servos (``servo_ext1``, ``servo_ext2``).
_MAX_EXT_SERVOS = 2
#: Ids of the robot's own boards: an external servo on one of them would answer for it.
_BOARD_IDS = {d.value: d.name.lower() for d in DeviceId if d is not DeviceId.BROADCAST}
#: HerkuleX positions are 10 bits.
_RAW_MAX = 1023
#: Event-loop delay the bus allows on top of the adapter's latency timer: DEFAULT_TIMEOUT_S
#: is the default 16 ms latency timer plus this.
_LOOP_MARGIN_S = 0.009
#: What a frame id may be: a ROS frame name has no spaces.
_FRAME_ALLOWED = "a non-empty name without spaces"
#: The PWM limit of the drive boards, for the PID descriptions.
_PWM = "PWM -1000..1000"
#: What ``mqtt_url`` may be.
_MQTT_URL_ALLOWED = "empty, mqtt://HOST[:PORT] or mqtts://HOST[:PORT], without a user or path"
#: What ``robot_id`` may be: one MQTT topic level that is also a Home Assistant node id.
_ROBOT_ID_ALLOWED = "empty, or 1..64 letters, digits, - and _"
_ROBOT_ID_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_")
_MAX_ROBOT_ID = 64
#: What the discovery prefix may be: MQTT topic levels without wildcards.
_TOPIC_ALLOWED = "topic levels separated by /, none empty, without + # or spaces"
#: What ``mqtt_rates`` may be.
_RATES_ALLOWED = "none, or NAME=HZ pairs separated by commas, each rate >0..100 Hz"
#: The fastest a stream is published to the broker (no stream is faster).
_MAX_MQTT_HZ = 100.0


def config_paths() -> list[Path]:
    """The TOML files :meth:`RobotConfig.load` looks for, in order; it reads the first found.

    ``$OHMNI_CONFIG`` (when set) comes first and must exist; the others are read only if
    they exist. An explicit ``config_file`` argument comes before all of them.
    """
    named = os.environ.get(CONFIG_ENV)
    return ([Path(named).expanduser()] if named else []) + _default_paths()


def _num(value: float) -> str:
    """A range bound or default as text: ``60`` not ``60.0``, ``1000000`` not ``1e+06``."""
    if isinstance(value, int) or value.is_integer():
        return str(int(value))
    return format(value, ".10g")


def _setting(
    default: float,
    low: float,
    high: float,
    unit: str,
    description: str,
    *,
    above: bool = False,
    off: str = "",
) -> Any:
    """A range-checked number: ``low..high``, ``above``: low excluded; ``off``: 0 allowed too.

    The allowed range is written into the description, and kept for error messages.
    """
    span = f"{'>' if above else ''}{_num(low)}..{_num(high)}"
    allowed = (f"0 ({off}) or {span}" if off else span) + (f" {unit}" if unit else "")
    return Field(
        default,
        description=f"{description} Allowed: {allowed}.",
        gt=low if above else None,
        ge=None if above else (0 if off else low),
        le=high,
        json_schema_extra={"allowed": allowed, "off_below": low if off else None},
    )


def _servo_default(name: str) -> int:
    """A HerkuleX RAM register's factory value, from the register map."""
    default = SERVO_RAM[name].default
    assert default is not None, name  # the settings the neck gets all have one
    return default


def _servo_range(name: str) -> tuple[int, int]:
    """The values a HerkuleX RAM register takes, from the register map."""
    return SERVO_RAM[name].low, SERVO_RAM[name].high


class RobotConfig(BaseSettings):
    """Every setting of a Robot: connection, geometry, limits, PID, safety, neck, rates.

    Frozen and validated: a bad value raises :class:`~ohmni_tb.errors.ConfigError`
    naming the setting, the value, the allowed range and where the value came from.

    ``RobotConfig(**settings)`` reads the arguments and ``OHMNI_*`` environment variables
    only; :meth:`load` also reads a TOML file. :meth:`describe` lists every setting.

    Example:
        >>> config = RobotConfig(port="sim://", watchdog_s=0.3)
        >>> config.drive().wheel_separation_m
        0.33
    """

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        case_sensitive=False,
        frozen=True,
        extra="forbid",
        allow_inf_nan=False,
        validate_default=True,
    )

    # Connection.
    port: str = Field(
        default="auto",
        min_length=1,
        description="Serial port of the robot's bus: a device path, a transport URL "
        "(serial:///dev/ttyUSB0, sim://), or auto: the FTDI adapter with USB id 0403:6015, "
        "else /dev/usb/tty1-2.1 (on the robot).",
        json_schema_extra={"allowed": "a device path or transport URL"},
    )
    baudrate: int = _setting(115200, 1200, 4_000_000, "baud", "Bus speed, baud.")
    usb_latency_ms: int = _setting(
        16,
        0,
        32,
        "ms",
        "Latency timer of the USB serial adapter, ms: it may hold a reply this long, so "
        "the bus waits this much longer for replies.",
    )
    reconnect: bool = Field(default=True, description="Reopen the port when the link is lost.")
    reconnect_max_backoff_s: float = _setting(
        5.0, 0.01, 60, "s", "Longest wait between two attempts to reopen a lost link, s."
    )

    # Geometry.
    wheel_radius_m: float = _setting(
        DEFAULT_WHEEL_RADIUS_M, 0.01, 1, "m", "Wheel radius, m (robots measure 0.07525)."
    )
    wheel_separation_m: float = _setting(
        DEFAULT_WHEEL_SEPARATION_M,
        0.05,
        2,
        "m",
        "Distance between the wheels' contact points, m (robots measure 0.330-0.332).",
    )
    ticks_per_rev: float = _setting(
        DEFAULT_TICKS_PER_REV,
        1,
        1e7,
        "ticks",
        "Encoder ticks per wheel turn: 16384 * 30/11 (inferred).",
    )

    # Limits.
    max_linear_mps: float = _setting(
        DEFAULT_MAX_LINEAR_MPS,
        0,
        5,
        "m/s",
        "Largest forward or backward speed, m/s; faster commands are scaled down, keeping "
        "their curvature.",
        above=True,
    )
    max_angular_radps: float = _setting(
        DEFAULT_MAX_ANGULAR_RADPS, 0, 20, "rad/s", "Largest yaw rate either way, rad/s.", above=True
    )
    max_wheel_mps: float = _setting(
        DEFAULT_MAX_LINEAR_MPS,
        0,
        5,
        "m/s",
        "Largest rim speed of either wheel, m/s (a fast turn while driving fast asks more "
        "of the outer wheel).",
        above=True,
    )
    linear_accel_mps2: float = _setting(
        0.5, 0, 100, "m/s²", "Linear acceleration limit while speeding up, m/s².", above=True
    )
    linear_decel_mps2: float = _setting(
        1.0, 0, 100, "m/s²", "Linear deceleration limit while braking, m/s².", above=True
    )
    angular_accel_radps2: float = _setting(
        2.0, 0, 100, "rad/s²", "Yaw acceleration limit while speeding up, rad/s².", above=True
    )
    angular_decel_radps2: float = _setting(
        4.0, 0, 100, "rad/s²", "Yaw deceleration limit while braking, rad/s².", above=True
    )
    linear_jerk_mps3: float = _setting(
        0.0,
        1,
        1000,
        "m/s³",
        "Linear jerk limit: how fast the acceleration may change, m/s³, so a drive "
        "command starts and ends smoothly; a stop is not held back by it.",
        off="off",
    )
    angular_jerk_radps3: float = _setting(
        0.0,
        1,
        1000,
        "rad/s³",
        "Yaw jerk limit: how fast the yaw acceleration may change, rad/s³; a stop is not "
        "held back by it.",
        off="off",
    )

    # Wheel PID: the loop's output is the drive board's PWM. Tuned on the simulator's
    # motor model (no-load 1 m/s at PWM 1000, 6 % dead band): 1-3 % overshoot on a
    # 0.5 m/s ramp; the speed estimate's 0.1 s window makes a larger ki wind up.
    pid_kp: float = _setting(
        600.0,
        *WHEEL_GAIN_RANGES["kp"],
        "PWM/(m/s)",
        f"Wheel PID proportional gain, PWM per m/s of error ({_PWM}).",
    )
    pid_ki: float = _setting(
        300.0,
        *WHEEL_GAIN_RANGES["ki"],
        "PWM/m",
        "Wheel PID integral gain, PWM per m/s of error and second.",
    )
    pid_kd: float = _setting(
        0.0,
        *WHEEL_GAIN_RANGES["kd"],
        "PWM/(m/s²)",
        "Wheel PID derivative gain on the measured speed, PWM per m/s².",
    )
    pid_kff: float = _setting(
        940.0,
        *WHEEL_GAIN_RANGES["kff"],
        "PWM/(m/s)",
        "Wheel velocity feed-forward, PWM per m/s of setpoint.",
    )
    pid_ff_offset: float = _setting(
        60.0,
        *WHEEL_GAIN_RANGES["ff_offset"],
        "PWM",
        "PWM added in the direction of a non-zero wheel setpoint, to overcome the motor's "
        "dead band.",
    )
    controllers: bool = Field(
        default=True,
        description="Run the wheel speed PIDs; off, only open-loop drive_pwm() moves the wheels.",
    )

    # Safety.
    watchdog_s: float = _setting(
        0.5,
        0.05,
        60,
        "s",
        "Motion watchdog: the wheels are stopped this long after the last drive command, s.",
        off="off",
    )
    command_sources: Annotated[tuple[str, ...], NoDecode] = Field(
        default=format_sources(DEFAULT_SOURCES),
        description="The command sources, highest priority first, each name:seconds: the "
        "highest source that commanded within its seconds drives, a lower one's drive "
        "commands are refused meanwhile (docs/robot.md, Command sources). From the "
        "environment or TOML: a list, or 'safety:0.5,local:0.5,remote:0.5,autonomy:1'. "
        f"Allowed: up to 16 sources, names of lower case letters, digits and _, each "
        f"{TIMEOUT_RANGE_S[0]:g}..{TIMEOUT_RANGE_S[1]:g} s; {', '.join(REQUIRED_SOURCES)} "
        "among them.",
        json_schema_extra={"allowed": "name:seconds entries, highest priority first"},
    )
    stale_ticks: int = _setting(
        5,
        1,
        100,
        "ticks",
        "Control ticks without both wheel counts before the wheels are stopped.",
    )
    stall_s: float = _setting(
        0.5,
        0.1,
        10,
        "s",
        "Stall guard: a wheel driven but not turning this long is a stall (fault "
        "wheel_stall:<sid>): the wheels are stopped and a motion goal ends, s.",
        off="off",
    )
    slip_s: float = _setting(
        1.0,
        0.5,
        10,
        "s",
        "Slip guard: the wheels off the commanded curve this long (one wheel slipping or "
        "lifted) is a slip (fault wheel_slip:<sid>): a motion goal ends, s.",
        off="off",
    )
    implausible_mps: float = _setting(
        3.0,
        0.5,
        50,
        "m/s",
        "A wheel count jump implying a faster wheel than this is rejected, m/s.",
    )
    thermal_guard: bool = Field(
        default=True,
        description="Watch the neck servo's temperature and status; rest, then free it.",
    )
    thermal_limit_raw: int = _setting(
        200,
        1,
        254,
        "raw",
        "Raw HerkuleX temperature at which a servo is rested, then freed.",
    )
    neck_hold_s: float = _setting(
        600.0,
        1,
        86400,
        "s",
        "Neck torque is held this long after the last neck command, then the neck is "
        "rested and freed, s.",
        off="never",
    )
    on_exit_neck: Literal["rest", "free", "keep"] = Field(
        default="free",
        description="The neck when the Robot closes: rest (move to the rest position), "
        "free (torque off) or keep (leave it as it is).",
    )
    stop_timeout_s: float = _setting(
        1.0, 0.05, 10, "s", "Time allowed to confirm the wheel stop on exit, s."
    )

    # Neck and servos.
    neck: Literal["auto", "herkulex", "worm", "none"] = Field(
        default="auto",
        description="The neck fitted: auto (probe the bus), herkulex (servo neck_id), worm "
        "(the worm-gear neck board) or none.",
    )
    neck_id: int = _setting(3, 0, _MAX_SERVO_ID, "", "Bus id of the HerkuleX neck servo.")
    neck_min_raw: int = _setting(
        NECK_RAW_RANGE[0],
        0,
        _RAW_MAX,
        "raw",
        "Lowest HerkuleX neck position, raw; below neck_max_raw. Also written to the "
        "servo's own min_position (RAM 20), so the servo holds it too (tb_control "
        "~servo_neck_min_pos).",
    )
    neck_max_raw: int = _setting(
        NECK_RAW_RANGE[1],
        0,
        _RAW_MAX,
        "raw",
        "Highest HerkuleX neck position, raw. Also written to the servo's own max_position "
        "(RAM 22) (tb_control ~servo_neck_max_pos).",
    )
    neck_rest_raw: int = _setting(
        465,
        0,
        _RAW_MAX,
        "raw",
        "Rest position of the HerkuleX neck, raw; within neck_min_raw..neck_max_raw.",
    )
    neck_zero_offset_raw: int = _setting(
        0,
        -512,
        511,
        "raw",
        "Offset of the level-head position from the neck servo's nominal zero, raw.",
    )
    # The neck servo's own settings: written to its RAM when the Robot opens, when the
    # neck is found late or comes back after a silence (a reboot, a power cut, a lost
    # link), and read back; tb_control's ~servo_neck_* parameters.
    neck_kp: int = _setting(
        _servo_default("position_kp"),
        *_servo_range("position_kp"),
        "",
        "Position P gain of the HerkuleX neck servo, written to its position_kp (RAM 24) "
        "(tb_control ~servo_neck_kp).",
    )
    neck_ki: int = _setting(
        _servo_default("position_ki"),
        *_servo_range("position_ki"),
        "",
        "Position I gain of the neck servo, written to its position_ki (RAM 28) "
        "(tb_control ~servo_neck_ki).",
    )
    neck_kd: int = _setting(
        _servo_default("position_kd"),
        *_servo_range("position_kd"),
        "",
        "Position D gain of the neck servo, written to its position_kd (RAM 26) "
        "(tb_control ~servo_neck_kd).",
    )
    neck_min_voltage_raw: int = _setting(
        _servo_default("min_voltage"),
        *_servo_range("min_voltage"),
        "raw",
        "Lowest supply the neck servo accepts, 0.074 V a count (91 = 6.7 V), written to "
        "its min_voltage (RAM 6); below neck_max_voltage_raw. Outside the two the servo "
        "reports an input-voltage error and releases its torque (tb_control "
        "~servo_neck_v_min).",
    )
    neck_max_voltage_raw: int = _setting(
        _servo_default("max_voltage"),
        *_servo_range("max_voltage"),
        "raw",
        "Highest supply the neck servo accepts, 0.074 V a count (137 = 10.1 V), written "
        "to its max_voltage (RAM 7) (tb_control ~servo_neck_v_max).",
    )
    neck_overload_pwm: int = _setting(
        _servo_default("overload_pwm_threshold"),
        *_servo_range("overload_pwm_threshold"),
        "",
        "PWM above which the neck servo counts an overload, written to its "
        "overload_pwm_threshold (RAM 18) (tb_control ~servo_neck_overload_pwm).",
    )
    neck_max_pwm: int = _setting(
        _servo_default("max_pwm"),
        *_servo_range("max_pwm"),
        "",
        "Largest PWM the neck servo drives its motor with (1023 = full), written to its "
        "max_pwm (RAM 16) (tb_control ~servo_neck_max_pwm).",
    )
    neck_use_eeprom: bool = Field(
        default=False,
        description="Write the neck servo's settings (neck_min_raw, neck_max_raw, neck_kp, "
        "neck_ki, neck_kd, the voltages and PWMs) to its EEP too, so it powers up with "
        "them; EEP is written only where it differs (tb_control ~servo_neck_use_eeprom). "
        "Off: RAM only.",
    )
    worm_min_raw: int = _setting(
        WORM_MIN,
        WORM_MIN,
        WORM_MAX,
        "raw",
        "Lowest worm neck target (up), raw; below worm_max_raw. Beyond the hardware range "
        "the motor stalls until power-cycled.",
    )
    worm_max_raw: int = _setting(
        WORM_MAX, WORM_MIN, WORM_MAX, "raw", "Highest worm neck target (down), raw."
    )
    ext_servo_ids: Annotated[tuple[int, ...], NoDecode] = Field(
        default=DEFAULT_EXT_SERVO_IDS,
        description="Bus ids of the external HerkuleX servos (assumed 11, 12). From the "
        "environment or TOML: a list, '11,12', or '' / 'none'. Allowed: at most "
        f"{_MAX_EXT_SERVOS} ids 0..{_MAX_SERVO_ID}, no repeats, none of the board ids "
        f"{', '.join(map(str, _BOARD_IDS))} nor neck_id.",
        json_schema_extra={"allowed": f"at most {_MAX_EXT_SERVOS} bus ids 0..{_MAX_SERVO_ID}"},
    )

    # The bus profile: what the project assumes of the boards until `ohmni probe` (or a
    # capture) says otherwise. Addresses take decimal or 0x hex (TOML 0xA0, "0xA0").
    wheel_form: Literal["s_jog", "i_jog"] = Field(
        default="s_jog",
        description="Packet of the wheel command (assumed s_jog): one S_JOG or one I_JOG to "
        "broadcast, a tag per drive board. `ohmni probe --allow-motion` finds which moves "
        "the wheels. Allowed: s_jog, i_jog.",
        json_schema_extra={"allowed": "s_jog, i_jog"},
    )
    right_mirrored: bool = Field(
        default=True,
        description="The right drive board counts and is commanded mirrored (forward = left "
        "+, right -), as on the Ohmni.",
    )
    drive_torque_addr: int = _setting(
        52, 0, 255, "", "RAM address of the drive boards' torque control (assumed 52)."
    )
    battery_addr: int = _setting(
        0xA0,
        0,
        255,
        "",
        "RAM address of the core board's battery/dock block (assumed 0xA0 = 160); "
        "`ohmni probe` searches for it.",
    )
    battery_length: int = _setting(
        18,
        BatteryLayout.CELLS.size,
        MAX_READ_LENGTH,
        "bytes",
        "Bytes read from the battery/dock block (assumed 18); at least its layout's size "
        "(tbcore 18, cells 10).",
    )
    battery_layout: Literal["tbcore", "cells"] = Field(
        default="tbcore",
        description="Byte layout of the battery/dock block (assumed tbcore): tbcore = cells "
        "1..5 mV (u16 LE), charging current mA (i16), docked, FET status, status 1..4 (u8); "
        "cells = the five cells alone (current, docked and status then read 0). Allowed: "
        "tbcore, cells.",
        json_schema_extra={"allowed": "tbcore, cells"},
    )
    worm_target_addr: int = _setting(
        0x70, 0, 255, "", "RAM address of the worm neck's int32 target (assumed 0x70 = 112)."
    )
    worm_feedback_addr: int = _setting(
        0x74,
        0,
        255,
        "",
        "RAM address of the worm neck's feedback, position int32 + flags (assumed 0x74 = 116).",
    )

    # Stream rates.
    wheel_hz: float = _setting(
        PID_RATE_HZ,
        *CONTROL_HZ_RANGE,
        "Hz",
        "Rate of the control slot (both wheel counts, odometry, the wheel command), Hz.",
    )
    servo_hz: float = _setting(
        30.0, 0, 50, "Hz", "Rate of the HerkuleX servo status reads, Hz; 0 turns them off."
    )
    core_hz: float = _setting(
        10.0, 0, 20, "Hz", "Rate of the core board status reads, Hz; 0 turns them off."
    )
    new_neck_hz: float = _setting(
        30.0,
        0,
        50,
        "Hz",
        "Rate of the worm neck feedback reads (new_neck), Hz; 0 turns them off.",
    )
    state_hz: float = _setting(1.0, 0.1, 10, "Hz", "Rate of the robot_state stream, Hz.")
    diagnostics_hz: float = _setting(
        1.0,
        0.1,
        10,
        "Hz",
        "Rate of the diagnostics stream (each device's health and the link's), Hz.",
        off="off",
    )
    pid_debug: bool = Field(
        default=False,
        description="Publish the pid_debug stream: both wheels' PID terms every tick.",
    )

    # Frames (tb_control's ~frame_id_odom, ~frame_id_baselink, ~enable_broadcast_transform).
    frame_id_odom: str = Field(
        default=DEFAULT_ODOM_FRAME,
        min_length=1,
        description="Frame of the odometry pose: wheel_odom's frame_id, the parent of the "
        f"transform on Foxglove's /tf. Allowed: {_FRAME_ALLOWED}.",
        json_schema_extra={"allowed": _FRAME_ALLOWED},
    )
    frame_id_baselink: str = Field(
        default=DEFAULT_BASE_FRAME,
        min_length=1,
        description="The robot's body frame: wheel_odom's child_frame_id, the child of the "
        f"transform on Foxglove's /tf; other than frame_id_odom. Allowed: {_FRAME_ALLOWED}.",
        json_schema_extra={"allowed": _FRAME_ALLOWED},
    )
    enable_broadcast_transform: bool = Field(
        default=True,
        description="Publish the odometry as the transform frame_id_odom -> "
        "frame_id_baselink on Foxglove's /tf (live and recorded); off, no /tf.",
    )

    # Fleets: the daemon on an MQTT broker (ohmni serve --mqtt, docs/fleet.md).
    mqtt_url: str = Field(
        default="",
        description="The MQTT broker ohmni serve publishes this robot to and takes commands "
        "from: mqtt://HOST[:PORT] (port 1883), or mqtts://HOST[:PORT] over TLS (8883); "
        f"empty: none. Needs the mqtt extra. Allowed: {_MQTT_URL_ALLOWED}.",
        json_schema_extra={"allowed": _MQTT_URL_ALLOWED},
    )
    robot_id: str = Field(
        default="",
        description="This robot's name on the broker: its topics are ohmni/<robot_id>/..., "
        "and Home Assistant's device is named so; empty: this computer's host name (its "
        f"first label). Allowed: {_ROBOT_ID_ALLOWED}.",
        json_schema_extra={"allowed": _ROBOT_ID_ALLOWED},
    )
    mqtt_username: str = Field(
        default="", description="User name on the broker; empty: connect without one."
    )
    mqtt_password: SecretStr = Field(
        default=cast("SecretStr", ""),
        description="Password on the broker (with mqtt_username). Never shown: ohmni config "
        "and the daemon's clients see **********.",
    )
    mqtt_ca_file: str = Field(
        default="",
        description="CA certificates (PEM file) the broker's certificate is checked against "
        "(mqtts:// only); empty: the system's.",
    )
    mqtt_cert_file: str = Field(
        default="",
        description="Client certificate (PEM file) for a broker that authenticates robots by "
        "certificate (mqtts:// only, with mqtt_key_file).",
    )
    mqtt_key_file: str = Field(
        default="", description="The client certificate's private key (PEM file)."
    )
    mqtt_keepalive_s: int = _setting(
        30,
        1,
        3600,
        "s",
        "MQTT keep-alive, s: a robot that goes silent (its process killed, its network cut) "
        "is announced offline by the broker within 1.5 times this.",
    )
    mqtt_discovery: bool = Field(
        default=False,
        description="Announce the robot to Home Assistant (MQTT discovery): a device with "
        "battery, dock, link and fault sensors, the light ring and the neck.",
    )
    mqtt_discovery_prefix: str = Field(
        default="homeassistant",
        min_length=1,
        description="Home Assistant's discovery prefix (its MQTT integration's setting). "
        f"Allowed: {_TOPIC_ALLOWED}.",
        json_schema_extra={"allowed": _TOPIC_ALLOWED},
    )
    mqtt_rates: str = Field(
        default="wheel_odom=5,tbcore_status=1",
        description="The streams published to ohmni/<robot_id>/stream/<name>, and at most "
        "how often, Hz: NAME=HZ,... (none: no stream). The state topic carries the "
        f"battery, dock and faults regardless. Allowed: {_RATES_ALLOWED}.",
        json_schema_extra={"allowed": _RATES_ALLOWED},
    )
    mqtt_drive: bool = Field(
        default=False,
        description="Let MQTT commands drive the wheels (drive_distance, rotate), through the "
        "daemon's control lease like any client; off, they are refused. Stopping is always "
        "allowed.",
    )

    if not TYPE_CHECKING:
        # Hidden from mypy, which then checks calls against the fields' own signature.
        def __init__(self, **values: Any) -> None:
            self._validate_into(values)

    @classmethod
    def load(
        cls, config_file: str | os.PathLike[str] | None = None, **overrides: object
    ) -> RobotConfig:
        """Settings from the arguments, the environment and a TOML file.

        Args:
            config_file: The TOML file to read; it must exist. Without it:
                ``$OHMNI_CONFIG`` (must exist), else ``./ohmni.toml``, else
                ``$XDG_CONFIG_HOME/ohmni/ohmni.toml``, else no file.
            **overrides: Settings that beat every other source.

        Returns:
            The validated settings.

        Raises:
            ConfigError: A file is missing or not valid TOML, a setting is unknown, or a
                value is invalid.
        """
        loading = _Loading(_find_config_file(config_file))
        token = _LOADING.set(loading)
        try:
            return cls(**cast("dict[str, Any]", overrides))
        finally:
            _LOADING.reset(token)

    @classmethod
    def load_explained(
        cls, config_file: str | os.PathLike[str] | None = None
    ) -> tuple[RobotConfig, Path | None, dict[str, str]]:
        """:meth:`load`, and where each setting's value came from (``ohmni config``).

        Returns:
            The settings, the config file read (``None``: none), and for each setting
            its source: ``"default"``, the environment variable's name
            (``"OHMNI_PORT"``), or the config file's path.

        Raises:
            ConfigError: As :meth:`load`.
        """
        loading = _Loading(_find_config_file(config_file))
        token = _LOADING.set(loading)
        try:
            config = cls()
            origins: dict[str, str] = {}
            for name in cls.model_fields:
                where, from_env = _origin(name, {})
                if not where:
                    origins[name] = "default"
                elif from_env:
                    origins[name] = where.removeprefix(" (from ").removesuffix(")")
                else:
                    origins[name] = str(loading.path)
        finally:
            _LOADING.reset(token)
        return config, loading.path, origins

    @classmethod
    def example_file(cls) -> str:
        """A commented TOML config file: every setting with its default and what it
        does, each commented out (``ohmni config init`` writes it). It loads as the
        defaults; uncomment a line to change one."""
        lines = [
            "# ohmni_tb settings. Every setting is here with its default, commented out:",
            "# uncomment a line and change its value. The environment (OHMNI_<NAME>) and",
            "# arguments beat this file. `ohmni config` shows what is in effect and why.",
            "",
        ]
        for name, info in cls.model_fields.items():
            lines.extend(f"# {text}" for text in _wrapped(info.description or "", 86))
            lines += [f"# {name} = {toml_value(name, info.default)}", ""]
        return "\n".join(lines)

    @classmethod
    def describe(cls) -> list[tuple[str, str, str]]:
        """Every setting as ``(name, default as text, description)``, for docs and ``--help``."""
        return [
            (name, _default_text(info.default), info.description or "")
            for name, info in cls.model_fields.items()
        ]

    @classmethod
    def check_setting(cls, name: str, value: object) -> None:
        """Check one setting's value alone, as a file or the environment would give it,
        without loading any (the checks between settings are not made).

        Raises:
            ConfigError: No such setting, or a value it does not take: the message names
                the value and what is allowed.
        """
        if name not in cls.model_fields:
            raise ConfigError(_unknown_message(name, ""))
        token = _ALONE.set(True)  # the value alone: not against the other defaults
        try:
            cls.__pydantic_validator__.validate_assignment(cls.model_construct(), name, value)
        except ValidationError as exc:
            raise ConfigError(_explain(exc, {name: value})) from None
        finally:
            _ALONE.reset(token)

    def replace(self, **changes: Any) -> RobotConfig:
        """A copy with ``changes`` applied and validated (the config itself is frozen).

        Raises:
            ConfigError: A change is unknown or invalid.
        """
        return type(self)(**{**self.model_dump(), **changes})

    def drive(self) -> DiffDrive:
        """The wheel geometry."""
        return DiffDrive(self.wheel_radius_m, self.wheel_separation_m)

    def top_linear_mps(self) -> float:
        """The fastest the robot may drive straight: the linear limit, within the wheels'."""
        return min(self.max_linear_mps, self.max_wheel_mps)

    def top_angular_radps(self) -> float:
        """The fastest it may turn on the spot: the angular limit, within the wheels'."""
        return min(self.max_angular_radps, 2 * self.max_wheel_mps / self.wheel_separation_m)

    def velocity_limits(self) -> VelocityLimits:
        """The speed limits a command is scaled into."""
        return VelocityLimits(self.max_linear_mps, self.max_angular_radps, self.max_wheel_mps)

    def twist_limiter(self) -> TwistLimiter:
        """A new acceleration limiter, standing, with the configured limits."""
        return TwistLimiter(
            AccelLimits(
                self.linear_accel_mps2,
                self.linear_decel_mps2,
                self.linear_jerk_mps3 or math.inf,  # 0 is off
            ),
            AccelLimits(
                self.angular_accel_radps2,
                self.angular_decel_radps2,
                self.angular_jerk_radps3 or math.inf,
            ),
        )

    def source_table(self) -> tuple[CommandSource, ...]:
        """The command sources, highest priority first (``command_sources``)."""
        return parse_sources(self.command_sources)

    def pid_gains(self) -> PidGains:
        """The wheel PID gains."""
        return PidGains(
            kp=self.pid_kp,
            ki=self.pid_ki,
            kd=self.pid_kd,
            kff=self.pid_kff,
            ff_offset=self.pid_ff_offset,
        )

    def encoders(self) -> tuple[EncoderConfig, EncoderConfig]:
        """The left and right wheel encoders (the right one counts mirrored)."""
        return (
            EncoderConfig(ticks_per_rev=self.ticks_per_rev, wheel_radius_m=self.wheel_radius_m),
            EncoderConfig(
                ticks_per_rev=self.ticks_per_rev,
                wheel_radius_m=self.wheel_radius_m,
                mirrored=True,
            ),
        )

    def profile(self) -> BusProfile:
        """The bus profile these settings describe (wheel form, battery block, ...)."""
        return BusProfile.from_settings({name: getattr(self, name) for name in PROFILE_SETTINGS})

    def bus_timeout_s(self) -> float:
        """The bus's reply timeout: the adapter's latency timer plus event-loop delay.

        Never less than the bus default (25 ms, for the default 16 ms latency timer).
        """
        return max(DEFAULT_TIMEOUT_S, self.usb_latency_ms / 1000 + _LOOP_MARGIN_S)

    def __setattr__(self, name: str, value: object) -> None:
        raise ConfigError(
            f"RobotConfig is frozen: cannot set {name}; use .replace({name}=...) for a copy"
        )

    def __delattr__(self, name: str) -> None:
        raise ConfigError(f"RobotConfig is frozen: cannot delete {name}")

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Arguments, then ``OHMNI_*``, then the TOML file of a :meth:`load` call."""
        # No .env or secrets directory: a robot's settings come from three places only.
        loading = _LOADING.get()
        if loading is None or loading.path is None:
            return (init_settings, env_settings)
        return (init_settings, env_settings, _TomlSource(settings_cls, loading))

    def _validate_into(self, values: dict[str, Any]) -> None:
        """Run pydantic-settings' validation, turning its errors into one ConfigError."""
        # BaseSettings takes "_env_file" and friends as arguments: not here, so that the
        # sources stay the three documented ones.
        for key in values:
            if key.startswith("_"):
                raise ConfigError(_unknown_message(key, " (argument)"))
        _warn_unknown_env()
        try:
            super().__init__(**values)
        except ValidationError as exc:
            raise ConfigError(_explain(exc, values)) from exc
        except SettingsError as exc:
            raise ConfigError(str(exc)) from exc

    @field_validator("*", mode="before")
    @classmethod
    def _refuse_bool_numbers(cls, value: object, info: ValidationInfo) -> object:
        # pydantic's lax mode reads True as 1; a switch given for a number is a mistake.
        declared = cls.model_fields.get(info.field_name or "")
        if isinstance(value, bool) and declared is not None and declared.annotation in (int, float):
            raise PydanticCustomError("not_a_number", "a boolean is not a number")
        return value

    @field_validator("*", mode="after")
    @classmethod
    def _check_off_gap(cls, value: object, info: ValidationInfo) -> object:
        off_below = _extra(info.field_name or "").get("off_below")
        if (
            isinstance(off_below, float | int)
            and isinstance(value, float | int)
            and 0 < value < off_below
        ):
            raise PydanticCustomError("out_of_range", "between off and the lowest value")
        return value

    @field_validator(
        "drive_torque_addr", "battery_addr", "worm_target_addr", "worm_feedback_addr", mode="before"
    )
    @classmethod
    def _parse_address(cls, value: object) -> object:
        # "0xA0" from the environment or a URL; TOML reads 0xA0 as an integer itself.
        if isinstance(value, str) and value.strip().lower().startswith("0x"):
            try:
                return int(value.strip(), 16)
            except ValueError:
                return value
        return value

    @field_validator("command_sources", mode="before")
    @classmethod
    def _parse_sources(cls, value: object) -> object:
        # One entry or the whole table in a line ("safety:0.5,local:0.5,…"), a list of
        # entries, or CommandSource rows: the same canonical entries either way.
        if isinstance(value, str) or (
            isinstance(value, list | tuple) and any(isinstance(v, CommandSource) for v in value)
        ):
            return format_sources(parse_sources(value))
        return value

    @field_validator("command_sources", mode="after")
    @classmethod
    def _check_sources(cls, entries: tuple[str, ...]) -> tuple[str, ...]:
        return format_sources(parse_sources(entries))

    @field_validator("ext_servo_ids", mode="before")
    @classmethod
    def _parse_id_list(cls, value: object) -> object:
        if not isinstance(value, str):
            return value
        try:
            return parse_ext_servo_ids(value)
        except OhmniError as exc:
            raise ValueError(str(exc)) from None

    @field_validator("ext_servo_ids", mode="after")
    @classmethod
    def _check_ext_ids(cls, ids: tuple[int, ...]) -> tuple[int, ...]:
        try:
            return check_ext_servo_ids(ids)
        except OhmniError as exc:
            raise ValueError(str(exc)) from None

    @field_validator("frame_id_odom", "frame_id_baselink", mode="after")
    @classmethod
    def _check_frame(cls, frame: str, info: ValidationInfo) -> str:
        if frame and any(char.isspace() for char in frame):
            raise ValueError(f"{info.field_name}={frame!r} has a space: allowed {_FRAME_ALLOWED}")
        return frame

    @field_validator("mqtt_url", mode="after")
    @classmethod
    def _check_mqtt_url(cls, url: str) -> str:
        if url and mqtt_address(url) is None:
            raise ValueError(f"mqtt_url={url!r} is not a broker URL: allowed {_MQTT_URL_ALLOWED}")
        return url

    @field_validator("robot_id", mode="after")
    @classmethod
    def _check_robot_id(cls, robot_id: str) -> str:
        if len(robot_id) > _MAX_ROBOT_ID or not set(robot_id) <= _ROBOT_ID_CHARS:
            raise ValueError(f"robot_id={robot_id!r} is not a name: allowed {_ROBOT_ID_ALLOWED}")
        return robot_id

    @field_validator("mqtt_discovery_prefix", mode="after")
    @classmethod
    def _check_topic(cls, prefix: str) -> str:
        levels = prefix.split("/")
        if any(not level or set(level) & set("+# ") for level in levels):
            raise ValueError(
                f"mqtt_discovery_prefix={prefix!r} is not a topic: allowed {_TOPIC_ALLOWED}"
            )
        return prefix

    @field_validator("mqtt_rates", mode="after")
    @classmethod
    def _check_rates(cls, text: str) -> str:
        _parse_rates(text)
        return text

    def mqtt_streams(self) -> dict[str, float]:
        """``mqtt_rates`` as {stream name: Hz} (empty for ``none``); the names are checked
        against the streams where they are published (:mod:`ohmni_tb.mqtt`)."""
        return _parse_rates(self.mqtt_rates)

    @model_validator(mode="after")
    def _check_mqtt(self) -> Self:
        if _ALONE.get():
            return self
        problems: list[tuple[str, str]] = []
        if bool(self.mqtt_cert_file) != bool(self.mqtt_key_file):
            given, missing = (
                ("mqtt_cert_file", "mqtt_key_file")
                if self.mqtt_cert_file
                else ("mqtt_key_file", "mqtt_cert_file")
            )
            problems.append((given, f"{given} is set but {missing} is not: give both"))
        address = mqtt_address(self.mqtt_url) if self.mqtt_url else None
        tls = address is not None and address[2]
        problems.extend(
            (
                name,
                f"{name}={getattr(self, name)!r} needs TLS: mqtt_url must be "
                f"mqtts://HOST[:PORT], not {self.mqtt_url!r}",
            )
            for name in ("mqtt_ca_file", "mqtt_cert_file")
            if getattr(self, name) and not tls
        )
        if self.mqtt_password.get_secret_value() and not self.mqtt_username:
            problems.append(("mqtt_username", "mqtt_password is set but mqtt_username is not"))
        if problems:
            raise _RelationError(problems)
        return self

    @model_validator(mode="after")
    def _check_relations(self) -> Self:
        if _ALONE.get():
            return self
        problems: list[tuple[str, str]] = []
        low, high, rest = self.neck_min_raw, self.neck_max_raw, self.neck_rest_raw
        if not low < high:
            problems.append(
                ("neck_min_raw", f"neck_min_raw={low} must be below neck_max_raw={high}")
            )
        elif not low <= rest <= high:
            problems.append(
                (
                    "neck_rest_raw",
                    f"neck_rest_raw={rest} is outside the neck's range: allowed "
                    f"neck_min_raw..neck_max_raw = {low}..{high}",
                )
            )
        if not self.neck_min_voltage_raw < self.neck_max_voltage_raw:
            problems.append(
                (
                    "neck_min_voltage_raw",
                    f"neck_min_voltage_raw={self.neck_min_voltage_raw} must be below "
                    f"neck_max_voltage_raw={self.neck_max_voltage_raw}: the servo would "
                    "report an input-voltage error at every supply and release its torque",
                )
            )
        if not self.worm_min_raw < self.worm_max_raw:
            problems.append(
                (
                    "worm_min_raw",
                    f"worm_min_raw={self.worm_min_raw} must be below "
                    f"worm_max_raw={self.worm_max_raw}",
                )
            )
        if self.frame_id_odom == self.frame_id_baselink:
            problems.append(
                (
                    "frame_id_baselink",
                    f"frame_id_baselink={self.frame_id_baselink!r} is frame_id_odom's too: "
                    "the body frame needs a name of its own",
                )
            )
        layout = BatteryLayout(self.battery_layout)
        if self.battery_length < layout.size:
            problems.append(
                (
                    "battery_length",
                    f"battery_length={self.battery_length} is shorter than the "
                    f"{layout.value} layout's {layout.size} bytes",
                )
            )
        if self.neck_id in self.ext_servo_ids:
            problems.append(
                (
                    "ext_servo_ids",
                    f"ext_servo_ids={self.ext_servo_ids} includes neck_id={self.neck_id}: "
                    "an external servo needs an id of its own",
                )
            )
        if problems:
            raise _RelationError(problems)
        return self


@dataclass
class _Loading:
    """The TOML file of one :meth:`RobotConfig.load` call, and what it held once read."""

    path: Path | None
    data: dict[str, Any] = field(default_factory=dict)


#: Set while :meth:`RobotConfig.check_setting` checks one value alone.
_ALONE: ContextVar[bool] = ContextVar("ohmni_config_alone", default=False)
#: Set for the duration of a load() call, so plain RobotConfig() never reads a file.
_LOADING: ContextVar[_Loading | None] = ContextVar("ohmni_config_loading", default=None)


class _RelationError(ValueError):
    """Cross-field problems, each ``(field, message)``, raised from the model validator."""

    def __init__(self, problems: list[tuple[str, str]]) -> None:
        super().__init__("; ".join(message for _, message in problems))
        self.problems = problems


class _TomlSource(TomlConfigSettingsSource):
    """pydantic-settings' TOML source: ``[robot]`` merged up, errors naming the file."""

    def __init__(self, settings_cls: type[BaseSettings], loading: _Loading) -> None:
        self._loading = loading
        super().__init__(settings_cls, toml_file=loading.path)

    def _read_file(self, file_path: Path | Traversable) -> dict[str, Any]:
        try:
            with file_path.open("rb") as file:
                data = toml_settings(file.read().decode("utf-8"), file_path)
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{file_path}: not UTF-8 text: {exc}") from exc
        except OSError as exc:
            raise ConfigError(f"cannot read config file {file_path}: {exc}") from exc
        table = data.pop("robot", None)
        if table is not None:
            if not isinstance(table, dict):
                raise ConfigError(f"{file_path}: robot must be a [robot] table, not {table!r}")
            for key in table:
                if key in data:
                    raise ConfigError(f"{file_path}: {key} is set both at top level and in [robot]")
            data.update(table)
        self._loading.data = data
        return data


#: pydantic error types that mean "a number outside its range".
_RANGE_ERRORS = frozenset(
    {"greater_than", "greater_than_equal", "less_than", "less_than_equal", "out_of_range"}
)
#: pydantic error types that mean "not the right kind of value", and that kind.
_KIND_ERRORS = {
    "int_parsing": "an integer",
    "int_from_float": "an integer",
    "int_type": "an integer",
    "float_parsing": "a number",
    "float_type": "a number",
    "not_a_number": "a number",
    "finite_number": "a finite number",
    "bool_parsing": "a boolean",
    "bool_type": "a boolean",
    "string_type": "a string",
    "string_too_short": "empty",
    "tuple_type": "a list",
}


#: The settings that are lists of text (the others' lists are of integers).
_TEXT_LIST_SETTINGS = frozenset({"command_sources"})


def toml_value(name: str, value: object) -> str:
    """``value`` as a TOML value (what :func:`toml_settings` reads back as the same):
    a bool, a number, a string, or a list of integers (the servo ids) or of strings (the
    command sources).

    Raises:
        ConfigError: A kind of value a setting never holds; the message names it.
    """
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)  # the shortest text that reads back as the same number
    if isinstance(value, str):
        # A JSON string is a TOML basic string: the same quotes and escapes.
        return json.dumps(value)
    if isinstance(value, (list, tuple)) and all(
        isinstance(v, int) and not isinstance(v, bool) for v in value
    ):
        return "[" + ", ".join(str(v) for v in value) + "]"
    if (
        name in _TEXT_LIST_SETTINGS
        and isinstance(value, (list, tuple))
        and all(isinstance(v, str) for v in value)
    ):
        return "[" + ", ".join(json.dumps(v) for v in value) + "]"
    raise ConfigError(
        f"{name}={value!r}: a setting is a number, a string, a boolean or a list of "
        "integers (command_sources: of strings)"
    )


def toml_settings(text: str, path: object) -> dict[str, Any]:
    """A config file's text parsed as TOML.

    Raises:
        ConfigError: It is not TOML, or it nests too deeply to parse; the message names
            ``path``.
    """
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:  # its message ends "(at line 3, column 7)"
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except RecursionError as exc:  # tomllib parses nested values recursively
        raise ConfigError(
            f"{path}: not read: its arrays or tables nest too deeply "
            "(a setting is a number, a string, a boolean or a list of ids)"
        ) from exc


def _explain(error: ValidationError, arguments: Mapping[str, object]) -> str:
    """One line per problem of ``error``: the setting, the value, what is allowed, whence."""
    unknown: list[str] = []  # first: a mistyped name often explains the rest
    lines: list[str] = []
    for problem in error.errors():
        loc = problem["loc"]
        kind = problem["type"]
        context = problem.get("ctx") or {}
        cause = context.get("error")
        if isinstance(cause, _RelationError):
            lines += [msg + _origin(name, arguments)[0] for name, msg in cause.problems]
            continue
        name = str(loc[0]) if loc else ""
        origin, from_env = _origin(name, arguments)
        if kind == "extra_forbidden":
            unknown.append(_unknown_message(name, origin))
            continue
        where = name + "".join(f"[{part}]" for part in loc[1:])
        value = problem["input"]
        shown = value if from_env and isinstance(value, str) else show(value)
        allowed = _allowed(name)
        if kind in _RANGE_ERRORS:
            text = f"{where}={shown} is out of range: allowed {allowed}"
        elif kind == "string_too_short":
            text = f"{where}={shown} is empty: allowed {allowed}"
        elif kind in {"bool_parsing", "bool_type"}:
            text = f"{where}={shown} is not a boolean: allowed true/false, 1/0, yes/no, on/off"
        elif kind in _KIND_ERRORS:
            text = f"{where}={shown} is not {_KIND_ERRORS[kind]}: allowed {allowed}"
        elif kind == "literal_error":
            text = f"{where}={shown} is not a choice: allowed {context.get('expected', '')}"
        elif kind == "value_error" and cause is not None:
            text = str(cause)
        else:
            text = f"{where}={shown} is invalid: {problem['msg']}"
        lines.append(text + origin)
    return "\n".join(unknown + lines)


def _origin(name: str, arguments: Mapping[str, object]) -> tuple[str, bool]:
    """Where the value of setting ``name`` came from, as `` (…)``, and whether from env."""
    if name.lower() in {key.lower() for key in arguments}:
        return " (argument)", False
    wanted = f"{ENV_PREFIX}{name}".lower()
    for key in os.environ:
        if key.lower() == wanted:
            return f" (from {key})", True
    loading = _LOADING.get()
    if loading is not None and name.lower() in {key.lower() for key in loading.data}:
        return f" (in {loading.path})", False
    return "", False


#: Unknown ``OHMNI_*`` names already warned about: once each.
_warned_env: set[str] = set()


def _warn_unknown_env() -> None:
    """Warn once about each ``OHMNI_*`` variable that nothing reads (``OHMNI_WATCHDOG_S``
    mistyped without its ``_S`` would otherwise leave the watchdog at its default
    unnoticed), naming the closest known name."""
    fields = {f"{ENV_PREFIX}{name}".upper() for name in RobotConfig.model_fields}
    for key in os.environ:
        if not key.upper().startswith(ENV_PREFIX) or key in _warned_env:
            continue
        if key.upper() in fields or key in _OTHER_ENV:  # settings in any case, others exact
            continue
        _warned_env.add(key)
        # Compared without the prefix, which every name shares.
        known = {name[len(ENV_PREFIX) :]: name for name in fields | _OTHER_ENV}
        close = difflib.get_close_matches(key.upper()[len(ENV_PREFIX) :], sorted(known), n=1)
        hint = (
            f"did you mean {known[close[0]]}?"
            if close
            else "the settings are listed by RobotConfig.describe() and in docs/robot.md"
        )
        _log.warning("environment variable %s is ignored: nothing reads that name; %s", key, hint)


def _unknown_message(key: str, origin: str) -> str:
    """An unknown setting, with the closest names as a suggestion."""
    close = difflib.get_close_matches(key.lower(), list(RobotConfig.model_fields), n=3)
    hint = f"; did you mean {' or '.join(map(repr, close))}?" if close else ""
    return f"unknown setting {key!r}{origin}{hint}"


def _extra(name: str) -> dict[str, Any]:
    """The ``json_schema_extra`` of field ``name`` (empty when it has none)."""
    info = RobotConfig.model_fields.get(name)
    extra = info.json_schema_extra if info is not None else None
    return extra if isinstance(extra, dict) else {}


def _allowed(name: str) -> str:
    """What field ``name`` allows, in words."""
    return str(_extra(name).get("allowed", "see RobotConfig.describe()"))


def _parse_rates(text: str) -> dict[str, float]:
    """``mqtt_rates``' text as {name: Hz}: ``"wheel_odom=5,tbcore_status=1"``, or ``none``."""
    body = text.strip()
    if body.lower() in {"", "none"}:
        return {}
    rates: dict[str, float] = {}
    for part in body.split(","):
        name, sep, value = (piece.strip() for piece in part.partition("="))
        try:
            hz = float(value)
        except ValueError:
            hz = math.nan
        if not sep or not name or not 0 < hz <= _MAX_MQTT_HZ:
            raise ValueError(
                f"mqtt_rates={text!r}: {part.strip()!r} is not NAME=HZ with a rate "
                f">0..{_num(_MAX_MQTT_HZ)} Hz (write rates like wheel_odom=5,tbcore_status=1, "
                "or none)"
            )
        if name in rates:
            raise ValueError(f"mqtt_rates={text!r} names {name} twice")
        rates[name] = hz
    return rates


def _default_text(value: object) -> str:
    """A default as one would write it in the environment."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return ",".join(map(str, value)) if value else "none"
    if isinstance(value, int | float):
        return _num(value)
    return str(value)


def user_config_dir() -> Path:
    """The user's ohmni directory: ``$XDG_CONFIG_HOME/ohmni`` (default ``~/.config/ohmni``)."""
    xdg = os.environ.get("XDG_CONFIG_HOME", "")
    # The XDG spec ignores a relative path.
    home = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".config"
    return home / "ohmni"


def _default_paths() -> list[Path]:
    """./ohmni.toml, then $XDG_CONFIG_HOME/ohmni/ohmni.toml (default ~/.config)."""
    return [Path.cwd() / CONFIG_FILE_NAME, user_config_dir() / CONFIG_FILE_NAME]


def _find_config_file(config_file: str | os.PathLike[str] | None) -> Path | None:
    """The TOML file a load() call reads, or None."""
    if config_file is not None:
        return _existing(Path(config_file).expanduser(), "")
    named = os.environ.get(CONFIG_ENV)
    if named:
        return _existing(Path(named).expanduser(), f" (named by {CONFIG_ENV})")
    return next((path for path in _default_paths() if path.is_file()), None)


def _existing(path: Path, why: str) -> Path:
    """``path`` if it is a file, else a ConfigError naming it."""
    if not path.exists():
        raise ConfigError(f"config file not found: {path}{why}")
    if not path.is_file():
        raise ConfigError(f"config file is not a file: {path}{why}")
    return path


def _wrapped(text: str, width: int) -> list[str]:
    """``text`` in lines of at most ``width`` characters (at spaces)."""
    lines: list[str] = []
    line = ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    return [*lines, line] if line else lines
