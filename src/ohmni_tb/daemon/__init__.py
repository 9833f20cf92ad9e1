"""``ohmni serve``: one process owns the robot and serves it to many clients (WebSocket).

The server (:mod:`ohmni_tb.daemon.server`) runs next to a :class:`~ohmni_tb.Robot`; the
client is :class:`ohmni_tb.client.RobotClient`; the messages and their schema are in
:mod:`ohmni_tb.daemon.protocol`. Read-only in this version: streams and the read-only
services (stats, info, latest, schedule). See docs/daemon.md.
"""

from __future__ import annotations

__all__: list[str] = []
