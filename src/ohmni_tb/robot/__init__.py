"""The asyncio Robot: one object that does tb_control's job (see :mod:`ohmni_tb.robot.core`)."""

from __future__ import annotations

from ohmni_tb.robot.core import BusFigures, Robot, RobotStats
from ohmni_tb.robot.devices import COMMAND_PRIORITY, ServoHandle, WormNeckHandle
from ohmni_tb.robot.samples import (
    STREAM_NAMES,
    STREAMS,
    Link,
    PidDebugSample,
    RobotStateSample,
    Sample,
    ServoSample,
    StreamSpec,
    TbcoreStatusSample,
    WheelEncoderSample,
    WheelOdomSample,
    WormNeckSample,
)
from ohmni_tb.robot.streams import DEFAULT_QUEUE_SIZE, StreamStats, Subscription

__all__ = [
    "COMMAND_PRIORITY",
    "DEFAULT_QUEUE_SIZE",
    "STREAMS",
    "STREAM_NAMES",
    "BusFigures",
    "Link",
    "PidDebugSample",
    "Robot",
    "RobotStateSample",
    "RobotStats",
    "Sample",
    "ServoHandle",
    "ServoSample",
    "StreamSpec",
    "StreamStats",
    "Subscription",
    "TbcoreStatusSample",
    "WheelEncoderSample",
    "WheelOdomSample",
    "WormNeckHandle",
    "WormNeckSample",
]
