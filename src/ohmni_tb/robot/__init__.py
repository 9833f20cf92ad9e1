"""The asyncio Robot: one object that does tb_control's job, on this process's port or
through ``ohmni serve``.

:class:`Robot` is the contract (:mod:`ohmni_tb.robot.api`) and ``Robot.open(port)`` picks
the implementation: :class:`LocalRobot` (:mod:`ohmni_tb.robot.core`) runs the bus itself,
:class:`RemoteRobot` (:mod:`ohmni_tb.robot.remote`) talks to the daemon. Both are imported
here, so both are registered with :meth:`Robot.open` whenever this package is.
"""

from __future__ import annotations

from ohmni_tb.robot.api import HerkulexHandle, NeckHandle, Robot, SampleStream
from ohmni_tb.robot.core import BusFigures, LocalRobot, RobotStats
from ohmni_tb.robot.devices import COMMAND_PRIORITY, ServoHandle, WormNeckHandle
from ohmni_tb.robot.motion import MotionResult
from ohmni_tb.robot.remote import RemoteRobot, RemoteServo
from ohmni_tb.robot.samples import (
    STREAM_NAMES,
    STREAMS,
    DiagnosticEntry,
    DiagnosticLevel,
    DiagnosticsSample,
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
    "DiagnosticEntry",
    "DiagnosticLevel",
    "DiagnosticsSample",
    "HerkulexHandle",
    "Link",
    "LocalRobot",
    "MotionResult",
    "NeckHandle",
    "PidDebugSample",
    "RemoteRobot",
    "RemoteServo",
    "Robot",
    "RobotStateSample",
    "RobotStats",
    "Sample",
    "SampleStream",
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
