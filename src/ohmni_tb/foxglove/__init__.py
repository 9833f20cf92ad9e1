"""See and record the robot with Foxglove and MCAP, through the official foxglove-sdk.

:class:`FoxgloveBridge` serves an open Robot's streams to the Foxglove app (WebSocket,
``ws://127.0.0.1:8765`` by default), with its parameters and services
(:class:`RobotControl`), which a client changes only after unlocking control with the
token (:mod:`ohmni_tb.foxglove.access`; the Teleop panel's Twists through the daemon:
:mod:`ohmni_tb.foxglove.teleop`); :class:`McapRecorder` writes them to an MCAP file, and
:class:`McapReplay` serves such a file to the app as if live.
Both publish the channels of :data:`CHANNELS` (:mod:`ohmni_tb.foxglove.channels`): the
odometry as ``foxglove.FrameTransform`` and ``foxglove.PoseInFrame`` for the 3D panel,
and every stream's samples as JSON, named like tb_control's topics. See docs/foxglove.md.

Needs the ``foxglove`` extra: ``pip install 'ohmni_tb[foxglove]'`` (foxglove-sdk, mcap).
"""

from __future__ import annotations

try:
    import foxglove as _sdk
except ImportError as exc:  # pragma: no cover - depends on what is installed
    raise ImportError(
        "ohmni_tb.foxglove needs foxglove-sdk: pip install 'ohmni_tb[foxglove]'"
    ) from exc

from ohmni_tb.foxglove._pump import ChannelStats
from ohmni_tb.foxglove.bridge import DEFAULT_HOST, DEFAULT_PORT, FoxgloveBridge
from ohmni_tb.foxglove.channels import CHANNELS, ChannelSpec
from ohmni_tb.foxglove.control import RobotControl
from ohmni_tb.foxglove.record import McapRecorder, RecordingError
from ohmni_tb.foxglove.replay import McapReplay, ReplayError

__all__ = [
    "CHANNELS",
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "ChannelSpec",
    "ChannelStats",
    "FoxgloveBridge",
    "McapRecorder",
    "McapReplay",
    "RecordingError",
    "ReplayError",
    "RobotControl",
]

del _sdk
