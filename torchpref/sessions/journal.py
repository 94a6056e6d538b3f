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
import errno
import json
import os
import threading
import warnings
import weakref
from collections.abc import Callable
from pathlib import Path

from torchpref.sessions.errors import (  # noqa: F401  (the errors stay importable from here, as before)
    SessionFileChanged,
    SessionFileCorrupt,
    SessionFileError,
    SessionFileGone,
    SessionForkError,
    SessionMismatchError,
    SessionReadOnlyError,
    SessionRepairWarning,
    SessionVersionError,
)
from torchpref.sessions.filebytes import dropped_path, file_kind, fsync_dir, prefix_digest, read_fd, stamp
from torchpref.sessions.records import (
    ANSWER_KINDS,
    FORMAT_VERSION,
    AnswerRecord,
    Record,
    check_new_record,
    parse_record,
    validate_header,
    validate_records,
)

__all__ = [
    "ANSWER_KINDS",
    "FORMAT_VERSION",
    "Journal",
    "MAX_FILE_BYTES",
    "read_session_file",
]

MAX_FILE_BYTES = 1 << 30
"""The largest session file opened (1 GiB, some three million answers): a larger one is refused by
name before it is read (a file of that size is not a session's)."""


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


_HEADER_START = b'{"type":"header",'


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


_DECODER = json.JSONDecoder(
    parse_constant=_reject_constant
)  # one decoder for every line (json.loads makes one per call)


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
            rec = _DECODER.decode(line.decode())
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


def read_session_file(path: str | os.PathLike[str]) -> tuple[dict | None, list[dict], int]:
    """Parse and validate a session file without changing it (and without locking it).

    Returns:
        ``(header, records, size)``: the header (``None`` for an empty file), the records after
        it in order, and the file's size in bytes.

    Raises:
        SessionFileCorrupt: a line is incomplete or not JSON (with its line number).
        SessionVersionError: a record is of a newer format version.
        SessionFileError: a record breaks the format (a missing or wrong field, sequence
            numbers, undo targets), naming the file and the line; or the path is a directory, a
            device, a FIFO or a file over :data:`MAX_FILE_BYTES`.
    """
    path = Path(path)
    fd = _open(path, os.O_RDONLY)
    try:
        data = read_fd(fd, _checked_size(fd, path))
    finally:
        os.close(fd)
    header, records, _ = _parse(path, data)
    return header, records, len(data)


