r"""Pictures off the answer path: the summary plot and the items' pictures of ``torchpref serve``
are drawn by workers of their own, cached, and started before the page asks for them.

* **The summary plot** (``/s/SID/utility.png``): its numbers (the posterior over the pool, a few
  milliseconds) are taken under the session's lock; the drawing (hundreds of milliseconds of
  matplotlib) happens in a separate, lower-priority process
  (:mod:`~torchpref.frontends.serve.plot_worker`), so it holds neither the session's lock nor
  the server's interpreter lock. One thread feeds that process, one job at a time. Plots are
  cached by session, number of records and axes (:data:`SUMMARY_CACHE` of them), and a session's
  plot is started as soon as its last question is answered, before the summary page asks.
  Where no process can be started, the plot is drawn in that thread instead (under
  :data:`~torchpref.frontends.serve.items.PLOT_LOCK`), still outside any answer's request.
* **Items' pictures** (``/picture/I``): drawn by a thread of their own (a render function written
  in Python cannot be sent to another process), at a lower priority on Linux; the pictures of a
  question are started when the question is computed, before the browser asks for them, and
  kept (:class:`~torchpref.frontends.serve.items.ServeItems` caches them).

An answer's request never waits for either worker: it only puts a job in a queue.
"""

from __future__ import annotations

import os
import select
import struct
import subprocess
import sys
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable, Iterable
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Protocol

from torchpref.frontends.serve.items import PLOT_LOCK, ServeItems
from torchpref.frontends.serve.pool import PoolEntry

__all__ = ["DRAW_TIMEOUT", "Plots", "ProcessDrawer", "SUMMARY_CACHE", "Worker"]


class SessionEntries(Protocol):
    """What the summary plots ask of a store: a session's pool entry (its lock and session);
    :class:`~torchpref.frontends.serve.store.SessionStore` is one (a Protocol: it imports this module)."""

    def entry(self, sid: str) -> PoolEntry: ...


SUMMARY_CACHE = 8
"""Summary plots kept (some 60 KB each): a finished session's, drawn at its last answer, until its page has loaded it."""

DRAW_TIMEOUT = 120.0
"""Seconds a summary plot may take in the worker process before it is restarted."""

QUEUE_LIMIT = 256
"""Jobs waiting at most in a worker; a pre-render beyond it is skipped (it is drawn when asked for)."""

WORKER_SCRIPT = Path(__file__).with_name("plot_worker.py")

IDLE_EXIT = 30.0
"""Seconds a worker's thread waits for a job before it ends (the next job starts another)."""


class Worker:
    """One thread running jobs one at a time, each at most once while it is pending (jobs are
    named by a key: a second request for the same key gets the same :class:`~concurrent.futures.Future`);
    urgent jobs (a page waiting) go before pre-renders."""

    def __init__(self, name: str, nice: int = 10):
        self.name, self.nice = name, nice
        self._cv = threading.Condition()
        self._queue: deque[tuple[Hashable, Callable[[], Any], Future]] = deque()
        self._pending: dict[Hashable, Future] = {}
        self._thread: threading.Thread | None = None
        self._closed = False
        self.running: Hashable | None = None  # the key of the job running now
        self.done = 0

    def submit(self, key: Hashable, job: Callable[[], Any], urgent: bool = False) -> Future | None:
        """Run ``job`` in the worker; its future (``None``: a pre-render skipped, the queue is full)."""
        with self._cv:
            if self._closed:
                raise RuntimeError(f"the {self.name} worker is closed")
            fut = self._pending.get(key)
            if fut is not None:
                if urgent:  # a page waits for a pre-render still queued: move it to the front
                    for k, item in enumerate(self._queue):
                        if item[0] == key:
                            del self._queue[k]
                            self._queue.appendleft(item)
                            break
                return fut
            if not urgent and len(self._queue) >= QUEUE_LIMIT:
                return None
            fut = Future()
            self._pending[key] = fut
            (self._queue.appendleft if urgent else self._queue.append)((key, job, fut))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=f"torchpref-serve-{self.name}", daemon=True)
                self._thread.start()
            self._cv.notify()
            return fut

    def _run(self) -> None:
        _lower_priority(self.nice)
        while True:
            with self._cv:
                if not self._queue and not self._closed:
                    self._cv.wait(IDLE_EXIT)
                if not self._queue:  # closed, or idle: the thread ends (the next job starts another)
                    self._thread = None
                    return
                key, job, fut = self._queue.popleft()
                self.running = key
            try:
                result = job()
            except BaseException as exc:  # the page asking gets the error; the worker goes on
                fut.set_exception(exc)
            else:
                fut.set_result(result)
            finally:
                with self._cv:
                    self._pending.pop(key, None)
                    self.running = None
                    self.done += 1
                    self._cv.notify_all()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until no job is queued or running; whether it is so (``False``: ``timeout`` passed)."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._pending, timeout)

    def close(self) -> None:
        """Finish the queued jobs' futures with an error and stop the thread."""
        with self._cv:
            self._closed = True
            queued, self._queue = list(self._queue), deque()
            for key, _, fut in queued:
                self._pending.pop(key, None)
                fut.set_exception(RuntimeError(f"the {self.name} worker is closed"))
            self._cv.notify_all()


