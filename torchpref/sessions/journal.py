r"""The session file: an append-only JSON Lines journal of a person's answers.

A :class:`Journal` owns one file: it locks it (``flock``) *before* reading it, validates every
record against the format (:mod:`torchpref.sessions.records`: types, ranges, item counts; an error names
the file and the line), repairs a partial last line on request, and appends records with
``fsync`` so that an acknowledged answer survives a crash. :class:`~torchpref.sessions.session.PreferenceSession` is the
ask/tell/undo logic on top of it.

File format (version 1, see ``docs/sessions.md``)::

    {"type": "header", "version": 1, "dim": 2, "seed": 0, "num_queries": 14, "num_levels": 5,
     "bounds": [[...], [...]], "candidates": {"kind": "pool", "items": [[...], ...]}, ...}
    {"type": "answer", "v": 1, "seq": 1, "time": "...", "kind": "rating", "items": [[...]],
     "answer": 4, "value": 0.7, "query": {"kind": "rating", "step": 0, "pool_indices": [17]}}
    {"type": "undo", "v": 1, "seq": 2, "time": "...", "undoes": 1}

A last line that is not a valid record (a crash mid-write) raises :class:`SessionFileCorrupt`
with the line number; ``repair=True`` reports it (a :class:`SessionRepairWarning`), moves the
partial bytes to ``FILE.dropped`` and truncates the file to its last complete record. A last
record that is complete but lacks only its newline is kept (the newline is added on open).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import warnings
from pathlib import Path
from collections.abc import Callable

from torchpref.sessions.records import (
    ANSWER_KINDS,
    FORMAT_VERSION,
    SessionFileCorrupt,
    SessionFileError,
    SessionMismatchError,
    SessionRepairWarning,
    SessionVersionError,
    check_new_record,
    validate_header,
    validate_records,
)

__all__ = [
    "ANSWER_KINDS",
    "FORMAT_VERSION",
    "Journal",
    "SessionFileCorrupt",
    "SessionFileError",
    "SessionMismatchError",
    "SessionRepairWarning",
    "SessionVersionError",
    "read_session_file",
]


def now() -> str:
    """The current UTC time, ISO 8601 with milliseconds (the records' ``time``)."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _write_all(fd: int, data: bytes) -> None:
    """Write all of ``data`` to ``fd`` (``os.write`` may write less than asked)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _encode(record: dict) -> bytes:
    return (json.dumps(record, allow_nan=False, separators=(",", ":")) + "\n").encode()


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def _parse(path, data: bytes) -> tuple[dict | None, list[dict], bool]:
    """``(header, records, newline_missing)`` from a file's bytes, every record validated."""
    if not data:
        return None, [], False
    lines = data.split(b"\n")
    newline_missing = bool(lines[-1])
    if not newline_missing:
        lines = lines[:-1]
    parsed, offset = [], 0
    for i, line in enumerate(lines):
        last = i == len(lines) - 1
        try:
            rec = json.loads(line.decode(), parse_constant=_reject_constant)
            if not isinstance(rec, dict) or "type" not in rec:
                raise ValueError("not a JSON object with a 'type'")
        except RecursionError:
            reason = "not a valid record (nested too deeply)"
            raise SessionFileCorrupt(path, i + 1, reason, last, line, offset) from None
        except (UnicodeDecodeError, ValueError) as exc:
            reason = (
                f"the last line is incomplete (no newline at its end; {exc})"
                if last and newline_missing
                else f"not a valid record ({exc})"
            )
            raise SessionFileCorrupt(path, i + 1, reason, last, line, offset) from None
        parsed.append(rec)
        offset += len(line) + 1
    header = parsed[0]
    validate_header(path, header)
    validate_records(path, header, parsed[1:])
    return header, parsed[1:], newline_missing


def read_session_file(path) -> tuple[dict | None, list[dict], int]:
    """Parse and validate a session file without changing it (and without locking it).

    Returns:
        ``(header, records, size)``: the header (``None`` for an empty file), the records after
        it in order, and the file's size in bytes.

    Raises:
        SessionFileCorrupt: a line is incomplete or not JSON (with its line number).
        SessionVersionError: a record is of a newer format version.
        SessionFileError: a record breaks the format (a missing or wrong field, sequence
            numbers, undo targets), naming the file and the line.
    """
    path = Path(path)
    if path.is_dir():
        raise SessionFileError(f"session file {path} is a directory; give a file name.")
    data = path.read_bytes()
    header, records, _ = _parse(path, data)
    return header, records, len(data)


def _lock(fd: int, path) -> None:
    try:
        import fcntl
    except ImportError:  # not POSIX: no advisory lock
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise SessionFileError(f"session file {path} is in use by another process.") from None


def _fsync_dir(path: Path) -> None:
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


def _read_fd(fd: int) -> bytes:
    chunks, offset = [], 0
    while True:
        chunk = os.pread(fd, 1 << 20, offset)
        if not chunk:
            return b"".join(chunks)
        chunks.append(chunk)
        offset += len(chunk)


class Journal:
    """One session file, locked for as long as it is open.

    Args:
        path: the file; created (with ``new_header()``) if missing or empty.
        new_header: builds the header record of a new file (``None``: an empty file stays empty
            and :attr:`header` is ``None``).
        repair: if the file ends in a partial line, report it, move it to ``FILE.dropped`` and
            continue; by default that raises :class:`SessionFileCorrupt`.

    Raises:
        SessionFileError: the path is a directory, the file is in use, or a record is invalid.
        SessionFileCorrupt: a partial or invalid line (``repair=True`` fixes a bad last line).
        SessionVersionError: a newer format version.
    """

    def __init__(self, path, new_header: Callable[[], dict] | None, *, repair: bool = False):
        self.path = Path(path)
        if self.path.is_dir():
            raise SessionFileError(f"session file {self.path} is a directory; give a file name.")
        self._fd: int | None = os.open(self.path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            _lock(self._fd, self.path)  # before reading: no other writer can slip in between
            self.header, self.records = self._read(repair)
            if self.header is None and new_header is not None:
                self.header = new_header()
                self._write(_encode(self.header))
                _fsync_dir(self.path)
        except BaseException:
            os.close(self._fd)
            self._fd = None
            raise

    def _read(self, repair: bool) -> tuple[dict | None, list[dict]]:
        data = _read_fd(self._fd)
        try:
            header, records, newline_missing = _parse(self.path, data)
        except SessionFileCorrupt as err:
            if not (repair and err.repairable):
                raise
            self._repair(err)
            header, records, newline_missing = _parse(self.path, data[: err.offset])
        if newline_missing:  # a complete last record: keep it, end its line
            self._write(b"\n")
        return header, records

    def _repair(self, err: SessionFileCorrupt) -> None:
        """Move a partial last line to ``path.dropped`` and truncate the file before it (reported)."""
        dropped = Path(str(self.path) + ".dropped")
        with open(dropped, "ab") as f:
            f.write(
                f"# {now()} line {err.line_number} of {self.path.name}: {err.reason}\n".encode() + err.partial + b"\n"
            )
            f.flush()
            os.fsync(f.fileno())
        os.ftruncate(self._fd, err.offset)
        os.fsync(self._fd)
        warnings.warn(
            f"session file {self.path}: removed the incomplete line {err.line_number} ({len(err.partial)} bytes, "
            f"kept in {dropped}); its answer, if any, will be asked again.",
            SessionRepairWarning,
            stacklevel=4,
        )

    def _write(self, data: bytes) -> None:
        _write_all(self._fd, data)
        os.fsync(self._fd)

    def append(self, record: dict) -> None:
        """Append ``record`` (fsynced) and add it to :attr:`records`; on any failure,
        ``BaseException`` included, the file is truncated back and :attr:`records` is as it was."""
        if self._fd is None:
            raise SessionFileError(f"session file {self.path} is closed.")
        check_new_record(f"session file {self.path}, line {len(self.records) + 2}", self.header, self.records, record)
        data = _encode(record)
        size, count = os.fstat(self._fd).st_size, len(self.records)
        try:
            self._write(data)
            self.records.append(record)
        except BaseException:
            del self.records[count:]
            os.ftruncate(self._fd, size)
            os.fsync(self._fd)
            raise

    def close(self) -> None:
        """Release the file (every record is already on disk)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
