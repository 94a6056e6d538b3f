r"""The open sessions of a ``torchpref serve`` process as a bounded cache over their files.

A session's state is its file (:class:`~torchpref.PreferenceSession`): every answer is in the
journal, and the model's mode is kept beside it (``FILE.mode``). So an open session is only a
cache, and :class:`SessionPool` keeps a bounded number of them:

* a session not used for ``idle_close`` seconds (a participant who has gone away), or for
  ``finished_close`` seconds once all its questions are answered, is **closed**: its file is
  released and its model dropped;
* at most ``max_open`` are open at once: opening one more closes the least recently used idle
  one first (a session in the middle of a request is never closed; if every open one is busy the
  limit is passed for that moment rather than a participant refused);
* a closed session **reopens on demand** from its file and mode snapshot, with the same answers,
  the same posterior (to round-off) and the same next question (its queries are a function of the
  file: ``step_generator(seed, k)``), so a participant never notices.

The default ``max_open`` follows the process's descriptor limit (``RLIMIT_NOFILE``): each open
session holds one descriptor, and a margin is left for connections, pictures and the plot worker.

When no descriptor or memory is left, a *new* participant is refused with :class:`ServerBusy`
(HTTP 503 with ``Retry-After``) and the server writes one line to its log (and one when it has
recovered), not a traceback per request; :func:`quiet_resource_errors` does the same for the
event loop's "socket.accept() out of system resource" tracebacks.
"""

from __future__ import annotations

import errno
import logging
import os
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

from torchpref.frontends.serve.errors import AnswerRefused

if TYPE_CHECKING:
    from torchpref.sessions.session import PreferenceSession

__all__ = [
    "PoolEntry",
    "PoolLimits",
    "ServerBusy",
    "SessionPool",
    "available_memory",
    "default_max_open",
    "open_descriptors",
    "quiet_resource_errors",
    "resource_error",
]

FD_MARGIN = 64
"""Descriptors kept free of sessions by the default ``max_open``: the listening socket, the
connections, the plot worker's pipes, a snapshot being written, libraries' own files."""

MAX_OPEN_CAP = 512
"""The default ``max_open`` never exceeds this (an open session holds its model: some 0.5 MB)."""

RESOURCE_ERRNOS = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOMEM, errno.ENOBUFS})
OOM_MESSAGES = ("can't allocate memory", "Cannot allocate memory", "not enough memory")


