r"""The session file: an append-only JSON Lines journal of a person's answers.

A :class:`Journal` owns one file: it locks it (``flock``) *before* reading it, validates every
record against the format below (types, ranges, item counts; an error names the file and the
line), repairs a partial last line on request, and appends records with ``fsync`` so that an
acknowledged answer survives a crash. :class:`~torchpref.session.PreferenceSession` is the
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
import math
import os
import warnings
from pathlib import Path
from typing import Any, Callable

from torchpref.data import likert_to_unit
from torchpref.version import __version__

__all__ = [
    "ANSWER_KINDS",
    "FORMAT_VERSION",
    "Journal",
    "SessionFileCorrupt",
    "SessionFileError",
    "SessionMismatchError",
    "SessionRepairWarning",
    "SessionVersionError",
    "check_new_record",
    "read_session_file",
    "records_in_force",
    "validate_records",
]

FORMAT_VERSION = 1
"""The newest session-file format this version reads and the one it writes."""

ANSWER_KINDS = ("rating", "choice", "no_preference")
"""An answer is a rating (of one item), a choice (the best of ``m >= 2``) or no preference."""


class SessionFileError(ValueError):
    """A session file that cannot be used as it is (the message names the file and line)."""


class SessionFileCorrupt(SessionFileError):
    """A line of a session file is incomplete or not a JSON record.

    Attributes:
        path: the file.
        line_number: the 1-based number of the bad line.
        reason: what is wrong with it.
        repairable: whether ``repair=True`` can fix it (only a bad *last* line: a crash
            mid-write; a bad line followed by good ones is never dropped).
        partial: the bad line's bytes.
        offset: the byte offset where the bad line starts.
    """

    def __init__(self, path, line_number: int, reason: str, repairable: bool, partial: bytes, offset: int):
        self.path, self.line_number, self.reason = str(path), line_number, reason
        self.repairable, self.partial, self.offset = repairable, partial, offset
        fix = (
            "It looks like a crash in the middle of writing the last answer. To recover, open it with "
            "repair=True (PreferenceSession(..., repair=True) or PreferenceSession.load(path, repair=True)): "
            f"the partial line is moved to {self.path}.dropped, the file is truncated to its last complete "
            "record, and that answer is asked again."
            if repairable
            else "The lines after it are valid, so this is not an interrupted write; the file was edited or "
            "damaged and must be fixed by hand."
        )
        super().__init__(f"session file {self.path}, line {line_number}: {reason}. {fix}")


class SessionVersionError(SessionFileError):
    """The file was written by a newer format version than this library reads."""


class SessionMismatchError(SessionFileError):
    """The file was written for other items, dimensions or settings than those given.

    Attributes:
        setting: the header field that differs (``"dim"``, ``"candidates"``, ``"bounds"``, ...).
        theirs: the file's value, described.
        mine: the value given, described.
    """

    def __init__(self, message: str, setting: str = "", theirs: str = "", mine: str = ""):
        super().__init__(message)
        self.setting, self.theirs, self.mine = setting, theirs, mine


class SessionRepairWarning(UserWarning):
    """A partial last line was removed from a session file (``repair=True``)."""


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


# ----------------------------------------------------------------------------- validation
class _Line:
    """Checks on one record; every failure names the file and the line."""

    def __init__(self, where: str, rec: dict):
        self.where, self.rec = where, rec

    def fail(self, msg: str, error: type = SessionFileError):
        raise error(f"{self.where}: {msg}.")

    def get(self, key: str, required: bool = True):
        if key not in self.rec:
            if required:
                self.fail(f"the {self.rec.get('type')} record has no {key!r}")
            return None
        return self.rec[key]

    def integer(self, key: str, lo: int | None = None, hi: int | None = None, optional: bool = False) -> int | None:
        v = self.get(key, required=not optional)
        if v is None and optional:
            return None
        if not isinstance(v, int) or isinstance(v, bool) or (lo is not None and v < lo) or (hi is not None and v > hi):
            rng = f" in {lo}..{hi}" if hi is not None else (f" >= {lo}" if lo is not None else "")
            self.fail(f"{key!r} must be an integer{rng}, got {v!r:.80}")
        return v

    def matrix(self, value, name: str, cols: int, min_rows: int = 1, max_rows: int | None = None) -> list:
        ok = isinstance(value, list) and all(
            isinstance(r, list) and len(r) == cols and all(_is_number(x) and math.isfinite(x) for x in r)
            for r in value)
        if not ok:
            self.fail(f"{name} must be a list of rows of {cols} finite numbers, got {value!r:.120}")
        if len(value) < min_rows or (max_rows is not None and len(value) > max_rows):
            want = f"exactly {min_rows}" if max_rows == min_rows else f"at least {min_rows}"
            self.fail(f"{name} must have {want} row(s), got {len(value)}")
        return value

    def bounds(self, value, name: str, dim: int) -> list:
        b = self.matrix(value, name, dim, 2, 2)
        if not all(lo < hi for lo, hi in zip(*b)):
            self.fail(f"{name} must have lower < upper in every dimension, got {b!r:.120}")
        return b


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _check_header(path, h: dict) -> None:
    c = _Line(f"session file {path}, line 1", h)
    if h.get("type") != "header":
        c.fail(f"the first record must be the header, got {h!r:.200}")
    version = c.integer("version", lo=1)
    if version > FORMAT_VERSION:
        c.fail(f"format version {version} is newer than this torchpref {__version__} reads (up to "
               f"{FORMAT_VERSION}); upgrade torchpref to open it", SessionVersionError)
    dim = c.integer("dim", lo=1)
    c.integer("seed")
    c.integer("num_queries", lo=1)
    if c.get("num_levels") is not None:  # required, null for ratings in [0, 1]
        c.integer("num_levels", lo=2)
    c.bounds(c.get("bounds"), "bounds", dim)
    names = h.get("names")
    names_ok = isinstance(names, list) and len(names) == dim and all(isinstance(n, str) for n in names)
    if names is not None and not names_ok:
        c.fail(f"names must be null or {dim} strings, got {names!r:.120}")
    if not isinstance(h.get("metadata", {}), dict):
        c.fail(f"metadata must be a JSON object, got {h.get('metadata')!r:.80}")
    spec = c.get("candidates")
    if not isinstance(spec, dict) or spec.get("kind") not in ("pool", "box"):
        c.fail(f"candidates must be {{'kind': 'pool' or 'box', ...}}, got {spec!r:.120}")
    if spec["kind"] == "pool":
        c.matrix(spec.get("items"), "candidates' items", dim)
    else:
        c.bounds(spec.get("bounds"), "candidates' bounds", dim)
        _Line(c.where, spec).integer("num", lo=1)


def _check_answer(c: _Line, rec: dict, header: dict) -> None:
    kind = rec.get("kind")
    if kind not in ANSWER_KINDS:
        c.fail(f"unknown answer kind {kind!r:.80} (one of {', '.join(ANSWER_KINDS)})")
    c.get("time")
    if not isinstance(rec["time"], str):
        c.fail(f"'time' must be a string, got {rec['time']!r:.80}")
    dim = header["dim"]
    if kind == "rating":
        items = c.matrix(c.get("items"), "a rating's items", dim, 1, 1)
    else:
        items = c.matrix(c.get("items"), f"a {kind.replace('_', ' ')}'s items", dim, 2)
    answer, levels = c.get("answer"), header.get("num_levels")
    if kind == "rating":
        value = c.get("value")
        if levels is not None:
            level = c.integer("answer", lo=1, hi=levels)
            expected = float(likert_to_unit(level, levels))
        else:
            if not (_is_number(answer) and 0.0 <= answer <= 1.0):
                c.fail(f"a rating must be a number in [0, 1], got {answer!r:.80}")
            expected = float(answer)
        if not _is_number(value) or value != expected:
            c.fail(f"the rating's value {value!r:.80} does not match its answer {answer!r} (expected {expected})")
    elif kind == "choice":
        c.integer("answer", lo=0, hi=len(items) - 1)
    elif answer is not None:
        c.fail(f"no preference has answer null, got {answer!r:.80}")
    _check_query(c, rec.get("query"), kind, len(items), header)


def _check_query(c: _Line, q, kind: str, m: int, header: dict) -> None:
    if q is None:
        return
    if not isinstance(q, dict):
        c.fail(f"'query' must be null or a JSON object, got {q!r:.80}")
    want = "rating" if kind == "rating" else "ranking"
    if q.get("kind") != want:
        c.fail(f"a {kind} answers a {want} query, not {q.get('kind')!r:.80}")
    _Line(c.where, q).integer("step", lo=0, optional=True)
    idx = q.get("pool_indices")
    if idx is None:
        return
    spec = header["candidates"]
    n = len(spec["items"]) if spec["kind"] == "pool" else 0
    if not (isinstance(idx, list) and len(idx) == m and all(isinstance(i, int) and not isinstance(i, bool)
                                                           and 0 <= i < n for i in idx)):
        c.fail(f"pool_indices must be {m} rows of the pool of {n} items, got {idx!r:.80}")
    if any(spec["items"][i] != row for i, row in zip(idx, c.rec["items"])):
        c.fail(f"the items are not the pool's rows {idx}")


def validate_records(path, header: dict, records: list[dict], first_line: int = 2) -> None:
    """Check every record after the header: format version, sequence numbers, answer schema,
    undo targets. Raises :class:`SessionFileError` (or :class:`SessionVersionError`) naming the line."""
    last_seq, active = 0, set()
    for i, rec in enumerate(records, start=first_line):
        last_seq = _check_record(_Line(f"session file {path}, line {i}", rec), header, last_seq, active)


def _check_record(c: _Line, header: dict, last_seq: int, active: set[int]) -> int:
    """Check one record after those with sequence numbers up to ``last_seq`` and answers
    ``active`` in force (updated); returns its sequence number."""
    rec = c.rec
    v = rec.get("v", 1)
    if not isinstance(v, int) or isinstance(v, bool) or v < 1:
        c.fail(f"record format version 'v' must be a positive integer, got {v!r:.80}")
    if v > FORMAT_VERSION:
        c.fail(f"record format version {v} is newer than {FORMAT_VERSION}; upgrade torchpref to open it",
               SessionVersionError)
    seq = c.integer("seq", lo=1)
    if seq <= last_seq:
        c.fail(f"sequence number {seq} does not follow {last_seq}")
    if rec["type"] == "answer":
        _check_answer(c, rec, header)
        active.add(seq)
    elif rec["type"] == "undo":
        if not isinstance(rec.get("time"), str):
            c.fail(f"'time' must be a string, got {rec.get('time')!r:.80}")
        if rec.get("undoes") not in active or isinstance(rec.get("undoes"), bool):
            c.fail(f"undo of {rec.get('undoes')!r:.80}, not an answer in force")
        active.discard(rec["undoes"])
    else:
        c.fail(f"unknown record type {rec['type']!r:.80}")
    return seq


def check_new_record(where: str, header: dict, records: list[dict], record: dict) -> None:
    """Check ``record`` as the next one after ``records`` (before it is written: the file never
    gets a record it could not read back)."""
    active = {r["seq"] for r in records_in_force(records)}
    _check_record(_Line(where, record), header, records[-1]["seq"] if records else 0, active)


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
            reason = (f"the last line is incomplete (no newline at its end; {exc})" if last and newline_missing
                      else f"not a valid record ({exc})")
            raise SessionFileCorrupt(path, i + 1, reason, last, line, offset) from None
        parsed.append(rec)
        offset += len(line) + 1
    header = parsed[0]
    _check_header(path, header)
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
            f.write(f"# {now()} line {err.line_number} of {self.path.name}: {err.reason}\n".encode() + err.partial
                    + b"\n")
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

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def records_in_force(records: list[dict]) -> list[dict]:
    """The answer records not undone, oldest first."""
    active: list[dict] = []
    for rec in records:
        if rec["type"] == "answer":
            active.append(rec)
        else:
            active = [r for r in active if r["seq"] != rec["undoes"]]
    return active


def dumps_settings(value: Any) -> str:
    """A canonical JSON text of a header setting, to compare a file's settings with a session's."""
    return json.dumps(value, sort_keys=True)
