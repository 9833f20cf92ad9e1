"""RobotConfig: defaults, precedence, TOML files, and the messages a bad setting gives."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from ohmni_tb.config import CONFIG_ENV, RobotConfig, config_paths
from ohmni_tb.control.defaults import (
    DEFAULT_MAX_ANGULAR_RADPS,
    DEFAULT_MAX_LINEAR_MPS,
    DEFAULT_TICKS_PER_REV,
    DEFAULT_WHEEL_RADIUS_M,
    DEFAULT_WHEEL_SEPARATION_M,
    PID_RATE_HZ,
)
from ohmni_tb.control.encoder import EncoderConfig
from ohmni_tb.control.kinematics import Twist
from ohmni_tb.errors import ConfigError
from ohmni_tb.protocol.connection import DEFAULT_TIMEOUT_S
from ohmni_tb.protocol.devices import DEFAULT_EXT_SERVO_IDS, NECK_RAW_RANGE
from ohmni_tb.protocol.worm_neck import WORM_MAX, WORM_MIN

#: Every setting, in order: other code relies on these names.
FIELDS = [
    "port", "baudrate", "usb_latency_ms", "reconnect", "reconnect_max_backoff_s",
    "wheel_radius_m", "wheel_separation_m", "ticks_per_rev",
    "max_linear_mps", "max_angular_radps", "max_wheel_mps", "linear_accel_mps2",
    "linear_decel_mps2", "angular_accel_radps2", "angular_decel_radps2",
    "linear_jerk_mps3", "angular_jerk_radps3",
    "pid_kp", "pid_ki", "pid_kd", "pid_kff", "pid_ff_offset", "controllers",
    "watchdog_s", "command_sources", "stale_ticks", "stall_s", "slip_s", "implausible_mps",
    "thermal_guard", "thermal_limit_raw", "neck_hold_s", "on_exit_neck", "stop_timeout_s",
    "neck", "neck_id", "neck_min_raw", "neck_max_raw", "neck_rest_raw",
    "neck_zero_offset_raw", "neck_kp", "neck_ki", "neck_kd", "neck_min_voltage_raw",
    "neck_max_voltage_raw", "neck_overload_pwm", "neck_max_pwm", "neck_use_eeprom",
    "worm_min_raw", "worm_max_raw", "ext_servo_ids",
    "wheel_form", "right_mirrored", "drive_torque_addr", "battery_addr", "battery_length",
    "battery_layout", "worm_target_addr", "worm_feedback_addr",
    "wheel_hz", "servo_hz", "core_hz", "new_neck_hz", "state_hz", "diagnostics_hz", "pid_debug",
    "frame_id_odom", "frame_id_baselink", "enable_broadcast_transform",
    "mqtt_url", "robot_id", "mqtt_username", "mqtt_password", "mqtt_ca_file",
    "mqtt_cert_file", "mqtt_key_file", "mqtt_keepalive_s", "mqtt_discovery",
    "mqtt_discovery_prefix", "mqtt_rates", "mqtt_drive",
]  # fmt: skip


#: Every test here without the machine's own settings (conftest's ``hermetic``).
pytestmark = pytest.mark.usefixtures("hermetic")


def build(**values: Any) -> RobotConfig:
    """RobotConfig(**values), for values of the wrong type on purpose."""
    return RobotConfig(**values)


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def config_error(**values: Any) -> str:
    """The message of the ConfigError that RobotConfig(**values) raises."""
    with pytest.raises(ConfigError) as caught:
        build(**values)
    return str(caught.value)


# Defaults.


def test_the_fields_are_pinned() -> None:
    assert list(RobotConfig.model_fields) == FIELDS


def test_defaults_are_design_section_4_and_the_control_constants() -> None:
    config = RobotConfig()
    assert config.port == "auto"
    assert config.baudrate == 115200
    assert config.wheel_radius_m == DEFAULT_WHEEL_RADIUS_M == 0.0760
    assert config.wheel_separation_m == DEFAULT_WHEEL_SEPARATION_M == 0.330
    assert config.ticks_per_rev == DEFAULT_TICKS_PER_REV == pytest.approx(16384 * 30 / 11)
    assert config.max_linear_mps == DEFAULT_MAX_LINEAR_MPS == 1.0
    assert config.max_angular_radps == DEFAULT_MAX_ANGULAR_RADPS
    assert config.watchdog_s == 0.5
    assert config.neck_id == 3
    assert (config.neck_min_raw, config.neck_max_raw) == NECK_RAW_RANGE == (280, 650)
    assert config.neck_min_raw <= config.neck_rest_raw <= config.neck_max_raw
    assert (config.worm_min_raw, config.worm_max_raw) == (WORM_MIN, WORM_MAX)
    assert (config.worm_min_raw, config.worm_max_raw) == (-127_000, 120_000)
    assert config.ext_servo_ids == DEFAULT_EXT_SERVO_IDS
    assert (config.wheel_hz, config.servo_hz, config.core_hz) == (PID_RATE_HZ, 30.0, 10.0)
    assert config.on_exit_neck == "free"
    assert config.neck == "auto"


def test_every_setting_is_described_with_its_allowed_values() -> None:
    rows = RobotConfig.describe()
    assert [name for name, _, _ in rows] == FIELDS
    described = {name: (default, text) for name, default, text in rows}
    assert described["watchdog_s"] == (
        "0.5",
        "Motion watchdog: the wheels are stopped this long after the last drive command, s. "
        "Allowed: 0 (off) or 0.05..60 s.",
    )
    assert described["ext_servo_ids"][0] == "11,12"
    assert described["reconnect"][0] == "true"
    assert described["max_linear_mps"][1].endswith("Allowed: >0..5 m/s.")
    for name, (_, text) in described.items():
        assert text, name
        annotation = RobotConfig.model_fields[name].annotation
        if annotation in (int, float):
            assert "Allowed: " in text, name


# Where settings come from.


def test_plain_construction_reads_arguments_and_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OHMNI_PORT", "sim://")
    monkeypatch.setenv("OHMNI_WATCHDOG_S", "0.3")
    config = RobotConfig(watchdog_s=0.2)
    assert (config.port, config.watchdog_s) == ("sim://", 0.2)


def test_plain_construction_never_reads_a_file(hermetic: Path) -> None:
    write(hermetic / "ohmni.toml", 'port = "from-file"\n')
    assert RobotConfig().port == "auto"
    assert RobotConfig.load().port == "from-file"


def test_without_any_file_load_gives_the_defaults() -> None:
    assert RobotConfig.load() == RobotConfig()


def test_each_source_beats_the_ones_below(monkeypatch: pytest.MonkeyPatch, hermetic: Path) -> None:
    toml = write(hermetic / "robot.toml", "watchdog_s = 0.3\nbaudrate = 57600\nneck_id = 5\n")
    monkeypatch.setenv("OHMNI_WATCHDOG_S", "0.4")
    monkeypatch.setenv("OHMNI_BAUDRATE", "9600")
    config = RobotConfig.load(toml, watchdog_s=0.2)
    assert config.watchdog_s == 0.2  # argument over environment
    assert config.baudrate == 9600  # environment over file
    assert config.neck_id == 5  # file over default
    assert config.port == "auto"  # default


def test_environment_names_are_case_insensitive(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ohmni_Port", "sim://")
    assert RobotConfig().port == "sim://"


@pytest.mark.parametrize(
    ("text", "expected"), [("1", True), ("0", False), ("true", True), ("False", False)]
)
def test_environment_booleans(monkeypatch: pytest.MonkeyPatch, text: str, expected: bool) -> None:
    monkeypatch.setenv("OHMNI_RECONNECT", text)
    monkeypatch.setenv("OHMNI_PID_DEBUG", text)
    config = RobotConfig()
    assert (config.reconnect, config.pid_debug) == (expected, expected)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("11,12", (11, 12)),
        (" 11 , 12 ", (11, 12)),
        ("13", (13,)),
        ("none", ()),
        ("None", ()),
        ("", ()),
        ("[11]", (11,)),
        ("[11, 12]", (11, 12)),
        ("[]", ()),
    ],
)
def test_ext_servo_ids_from_the_environment(
    monkeypatch: pytest.MonkeyPatch, text: str, expected: tuple[int, ...]
) -> None:
    monkeypatch.setenv("OHMNI_EXT_SERVO_IDS", text)
    assert RobotConfig().ext_servo_ids == expected


def test_ext_servo_ids_from_toml_as_list_or_text(hermetic: Path) -> None:
    as_list = write(hermetic / "a.toml", "ext_servo_ids = [13]\n")
    as_text = write(hermetic / "b.toml", 'ext_servo_ids = "none"\n')
    assert RobotConfig.load(as_list).ext_servo_ids == (13,)
    assert RobotConfig.load(as_text).ext_servo_ids == ()


def test_a_bad_id_in_the_environment_names_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OHMNI_EXT_SERVO_IDS", "11,x")
    with pytest.raises(ConfigError, match=r"^ext_servo_ids='11,x': 'x' is not a bus id") as caught:
        RobotConfig()
    assert str(caught.value).endswith("(from OHMNI_EXT_SERVO_IDS)")


# TOML files.


def test_toml_settings_at_top_level_and_in_a_robot_table(hermetic: Path) -> None:
    top = write(hermetic / "top.toml", 'port = "sim://"\nwheel_hz = 25.0\n')
    table = write(hermetic / "table.toml", 'port = "sim://"\n[robot]\nwheel_hz = 25.0\n')
    assert (
        RobotConfig.load(top) == RobotConfig.load(table) == RobotConfig(port="sim://", wheel_hz=25)
    )


def test_a_setting_both_at_top_level_and_in_the_robot_table_is_refused(hermetic: Path) -> None:
    toml = write(hermetic / "both.toml", "wheel_hz = 25.0\n[robot]\nwheel_hz = 20.0\n")
    with pytest.raises(ConfigError, match="wheel_hz is set both at top level and in \\[robot\\]"):
        RobotConfig.load(toml)


def test_the_working_directory_file_beats_the_user_file(hermetic: Path, tmp_path: Path) -> None:
    user = write(tmp_path / "xdg" / "ohmni" / "ohmni.toml", 'port = "user"\n')
    assert RobotConfig.load().port == "user"
    write(hermetic / "ohmni.toml", 'port = "here"\n')
    assert RobotConfig.load().port == "here"
    assert config_paths() == [hermetic / "ohmni.toml", user]


def test_the_user_file_defaults_to_dot_config(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("XDG_CONFIG_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    write(tmp_path / "home" / ".config" / "ohmni" / "ohmni.toml", 'port = "home"\n')
    assert RobotConfig.load().port == "home"


def test_ohmni_config_names_the_file(
    monkeypatch: pytest.MonkeyPatch, hermetic: Path, tmp_path: Path
) -> None:
    write(hermetic / "ohmni.toml", 'port = "here"\n')
    named = write(tmp_path / "named.toml", 'port = "named"\n')
    explicit = write(tmp_path / "explicit.toml", 'port = "explicit"\n')
    monkeypatch.setenv(CONFIG_ENV, str(named))
    assert RobotConfig.load().port == "named"  # above the default locations
    assert RobotConfig.load(explicit).port == "explicit"  # below an explicit file
    assert config_paths()[:2] == [named, hermetic / "ohmni.toml"]


def test_a_missing_ohmni_config_file_is_an_error(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    missing = tmp_path / "nowhere.toml"
    monkeypatch.setenv(CONFIG_ENV, str(missing))
    with pytest.raises(ConfigError) as caught:
        RobotConfig.load()
    assert str(caught.value) == f"config file not found: {missing} (named by OHMNI_CONFIG)"


def test_a_missing_explicit_file_is_an_error(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.toml"
    with pytest.raises(ConfigError) as caught:
        RobotConfig.load(missing)
    assert str(caught.value) == f"config file not found: {missing}"


def test_a_directory_is_not_a_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="config file is not a file"):
        RobotConfig.load(tmp_path)


def test_a_toml_syntax_error_names_the_file_and_line(hermetic: Path) -> None:
    toml = write(hermetic / "broken.toml", 'port = "sim://"\nwatchdog_s 0.3\n')
    with pytest.raises(ConfigError) as caught:
        RobotConfig.load(toml)
    message = str(caught.value)
    assert message.startswith(f"{toml}: not valid TOML: ")
    assert "line 2" in message


def test_a_bad_value_in_a_file_names_the_file(hermetic: Path) -> None:
    toml = write(hermetic / "ohmni.toml", "[robot]\nstale_ticks = 0\n")
    with pytest.raises(ConfigError) as caught:
        RobotConfig.load()
    assert str(caught.value) == (f"stale_ticks=0 is out of range: allowed 1..100 ticks (in {toml})")


def test_an_unknown_key_in_a_file_is_named_with_a_suggestion(hermetic: Path) -> None:
    toml = write(hermetic / "ohmni.toml", "watchdog = 0.3\n")
    with pytest.raises(ConfigError) as caught:
        RobotConfig.load()
    assert str(caught.value) == (
        f"unknown setting 'watchdog' (in {toml}); did you mean 'watchdog_s'?"
    )


def test_the_environment_beats_a_bad_file_value(
    monkeypatch: pytest.MonkeyPatch, hermetic: Path
) -> None:
    write(hermetic / "ohmni.toml", "stale_ticks = 0\n")
    monkeypatch.setenv("OHMNI_STALE_TICKS", "7")
    assert RobotConfig.load().stale_ticks == 7


# Bad values.


def test_a_bad_environment_value_names_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OHMNI_WATCHDOG_S", "-1.0")
    with pytest.raises(ConfigError) as caught:
        RobotConfig()
    assert str(caught.value) == (
        "watchdog_s=-1.0 is out of range: allowed 0 (off) or 0.05..60 s (from OHMNI_WATCHDOG_S)"
    )


def test_nan_from_the_environment_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OHMNI_WHEEL_RADIUS_M", "nan")
    with pytest.raises(ConfigError) as caught:
        RobotConfig.load()
    assert str(caught.value) == (
        "wheel_radius_m=nan is not a finite number: allowed 0.01..1 m (from OHMNI_WHEEL_RADIUS_M)"
    )


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"watchdog_s": -1.0}, "watchdog_s=-1.0 is out of range: allowed 0 (off) or 0.05..60 s"),
        ({"watchdog_s": 0.01}, "watchdog_s=0.01 is out of range: allowed 0 (off) or 0.05..60 s"),
        ({"neck_hold_s": 0.5}, "neck_hold_s=0.5 is out of range: allowed 0 (never) or 1..86400 s"),
        ({"max_linear_mps": 0}, "max_linear_mps=0 is out of range: allowed >0..5 m/s"),
        ({"max_angular_radps": 21.0}, "max_angular_radps=21.0 is out of range: allowed >0..20"),
        ({"baudrate": 300}, "baudrate=300 is out of range: allowed 1200..4000000 baud"),
        ({"usb_latency_ms": 33}, "usb_latency_ms=33 is out of range: allowed 0..32 ms"),
        ({"thermal_limit_raw": 255}, "thermal_limit_raw=255 is out of range: allowed 1..254"),
        ({"worm_max_raw": 130_000}, "worm_max_raw=130000 is out of range: allowed -127000..120000"),
        ({"wheel_radius_m": math.nan}, "wheel_radius_m=nan is not a finite number"),
        ({"pid_kp": math.inf}, "pid_kp=inf is not a finite number: allowed 0..10000 PWM/(m/s)"),
        ({"baudrate": "fast"}, "baudrate='fast' is not an integer: allowed 1200..4000000 baud"),
        ({"stale_ticks": 2.5}, "stale_ticks=2.5 is not an integer: allowed 1..100 ticks"),
        ({"watchdog_s": True}, "watchdog_s=True is not a number"),
        ({"reconnect": "maybe"}, "reconnect='maybe' is not a boolean"),
        ({"port": ""}, "port='' is empty"),
        ({"port": 5}, "port=5 is not a string"),
        ({"neck": "giraffe"}, "neck='giraffe' is not a choice: allowed 'auto', 'herkulex'"),
        ({"on_exit_neck": "drop"}, "on_exit_neck='drop' is not a choice: allowed 'rest', 'free'"),
        (
            {"neck_rest_raw": 700},
            "neck_rest_raw=700 is outside the neck's range: allowed "
            "neck_min_raw..neck_max_raw = 280..650",
        ),
        ({"neck_min_raw": 650, "neck_max_raw": 280}, "neck_min_raw=650 must be below neck_max_raw"),
        ({"worm_min_raw": 0, "worm_max_raw": 0}, "worm_min_raw=0 must be below worm_max_raw=0"),
        (
            {"ext_servo_ids": (11, 3)},
            "ext_servo_ids=(11, 3): id 3 is the herkulex_neck board's; "
            "board ids 0, 1, 3, 4, 20 are taken",
        ),
        ({"ext_servo_ids": [20]}, "ext_servo_ids=(20,): id 20 is the core board's"),
        ({"ext_servo_ids": (12, 12)}, "ext_servo_ids=(12, 12) repeats id 12"),
        ({"ext_servo_ids": (11, 12, 13)}, "ext_servo_ids=(11, 12, 13) lists 3 servos: at most 2"),
        ({"ext_servo_ids": (254,)}, "ext_servo_ids=254 is out of range: allowed 0..253"),
        ({"ext_servo_ids": (11, "x")}, "ext_servo_ids[1]='x' is not an integer"),
        (
            {"ext_servo_ids": (11,), "neck_id": 11},
            "ext_servo_ids=(11,) includes neck_id=11: an external servo needs an id of its own",
        ),
    ],
)
def test_a_bad_value_names_the_setting_and_what_is_allowed(
    values: dict[str, Any], message: str
) -> None:
    text = config_error(**values)
    assert text.startswith(message)
    assert text.endswith(" (argument)")


def test_every_problem_gets_a_line_unknown_names_first() -> None:
    lines = config_error(baudrate=1, pid_kp=-1, watchdogs=1).splitlines()
    assert lines == [
        "unknown setting 'watchdogs' (argument); did you mean 'watchdog_s'?",
        "baudrate=1 is out of range: allowed 1200..4000000 baud (argument)",
        "pid_kp=-1 is out of range: allowed 0..10000 PWM/(m/s) (argument)",
    ]


def test_an_unknown_argument_without_a_close_match() -> None:
    assert config_error(colour="red") == "unknown setting 'colour' (argument)"


def test_an_unknown_argument_to_load_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"^unknown setting 'wheel_radius' .*'wheel_radius_m'"):
        RobotConfig.load(wheel_radius=0.07)


def test_pydantic_settings_own_arguments_are_unknown_here() -> None:
    # _env_file would quietly add a .env source.
    # (The hint after it names the settings whose names are closest.)
    assert config_error(_env_file=".env").startswith("unknown setting '_env_file' (argument)")


def test_the_error_is_a_value_error_and_keeps_the_cause() -> None:
    with pytest.raises(ValueError, match="baudrate") as caught:
        build(baudrate=0)
    assert isinstance(caught.value, ConfigError)
    assert not isinstance(caught.value, ValidationError)
    assert isinstance(caught.value.__cause__, ValidationError)


# Frozen.


def test_a_config_cannot_be_changed() -> None:
    config = RobotConfig()
    with pytest.raises(ConfigError, match=r"frozen: cannot set port; use \.replace\(port=\.\.\.\)"):
        config.port = "sim://"
    with pytest.raises(ConfigError, match="frozen"):
        del config.port
    assert config.port == "auto"


def test_replace_makes_a_validated_copy() -> None:
    config = RobotConfig(neck_id=5)
    copy = config.replace(port="sim://")
    assert (copy.port, copy.neck_id, config.port) == ("sim://", 5, "auto")
    with pytest.raises(ConfigError, match=r"^watchdog_s=0\.01 is out of range"):
        config.replace(watchdog_s=0.01)


def test_equal_configs_are_equal_and_hashable() -> None:
    assert RobotConfig(port="sim://") == RobotConfig(port="sim://")
    assert len({RobotConfig(), RobotConfig()}) == 1


# Derived objects.


def test_geometry_and_limits() -> None:
    config = RobotConfig(
        wheel_radius_m=0.07525,
        wheel_separation_m=0.332,
        max_linear_mps=0.8,
        max_angular_radps=1.5,
        max_wheel_mps=0.9,
    )
    drive = config.drive()
    assert (drive.wheel_radius_m, drive.wheel_separation_m) == (0.07525, 0.332)
    limits = config.velocity_limits()
    assert (limits.max_linear_mps, limits.max_angular_radps, limits.max_wheel_mps) == (
        0.8,
        1.5,
        0.9,
    )


def test_twist_limiter_is_fresh_and_configured() -> None:
    config = RobotConfig(
        linear_accel_mps2=0.25,
        linear_decel_mps2=0.75,
        angular_accel_radps2=1.0,
        angular_decel_radps2=3.0,
    )
    limiter = config.twist_limiter()
    assert (limiter.linear.max_accel, limiter.linear.max_decel) == (0.25, 0.75)
    assert (limiter.angular.max_accel, limiter.angular.max_decel) == (1.0, 3.0)
    limiter.step(Twist(1.0, 1.0), dt_s=1.0)
    assert config.twist_limiter() is not limiter
    assert config.twist_limiter().current == Twist()


def test_jerk_limits_are_off_by_default_and_set_from_arguments_env_and_file(
    monkeypatch: pytest.MonkeyPatch, hermetic: Path
) -> None:
    default = RobotConfig().twist_limiter()
    assert (default.linear.max_jerk, default.angular.max_jerk) == (math.inf, math.inf)
    assert RobotConfig(linear_jerk_mps3=0).twist_limiter().linear.max_jerk == math.inf
    assert RobotConfig(linear_jerk_mps3=2.5).twist_limiter().linear.max_jerk == 2.5
    monkeypatch.setenv("OHMNI_ANGULAR_JERK_RADPS3", "8")
    assert RobotConfig().twist_limiter().angular.max_jerk == 8.0
    monkeypatch.delenv("OHMNI_ANGULAR_JERK_RADPS3")
    (hermetic / "ohmni.toml").write_text("linear_jerk_mps3 = 4.0\n", encoding="utf-8")
    assert RobotConfig.load().twist_limiter().linear.max_jerk == 4.0


@pytest.mark.parametrize(
    ("name", "value", "allowed"),
    [
        ("linear_jerk_mps3", 0.5, "allowed 0 (off) or 1..1000 m/s³"),
        ("linear_jerk_mps3", -2, "allowed 0 (off) or 1..1000 m/s³"),
        ("angular_jerk_radps3", 5000, "allowed 0 (off) or 1..1000 rad/s³"),
    ],
)
def test_a_bad_jerk_limit_is_named_with_its_range(name: str, value: float, allowed: str) -> None:
    assert config_error(**{name: value}) == f"{name}={value} is out of range: {allowed} (argument)"


def test_pid_gains() -> None:
    gains = RobotConfig(pid_kp=1.0, pid_ki=2.0, pid_kd=3.0, pid_kff=4.0, pid_ff_offset=5.0)
    got = gains.pid_gains()
    assert (got.kp, got.ki, got.kd, got.kff, got.ff_offset) == (1.0, 2.0, 3.0, 4.0, 5.0)
    default = RobotConfig().pid_gains()
    assert (default.kp, default.ki, default.kff, default.ff_offset) == (600, 300, 940, 60)


def test_encoders_left_then_mirrored_right() -> None:
    left, right = RobotConfig(wheel_radius_m=0.07525, ticks_per_rev=40_000).encoders()
    assert left == EncoderConfig(ticks_per_rev=40_000, wheel_radius_m=0.07525)
    assert right == EncoderConfig(ticks_per_rev=40_000, wheel_radius_m=0.07525, mirrored=True)
    assert (left.mirrored, right.mirrored) == (False, True)


@pytest.mark.parametrize(
    ("latency_ms", "timeout_s"), [(0, DEFAULT_TIMEOUT_S), (16, 0.025), (1, 0.025), (32, 0.041)]
)
def test_bus_timeout_covers_the_usb_latency(latency_ms: int, timeout_s: float) -> None:
    assert RobotConfig(usb_latency_ms=latency_ms).bus_timeout_s() == pytest.approx(timeout_s)
