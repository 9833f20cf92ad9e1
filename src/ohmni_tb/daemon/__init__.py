"""``ohmni serve``: one process owns the robot and serves it to many clients (WebSocket).

The server (:mod:`ohmni_tb.daemon.server`) runs next to a :class:`~ohmni_tb.Robot`; a
program opens the daemon's robot with ``Robot.open("ws://127.0.0.1:8766")``
(:class:`~ohmni_tb.robot.RemoteRobot`; :class:`ohmni_tb.client.RobotClient` adds explicit
control of the lease); the messages and their schema are in :mod:`ohmni_tb.robot.wire`.
See docs/daemon.md.
"""

from __future__ import annotations

__all__: list[str] = []
