r"""Refitting a study's population on every finished participant, in a process of its own.

``python -m torchpref.study.refit DIR`` (started by the study's server when a participant
finishes, :class:`RefitRunner`): reads the finished participants' session files without locking
them (the server may hold them open), builds each person's data as their session's model sees it
(:func:`~torchpref.sessions.contents.read_session`), fits the population (:func:`~torchpref.fit_population`), warm-started from
the current population's kernels, writes it as a new version and then points ``current.json`` at
it, each atomically: a kill at any moment leaves the previous population in force and loadable.
One refit runs at a time (a lock file); a failure is logged and keeps the previous population.
"""

from __future__ import annotations

import argparse
import copy
import fcntl
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import torch

from torchpref.data.preference_data import PreferenceData
from torchpref.population.fit import fit_population
from torchpref.population.io import save_population
from torchpref.study.export import study_sessions
from torchpref.study.folder import PRIVATE_FILE, StudyFolder, make_private, private_dir

__all__ = ["RefitRunner", "finished_participants", "refit", "worker_command"]

MIN_PEOPLE = 2
"""A population is fitted once this many participants have finished."""
WARM_MAX_ITER = 15
"""L-BFGS iterations of a refit warm-started from the current population's kernels."""
COLD_MAX_ITER = 30
"""L-BFGS iterations of the first fit (no population to start from)."""


def finished_participants(folder: StudyFolder) -> list[tuple[str, PreferenceData, tuple[str, ...] | None]]:
    """``(sid, data, feature names)`` of every participant with all their questions answered, by
    sid: the data of their answers in force as their session's model sees it
    (:func:`~torchpref.sessions.contents.read_session`)."""
    out = []
    for s in study_sessions(folder):  # an unreadable file is not fitted (the page reports it)
        if s.finished and s.data.num_observations:
            out.append((s.sid, s.data, s.header.names))
    return out


def refit(folder: StudyFolder, max_iter: int | None = None) -> int | None:
    """Fit the population on every finished participant and make it current; returns its version
    (``None``: fewer than :data:`MIN_PEOPLE` finished). A refit already running is waited for."""
    with open(private_dir(folder.populations) / ".lock", "w") as lock:
        make_private(folder.populations / ".lock")
        fcntl.flock(lock, fcntl.LOCK_EX)  # one refit at a time: a second waits, then fits everyone finished
        people = finished_participants(folder)
        pointer = folder.current()
        if len(people) < MIN_PEOPLE:
            return None
        sids = [sid for sid, _, _ in people]
        if pointer is not None and pointer.fallback is None and set(pointer.participants) == set(sids):
            return pointer.version  # the current population has everyone finished already
        t0 = time.perf_counter()
        names = people[0][2]
        kernels = {}
        if pointer is not None:  # warm start: the current population's kernels
            try:
                prev = folder.population(pointer.version, names=None if names is None else list(names))
            except (OSError, ValueError):
                prev = None
            if prev is not None:
                kernels = {"k_m": copy.deepcopy(prev.k_m), "k_g": copy.deepcopy(prev.k_g)}
        iters = max_iter if max_iter is not None else (WARM_MAX_ITER if kernels else COLD_MAX_ITER)
        pop = fit_population([d for _, d, _ in people], names=names, max_iter=iters, **kernels)
        pop.stats["study_participants"] = json.dumps(sids)
        version = folder.next_version()
        save_population(pop, folder.version_path(version))
        make_private(folder.version_path(version))
        seconds = time.perf_counter() - t0
        folder.set_current(version, sids, seconds)
        folder.log(
            "refit",
            version=version,
            participants=len(sids),
            seconds=round(seconds, 3),
            warm=bool(kernels),
            solver=pop.stats.get("solver"),
        )
        return version


def worker_command(folder: StudyFolder) -> tuple[list[str], str]:
    """``(argv, cwd)`` of a refit worker for ``folder``: this Python, isolated (``-I``: neither the
    working folder nor ``PYTHONPATH`` nor the user's site-packages on its path, so a ``torch.py``
    lying in the folder the server was started from is never imported), with torchpref's own
    folder and the server's other import paths put back explicitly, run in the study's private
    ``population`` folder."""
    import torchpref

    here = {os.path.realpath(os.getcwd()), ""}
    root = str(Path(torchpref.__file__).resolve().parent.parent)
    paths = [root] + [p for p in sys.path if p and os.path.realpath(p) not in here and p != root and os.path.isdir(p)]
    boot = f"import sys; sys.path[:0] = {paths!r}; from torchpref.study.refit import main; sys.exit(main(sys.argv[1:]))"
    return [sys.executable, "-I", "-c", boot, str(folder.path.resolve()), "--serve"], str(folder.populations)


