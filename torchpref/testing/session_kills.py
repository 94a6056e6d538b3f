r"""The kill harness of ``benchmarks/durability/session_kills.py`` (shared with
``tests/sessions/test_session_kill.py``).

Kill session processes (SIGKILL) at random points, mid-write, mid-rollback and mid-header, many
times, and check that no acknowledged answer is lost or doubled and that every file opens again.

A parent process (torch and torchpref imported once, one thread) forks a child per run. The child
opens the session file with ``repair=True`` (a torn last line from the previous kill is dropped,
with a warning; a half header is repaired anyway), answers out of turn, undoes now and then, and
reports each answer and undo on a pipe once the call has returned (acknowledged). Each answer is
named by its ``response_time`` (unique across runs). Kill points, in turn:

* ``random``: after a random delay;
* ``write``: half of a record written, the rest delayed (the kill lands in between);
* ``rollback``: a write fails half-way (a simulated I/O error, caught and retried by the child),
  and the kill lands in the middle of its rollback (the truncation delayed);
* ``header``: a new file, killed half-way through writing its header.

After every kill the next run must open the file. At the end each file is opened once more and
checked: sequence numbers 1, 2, ...; every acknowledged answer exactly once, every acknowledged undo
in the file, and the posterior equal to replaying the answers in force one by one.

Writes ``results/sessions/session_kills.json`` (and a CSV of the runs).

Usage::

    .venv/bin/python benchmarks/durability/session_kills.py [--kills 200] [--files 10] [--seed 0]
"""

from __future__ import annotations

import os
import random
import select
import signal
import time
import warnings
from pathlib import Path

import torch

MODES = ("random", "write", "rollback", "header")


def make_pool() -> torch.Tensor:
    """The candidate items of the kill runs' sessions."""
    g = torch.Generator().manual_seed(5)
    return torch.rand(12, 2, generator=g, dtype=torch.float64) * torch.tensor([50.0, 2.0], dtype=torch.float64)


