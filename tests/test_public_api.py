"""The public names of each module are pinned: a change to them is a decision, not a slip."""

from __future__ import annotations

import importlib

import pytest

PUBLIC = {
    "ohmni_tb.protocol": [
        "BROADCAST_ID", "MAX_PACKET_SIZE", "MIN_PACKET_SIZE", "REPLY_FLAG", "AckPolicy",
        "Command", "DecoderStats", "Memory", "Packet", "PacketDecoder", "ReadReply",
        "RejectReason", "StatusDetail", "StatusError", "StatusReply", "check_sid", "checksum",
        "encode_packet", "flag_names", "read_request", "reply_expected", "reply_matches",
        "write_request",
    ],
    "ohmni_tb.protocol.devices": [
        "DEFAULT_EXT_SERVO_IDS", "DEVICE_MAP", "NECK_RAW_RANGE", "DeviceId", "DeviceInfo",
        "device_name",
    ],
    "ohmni_tb.protocol.drive": [
        "DRIVE_PROFILE", "MOTOR_POSITION_MODULUS", "PWM_LIMIT", "DriveProfile", "DriveTorque",
        "decode_wheel_command", "parse_count", "parse_motor_position", "read_count",
        "read_firmware_tag", "read_motor_position", "set_torque", "wheel_command",
    ],
    "ohmni_tb.protocol.core": [
        "CELL_COUNT", "CORE_PROFILE", "CoreProfile", "TbcoreStatus", "encode_status",
        "parse_status", "percent_from_cells", "read_status", "set_light_ring",
    ],
    "ohmni_tb.protocol.worm_neck": [
        "WORM_MAX", "WORM_MIN", "WORM_PROFILE", "WormFeedback", "WormFlags", "WormProfile",
        "check_worm_target", "encode_feedback", "parse_feedback", "read_feedback", "set_target",
    ],
    "ohmni_tb.transport": [
        "DEFAULT_BAUDRATE", "Manipulator", "MemoryTransport", "SerialTransport", "Transport",
        "TransportFactory", "corrupt_byte", "delay", "drop_bytes", "open_transport",
        "option_bool", "option_int", "register_transport", "registered_schemes",
        "reject_unknown_options", "split",
    ],
    "ohmni_tb.bus": [
        "DEFAULT_GAP_S", "DEFAULT_RETRIES", "DEFAULT_TIMEOUT_S", "Bus", "BusStats",
        "DeviceStats",
    ],
    "ohmni_tb.herkulex.servo": ["Servo", "ServoStatus", "move_group"],
    "ohmni_tb.monitor": ["BusMonitor", "DeviceTraffic", "MonitorEvent", "describe"],
    "ohmni_tb.sim.line": [
        "LineFaults", "LineStats", "SimLine", "SimTransport", "build_line", "open_sim",
    ],
    "ohmni_tb.sim.robot": ["NECK_CHOICES", "SimRobot"],
    "ohmni_tb.sim.clock": ["VirtualClockLoop", "run_virtual"],
}  # fmt: skip


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_public_names_are_pinned_and_importable(module: str) -> None:
    mod = importlib.import_module(module)
    assert mod.__all__ == PUBLIC[module]
    for name in mod.__all__:
        assert hasattr(mod, name), f"{module}.{name} is in __all__ but missing"
