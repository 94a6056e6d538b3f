r"""Time per answer, per undo and per resume of a session with 10, 100, 1,000 and 5,000 answers
(issue #22), against the previous release's sessions, which replayed every answer.

A session over a pool of 100 items (2 objectives) holds answers given out of turn (ratings, best-of-3
and best-of-5 choices, no preference, in a fixed pseudo-random mix), one file per size. For each:

* ``answer``: one ``tell_rating`` (the model's update and the fsynced append), then undone, median
  of ``--repeats``;
* ``ask``: the next query (UCBC over the pool), median of ``--repeats``;
* ``undo``: one ``undo`` after a ``tell_rating``, median of ``--repeats``;
* ``resume``: ``PreferenceSession.load`` (the file read, validated, the model built), median of
  ``--repeats``; ``resume_cold`` the same without the mode snapshot ``FILE.mode``.

With ``--baseline DIR`` (a checkout of the previous code, e.g. ``git worktree add --detach DIR
6ae28eb``) the same operations run on the same files in a subprocess importing that code, at the
sizes up to ``--baseline-max`` (its undo and resume replay every answer). One torch thread. By
default each operation is timed by the process's CPU time (``--clock cpu``): on a machine loaded by
other processes the wall time mostly measures the waiting (the fsync's wait is not CPU time; it is
the same for every size). The load average is recorded beside the timings.

Writes ``results/sessions/session_scale.{csv,json,png}``.

Usage::

    .venv/bin/python benchmarks/durability/session_scale.py [--sizes 10 100 1000 5000] [--repeats 5]
        [--baseline /path/to/old/checkout --baseline-max 1000]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from torchpref.experiments.results import write_json

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "results" / "sessions"
POOL_SEED = 3

MEASURE = r'''
import json, shutil, statistics, sys, time, warnings
import torch
torch.set_num_threads(1)
from torchpref.sessions.session import PreferenceSession

def measure(path, repeats, clock="wall"):
    now = time.process_time if clock == "cpu" else time.perf_counter
    X = torch.tensor(json.loads(open(path).readline())["candidates"]["items"], dtype=torch.float64)
    out = {}
    PreferenceSession.load(path).close()  # imports' and first calls' one-time costs, not timed
    times = []
    for _ in range(repeats):
        t = now()
        s = PreferenceSession.load(path)
        s.model
        times.append(now() - t)
        s.close()
    out["resume"] = statistics.median(times)
    s = PreferenceSession.load(path)
    ask, tell, undo = [], [], []
    for k in range(repeats):
        s._pending = None
        t = now(); s.ask(); ask.append(now() - t)
        t = now(); s.tell_rating(X[k % X.shape[0]], 1 + k % 5); tell.append(now() - t)
        t = now(); s.undo(); undo.append(now() - t)
    s.close()
    out.update(answer=statistics.median(tell), ask=statistics.median(ask), undo=statistics.median(undo))
    return out

if __name__ == "__main__":
    import torchpref
    print(json.dumps(dict(measure(sys.argv[1], int(sys.argv[2]), sys.argv[3]), module=torchpref.__file__)))
'''


def make_pool() -> torch.Tensor:
    g = torch.Generator().manual_seed(POOL_SEED)
    return torch.rand(100, 2, generator=g, dtype=torch.float64) * torch.tensor([400.0, 200.0], dtype=torch.float64)


def build_files(sizes: list[int], workdir: Path) -> dict[int, Path]:
    """A session file with each number of answers (a fixed pseudo-random mix of ratings, best-of-3
    and best-of-5 choices and no preference over the pool), written as records (the cost measured
    is that of sessions holding them, not of telling them), each opened once and given one answer
    and its undo so that its mode snapshot is current."""
    from tqdm import tqdm

    from torchpref.data.preference_data import likert_to_unit
    from torchpref.sessions.journal import now
    from torchpref.sessions.session import PreferenceSession

    X = make_pool()
    files = {}
    for n in tqdm(sorted(sizes), desc="session files", unit="file"):
        path = workdir / f"s{n}.jsonl"
        PreferenceSession(X, session_file=path, seed=1, num_queries=max(sizes)).close()
        g = torch.Generator().manual_seed(7)
        lines = []
        for k in range(1, n + 1):
            kind = int(torch.randint(10, (1,), generator=g))
            rec = {"type": "answer", "v": 1, "seq": k, "time": now()}
            if kind < 4:
                level = int(torch.randint(1, 6, (1,), generator=g))
                item = X[int(torch.randint(100, (1,), generator=g))]
                value = float(likert_to_unit(level, 5))
                rec.update(kind="rating", items=[item.tolist()], answer=level, value=value)
            else:
                m = 3 if kind < 7 else 5
                rows = torch.randperm(100, generator=g)[: 3 if kind == 9 else m]
                chosen = None if kind == 9 else int(torch.randint(m, (1,), generator=g))
                rec.update(kind="no_preference" if kind == 9 else "choice", items=X[rows].tolist(), answer=chosen)
            rec.update(query=None, response_time=None)
            lines.append(json.dumps(rec, separators=(",", ":")))
        with open(path, "a") as fh:
            fh.write("".join(line + "\n" for line in lines))
        s = PreferenceSession.load(path)  # checks every record; one answer and its undo write the snapshot
        s.tell_rating(X[0], 3)
        s.undo()
        s.close()
        files[n] = path
    return files


def measure_here(path: Path, repeats: int, clock: str) -> dict[str, float]:
    ns: dict = {}
    exec(compile(MEASURE.replace('if __name__ == "__main__":', "if False:"), "measure", "exec"), ns)
    out = ns["measure"](str(path), repeats, clock)
    now = time.process_time if clock == "cpu" else time.perf_counter
    from torchpref.sessions.model_state import snapshot_path
    from torchpref.sessions.session import PreferenceSession

    cold = []
    for _ in range(repeats):
        snap = snapshot_path(path)
        saved = snap.read_bytes()
        snap.unlink()
        t = now()
        PreferenceSession.load(path).close()
        cold.append(now() - t)
        snap.write_bytes(saved)
    out["resume_cold"] = statistics.median(cold)
    return out


def measure_baseline(checkout: Path, path: Path, repeats: int, clock: str) -> dict[str, float]:
    copy = path.with_name(path.stem + "_old.jsonl")
    shutil.copy(path, copy)
    env = dict(os.environ, PYTHONPATH=str(checkout), OMP_NUM_THREADS="1")
    out = subprocess.run(  # run from the checkout: "-c" puts the working directory first on sys.path
        [sys.executable, "-c", MEASURE, str(copy), str(repeats), clock],
        env=env,
        cwd=str(checkout),
        capture_output=True,
        text=True,
        check=True,
    )
    result = json.loads(out.stdout.strip().splitlines()[-1])
    if not result.pop("module").startswith(str(checkout.resolve())):
        raise RuntimeError(f"the baseline imported torchpref from outside {checkout}")
    return result


def plot(rows: list[dict], path: Path, clock: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ops = ["answer", "undo", "resume"]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), constrained_layout=True)
    for ax, op in zip(axes, ops, strict=True):
        for code, style in (("this", "o-"), ("previous (replay)", "s--")):
            pts = [(r["answers"], r["seconds"] * 1e3) for r in rows if r["operation"] == op and r["code"] == code]
            if pts:
                ax.plot(*zip(*pts, strict=True), style, label=code)
        if op == "resume":
            pts = [(r["answers"], r["seconds"] * 1e3) for r in rows if r["operation"] == "resume_cold"]
            ax.plot(*zip(*pts, strict=True), "^:", label="this, no snapshot")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("answers in the session")
        ax.set_title(f"one {op}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"milliseconds (median, {'CPU' if clock == 'cpu' else 'wall'} time)")
    axes[0].legend()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000, 5000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline", type=Path, default=None)
    ap.add_argument("--baseline-max", type=int, default=1000)
    ap.add_argument("--baseline-repeats", type=int, default=1, help="repeats of the baseline's (slow) operations")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument(
        "--clock", choices=["wall", "cpu"], default="cpu", help="cpu: this process's CPU time (robust to load)"
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        files = build_files(sorted(args.sizes), Path(tmp))
        for n in sorted(args.sizes):
            mine = measure_here(files[n], args.repeats, args.clock)
            rows += [dict(answers=n, code="this", operation=k, seconds=v) for k, v in mine.items()]
            print(n, "this", {k: f"{v * 1e3:.1f} ms" for k, v in mine.items()}, flush=True)
            if args.baseline is not None and n <= args.baseline_max:
                old = measure_baseline(args.baseline, files[n], args.baseline_repeats, args.clock)
                rows += [dict(answers=n, code="previous (replay)", operation=k, seconds=v) for k, v in old.items()]
                print(n, "previous", {k: f"{v * 1e3:.1f} ms" for k, v in old.items()}, flush=True)
    load_after = os.getloadavg()
    with open(args.out / "session_scale.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["answers", "code", "operation", "seconds"])
        w.writeheader()
        w.writerows(rows)

    def t(n, op, code="this"):
        return next((r["seconds"] for r in rows if (r["answers"], r["operation"], r["code"]) == (n, op, code)), None)

    lo, hi = min(args.sizes), 1000 if 1000 in args.sizes else max(args.sizes)
    target = {op: (t(hi, op) - t(lo, op)) * 1e3 for op in ("answer", "undo", "resume")}
    summary = {
        "sizes": sorted(args.sizes),
        "repeats": args.repeats,
        "torch_threads": 1,
        "clock": args.clock,
        "load_average_before": load_before,
        "load_average_after": load_after,
        f"ms_more_at_{hi}_than_at_{lo}": target,
        "target_under_50_ms": all(v < 50 for v in target.values()),
        "rows": rows,
    }
    write_json((args.out / "session_scale.json"), summary, measured="user")
    plot(rows, args.out / "session_scale.png", args.clock)
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=1))


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