def _lower_priority(nice: int) -> None:
    """Lower this thread's CPU priority (Linux: a thread is a task of its own); elsewhere nothing."""
    if nice and sys.platform.startswith("linux"):
        try:
            os.setpriority(
                os.PRIO_PROCESS, threading.get_native_id(), min(19, os.getpriority(os.PRIO_PROCESS, 0) + nice)
            )
        except (OSError, AttributeError):
            pass


class ProcessDrawer:
    """The summary plot drawn in a process of its own (:mod:`~torchpref.frontends.serve.plot_worker`),
    started on first use and again if it dies or takes longer than ``timeout`` seconds."""

    def __init__(self, timeout: float = DRAW_TIMEOUT):
        self.timeout = timeout
        self._proc: subprocess.Popen | None = None
        self._lock = threading.Lock()
        self.starts = 0

    @property
    def pid(self) -> int | None:
        """The worker process's id (``None`` while none runs)."""
        proc = self._proc
        return None if proc is None or proc.poll() is not None else proc.pid

    def __call__(self, data: dict) -> bytes:
        with self._lock:
            for attempt in (0, 1):
                proc = self._start()
                try:
                    _send(proc, data)
                    kind, payload = _receive(proc, self.timeout)
                except (OSError, EOFError, TimeoutError, ValueError):
                    self._stop()
                    if attempt:
                        raise
                    continue
                if kind != "ok":
                    raise RuntimeError(f"the plot could not be drawn: {payload}")
                return payload
        raise AssertionError("unreachable")  # pragma: no cover

    def _start(self) -> subprocess.Popen:
        if self._proc is not None and self._proc.poll() is None:
            return self._proc
        env = dict(os.environ, MPLBACKEND="Agg")
        proc = subprocess.Popen(
            [sys.executable, str(WORKER_SCRIPT)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=env,
            bufsize=0,
            close_fds=True,
        )
        self._proc = proc
        self.starts += 1
        try:
            kind, _ = _receive(proc, max(self.timeout, 60.0))  # matplotlib's import, on a busy machine
        except BaseException:
            self._stop()
            raise
        if kind != "ready":
            self._stop()
            raise EOFError("the plot worker did not start")
        return proc

    def _stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        for stream in (proc.stdin, proc.stdout):
            try:
                if stream is not None:
                    stream.close()
            except OSError:
                pass
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)

    def close(self) -> None:
        """Stop the worker process."""
        with self._lock:
            self._stop()

    def __del__(self) -> None:
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.stdin is not None:
            try:
                proc.stdin.close()  # the worker ends at the end of its input
            except OSError:
                pass


def _send(proc: subprocess.Popen, obj: object) -> None:
    import pickle

    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    assert proc.stdin is not None
    proc.stdin.write(struct.pack(">I", len(data)) + data)


def _receive(proc: subprocess.Popen, timeout: float) -> tuple[str, Any]:
    import pickle

    assert proc.stdout is not None
    fd, deadline = proc.stdout.fileno(), time.monotonic() + timeout

    def exactly(n: int) -> bytes:
        chunks, got = [], 0
        while got < n:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise TimeoutError(f"the plot worker gave no answer in {timeout:.0f} s")
            chunk = os.read(fd, min(n - got, 1 << 20))
            if not chunk:
                raise EOFError("the plot worker stopped")
            chunks.append(chunk)
            got += len(chunk)
        return b"".join(chunks)

    (n,) = struct.unpack(">I", exactly(4))
    return pickle.loads(exactly(n))


def _draw_here(data: dict) -> bytes:
    from torchpref.frontends.serve.plot_worker import draw_utility

    with PLOT_LOCK:
        return draw_utility(data)


def _picture_job(items: ServeItems, i: int) -> Callable[[], tuple[bytes, str] | None]:
    return lambda: items.picture(i)