def child(path: Path, run: int, mode: str, wfd: int, seed: int) -> None:
    """Open the session and answer until killed; report acknowledged answers and undos."""
    import errno

    import torchpref.sessions.journal as journal
    from torchpref.sessions.session import PreferenceSession

    rng = random.Random(seed * 1000 + run)
    say = lambda text: os.write(wfd, (text + "\n").encode())  # noqa: E731
    write_all, ftruncate = journal._write_all, os.ftruncate

    def slow_write(fd, data):
        header = data.startswith(b'{"type":"header"')
        if mode == "header" and header or mode == "write" and not header:
            write_all(fd, data[: len(data) // 2])
            say("HEADER" if header else "WRITING")
            time.sleep(0.2)
            write_all(fd, data[len(data) // 2 :])
        elif mode == "rollback" and not header and rng.random() < 0.5:
            write_all(fd, data[: len(data) // 2])
            raise OSError(errno.EIO, "simulated I/O error")
        else:
            write_all(fd, data)

    def slow_truncate(fd, size):
        say("ROLLBACK")
        time.sleep(0.2)
        ftruncate(fd, size)

    journal._write_all = slow_write
    if mode == "rollback":
        os.ftruncate = slow_truncate
    X = make_pool()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            s = PreferenceSession(X, session_file=path, seed=1, num_queries=10**6, repair=True)
    except Exception as err:  # the check: every file opens again
        say(f"OPENFAIL {type(err).__name__}: {err}")
        return
    say("OPEN")
    i = 0
    while True:
        stamp = float(run * 100_000 + i)
        i += 1
        try:
            if rng.random() < 0.6:
                s.tell_rating(X[rng.randrange(12)], rng.randint(1, 5), response_time=stamp)
            else:
                rows = rng.sample(range(12), 3)
                s.tell_choice(X[rows], rng.randrange(3), response_time=stamp)
        except OSError:
            continue  # the simulated I/O error: rolled back, not acknowledged
        say(f"ACK {stamp!r}")
        if rng.random() < 0.1:
            try:
                undone = s.undo()
            except OSError:
                continue
            say(f"UNDO {undone.response_time!r}")


def one_run(path: Path, run: int, mode: str, seed: int, rng: random.Random) -> dict:
    """One child process on ``path``, killed at the ``mode`` kill point; what it acknowledged."""
    rfd, wfd = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(rfd)
        try:
            child(path, run, mode, wfd, seed)
        finally:
            os._exit(0)
    os.close(wfd)
    events, buf, killed_at = [], b"", None
    trigger = {"write": "WRITING", "rollback": "ROLLBACK", "header": "HEADER"}.get(mode)
    deadline = time.monotonic() + (rng.uniform(0.2, 2.5) if mode == "random" else 60)
    opened: str | bool | None
    opened, need = None, 1 if mode == "header" else rng.randint(1, 4)  # kill at the need-th trigger
    while killed_at is None:
        ready, _, _ = select.select([rfd], [], [], max(0.0, deadline - time.monotonic()))
        if ready:
            chunk = os.read(rfd, 65536)
            if not chunk:
                break  # the child ended by itself (it should not)
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for line in lines:
                text = line.decode()
                events.append(text)
                if text.startswith("OPENFAIL"):
                    opened = text
                elif text == "OPEN":
                    opened = True
                if trigger and text == trigger and (opened is True or mode == "header"):
                    need -= 1
                    if need == 0:
                        time.sleep(rng.uniform(0.0, 0.15))  # somewhere in the 0.2 s the step is delayed
                        killed_at = text
                        break
        if time.monotonic() >= deadline and killed_at is None:
            killed_at = "timeout" if trigger else "random"
        if opened not in (None, True):
            break
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    while True:  # what the child reported before it died
        chunk = os.read(rfd, 65536)
        if not chunk:
            break
        buf += chunk
    os.close(rfd)
    events += [line.decode() for line in buf.split(b"\n") if line]
    return {
        "run": run,
        "mode": mode,
        "killed_at": killed_at,
        "opened": opened is True,
        "open_error": None if opened in (None, True) else opened,
        "acked": [float(e.split()[1]) for e in events if e.startswith("ACK ")],
        "undone": [float(e.split()[1]) for e in events if e.startswith("UNDO ")],
    }


def check_file(path: Path, acked: list[float], undone: list[float]) -> dict:
    """The final checks on one file (see the module docstring)."""
    from torchpref.sessions.session import PreferenceSession, read_session_file

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = PreferenceSession(make_pool(), session_file=path, seed=1, num_queries=10**6, repair=True)
    _, records, _ = read_session_file(path)
    seqs_ok = [r["seq"] for r in records] == list(range(1, len(records) + 1))
    stamps = [r["response_time"] for r in records if r["type"] == "answer"]
    lost = sorted(set(acked) - set(stamps))
    doubled = sorted({t for t in stamps if stamps.count(t) > 1})
    by_seq = {r["seq"]: r["response_time"] for r in records if r["type"] == "answer"}
    undone_in_file = [by_seq[r["undoes"]] for r in records if r["type"] == "undo"]
    undo_lost = sorted(set(undone) - set(undone_in_file))
    X = s.transform(make_pool())
    ref = s.reference_model()
    with torch.no_grad():
        diff = float((s.model.posterior(X.unsqueeze(-2)).mean - ref.posterior(X.unsqueeze(-2)).mean).abs().max())
    s.close()
    return {
        "file": path.name,
        "records": len(records),
        "acknowledged_answers": len(acked),
        "lost": lost,
        "doubled": doubled,
        "undos_lost": undo_lost,
        "sequence_ok": seqs_ok,
        "posterior_vs_replay": diff,
    }


def run_all(kills: int, files: int, seed: int, workdir: Path, progress: bool = True) -> dict:
    """``kills`` kill runs over ``files`` session files in ``workdir``, then every file checked (the module docstring)."""
    from torchpref.sessions.session import PreferenceSession

    torch.set_num_threads(1)
    warm = PreferenceSession(make_pool())  # imports and first-call compilations once, not in every child
    warm.tell_rating(make_pool()[0], 3)
    warm.tell_choice(make_pool()[:3], 1)
    warm.ask()
    rng = random.Random(seed)
    per_file: dict[int, dict[str, list]] = {i: {"acked": [], "undone": []} for i in range(files)}
    runs = []
    iterator = range(kills)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="kills", unit="kill")
    for k in iterator:
        f = k % files
        path = workdir / f"s{f}.jsonl"
        mode = MODES[(k // files) % len(MODES)]
        if mode == "header":  # a new file: the old one is checked and set aside first
            if path.exists():
                per_file[f]["result"] = per_file[f].get("result", []) + [
                    check_file(path, per_file[f]["acked"], per_file[f]["undone"])
                ]
                path.rename(path.with_suffix(f".{k}.done"))
                per_file[f]["acked"], per_file[f]["undone"] = [], []
        r = one_run(path, k, mode, seed, rng)
        runs.append(dict(r, file=f, acked=len(r["acked"]), undone=len(r["undone"])))
        per_file[f]["acked"] += r["acked"]
        per_file[f]["undone"] += r["undone"]
    results = []
    for f in range(files):
        results += per_file[f].get("result", [])
        path = workdir / f"s{f}.jsonl"
        if path.exists():
            results.append(check_file(path, per_file[f]["acked"], per_file[f]["undone"]))
    return {
        "kills": kills,
        "by_mode": {m: sum(1 for r in runs if r["mode"] == m) for m in MODES},
        "killed_at": {
            a: sum(1 for r in runs if r["killed_at"] == a) for a in sorted({str(r["killed_at"]) for r in runs})
        },
        "open_failures": [r for r in runs if r["open_error"]],
        "acknowledged_answers": sum(r["acked"] for r in runs),
        "acknowledged_undos": sum(r["undone"] for r in runs),
        "lost": sum(len(c["lost"]) for c in results),
        "doubled": sum(len(c["doubled"]) for c in results),
        "undos_lost": sum(len(c["undos_lost"]) for c in results),
        "files_checked": len(results),
        "all_sequences_ok": all(c["sequence_ok"] for c in results),
        "max_posterior_vs_replay": max(c["posterior_vs_replay"] for c in results),
        "files": results,
        "runs": runs,
    }
