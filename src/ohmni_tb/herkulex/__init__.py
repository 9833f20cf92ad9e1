"""HerkuleX DRS-0101 / DRS-0201 servos: registers, commands, replies and units (sans-IO).

Everything here builds or parses :class:`~ohmni_tb.protocol.Packet` objects and never
touches a port or a clock::

    from ohmni_tb.herkulex import (
        JogTarget,
        Led,
        TorqueControl,
        i_jog,
        playtime_ticks_from_s,
        ram_write,
    )

    torque_on = ram_write(3, "torque_control", TorqueControl.ON)
    move = i_jog(JogTarget(3, 650, led=Led.GREEN, playtime_ticks=playtime_ticks_from_s(1.0)))
    print(torque_on, move)

Whether a request is answered is decided by :func:`reply_expected` alone (the same
function as :func:`ohmni_tb.protocol.reply_expected`). The bits of a jog tag are written
once, in :mod:`ohmni_tb.protocol.jog`, which the drive boards' wheel command shares.
"""

from __future__ import annotations

from ohmni_tb.herkulex.commands import (
    MAX_I_JOG_TARGETS,
    MAX_PWM,
    MAX_S_JOG_TARGETS,
    TURN_SIGN_BIT,
    JogMode,
    JogTarget,
    Reply,
    clear_status,
    decode_jog,
    eep_read,
    eep_write,
    eep_write_many,
    i_jog,
    model_read,
    parse_model,
    parse_reply,
    ram_read,
    ram_write,
    ram_write_many,
    reboot,
    rollback,
    s_jog,
    stat,
)
from ohmni_tb.herkulex.registers import (
    EEP,
    RAM,
    BaudRate,
    Led,
    Model,
    Register,
    RegisterMap,
    TorqueControl,
    model_from_bytes,
)
from ohmni_tb.herkulex.units import (
    DEG_PER_COUNT,
    MAX_PLAYTIME_TICKS,
    TICK_S,
    angle_deg_from_raw,
    angle_rad_from_raw,
    playtime_s_from_ticks,
    playtime_sent_s,
    playtime_ticks_from_s,
    pos_raw_from_deg,
    pos_raw_from_rad,
    speed_dps_from_raw,
    speed_rad_s_from_raw,
    voltage_raw_from_v,
    voltage_v_from_raw,
)
from ohmni_tb.protocol import AckPolicy, StatusDetail, StatusError, reply_expected

__all__ = [
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
]
