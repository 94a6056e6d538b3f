r"""Wall and CPU time of the wave experiment (Fig. 6: 100 trials, 20 queries, 5 strategies), ours
against the authors' NumPy code, both in one run.

Each repeat runs ``torchpref reproduce wave`` in a fresh process, once with one process
(``--workers 1``: the same process count as the authors' script) and once with the default
worker pool (``--workers`` unset: one process per CPU), and, if ``--authors DIR`` is given, the
authors' script in a fresh process, alternating so that load from other processes falls on all
alike; medians are kept. Three times per run:

* ``compute_s``: the experiment itself, as each program reports it (ours:
  ``wave_summary.json: wall_time_s``, from the first trial to the last result, worker start-up
  included; theirs: the script's own ``wall`` line, from after its imports to its last trial);
* ``command_s``: the whole process, imports and (ours) writing the JSON/CSV files and figures
  included;
* ``cpu_s``: the CPU time (user + system) of the whole process and its worker processes
  (``getrusage(RUSAGE_CHILDREN)`` around the run): a comparison per CPU second, which a
  different process count does not change.

Ratios reported: authors / ours for each of our two process counts, per time.

The authors' code is not part of this repository: ``DIR`` must hold a Python 3 port of their
``active_statruns.py`` (osurdml/GPtest, May 2017) that prints a line
``100 trials x 20 queries, 5 learners: 38.7 s wall``; it is run as ``KVAR=0.36 python SCRIPT 100``
(kernel variance 0.36, as in ``docs/wave.md``).

Writes ``results/speed_wave.{json,csv}``.

Usage::

    .venv/bin/python benchmarks/speed/speed_wave.py [--repeats 3] [--authors DIR] [--script explore_1d.py]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from torchpref.experiments.results import write_json

RESULTS = Path(__file__).resolve().parents[1] / "results"
ROOT = Path(__file__).resolve().parents[2]


def _children_cpu() -> float:
    """User + system CPU seconds of this process's waited-for descendants so far."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_ours(trials: int, queries: int, workers: int | None = None) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as out:
        cmd = [
            sys.executable,
            "-m",
            "torchpref.cli",
            "reproduce",
            "wave",
            "--trials",
            str(trials),
            "--queries",
            str(queries),
            "--out",
            out,
        ] + ([] if workers is None else ["--workers", str(workers)])
        c0, t0 = _children_cpu(), time.perf_counter()
        subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True, text=True)
        command, cpu = time.perf_counter() - t0, _children_cpu() - c0
        compute = json.loads((Path(out) / "wave_summary.json").read_text())["wall_time_s"]
    return {"compute_s": compute, "command_s": command, "cpu_s": cpu}


def run_authors(directory: Path, script: str, trials: int, python: str) -> dict[str, float]:
    env = {**os.environ, "KVAR": "0.36"}
    c0, t0 = _children_cpu(), time.perf_counter()
    proc = subprocess.run(
        [python, script, str(trials)], check=True, cwd=directory, capture_output=True, text=True, env=env
    )
    command, cpu = time.perf_counter() - t0, _children_cpu() - c0
    found = re.search(r"learners: ([0-9.]+) s wall", proc.stdout)
    if found is None:
        raise RuntimeError(f"no 'learners: ... s wall' line in the authors' output:\n{proc.stdout[-2000:]}")
    return {"compute_s": float(found.group(1)), "command_s": command, "cpu_s": cpu}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--queries", type=int, default=20)
    p.add_argument("--authors", type=Path, default=None, help="folder of the authors' ported script")
    p.add_argument("--script", default="explore_1d.py", help="the authors' script in that folder")
    p.add_argument("--python", default=sys.executable, help="interpreter for the authors' script")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.authors is not None and args.queries != 20:
        p.error("the authors' script runs 20 queries; leave --queries at 20 to compare.")
    runs: dict[str, list[dict[str, float]]] = {"torchpref": [], "torchpref_1_process": []}
    if args.authors is not None:
        runs["authors"] = []
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover

        def tqdm(x, **_):
            return x

    load_start = os.getloadavg()
    for _ in tqdm(range(args.repeats), desc="repeats"):
        runs["torchpref"].append(run_ours(args.trials, args.queries))
        runs["torchpref_1_process"].append(run_ours(args.trials, args.queries, workers=1))
        if args.authors is not None:
            runs["authors"].append(run_authors(args.authors, args.script, args.trials, args.python))
    keys = ("compute_s", "command_s", "cpu_s")
    med = {name: {k: statistics.median(r[k] for r in rs) for k in keys} for name, rs in runs.items()}
    result = {
        "trials": args.trials,
        "queries": args.queries,
        "repeats": args.repeats,
        "median": med,
        "runs": runs,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "processes": {"torchpref": f"default pool ({os.cpu_count()} workers)", "torchpref_1_process": 1, "authors": 1},
    }
    if "authors" in med:
        result["speedup"] = {
            ours: {k: med["authors"][k] / med[ours][k] for k in keys} for ours in ("torchpref", "torchpref_1_process")
        }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json((args.out / "speed_wave.json"), result, measured="user")
    with open(args.out / "speed_wave.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["program", "repeat", *keys])
        for name, rs in runs.items():
            for i, r in enumerate(rs):
                w.writerow([name, i, *(f"{r[k]:.2f}" for k in keys)])
    for name, m in med.items():
        print(
            f"{name:20s} compute {m['compute_s']:6.1f} s   whole command {m['command_s']:6.1f} s   CPU {m['cpu_s']:6.1f} s"
        )
    for ours, s in result.get("speedup", {}).items():
        print(f"authors / {ours}: " + "   ".join(f"{k} {v:.2f}x" for k, v in s.items()))
    return 0


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        sys.exit(main())