class RefitRunner:
    """Refits in a worker process of its own (:func:`worker_command`), started ahead of the first
    request (:meth:`start`) and kept, so a refit costs the fit, not Python's and torch's start-up:
    one refit at a time, a request while one runs makes one more run after it.

    A refit that fails is logged by the worker. A worker that dies, or whose refit runs past
    ``timeout`` seconds (it is then stopped), is logged; the refit is asked again of a new worker
    (``retries`` times in a row at most; always when another request is waiting), so the queue
    never stalls and :meth:`busy` never stays true for a worker that is gone. The previous
    population stays current meanwhile. Never blocks the caller. If the server dies, the worker
    finishes the refit it is in (its files are written atomically) and exits.

    Args:
        say: called with one line for the server's terminal per population made current.
        command: the worker's ``(argv, cwd)`` (default :func:`worker_command`; tests give another).
    """

    def __init__(
        self,
        folder: StudyFolder,
        timeout: float = 600.0,
        nice: int = 10,
        *,
        retries: int = 1,
        say: Callable[[str], None] | None = None,
        command: tuple[list[str], str] | None = None,
    ):
        self.folder, self.timeout, self.nice, self.retries = folder, timeout, nice, retries
        self.say = say or (lambda line: None)
        self.command = command
        self._lock = threading.Lock()
        self._worker: subprocess.Popen | None = None
        self._busy = False  # a refit asked of the worker and not answered yet
        self._pending = False
        self._asked = 0  # the number of the refit asked last (for the timeout's check)
        self._failures = 0  # workers lost in a row
        self.completed = 0
        self.spawned = 0

    def start(self) -> None:
        """Start the worker now (it waits for a request), so that the first refit does not wait for
        Python and torch to start."""
        with self._lock:
            if self._worker is None or self._worker.poll() is not None:
                self._worker = self._spawn()

    def request(self) -> None:
        """Refit soon (now if none is running)."""
        with self._lock:
            if self._busy:
                self._pending = True
                return
            self._ask()

    def _spawn(self) -> subprocess.Popen:
        argv, cwd = self.command if self.command is not None else worker_command(self.folder)
        log_fd = os.open(self.folder.path / "refit.log", os.O_WRONLY | os.O_APPEND | os.O_CREAT, PRIVATE_FILE)
        # one thread (torch's and BLAS's): a refit shares the machine with the server's answers
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
        try:
            proc = subprocess.Popen(
                argv,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log_fd,
                text=True,
                env=env,
                cwd=cwd,
                preexec_fn=(lambda: os.nice(self.nice)) if self.nice else None,
            )
        finally:
            os.close(log_fd)
        self.spawned += 1
        threading.Thread(target=self._read, args=(proc,), daemon=True).start()
        return proc

    def _ask(self) -> None:
        """Ask the worker (started if need be) for one refit; called under the lock."""
        if self._worker is None or self._worker.poll() is not None:
            self._worker = self._spawn()
        self._busy, self._asked = True, self._asked + 1
        try:
            assert self._worker.stdin is not None
            self._worker.stdin.write("refit\n")
            self._worker.stdin.flush()
        except (OSError, ValueError):  # the worker is gone: its reader sees it exit and asks again
            pass
        timer = threading.Timer(self.timeout, self._check_timeout, args=(self._asked,))
        timer.daemon = True
        timer.start()

    def _read(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if not line.startswith(("done", "failed")):
                continue
            with self._lock:
                if proc is not self._worker:
                    continue
                self._busy = False
                self.completed += 1
                self._failures = 0
                if self._pending:
                    self._pending = False
                    self._ask()
            words = line.split()
            if line.startswith("done") and len(words) >= 4 and words[1].startswith("v"):
                self.say(
                    f"torchpref study: population {words[1]} in force: {words[2]} participants, fitted in {words[3]} s"
                )
            elif line.startswith("failed"):
                self.say(f"torchpref study: a refit failed ({line[7:].strip()}); the previous population stays")
        code = proc.wait()
        with self._lock:  # the worker exited: stopped by us, or it died
            if proc is not self._worker:
                return
            self._worker = None
            if not self._busy:
                return
            self._lost(f"the refit worker exited with status {code} during a refit")

    def _lost(self, why: str) -> None:
        """A worker was lost with a refit asked of it (under the lock): logged, and the refit asked
        again of a new worker, unless it was lost too often in a row and nothing else waits."""
        self._busy = False
        self._failures += 1
        again = self._pending or self._failures <= self.retries
        self._pending = False
        self.folder.log("refit worker lost", why=why, asked_again=again)
        self.say(f"torchpref study: {why}; " + ("asking a new worker" if again else "the previous population stays"))
        if again:
            self._ask()

    def _check_timeout(self, asked: int) -> None:
        with self._lock:
            if not (self._busy and asked == self._asked and self._worker is not None):
                return
            proc, self._worker = self._worker, None
        proc.kill()
        proc.wait()
        self.folder.log("refit stopped", why=f"ran past {self.timeout:.0f} s; the previous population stays")
        with self._lock:
            if self._busy and asked == self._asked:
                self._lost(f"a refit ran past {self.timeout:.0f} s and was stopped")

    def busy(self) -> bool:
        """Whether a refit is running or asked for (false once its worker is gone and not replaced)."""
        with self._lock:
            return self._busy or self._pending

    def close(self, wait: float = 0.0) -> None:
        """Stop the worker, once a refit still running has had ``wait`` seconds (its population is
        made current only if it got that far: the files are written atomically)."""
        deadline = time.monotonic() + wait
        while self.busy() and time.monotonic() < deadline:
            time.sleep(0.1)
        with self._lock:
            self._pending = False
            proc, self._worker, self._busy = self._worker, None, False
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="refit a study's population on its finished participants")
    ap.add_argument("folder", type=Path)
    ap.add_argument("--max-iter", type=int, default=None)
    ap.add_argument("--serve", action="store_true", help="refit once per line read from standard input")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    folder = StudyFolder(args.folder)
    for _ in sys.stdin if args.serve else [None]:
        try:
            version = refit(folder, args.max_iter)
        except Exception as exc:  # logged; the previous population stays current
            folder.log("refit failed", why=f"{type(exc).__name__}: {str(exc)[:300]}")
            print(f"failed {type(exc).__name__}: {str(exc)[:200]}".replace("\n", " "), flush=True)
            if not args.serve:
                raise
            continue
        pointer = folder.current() if version else None
        if version and pointer is not None and pointer.version == version:
            print(f"done v{version} {len(pointer.participants)} {pointer.seconds or 0:.1f}", flush=True)
        else:
            print(f"done {f'v{version}' if version else 'nothing to fit yet'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
