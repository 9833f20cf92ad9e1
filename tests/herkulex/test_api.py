"""The public surface of ohmni_tb.herkulex is pinned, and its codec half stays sans-IO."""

from __future__ import annotations

import ast
from pathlib import Path

import ohmni_tb.sim.servo as sim_servo
from ohmni_tb import herkulex

EXPECTED = {
    "DEG_PER_COUNT",
    "EEP",
    "MAX_I_JOG_TARGETS",
    "MAX_PLAYTIME_TICKS",
    "MAX_PWM",
    "MAX_S_JOG_TARGETS",
    "RAM",
    "TICK_S",
    "TURN_SIGN_BIT",
    "AckPolicy",
    "BaudRate",
    "JogMode",
    "JogTarget",
    "Led",
    "Model",
    "Register",
    "RegisterMap",
    "Reply",
    "StatusDetail",
    "StatusError",
    "TorqueControl",
    "angle_deg_from_raw",
    "angle_rad_from_raw",
    "clear_status",
    "decode_jog",
    "eep_read",
    "eep_write",
    "eep_write_many",
    "i_jog",
    "model_from_bytes",
    "model_read",
    "parse_model",
    "parse_reply",
    "playtime_s_from_ticks",
    "playtime_sent_s",
    "playtime_ticks_from_s",
    "pos_raw_from_deg",
    "pos_raw_from_rad",
    "ram_read",
    "ram_write",
    "ram_write_many",
    "reboot",
    "reply_expected",
    "rollback",
    "s_jog",
    "speed_dps_from_raw",
    "speed_rad_s_from_raw",
    "stat",
    "voltage_raw_from_v",
    "voltage_v_from_raw",
}
# No I/O and no clock in the codec or the virtual firmware: time is an argument.
FORBIDDEN = {"asyncio", "serial", "socket", "threading", "time", "datetime", "random"}


def test_all_is_pinned() -> None:
    assert set(herkulex.__all__) == EXPECTED
    for name in EXPECTED:
        assert hasattr(herkulex, name), name


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module.split(".")[0])
    return names


def test_codec_and_sim_servo_import_no_io_or_clock() -> None:
    herkulex_dir = Path(herkulex.__file__).parent
    paths = [
        herkulex_dir / "registers.py",
        herkulex_dir / "commands.py",
        herkulex_dir / "units.py",
        Path(sim_servo.__file__),
    ]
    for path in paths:
        assert not imported_modules(path) & FORBIDDEN, path.name
