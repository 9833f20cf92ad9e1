"""The public names of each module are pinned: a change to them is a decision, not a slip."""

from __future__ import annotations

import importlib

import pytest

PUBLIC = {
    "ohmni_tb.protocol": [
        "BROADCAST_ID", "MAX_PACKET_SIZE", "MIN_PACKET_SIZE", "REPLY_FLAG", "AckPolicy",
        "BusConnection", "Command", "DecoderStats", "Memory", "Packet", "PacketDecoder",
        "ReadReply", "RejectReason", "ReplyPacket", "StatusDetail", "StatusError",
        "StatusReply", "check_sid", "checksum", "encode_packet", "flag_names", "read_request",
        "reply_expected", "reply_matches", "transaction_cost_s", "wire_time_s", "write_request",
    ],
    "ohmni_tb.protocol.timing": [
        "BITS_PER_BYTE", "DEFAULT_BAUDRATE", "DEFAULT_GUARD_S", "DEFAULT_TURNAROUND_S",
        "reply_size_range", "transaction_cost_s", "wire_time_s",
    ],
    "ohmni_tb.protocol.connection": [
        "DEFAULT_BREAKER_QUIET_S", "DEFAULT_BREAKER_TIMEOUTS", "DEFAULT_CAUTION_S",
        "DEFAULT_PROBE_INTERVAL_S",
        "DEFAULT_TIMEOUT_S", "BreakerState", "BusConnection", "ConnectionStats", "DeviceStats",
        "Event", "Exchange", "MissingReason", "ReplyMatcher", "ReplyMissing", "ReplyPacket",
        "ReplyReceived", "StrayKind", "StrayPacket", "is_idempotent",
    ],
    "ohmni_tb.transport.base": [
        "DEFAULT_WRITE_TIMEOUT_S", "LostHandler", "ReceiveBuffer", "Receiver", "Transport",
    ],
    "ohmni_tb.protocol.devices": [
        "DEFAULT_EXT_SERVO_IDS", "DEVICE_MAP", "KNOWN_FIRMWARE_TAGS", "NECK_RAW_RANGE",
        "DeviceId", "DeviceInfo", "device_name", "firmware_known",
    ],
    "ohmni_tb.protocol.drive": [
        "DRIVE_PROFILE", "MOTOR_POSITION_MODULUS", "PWM_LIMIT", "DriveProfile", "DriveTorque",
        "WheelJogForm", "decode_wheel_command", "parse_count", "parse_motor_position",
        "read_count", "read_firmware_tag", "read_motor_position", "set_board_id", "set_torque",
        "wheel_command",
    ],
    "ohmni_tb.protocol.jog": [
        "I_JOG_TAG_SIZE", "MAX_JOG_POSITION", "MAX_TURN_MAGNITUDE", "S_JOG_TAG_SIZE",
        "TURN_SIGN_BIT", "JogSet", "JogTag", "decode_jog_word", "encode_jog_word", "jog_data",
        "jog_tags",
    ],
    "ohmni_tb.protocol.core": [
        "CELL_COUNT", "CELL_MAX_MV", "CELL_MIN_MV", "CELL_SPREAD_MAX_MV", "CORE_PROFILE",
        "BatteryLayout", "CoreProfile", "TbcoreStatus", "cells_plausible", "decode_status",
        "encode_status", "parse_status", "percent_from_cells", "read_status", "set_light_ring",
    ],
    "ohmni_tb.protocol.profile": [
        "DEFAULT_PROFILE", "PROFILE_SETTINGS", "BusProfile", "check_ext_servo_ids",
        "parse_ext_servo_ids",
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
        "DEFAULT_CLOSE_TIMEOUT_S", "DEFAULT_GUARD_S", "DEFAULT_MAX_WAIT_S", "DEFAULT_RETRIES",
        "DEFAULT_STALL_S", "DEFAULT_TIMEOUT_S", "DEFAULT_TURNAROUND_S", "BreakerState", "Bus",
        "BusStats", "DeviceStats", "ReplyPacket", "Slot", "Tap", "transaction_cost_s",
    ],
    "ohmni_tb.herkulex.servo": ["Requester", "Servo", "ServoStatus", "move_group"],
    "ohmni_tb.safety": [
        "DEFAULT_REPEAT_S", "DEFAULT_SETTLE_S", "DEFAULT_STOP_TIMEOUT_S",
        "DEFAULT_TOLERANCE_TICKS", "SETTLE_READS", "SettleWindow", "StopReport",
        "stop_wheels",
    ],
    "ohmni_tb.monitor": ["BusMonitor", "DeviceTraffic", "MonitorEvent", "describe"],
    "ohmni_tb.sim.line": [
        "DEFAULT_TURNAROUND_S", "MAX_USB_LATENCY_S", "USB_PACKET_PAYLOAD", "HostReceiver",
        "LineFaults", "LineStats", "LineTap", "SimLine",
    ],
    "ohmni_tb.sim.tbnode_log": ["TbnodeLog"],
    "ohmni_tb.capture.tbnode": [
        "FIELDS", "MAX_LINE_BYTES", "MAX_SKIPPED_KEPT", "MAX_T_S", "PLUGIN_FILE", "RX", "TX",
        "LogReader", "LogRecord", "LogSummary", "SkippedLine", "format_record",
        "parse_record", "plugin_source",
    ],
    "ohmni_tb.sim.transport": ["SimTransport"],
    "ohmni_tb.sim.url": ["build_line", "open_sim"],
    "ohmni_tb.sim.robot": ["NECK_CHOICES", "SimRobot"],
    "ohmni_tb.sim.clock": ["VirtualClockLoop", "run_virtual"],
    "ohmni_tb": ["MotionResult", "OhmniError", "Robot", "RobotConfig", "__version__", "run"],
    "ohmni_tb.eventloop": [
        "DEFAULT_RT_PRIORITY", "LineClock", "PreciseEpollSelector", "line_clock",
        "new_event_loop", "realtime_priority", "run", "set_realtime", "timer_resolution_s",
    ],
    "ohmni_tb.config": [
         "CONFIG_ENV", "CONFIG_FILE_NAME", "ENV_PREFIX", "RobotConfig", "config_paths",
         "user_config_dir",
    ],
    "ohmni_tb.config_file": [
        "SettingValue", "WriteOutcome", "default_config_file", "loaded_config_file",
        "read_settings", "write_settings",
    ],
    "ohmni_tb.probe": [
        "ALL_IDS", "AdapterInfo", "Device", "Finding", "ProbeReport", "RawRead", "Skipped",
        "Status", "WheelTrial", "probe", "probe_port", "read_adapter", "shareable",
        "wheel_stops",
    ],
    "ohmni_tb.robot": [
        "COMMAND_PRIORITY", "DEFAULT_QUEUE_SIZE", "STREAMS", "STREAM_NAMES", "BusFigures",
        "DiagnosticEntry", "DiagnosticLevel", "DiagnosticsSample", "HerkulexHandle", "Link",
        "LocalRobot", "MotionResult", "NeckHandle",
        "PidDebugSample", "RemoteRobot", "RemoteServo", "Robot", "RobotStateSample",
        "RobotStats", "Sample", "SampleStream", "ServoHandle", "ServoSample", "StreamSpec",
        "StreamStats", "Subscription", "TbcoreStatusSample", "WheelEncoderSample",
        "WheelOdomSample", "WormNeckHandle", "WormNeckSample",
    ],
    "ohmni_tb.robot.teleop": [
        "ACTIONS", "DEFAULT_ANGULAR_RADPS", "DEFAULT_LINEAR_MPS", "KEYS", "KEY_HOLD_S",
        "SCALE_STEP", "KeyParser", "KeyTeleop",
    ],
    "ohmni_tb.client": [
        "DEFAULT_TIMEOUT_S", "DEFAULT_URL", "RobotClient",
    ],
    "ohmni_tb.robot.wire": [
        "CLIENT_OPS", "ERROR_CODES", "LEASE_METHODS", "MAX_QUEUE", "METHODS",
        "METHOD_SPECS", "PROTOCOL_VERSION", "TOKEN_ENV", "AcquireArgs", "BatchMessage",
        "BoardIdArgs", "Call", "ClientMessage", "ConnectArgs", "DriveArgs",
        "DriveDistanceArgs", "DrivePwmArgs",
        "DriveWheelsArgs", "EnabledArgs", "ErrorCode", "ErrorMessage", "GoToArgs", "Hello",
        "LatestArgs", "LeaseMessage", "LightArgs", "Limits", "MethodSpec", "Motion",
        "MoveArgs", "NoArgs", "OdometryArgs", "PidArgs", "PoseArgs", "RateArgs", "ReleaseArgs",
        "ReleasePortArgs", "RequestError", "RestArgs", "Result", "RotateArgs", "SampleMessage",
        "ServerMessage", "ServoArgs", "ServoCommand", "ServoIdArgs", "ServoWriteArgs",
        "SourceArgs", "SourceName", "StreamArgs", "Subscribe", "TorqueArgs", "Unsubscribe",
        "WheelArgs", "WheelName",
        "ZeroOffsetArgs", "call_args", "encode", "goal_from_json", "goal_json",
        "info_from_json", "json_schema", "parse_client_message", "parse_server_message",
        "pid_from_json", "pid_state_from_json", "pid_state_json", "raised_error",
        "result_json", "sample_from_json", "sample_json",
        "schedule_from_json", "schema_text", "servo_status_from_json", "servo_status_json",
        "stats_from_json", "stats_json",
        "write_schema",
    ],
    "ohmni_tb.robot.api": [
        "HerkulexHandle", "NeckHandle", "Robot", "RobotStreams", "SampleStream",
    ],
    "ohmni_tb.robot.remote": [
        "DEFAULT_TIMEOUT_S", "DEFAULT_URL", "STATS_IDLE_REFRESH_S", "STATS_IDLE_S",
        "STATS_REFRESH_S", "RemoteRobot", "RemoteServo",
    ],
    "ohmni_tb.daemon.server": [
         "BURST_MESSAGES", "DEFAULT_HOST", "DEFAULT_MAX_CLIENTS", "DEFAULT_PORT",
         "HARD_MAX_MESSAGE_BYTES", "MAX_MESSAGES_PER_S", "MAX_MESSAGE_BYTES",
         "READER_BURST", "READER_MESSAGES_PER_S", "REFUSAL_LOG_S", "SAMPLE_FLUSH_S",
         "STATS_INTERVAL_S", "ClientFigures", "RobotServer", "check_listen", "is_loopback",
    ],
    "ohmni_tb.foxglove": [
         "CHANNELS", "DEFAULT_HOST", "DEFAULT_PORT", "ChannelSpec", "ChannelStats",
         "FoxgloveBridge", "McapRecorder", "McapReplay", "RecordingError", "ReplayError",
         "RobotControl",
    ],
    "ohmni_tb.foxglove.control": [
         "LIMIT_PARAMETERS", "NECK_MOVE_SERVICE", "PARAMETER_PREFIX", "PID_PARAMETERS",
         "RATE_STREAMS", "RESET_ODOM_SERVICE", "SERVICE_SCHEMAS", "SET_ODOMETRY_SERVICE",
         "RobotControl",
    ],
    "ohmni_tb.foxglove.replay": ["MAX_SPEED", "McapReplay", "ReplayError", "raw_bus_bytes"],
    "ohmni_tb.foxglove.channels": [
         "BASE_FRAME", "CHANNELS", "ODOM_FRAME", "ChannelSpec", "Encoder", "WallClock",
         "channel_schema", "channels_of", "encoder_for", "json_schema_of",
    ],
    "ohmni_tb.foxglove.bridge": [
         "DEFAULT_BACKLOG", "DEFAULT_HOST", "DEFAULT_PORT", "TELEOP_RAMPED", "TELEOP_TOPICS",
         "FoxgloveBridge",
         "Teleop", "parse_twist",
    ],
    "ohmni_tb.foxglove.record": [
         "DEFAULT_FLUSH_INTERVAL_S", "MAX_BACKLOG_BYTES", "MAX_DURATION_S", "RAW_SCHEMA_NAME",
         "RAW_TOPICS", "McapRecorder", "RecordingError", "write_raw_recording",
    ],
    "ohmni_tb.foxglove.access": [
         "LOCKED_MESSAGE", "LOCKED_STATUS_ID", "UNLOCK_SCHEMAS", "UNLOCK_SERVICE",
         "AccessStats", "ControlGate",
    ],
    "ohmni_tb.foxglove.teleop": [
         "DEFAULT_RATE_HZ", "MAX_RATE_HZ", "TELEOP_IDLE_S", "FoxgloveTeleop", "TeleopStats",
    ],
    "ohmni_tb.daemon.supervisor": [
         "HEARTBEAT_S", "HUNG_S", "MAX_QUICK_DEATHS", "QUICK_DEATH_S", "RESTART_BACKOFF_S",
         "WORKER_EXIT_S", "WorkerCommand", "stop_wheels_at", "supervise", "until_stopped",
    ],
    "ohmni_tb.daemon.local": ["LocalClient"],
    "ohmni_tb.mqtt": ["Backoff", "Broker", "MqttBridge", "default_robot_id"],
    "ohmni_tb.mqtt.bridge": [
         "COMMANDS_AT_ONCE", "COMMANDS_PER_S", "MqttBridge", "default_robot_id",
    ],
    "ohmni_tb.mqtt.broker": [
         "BACKOFF_FIRST_S", "BACKOFF_MAX_S", "Backoff", "Broker", "require_client",
    ],
    "ohmni_tb.mqtt.payloads": [
         "AVAILABILITY", "COMMANDS", "DRIVING", "ERROR_CODES_MQTT", "OFFLINE", "ONLINE",
         "RESPONSE", "ROOT", "STATE_PERIOD_S", "BatteryState", "BridgeFigures", "ErrorReply",
         "NeckState", "ResultReply", "StatePayload", "command_topic", "discovery_messages",
         "fleet_schema", "ha_light_args", "response_topic_allowed", "robot_topic", "state_key",
         "write_fleet_schema",
    ],
    "ohmni_tb.fleet": ["DEFAULT_CALL_TIMEOUT_S", "Fleet", "FleetRobot"],
    "ohmni_tb.daemon.auth": [
         "MIN_TOKEN_CHARS", "TOKEN_ENV", "TOKEN_FILE_NAME", "TOKEN_PROTOCOL_PREFIX",
         "WEB_PROTOCOL", "check_origin", "check_token", "default_token_path",
         "load_or_create_token", "presented_token", "read_token",
    ],
    "ohmni_tb.daemon.web": [
        "AUTH_PATH", "CONTENT_TYPES", "HEADLESS_CHROMIUM_ARGS", "WEB_FOLDER", "WebConsole",
        "page_url",
    ],
}  # fmt: skip


def test_the_robot_and_its_config_are_importable_from_the_package() -> None:
    from ohmni_tb import Robot, RobotConfig
    from ohmni_tb.config import RobotConfig as Config
    from ohmni_tb.robot import LocalRobot, RemoteRobot
    from ohmni_tb.robot import Robot as RobotClass
    from ohmni_tb.robot.api import Robot as Contract

    assert Robot is RobotClass is Contract
    assert issubclass(LocalRobot, Robot)
    assert issubclass(RemoteRobot, Robot)
    assert RobotConfig is Config


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_public_names_are_pinned_and_importable(module: str) -> None:
    mod = importlib.import_module(module)
    assert mod.__all__ == PUBLIC[module]
    for name in mod.__all__:
        assert hasattr(mod, name), f"{module}.{name} is in __all__ but missing"
