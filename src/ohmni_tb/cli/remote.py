"""The commands through ``ohmni serve``: whether the daemon serves the simulator.

A command opens the port itself unless a daemon answers (then the port is the daemon's:
a second opener would only get "port busy"): ``common.daemon_for`` decides, and
``common.open_robot`` opens the daemon's robot with ``RemoteRobot.open(url)`` — what
``Robot.open(url)`` gives, the same API as a port's.
"""

from __future__ import annotations

__all__ = ["serves_simulator"]


async def serves_simulator(url: str) -> bool:
    """Whether the daemon at ``url`` serves the built-in simulator, as its ``hello`` says
    (a command's motion then needs no consent, as on ``sim://``).

    Raises:
        TransportError: The daemon does not answer or refused the connection.
    """
    from ohmni_tb.robot import RemoteRobot  # noqa: PLC0415  # the client: when used

    async with RemoteRobot.open(url) as robot:
        return robot.simulated