def _open(path: Path, flags: int) -> int:
    """Open ``path`` (never blocking on a FIFO); a directory, device, FIFO or socket is refused by
    name before anything is read, as is a name the file system refuses."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        st = None
    except OSError as err:
        raise _name_error(path, err) from None
    if st is not None and file_kind(st.st_mode):
        raise SessionFileError(f"session file {path} is {file_kind(st.st_mode)}; a session file is a regular file.")
    try:
        fd = os.open(path, flags | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0), 0o644)
    except IsADirectoryError:
        raise SessionFileError(f"session file {path} is a directory; give a file name.") from None
    except (FileNotFoundError, PermissionError):
        raise
    except OSError as err:
        raise _name_error(path, err) from None
    kind = file_kind(os.fstat(fd).st_mode)  # it may have changed between the stat and the open
    if kind:
        os.close(fd)
        raise SessionFileError(f"session file {path} is {kind}; a session file is a regular file.")
    return fd


def _name_error(path: Path, err: OSError) -> SessionFileError:
    if err.errno == errno.ENAMETOOLONG:
        return SessionFileError(f"session file name {path} is too long for the file system ({err.strerror}).")
    return SessionFileError(f"session file {path} cannot be opened: {err.strerror or err}.")


def _checked_size(fd: int, path) -> int:
    size = os.fstat(fd).st_size
    if size > MAX_FILE_BYTES:
        raise SessionFileError(
            f"session file {path} is {size:,} bytes, more than a session file may be ({MAX_FILE_BYTES:,}); "
            "it is not a session's file."
        )
    return size


def _lock(fd: int, path, shared: bool = False) -> None:
    try:
        import fcntl
    except ImportError:  # not POSIX: no advisory lock
        return
    try:
        fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except BlockingIOError:
        st = os.fstat(fd)
        if any(j._fd is not None and j._ident == (st.st_dev, st.st_ino) for j in list(_OPEN)):
            raise SessionFileError(
                f"session file {path} is in use: it is already open in this process (a session opened before, e.g. by a "
                "notebook cell run again): close that one first (session.close()), or open sessions with "
                "'with PreferenceSession(...) as session:' so that they close themselves."
            ) from None
        raise SessionFileError(f"session file {path} is in use by another process.") from None


_OPEN: weakref.WeakSet = weakref.WeakSet()  # journals open in this process (closed in a forked child)


def _after_fork_in_child() -> None:
    for journal in list(_OPEN):
        journal._forked()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


class Journal:
    """One session file, locked for as long as it is open.

    Args:
        path: the file; created (with ``new_header()``) if missing or empty.
        new_header: builds the header record of a new file (``None``: an empty file stays empty
            and :attr:`header` is ``None``).
        repair: if the file ends in a partial line, report it, move it to ``FILE.dropped`` and
            continue; by default that raises :class:`SessionFileCorrupt`.

    Attributes:
        header: the file's header (a validated JSON object).
        records: the records after it, in order, typed once when the file is read
            (:class:`~torchpref.sessions.records.AnswerRecord` / :class:`~torchpref.sessions.records.UndoRecord`).
        in_force: the answer records not undone, by sequence number, oldest first (kept up to date).
        last_seq: the last record's sequence number (0 for none).
        read_only: the file could not be opened for writing; :meth:`append` raises
            :class:`SessionReadOnlyError`.

    Raises:
        SessionFileError: the path is a directory, device, FIFO or socket, the file is too large or
            in use, or a record is invalid.
        SessionFileCorrupt: a partial or invalid line (``repair=True`` fixes a bad last line).
        SessionVersionError: a newer format version.
    """

    def __init__(self, path: str | os.PathLike[str], new_header: Callable[[], dict] | None, *, repair: bool = False):
        self.path = Path(path)
        self._fd: int | None = None  # None once closed (or, in a forked child, let go of)
        self._lock = threading.Lock()
        self._pid = os.getpid()
        self._broken: str | None = None  # why the file may be longer than its acknowledged records
        self.read_only = False
        try:
            self._fd = _open(self.path, os.O_RDWR | os.O_APPEND | os.O_CREAT)
        except PermissionError:
            if not self.path.exists():
                raise
            self._fd, self.read_only = _open(self.path, os.O_RDONLY), True
        try:
            if self.read_only:  # a shared lock: no writer while we read
                _lock(self._file(), self.path, True)
            else:
                _lock(self._file(), self.path)  # before reading: no writer slips in between
            self.header, raw = self._read(repair)
            self.records: list[Record] = [parse_record(r) for r in raw]  # validated by _read: typed once
            if self.header is None and new_header is not None:
                if self.read_only:
                    raise SessionReadOnlyError(f"session file {self.path} is empty and cannot be written.")
                header = new_header()
                self._write_or_undo(_encode(header), 0)
                fsync_dir(self.path)
                self.header = header
            st = os.fstat(self._file())
            self._ident, self._size = (st.st_dev, st.st_ino), st.st_size
            self._digest = prefix_digest(self._file(), self._size)  # of the acknowledged bytes
            self._stamp = stamp(st)
        except BaseException:
            os.close(self._fd)
            self._fd = None
            raise
        self.in_force: dict[int, AnswerRecord] = {}
        for rec in self.records:
            _account(self.in_force, rec)
        self.last_seq = self.records[-1].seq if self.records else 0
        _OPEN.add(self)

    def _file(self) -> int:
        """The open descriptor (:class:`SessionFileError` once the journal is closed)."""
        if self._fd is None:
            raise SessionFileError(f"session file {self.path} is closed.")
        return self._fd

    def _read(self, repair: bool) -> tuple[dict | None, list[dict]]:
        data = read_fd(self._file(), _checked_size(self._file(), self.path))
        try:
            header, records, newline_missing = _parse(self.path, data)
        except SessionFileCorrupt as err:
            # a header whose write failed: only line, incomplete, and the start of a header as this
            # module writes them (a file of anything else is never truncated without repair=True)
            head = err.partial[: len(_HEADER_START)]
            half_header = err.line_number == 1 and err.repairable and bool(head) and _HEADER_START.startswith(head)
            if not ((repair or half_header) and err.repairable) or self.read_only:
                raise
            self._repair(err, half_header)
            header, records, newline_missing = _parse(self.path, data[: err.offset])
        if newline_missing and not self.read_only:  # a complete last record: keep it, end its line
            self._write(b"\n")
        return header, records

    def _repair(self, err: SessionFileCorrupt, half_header: bool) -> None:
        """Move a partial last line to ``path.dropped`` and truncate the file before it (reported)."""
        dropped = dropped_path(self.path)
        name = os.fsencode(self.path.name)
        with open(dropped, "ab") as f:
            f.write(f"# {now()} line {err.line_number} of ".encode() + name + f": {err.reason}\n".encode())
            f.write(err.partial + b"\n")
            f.flush()
            os.fsync(f.fileno())
        os.ftruncate(self._file(), err.offset)
        os.fsync(self._file())
        what = (
            "an incomplete header (the file was being created when its write failed; it holds no answer)"
            if half_header
            else f"the incomplete line {err.line_number} ({len(err.partial)} bytes; its answer, if any, was never "
            "acknowledged and will be asked again)"
        )
        warnings.warn(
            f"session file {self.path}: removed {what}; kept in {dropped}.", SessionRepairWarning, stacklevel=4
        )

    def _write(self, data: bytes) -> None:
        _write_all(self._file(), data)
        os.fsync(self._file())

    def _write_or_undo(self, data: bytes, size: int) -> None:
        """Write ``data`` after the file's first ``size`` bytes, fsynced; on any failure truncate back."""
        try:
            self._write(data)
        except BaseException:
            self._truncate(size)
            raise

    def _truncate(self, size: int) -> None:
        """Truncate the file to ``size`` bytes, retried through interrupts; if it cannot be done,
        the journal refuses further writes until it can (:meth:`_heal`)."""
        for _ in range(100):
            try:
                os.ftruncate(self._file(), size)
                os.fsync(self._file())
                self._broken = None
                return
            except KeyboardInterrupt:  # a second Ctrl-C mid-rollback: finish the rollback first
                continue
            except OSError as err:
                self._broken = f"the rollback of a failed write failed ({err.strerror or err})"
                return
        self._broken = "the rollback of a failed write was interrupted"

    def _heal(self) -> None:
        """Bring the file back to its acknowledged size after a failed rollback, or refuse by name."""
        if os.fstat(self._file()).st_size < self._size:  # shortened since: never pad it with zeros
            self._check_unchanged()
        self._truncate(self._size)
        if self._broken is None and os.fstat(self._file()).st_size == self._size:
            return
        raise SessionFileError(
            f"session file {self.path}: {self._broken or 'its size changed'}; no answer is written until it is "
            "repaired: close the session and open the file again (repair=True drops the unacknowledged tail)."
        )

    def _check_unchanged(self) -> None:
        """The file still starts with exactly the bytes this session acknowledged, and holds nothing
        after them: its size, and where its change time says it was touched, a SHA-256 of that
        prefix (an answer's cost stays constant while no one else writes the file).

        Raises:
            SessionFileChanged: shortened, extended or rewritten in place by another program.
        """
        st = os.fstat(self._file())
        if st.st_size == self._size and stamp(st) == self._stamp:
            return
        if st.st_size < self._size:
            why = f"shortened from {self._size:,} to {st.st_size:,} bytes"
        elif st.st_size > self._size:
            why = f"extended from {self._size:,} to {st.st_size:,} bytes"
        elif prefix_digest(self._file(), self._size).digest() != self._digest.digest():
            why = "rewritten in place (its bytes differ from the records this session wrote)"
        else:
            self._stamp = stamp(st)  # touched, not changed
            return
        raise SessionFileChanged(
            f"session file {self.path} was {why} by another program while the session had it open: this answer "
            "was not saved, and nothing more is written to the file. The session's records in memory "
            "(session.records) are every acknowledged answer: close the session, restore the file (or write "
            "those records to a new one) and open it again."
        )

    def _check_same_file(self) -> None:
        """The path still names the open file (not deleted, moved away or replaced)."""
        try:
            st = os.stat(self.path)
            same = (st.st_dev, st.st_ino) == self._ident and os.fstat(self._file()).st_nlink > 0
        except OSError:
            same = False
        if not same:
            raise SessionFileGone(
                f"session file {self.path} was deleted, moved or replaced while the session had it open: this answer "
                "was not saved. Restore the file (or open a new session) before answering again."
            )

    def check_writable(self) -> None:
        """Raise by name where :meth:`append` could not write (a forked child, read-only, closed, gone)."""
        if os.getpid() != self._pid:
            raise SessionForkError(
                f"session file {self.path} was opened by process {self._pid}; this process ({os.getpid()}) is a "
                "fork of it and may not write to it: open the session in the child once the parent has closed it."
            )
        if self._fd is None:
            raise SessionFileError(f"session file {self.path} is closed.")
        if self.read_only:
            raise SessionReadOnlyError(
                f"session file {self.path} was opened read-only (this process may not write it): "
                "answers cannot be saved; copy the file somewhere writable to go on."
            )

    def append(self, record: Record) -> None:
        """Append ``record`` (fsynced) and add it to :attr:`records`; on any failure,
        ``BaseException`` included, the file is truncated back and :attr:`records` is as it was.

        Raises:
            SessionForkError, SessionReadOnlyError, SessionFileGone, SessionFileError: see the class.
        """
        self.check_writable()
        with self._lock:
            self.check_writable()
            if self._broken is not None:
                self._heal()  # our own failed rollback: the file may be longer than acknowledged
            self._check_unchanged()
            self._check_same_file()
            if self.header is None:
                raise SessionFileError(f"session file {self.path} has no header: no record can follow.")
            line = record.to_json()
            check_new_record(
                f"session file {self.path}, line {len(self.records) + 2}",
                self.header,
                None,
                line,
                last_seq=self.last_seq,
                in_force=self.in_force,
            )
            data = _encode(line)
            self._write_or_undo(data, self._size)
            try:
                self._check_same_file()  # deleted while writing: not acknowledged
            except BaseException:
                self._truncate(self._size)
                raise
            self._size += len(data)
            self._digest.update(data)
            self._stamp = stamp(os.fstat(self._file()))
            self.records.append(record)
            self.last_seq = record.seq
            _account(self.in_force, record)

    def _forked(self) -> None:
        """In a forked child: let go of the parent's descriptor (the lock stays the parent's)."""
        fd, self._fd = self._fd, None
        self._lock = threading.Lock()
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass

    def close(self) -> None:
        """Release the file (every record is already on disk)."""
        if os.getpid() == self._pid:
            with self._lock:
                if self._fd is not None:
                    os.close(self._fd)
                    self._fd = None
        _OPEN.discard(self)

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _account(in_force: dict[int, AnswerRecord], rec: Record) -> None:
    """Update the answers in force by one record (an answer joins, an undo removes its target)."""
    if isinstance(rec, AnswerRecord):
        in_force[rec.seq] = rec
    else:
        in_force.pop(rec.undoes, None)


