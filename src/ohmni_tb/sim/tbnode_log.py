"""The simulated line's traffic as a tb-node capture log (``sim://?tbnode_log=PATH``).

On a real robot the tb-node plugin logs the bytes the vendor's driver writes and reads;
the simulator logs its host's the same way, in the same format
(:mod:`ohmni_tb.capture.tbnode`), with the line's time. ``ohmni bus convert`` and
``ohmni bus monitor --capture`` then run on traffic whose truth is known.
"""

from __future__ import annotations

import logging
import os

from ohmni_tb.capture.tbnode import format_record
from ohmni_tb.errors import ConfigError

__all__ = ["TbnodeLog"]

_log = logging.getLogger(__name__)


class TbnodeLog:
    """Appends a line's traffic to a file as a tb-node capture log: a
    :data:`~ohmni_tb.sim.line.LineTap` (``line.add_tap(TbnodeLog(path))``).

    The file is created (emptied if it exists) when this is made. Each chunk is then
    appended as one line, on disk when the call returns: the file is opened for it and
    closed again, so nothing stays open however long the line lives, across the host's
    reconnections. A write that fails (a full disk) is counted in :attr:`write_errors`,
    logged the first time, and the line goes on.

    Args:
        path: The log file.

    Raises:
        ConfigError: The file cannot be created; the message names the option.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = os.fspath(path)
        #: Lines written.
        self.records = 0
        #: Lines lost to failed writes.
        self.write_errors = 0
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | _CLOEXEC, 0o644)
        except (OSError, ValueError) as exc:  # ValueError: a NUL in the path
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise ConfigError(
                f"option tbnode_log={self.path!r}: cannot create it: {reason}"
            ) from exc
        os.close(fd)

    def __call__(self, sent: bool, data: bytes, t_s: float) -> None:
        """Log ``data``, written by the host (``sent``) or handed to it, at ``t_s``."""
        line = format_record(t_s, sent, data).encode()
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | _CLOEXEC, 0o644)
            try:
                view = memoryview(line)
                while view:
                    view = view[os.write(fd, view) :]
            finally:
                os.close(fd)
        except OSError as exc:
            self.write_errors += 1
            if self.write_errors == 1:
                _log.warning(
                    "tbnode_log %s: a write failed (%s); counting the lines lost", self.path, exc
                )
            return
        self.records += 1


_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