def default_max_open(soft_limit: int | None = None) -> int:
    """How many sessions may be open at once by default: half of what the descriptor limit leaves
    after :data:`FD_MARGIN` (each participant's browser holds connections too), at least 4 and at
    most :data:`MAX_OPEN_CAP`. ``soft_limit``: ``RLIMIT_NOFILE``'s soft limit (read if not given;
    an unlimited or unknown limit counts as the cap)."""
    if soft_limit is None:
        soft_limit = _fd_limit()
    if soft_limit is None:
        return MAX_OPEN_CAP
    return max(4, min(MAX_OPEN_CAP, (soft_limit - FD_MARGIN) // 2))


def _fd_limit() -> int | None:
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    except (ImportError, OSError, ValueError):  # pragma: no cover - not POSIX
        return None
    return None if soft == getattr(resource, "RLIM_INFINITY", -1) or soft < 0 else int(soft)


def open_descriptors() -> int | None:
    """The number of descriptors this process has open (Linux: ``/proc/self/fd``), ``None`` where
    that cannot be counted; with no descriptor left to list them, the limit itself."""
    try:
        return len(os.listdir("/proc/self/fd")) - 1  # the listing's own
    except OSError as err:
        if err.errno in (errno.EMFILE, errno.ENFILE):
            return _fd_limit()
        return None


def available_memory() -> int | None:
    """Bytes of memory available to new work (``MemAvailable`` of ``/proc/meminfo``; ``None`` elsewhere)."""
    try:
        with open("/proc/meminfo", "rb") as f:
            for line in f:
                if line.startswith(b"MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def resource_error(exc: BaseException) -> bool:
    """Whether ``exc`` (or an exception it was raised from or during) is running out of descriptors
    or memory: ``MemoryError``, an ``OSError`` ``EMFILE`` / ``ENFILE`` / ``ENOMEM`` / ``ENOBUFS``, or
    torch's allocator failing (a ``RuntimeError`` saying so)."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, MemoryError) or (isinstance(e, OSError) and e.errno in RESOURCE_ERRNOS):
            return True
        if isinstance(e, RuntimeError) and any(m in str(e) for m in OOM_MESSAGES):  # torch's allocator
            return True
        e = e.__cause__ or e.__context__
    return False


class ServerBusy(AnswerRefused):
    """Refused for want of descriptors or memory (HTTP 503): nothing was recorded or created;
    ``retry_after`` is the number of seconds to wait before trying again (the ``Retry-After`` header)."""

    def __init__(self, message: str, retry_after: int = 30):
        super().__init__(message, 503)
        self.retry_after = int(retry_after)


@dataclass(frozen=True)
class PoolLimits:
    """How many sessions stay open, and for how long.

    Args:
        max_open: sessions open at once (``None``: :func:`default_max_open` of the descriptor limit).
        idle_close: seconds without a request after which a session is closed.
        finished_close: the same for a session whose questions are all answered.
        retry_after: seconds a refused participant is told to wait (``Retry-After``).
        fd_reserve: descriptors that must stay free for a new session to be created (connections
            and answers of the participants already in; ``None``: 1/16 of the limit, at least 16).
        memory_reserve: bytes of available memory below which new sessions are refused.
    """

    max_open: int | None = None
    idle_close: float = 120.0
    finished_close: float = 1.0
    retry_after: int = 30
    fd_reserve: int | None = None
    memory_reserve: int = 64 * 2**20

    def __post_init__(self) -> None:
        if self.max_open is not None and (
            isinstance(self.max_open, bool) or not isinstance(self.max_open, int) or self.max_open < 1
        ):
            raise ValueError(f"max_open must be a whole number >= 1 (or None), got {self.max_open!r:.40}.")
        for name in ("idle_close", "finished_close"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < float("inf"):
                raise ValueError(f"{name} must be a number of seconds >= 0, got {v!r:.40}.")
        if isinstance(self.retry_after, bool) or not isinstance(self.retry_after, int) or self.retry_after < 1:
            raise ValueError(f"retry_after must be a whole number of seconds >= 1, got {self.retry_after!r:.40}.")

    def open_limit(self) -> int:
        """``max_open``, or its default from the descriptor limit now."""
        return self.max_open if self.max_open is not None else default_max_open()


class PoolEntry:
    """One participant's session in a :class:`SessionPool`: ``sid``, the ``lock`` every request to
    it holds, and :attr:`session` (opened again from its file if the pool closed it)."""

    __slots__ = ("__weakref__", "_pool", "_session", "last_used", "lock", "pinned", "sid")

    def __init__(self, pool: SessionPool, sid: str, session: PreferenceSession | None = None, pinned: bool = False):
        self._pool, self.sid, self._session, self.pinned = pool, sid, session, pinned
        self.lock = threading.Lock()
        self.last_used = pool.clock()

    @property
    def session(self) -> PreferenceSession:
        """The open :class:`~torchpref.PreferenceSession` (call with :attr:`lock` held): opened from
        its file if it was closed. Raises what the pool's opener raises (``AnswerRefused``)."""
        s = self._session
        if s is None:
            s = self._pool._reopen(self)
        return s

    @property
    def is_open(self) -> bool:
        """Whether the session is open now (its file held, its model in memory)."""
        return self._session is not None


class SessionPool:
    """Open sessions, closed when idle or over the limit and reopened on demand (see the module).

    Args:
        opener: ``sid -> PreferenceSession`` from its file; raises ``AnswerRefused`` when it cannot.
        limits: :class:`PoolLimits`.
        clock: seconds, monotonic (tests give their own).
        log: where the one-line notes go (default: printed, as the server's other notes).
        sweep: whether a background thread closes idle sessions (otherwise only :meth:`sweep` does).
    """

    def __init__(
        self,
        opener: Callable[[str], PreferenceSession],
        limits: PoolLimits | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        log: Callable[[str], None] | None = None,
        sweep: bool = True,
    ) -> None:
        self.limits = limits or PoolLimits()
        self.max_open = self.limits.open_limit()
        self.clock, self._opener = clock, opener
        self._log = log or (lambda line: print(line, flush=True))
        self._lock = threading.Lock()
        self._open: OrderedDict[str, PoolEntry] = OrderedDict()  # least recently used first
        self._known: weakref.WeakValueDictionary[str, PoolEntry] = weakref.WeakValueDictionary()
        self._sweeper: threading.Thread | None = None
        self._stop = threading.Event()
        self._use_sweeper = sweep
        self._short: str | None = None  # what ran out, while new participants are refused
        self.opened = self.closed = 0  # counts, for the soak and the tests

    # ------------------------------------------------------------ entries
    def add(self, sid: str, session: PreferenceSession, pinned: bool = False) -> PoolEntry:
        """Put a session just opened (a new participant's, or one served from Python: ``pinned``,
        never closed) in the pool; returns its entry."""
        entry = PoolEntry(self, sid, session, pinned)
        with self._lock:
            self._known[sid] = entry
            self._open[sid] = entry
            self.opened += 1
        self._after_open()
        return entry

    def get(self, sid: str) -> PoolEntry | None:
        """The entry of ``sid`` if the pool knows it (open, or closed while a request holds it), marked used."""
        with self._lock:
            entry = self._known.get(sid)
            if entry is not None:
                entry.last_used = self.clock()
                if sid in self._open:
                    self._open.move_to_end(sid)
            return entry

    def entry(self, sid: str) -> PoolEntry:
        """The entry of ``sid``, opened (from its file, by the opener) if it is not open."""
        with self._lock:
            entry = self._known.get(sid)
            if entry is None:
                entry = self._known[sid] = PoolEntry(self, sid)
            entry.last_used = self.clock()
            if sid in self._open:
                self._open.move_to_end(sid)
        with entry.lock:
            entry.session  # noqa: B018  (opens it now: errors surface here)
        return entry

    def _reopen(self, entry: PoolEntry) -> PreferenceSession:
        """Open ``entry``'s session from its file (called with ``entry.lock`` held)."""
        session = self._opener(entry.sid)
        with self._lock:
            entry._session = session
            entry.last_used = self.clock()
            self._open[entry.sid] = entry
            self._known[entry.sid] = entry
            self.opened += 1
        self._after_open()
        return session

    def _after_open(self) -> None:
        self.make_room()
        if self._use_sweeper and self._sweeper is None and not self._stop.is_set():
            self._start_sweeper()

    @property
    def open_sids(self) -> list[str]:
        """The sessions open now, least recently used first."""
        with self._lock:
            return list(self._open)

    # ------------------------------------------------------------ closing
    def make_room(self) -> int:
        """Close least recently used idle sessions until at most ``max_open`` are open; returns how many."""
        return self._close_where(lambda e, idle: True, over_only=True)

    def sweep(self) -> int:
        """Close the sessions idle for longer than their limit (``finished_close`` once all their
        questions are answered, else ``idle_close``), and the least recently used beyond
        ``max_open`` (open while busy, when the limit was passed); returns how many were closed."""
        lim = self.limits

        def stale(entry: PoolEntry, idle: float) -> bool:
            s = entry._session
            return idle >= (lim.finished_close if s is not None and s.done else lim.idle_close)

        return self._close_where(stale, over_only=False) + self.make_room()

    def _close_where(self, pick: Callable[[PoolEntry, float], bool], over_only: bool) -> int:
        floor = min(self.limits.idle_close, self.limits.finished_close)
        closed = []
        with self._lock:
            now = self.clock()
            for sid, entry in list(self._open.items()):
                if over_only and len(self._open) <= self.max_open:
                    break
                idle = now - entry.last_used
                if entry.pinned or (not over_only and idle < floor):
                    continue
                if not entry.lock.acquire(blocking=False):  # in a request now: never closed under it
                    continue
                try:
                    if entry._session is None or not pick(entry, idle):
                        continue
                    session, entry._session = entry._session, None
                    del self._open[sid]
                    closed.append(session)
                finally:
                    entry.lock.release()
            self.closed += len(closed)
        for session in closed:  # outside the pool's lock: closing waits for nothing of ours
            _close_quietly(session)
        count = len(closed)
        if count:
            closed.clear()
            _release_memory()
        return count

    def _start_sweeper(self) -> None:
        every = max(0.2, min(30.0, min(self.limits.idle_close, self.limits.finished_close) / 2 or 0.2))
        ref = weakref.ref(self)
        stop = self._stop

        def run() -> None:
            while not stop.wait(every):
                pool = ref()
                if pool is None:
                    return
                try:
                    pool.sweep()
                except Exception as exc:  # pragma: no cover - a sweep must never kill the server
                    pool._log(f"torchpref serve: closing idle sessions failed: {type(exc).__name__}: {exc}")
                del pool

        self._sweeper = threading.Thread(target=run, name="torchpref-serve-sweeper", daemon=True)
        self._sweeper.start()

    def close(self, keep_pinned: bool = True) -> None:
        """Stop the sweeper and close every open session (a pinned one, given from Python, stays open)."""
        self._stop.set()
        with self._lock:
            entries = [e for e in self._open.values() if not (keep_pinned and e.pinned)]
        for entry in entries:
            with entry.lock:
                session, entry._session = entry._session, None
            with self._lock:
                self._open.pop(entry.sid, None)
            if session is not None:
                _close_quietly(session)

    # ------------------------------------------------------- running out
    def check_room(self) -> None:
        """Raise :class:`ServerBusy` if a new session should not be created now: too few
        descriptors left under the limit, or too little memory available."""
        short = self._shortage()
        if short is not None:
            self.refuse(short)

    def _shortage(self) -> str | None:
        limit, used = _fd_limit(), open_descriptors()
        if limit is not None and used is not None:
            reserve = self.limits.fd_reserve if self.limits.fd_reserve is not None else max(16, limit // 16)
            if used + reserve >= limit:
                return f"file descriptors ({used} of {limit} open)"
        avail = available_memory()
        if avail is not None and avail < self.limits.memory_reserve:
            return f"memory ({avail / 2**20:.0f} MB available)"
        return None

    def refuse(self, what: str) -> None:
        """Refuse a new participant for want of ``what``: :class:`ServerBusy`, and one log line per shortage."""
        with self._lock:
            first, self._short = self._short is None, what
        if first:
            self._log(
                f"torchpref serve: out of {what}: new participants get 503 (retry in {self.limits.retry_after} s) "
                "until some are free; no answer is lost"
            )
        raise ServerBusy(
            "the server is busy (out of memory or open files): no session was started. "
            f"Please try again in {self.limits.retry_after} seconds.",
            self.limits.retry_after,
        )

    def as_busy(self, exc: BaseException) -> BaseException:
        """``exc`` as :class:`ServerBusy` if it is running out of descriptors or memory (any request:
        nothing was recorded, the page sends it again), logged once per shortage; else ``exc``."""
        if not resource_error(exc):
            return exc
        try:
            self.refuse("memory or file descriptors")
        except ServerBusy as busy:
            busy.args = (
                "the server is out of memory or open files for a moment: nothing was recorded. "
                f"Please try again in {self.limits.retry_after} seconds.",
            )
            return busy
        raise AssertionError("unreachable")  # pragma: no cover

    def recovered(self) -> None:
        """A new session was created: if participants were being refused, say once that it is over."""
        if self._short is None:
            return
        with self._lock:
            what, self._short = self._short, None
        if what is not None:
            self._log(f"torchpref serve: {what.split(' (')[0]} available again: new participants are accepted")


_LAST_RELEASE = [0.0]


def _release_memory(every_s: float = 5.0) -> None:
    """After sessions closed, at most every ``every_s`` seconds: collect their reference cycles
    (a session and its model refer to each other) and hand the freed heap back to the system
    (glibc's ``malloc_trim``; the server's threads each keep an arena otherwise, and its memory
    grew with every finished session)."""
    import gc
    import time

    now = time.monotonic()
    if now - _LAST_RELEASE[0] < every_s:
        return
    _LAST_RELEASE[0] = now
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: the collection alone
        pass


def _close_quietly(session: PreferenceSession) -> None:
    try:
        session.close()
    except Exception:  # pragma: no cover - a file already gone; every answer is on disk
        pass


class _ResourceLogFilter(logging.Filter):
    """Lets through one line per shortage (``EMFILE`` and kin in a log record's exception) instead
    of a traceback per failed ``accept``: the first as one line, the rest dropped until
    ``quiet_s`` seconds pass without one."""

    def __init__(self, quiet_s: float = 60.0):
        super().__init__()
        self.quiet_s, self.last, self.dropped = quiet_s, -float("inf"), 0

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if exc is None or not resource_error(exc):
            return True
        now = time.monotonic()
        quiet, self.last = now - self.last >= self.quiet_s, now
        if not quiet:
            self.dropped += 1
            return False
        record.msg = f"torchpref serve: {record.getMessage().splitlines()[0]}: {exc} (repeats not logged)"
        record.args, record.exc_info, record.exc_text = (), None, None
        return True


@contextmanager
def quiet_resource_errors(loggers: tuple[str, ...] = ("asyncio", "uvicorn.error")) -> Iterator[_ResourceLogFilter]:
    """While inside: the event loop's and uvicorn's tracebacks for running out of descriptors or
    memory become one line per shortage (see :class:`_ResourceLogFilter`). Removed on exit."""
    flt = _ResourceLogFilter()
    for name in loggers:
        logging.getLogger(name).addFilter(flt)
    try:
        yield flt
    finally:
        for name in loggers:
            logging.getLogger(name).removeFilter(flt)
