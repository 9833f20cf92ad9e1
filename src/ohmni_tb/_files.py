"""Opening a file the user names, for reading, without being held up by what it is.

A FIFO would block ``open()`` until a writer comes, and a device such as ``/dev/zero``
never ends: the commands that read recordings and captures take regular files only, and
say what the path is when it is not one.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import IO

__all__ = ["NotRegularFileError", "open_regular"]


class NotRegularFileError(ValueError):
    """The path is a directory, a FIFO, a device or a socket: the message says which."""


def open_regular(path: str | Path) -> IO[bytes]:
    """``path`` open for reading in binary, if it is a regular file; never blocks in
    ``open()``.

    Raises:
        OSError: It cannot be opened (missing, not allowed...).
        ValueError: A NUL in the path.
        NotRegularFileError: It is not a regular file ("it is a named pipe (FIFO), not a
            regular file").
    """
    # O_NONBLOCK: opening a FIFO would otherwise wait for a writer (a regular file ignores
    # the flag).
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise NotRegularFileError(f"it is {_kind(mode)}, not a regular file")
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _kind(mode: int) -> str:
    """What a file that is not a regular file is, in words."""
    kinds = (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a named pipe (FIFO)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    )
    return next((name for test, name in kinds if test(mode)), "a special file")