class Plots:
    """The summary plots and item pictures of one server (see the module).

    Args:
        items: the pool and its pictures.
        process: draw summary plots in a worker process (default where ``select`` works on pipes:
            not on Windows); otherwise in the summary thread.
    """

    def __init__(self, items: ServeItems, process: bool | None = None):
        self.items = items
        if process is None:
            process = sys.platform != "win32"
        self.drawer: Callable[[dict], bytes] = ProcessDrawer() if process else _draw_here
        self.summary = Worker("summary")
        self.pictures = Worker("pictures")
        self._cache: OrderedDict[tuple, bytes] = OrderedDict()
        self._lock = threading.Lock()
        self.fallbacks = 0

    # --------------------------------------------------------------- summary
    def utility_png(self, store: SessionEntries, sid: str, x: int, y: int, timeout: float = 2 * DRAW_TIMEOUT) -> bytes:
        """The summary plot of session ``sid`` over objectives ``x``, ``y`` now: from the cache,
        or drawn by the summary worker (this request waits for it; answers do not)."""
        entry = store.entry(sid)
        with entry.lock:
            key = (sid, len(entry.session.records), x, y)
        with self._lock:
            png = self._cache.get(key)
            if png is not None:
                self._cache.move_to_end(key)
                return png
        fut = self.summary.submit(key, lambda: self._draw(store, sid, x, y), urgent=True)
        assert fut is not None
        return fut.result(timeout=timeout)

    def prerender(self, store: SessionEntries, sid: str, x: int = 0, y: int | None = None) -> None:
        """Start drawing ``sid``'s summary plot (default axes: the first two objectives) in the
        background; returns at once."""
        if y is None:
            y = min(1, self.items.X.shape[1] - 1)
        try:
            self.summary.submit(("prerender", sid, x, y), lambda: self._draw(store, sid, x, y))
        except RuntimeError:  # closed: the server is stopping
            pass

    def _draw(self, store: SessionEntries, sid: str, x: int, y: int) -> bytes:
        from torchpref.frontends.serve.summary import utility_data

        entry = store.entry(sid)
        with entry.lock:  # the numbers only: milliseconds
            version = len(entry.session.records)
            key = (sid, version, x, y)
            with self._lock:
                png = self._cache.get(key)
            if png is None:
                data = utility_data(self.items, entry.session, x, y)
        if png is None:
            png = self._render(data)
        with self._lock:
            self._cache[key] = png
            self._cache.move_to_end(key)
            while len(self._cache) > SUMMARY_CACHE:
                self._cache.popitem(last=False)
        return png

    def _render(self, data: dict) -> bytes:
        try:
            return self.drawer(data)
        except (OSError, EOFError, TimeoutError):  # no process could draw it: drawn here instead
            self.fallbacks += 1
            return _draw_here(data)

    # -------------------------------------------------------------- pictures
    def picture(self, i: int, timeout: float = 2 * DRAW_TIMEOUT) -> tuple[bytes, str] | None:
        """Item ``i``'s picture (see :meth:`ServeItems.picture`), drawn by the pictures worker.

        Raises:
            IndexError: no item ``i``; what the render function raised.
        """
        items = self.items
        if not 0 <= i < len(items):
            raise IndexError(f"no item {i} (items 0..{len(items) - 1}).")
        if items.render is None:
            return None
        cache = getattr(items, "_cache", {})
        if i in cache:
            return items.picture(i)
        fut = self.pictures.submit(("picture", i), lambda: items.picture(i), urgent=True)
        assert fut is not None
        return fut.result(timeout=timeout)

    def prefetch(self, indices: Iterable[int | None]) -> None:
        """Start drawing the pictures of items ``indices`` (a question's options, the
        recommendation) that are not drawn yet; returns at once."""
        items = self.items
        if items.render is None:
            return
        cache = getattr(items, "_cache", {})
        for i in indices:
            if i is not None and 0 <= i < len(items) and i not in cache:
                try:
                    self.pictures.submit(("picture", i), _picture_job(items, i))
                except RuntimeError:
                    return

    def prefetch_state(self, state: dict) -> None:
        """:meth:`prefetch` the pictures a page state shows (its question's options, the recommendation)."""
        q, rec = state.get("question"), state.get("recommended")
        rows = [o.get("index") for o in q["options"]] if q else []
        self.prefetch(rows + ([rec.get("index")] if rec else []))

    def close(self) -> None:
        """Stop the workers and the plot process."""
        self.summary.close()
        self.pictures.close()
        if isinstance(self.drawer, ProcessDrawer):
            self.drawer.close()
