"""The package's version, in a module of its own: what reports it (the daemon's hello, a
recording's metadata, ``ohmni --version``) imports it without importing the package's
lazy names."""

from __future__ import annotations

__all__ = ["__version__"]

__version__ = "0.1.0"
