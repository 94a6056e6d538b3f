"""Reading a small input file safely: a regular file only (a FIFO, device, socket or directory is
refused by name without blocking), no larger than a bound, decoded as UTF-8."""

from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["read_regular_text"]

_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _kind(mode: int) -> str | None:
    for test, name in _KINDS:
        if test(mode):
            return name
    return None if stat.S_ISREG(mode) else "not a regular file"


def read_regular_text(path: str | os.PathLike[str], what: str, max_bytes: int = 16 * 2**20) -> str:
    """The text of ``path``, ``what`` naming the file in errors (``"question list"``).

    Raises:
        FileNotFoundError: no such file (naming ``what`` and the path).
        ValueError: the path is not a regular file (never opened for reading, so a FIFO cannot
            block), is larger than ``max_bytes``, or is not UTF-8 text.
    """
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"no {what} file {path}") from None
    kind = _kind(st.st_mode)
    if kind is not None:
        raise ValueError(f"the {what} {path} is {kind}; give a regular file.")
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)  # it may have changed between the stat and the open
        kind = _kind(st.st_mode)
        if kind is not None:
            raise ValueError(f"the {what} {path} is {kind}; give a regular file.")
        if st.st_size > max_bytes:
            raise ValueError(f"the {what} {path} is {st.st_size} bytes, over the {max_bytes} this reads.")
        with os.fdopen(os.dup(fd), "rb") as fh:
            data = fh.read(max_bytes + 1)
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise ValueError(f"the {what} {path} is over the {max_bytes} bytes this reads.")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"the {what} {path} is not UTF-8 text ({err}).") from None
