"""ohmni_tb: drive the OhmniLabs Ohmni robot over its serial bus, without ROS.

``from ohmni_tb import Robot, RobotConfig`` gives the asyncio Robot — ``Robot.open(port)``
on a serial port, ``sim://`` or a daemon's ``ws://`` URL, one API for all — and its
settings, and ``ohmni_tb.run(main())`` runs a program's coroutine as :func:`asyncio.run`
does, on a loop whose timers keep sub-millisecond time (:mod:`ohmni_tb.eventloop`). They are
imported on first use, so ``import ohmni_tb`` (and the CLI's start-up) stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ohmni_tb._version import __version__
from ohmni_tb.errors import MotionResult, OhmniError

if TYPE_CHECKING:
    from ohmni_tb.config import RobotConfig
    from ohmni_tb.eventloop import run
    from ohmni_tb.robot import Robot

__all__ = ["MotionResult", "OhmniError", "Robot", "RobotConfig", "__version__", "run"]

_LAZY = {"Robot": "ohmni_tb.robot", "RobotConfig": "ohmni_tb.config", "run": "ohmni_tb.eventloop"}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'ohmni_tb' has no attribute {name!r}")
    import importlib  # noqa: PLC0415  # lazy on purpose: see the module docstring

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
