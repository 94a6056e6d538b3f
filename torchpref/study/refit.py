r"""Refitting a study's population on every finished participant, in a process of its own.

``python -m torchpref.study.refit DIR`` (started by the study's server when a participant
finishes, :class:`RefitRunner`): reads the finished participants' session files without locking
them (the server may hold them open), builds each person's data as their session's model sees it
(:func:`person_data`), fits the population (:func:`~torchpref.fit_population`), warm-started from
the current population's kernels, writes it as a new version and then points ``current.json`` at
it, each atomically: a kill at any moment leaves the previous population in force and loadable.
One refit runs at a time (a lock file); a failure is logged and keeps the previous population.
"""

from __future__ import annotations

import argparse
import copy
import fcntl
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import torch

from torchpref.data.preference_data import DEFAULT_RATING_EPS, PreferenceData
from torchpref.population.fit import fit_population
from torchpref.population.io import save_population
from torchpref.sessions.journal import read_session_file
from torchpref.sessions.model_state import build_data
from torchpref.sessions.records import AnswerRecord, records_in_force
from torchpref.study.folder import StudyFolder

__all__ = ["RefitRunner", "finished_participants", "person_data", "refit"]

MIN_PEOPLE = 2
"""A population is fitted once this many participants have finished."""
WARM_MAX_ITER = 15
"""L-BFGS iterations of a refit warm-started from the current population's kernels."""
COLD_MAX_ITER = 30
"""L-BFGS iterations of the first fit (no population to start from)."""


def person_data(path: Path) -> tuple[PreferenceData, dict, int]:
    """``(data, header, answers in force)`` of a session file: the data of its answers in force in the
    unit cube its model sees (normalised by the header's bounds, the pool's first item the anchor),
    as :class:`~torchpref.PreferenceSession` builds it. Reads without locking."""
    header, raw, _ = read_session_file(path)
    if header is None:
        raise ValueError(f"session file {path} is empty.")
    in_force = [AnswerRecord.from_json(r) for r in records_in_force(raw)]
    lo, hi = torch.tensor(header["bounds"], dtype=torch.float64)
    spec = header["candidates"]  # the first item anchors the model (a large pool's header has it alone)
    pool = torch.tensor(spec["items"][:1] if "items" in spec else [spec["first_item"]], dtype=torch.float64)

    def transform(X: torch.Tensor) -> torch.Tensor:
        return (X - lo) / (hi - lo)

    data, _ = build_data(transform(pool[:1]), in_force, transform, DEFAULT_RATING_EPS, None)
    return data, header, len(in_force)


def finished_participants(folder: StudyFolder) -> list[tuple[str, PreferenceData, list[str] | None]]:
    """``(sid, data, feature names)`` of every participant with all their questions answered, by sid."""
    out = []
    for f in sorted(folder.sessions.glob("*.session.jsonl")):
        try:
            data, header, answered = person_data(f)
        except (OSError, ValueError):  # an unreadable file is not fitted (the server reports it)
            continue
        if answered >= header["num_queries"] and data.num_observations:
            out.append((f.name.split(".")[0], data, header.get("names")))
    return out


def refit(folder: StudyFolder, max_iter: int | None = None) -> int | None:
    """Fit the population on every finished participant and make it current; returns its version
    (``None``: fewer than :data:`MIN_PEOPLE` finished). A refit already running is waited for."""
    folder.populations.mkdir(parents=True, exist_ok=True)
    with open(folder.populations / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one refit at a time: a second waits, then fits everyone finished
        people = finished_participants(folder)
        pointer = folder.current()
        if len(people) < MIN_PEOPLE:
            return None
        if pointer is not None and set(pointer["participants"]) == {sid for sid, _, _ in people}:
            return int(pointer["version"])  # the current population has everyone finished already
        t0 = time.perf_counter()
        names = people[0][2]
        kernels = {}
        if pointer is not None:  # warm start: the current population's kernels
            try:
                prev = folder.population(pointer["version"], names=names)
            except (OSError, ValueError):
                prev = None
            if prev is not None:
                kernels = {"k_m": copy.deepcopy(prev.k_m), "k_g": copy.deepcopy(prev.k_g)}
        iters = max_iter if max_iter is not None else (WARM_MAX_ITER if kernels else COLD_MAX_ITER)
        pop = fit_population([d for _, d, _ in people], names=names, max_iter=iters, **kernels)
        version = folder.next_version()
        save_population(pop, folder.version_path(version))
        seconds = time.perf_counter() - t0
        sids = [s for s, _, _ in people]
        folder.set_current(version, sids, seconds)
        folder.log("refit", version=version, participants=len(sids), seconds=round(seconds, 3), warm=bool(kernels))
        return version


class RefitRunner:
    """Refits in a worker process of its own, ``python -m torchpref.study.refit DIR --serve``,
    started at the first request and kept (so a refit costs the fit, not Python's and torch's
    start-up): one refit at a time, a request while one runs makes one more run after it. A
    refit that fails is logged by the worker; one that runs past ``timeout`` seconds is stopped
    with its worker (a new one starts at the next request). The previous population stays
    current either way. Never blocks the caller. If the server dies, the worker finishes the
    refit it is in (its files are written atomically) and exits."""

    def __init__(self, folder: StudyFolder, timeout: float = 600.0, nice: int = 10):
        self.folder, self.timeout, self.nice = folder, timeout, nice
        self._lock = threading.Lock()
        self._worker: subprocess.Popen | None = None
        self._busy = False  # a refit asked of the worker and not answered yet
        self._pending = False
        self._asked = 0  # the number of the refit asked last (for the timeout's check)
        self.completed = 0

    def request(self) -> None:
        """Refit soon (now if none is running)."""
        with self._lock:
            if self._busy:
                self._pending = True
                return
            self._ask()

    def _spawn(self) -> subprocess.Popen:
        log = open(self.folder.path / "refit.log", "a")
        # one thread (torch's and BLAS's): a refit shares the machine with the server's answers
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p), OMP_NUM_THREADS="1")
        env.update(OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
        proc = subprocess.Popen(
            [sys.executable, "-m", "torchpref.study.refit", str(self.folder.path), "--serve"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            env=env,
            preexec_fn=(lambda: os.nice(self.nice)) if self.nice else None,
        )
        log.close()
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
        except (OSError, ValueError):  # the worker is gone: the next request starts another
            self._worker, self._busy = None, False
            return
        timer = threading.Timer(self.timeout, self._check_timeout, args=(self._asked,))
        timer.daemon = True
        timer.start()

    def _read(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith(("done", "failed")):
                with self._lock:
                    if proc is not self._worker:
                        continue
                    self._busy = False
                    self.completed += 1
                    if self._pending:
                        self._pending = False
                        self._ask()
        with self._lock:  # the worker exited (stopped, or it failed to start)
            if proc is self._worker:
                self._worker, self._busy = None, False

    def _check_timeout(self, asked: int) -> None:
        with self._lock:
            if not (self._busy and asked == self._asked and self._worker is not None):
                return
            proc, self._worker, self._busy = self._worker, None, False
        proc.kill()
        proc.wait()
        self.folder.log("refit stopped", why=f"ran past {self.timeout:.0f} s; the previous population stays")

    def busy(self) -> bool:
        """Whether a refit is running or asked for."""
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
            print(f"failed {type(exc).__name__}", flush=True)
            if not args.serve:
                raise
            continue
        print(f"done {f'v{version}' if version else 'nothing to fit yet'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