class MemoryJournal:
    """The records of a session without a file, with :class:`Journal`'s interface (every record
    is checked as a file's would be; nothing is written)."""

    read_only = False

    def __init__(self, header: dict):
        self.path, self.header = None, header
        self.records: list[Record] = []
        self.in_force: dict[int, AnswerRecord] = {}
        self.last_seq = 0

    def check_writable(self) -> None:
        """Always writable (a forked child has its own copy of the records)."""

    def append(self, record: Record) -> None:
        """Check ``record`` and add it."""
        line = record.to_json()
        check_new_record("session (no file)", self.header, None, line, last_seq=self.last_seq, in_force=self.in_force)
        self.records.append(record)
        self.last_seq = record.seq
        _account(self.in_force, record)

    def close(self) -> None:
        """Nothing to release."""


def read_header(path: str | os.PathLike[str]) -> dict | None:
    """The validated header of the session file ``path``, reading only its first line (``None`` if
    the file is empty or its first line is not complete: open it with :class:`Journal` to learn why).

    Raises:
        SessionFileError: the path is not a regular file, or the header breaks the format.
    """
    path = Path(path)
    fd = _open(path, os.O_RDONLY)
    try:
        size, data = _checked_size(fd, path), b""
        while b"\n" not in data and len(data) < size:
            chunk = os.pread(fd, 1 << 16, len(data))
            if not chunk:
                break
            data += chunk
    finally:
        os.close(fd)
    if b"\n" not in data:
        return None
    header, _, _ = _parse(path, data[: data.index(b"\n") + 1])
    return header


def existing_header(path: Path, repair: bool = False) -> dict:
    """The header of the session file ``path`` (its first line; an empty or torn first line is
    explained, or repaired with ``repair``, by the journal), else ``SessionFileError``."""
    header = read_header(path)
    if header is None:
        with Journal(path, None, repair=repair) as journal:
            header = journal.header
    if header is None:
        raise SessionFileError(f"session file {path} is empty: create the session with PreferenceSession(...).")
    return header
