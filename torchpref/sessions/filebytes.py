"""Bytes of a session file: reading it whole, flushing its folder, a companion file's name, the
SHA-256 of its acknowledged prefix and its change times (used by :mod:`torchpref.sessions.journal`)."""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

__all__ = [
    "dropped_path",
    "file_kind",
    "fsync_dir",
    "prefix_digest",
    "read_fd",
    "stamp",
]


def file_kind(mode: int) -> str | None:
    """What a file that is not a regular file is (``None`` for a regular file)."""
    for test, name in (
        (stat.S_ISDIR, "a directory; give a file name"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return None if stat.S_ISREG(mode) else "not a regular file"


def fsync_dir(path: Path) -> None:
    """Flush the entries of the folder holding ``path`` (a new file's name), where the system allows."""
    try:
        fd = os.open(path.parent if str(path.parent) else ".", os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def read_fd(fd: int, size: int) -> bytes:
    """The file's bytes, read up to ``size`` (checked against :data:`MAX_FILE_BYTES` first)."""
    chunks, offset = [], 0
    while offset < size:
        chunk = os.pread(fd, min(1 << 20, size - offset), offset)
        if not chunk:
            break
        chunks.append(chunk)
        offset += len(chunk)
    return b"".join(chunks)


def dropped_path(path: Path) -> Path:
    """``FILE.dropped`` beside the file, with the name shortened where that would be too long."""
    name = os.fsencode(path.name) + b".dropped"
    if len(name) > 255:
        name = os.fsencode(path.name)[:200] + b"~" + str(abs(hash(path.name)) % 10**8).encode() + b".dropped"
    return path.parent / os.fsdecode(name)


def prefix_digest(fd: int, size: int) -> hashlib._Hash:
    """A SHA-256 (a :mod:`hashlib` object, to be updated) of the file's first ``size`` bytes."""
    digest, offset = hashlib.sha256(), 0
    while offset < size:
        chunk = os.pread(fd, min(1 << 20, size - offset), offset)
        if not chunk:
            break
        digest.update(chunk)
        offset += len(chunk)
    return digest


def stamp(st: os.stat_result) -> tuple[int, int]:
    """The file's change and modification times: any write by another program moves the first."""
    return st.st_ctime_ns, st.st_mtime_ns
