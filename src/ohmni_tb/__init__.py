"""ohmni_tb: drive the OhmniLabs Ohmni robot over its serial bus, without ROS."""

from __future__ import annotations

from ohmni_tb.errors import OhmniError

__all__ = ["OhmniError", "__version__"]

__version__ = "0.1.0"
