r"""One server per study folder: ``DIR/.server.lock`` held (``flock``) while ``study serve`` runs,
naming the server's process id and address, so a second server of the same folder is refused with
both; the lock of a server that died (killed, the machine restarted) is released by the system
and taken over, the takeover logged."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from pathlib import Path

from torchpref.study.folder import PRIVATE_FILE, StudyFolder, now

__all__ = ["ServerLock", "StudyBusy"]


class StudyBusy(ValueError):
    """The study folder is served by another server (its process id and address in the message)."""


class ServerLock:
    """``DIR/.server.lock`` of ``folder``, held until :meth:`release` (module docstring).

    Raises:
        StudyBusy: another running server holds it.
    """

    def __init__(self, folder: StudyFolder):
        self.folder, self.path = folder, folder.path / ".server.lock"
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), PRIVATE_FILE)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            other = _read(fd)
            os.close(fd)
            address = other.get("address") or "(an address not printed yet)"
            raise StudyBusy(
                f"the study {folder.path} is served already, by process {other.get('pid', '?')} at {address} "
                f"(since {other.get('started', '?')}): two servers of one folder would ask for the same refits "
                "and keep separate sessions. Use that server, or stop it first."
            ) from None
        self._fd: int | None = fd
        stale = _read(fd)
        if stale.get("pid") not in (None, os.getpid()):
            folder.log("stale server lock taken over", pid=stale.get("pid"), address=stale.get("address"))
        self.info = {"pid": os.getpid(), "address": None, "started": now()}
        self._write()

    def _write(self) -> None:
        assert self._fd is not None
        data = json.dumps(self.info).encode()
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, data, 0)
        os.fsync(self._fd)

    def serving_at(self, address: str) -> None:
        """Record the address the server listens at (for a second server's message)."""
        if self._fd is not None:
            self.info["address"] = address
            self._write()

    def release(self) -> None:
        """Let go of the folder (the file is emptied: no process is named any more)."""
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
        os.close(self._fd)  # closing releases the flock
        self._fd = None


def _read(fd: int) -> dict:
    try:
        data = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def lock_path(folder: StudyFolder) -> Path:
    """Where the lock of ``folder`` is."""
    return folder.path / ".server.lock"
