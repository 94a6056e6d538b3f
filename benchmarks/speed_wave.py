r"""Wall time of the wave experiment (Fig. 6: 100 trials, 20 queries, 5 strategies), ours against
the authors' NumPy code, both in one run.

Each repeat runs ``torchpref reproduce wave`` in a fresh process (2 worker processes, batched
trials) and, if ``--authors DIR`` is given, the authors' script in a fresh process, alternating so
that load from other processes falls on both alike; medians are kept. Two times per run:

* ``compute_s``: the experiment itself, as each program reports it (ours:
  ``wave_summary.json: wall_time_s``, from the first trial to the last result, worker start-up
  included; theirs: the script's own ``wall`` line, from after its imports to its last trial);
* ``command_s``: the whole process, imports and (ours) writing the JSON/CSV files and figures
  included.

The authors' code is not part of this repository: ``DIR`` must hold a Python 3 port of their
``active_statruns.py`` (osurdml/GPtest, May 2017) that prints a line
``100 trials x 20 queries, 5 learners: 38.7 s wall``; it is run as ``KVAR=0.36 python SCRIPT 100``
(kernel variance 0.36, as in ``docs/wave.md``).

Writes ``results/speed_wave.{json,csv}``.

Usage::

    .venv/bin/python benchmarks/speed_wave.py [--repeats 3] [--authors DIR] [--script explore_1d.py]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parent.parent


def run_ours(trials: int, queries: int) -> dict[str, float]:
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
        ]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True, text=True)
        command = time.perf_counter() - t0
        compute = json.loads((Path(out) / "wave_summary.json").read_text())["wall_time_s"]
    return {"compute_s": compute, "command_s": command}


def run_authors(directory: Path, script: str, trials: int, python: str) -> dict[str, float]:
    env = {**os.environ, "KVAR": "0.36"}
    t0 = time.perf_counter()
    proc = subprocess.run(
        [python, script, str(trials)], check=True, cwd=directory, capture_output=True, text=True, env=env
    )
    command = time.perf_counter() - t0
    found = re.search(r"learners: ([0-9.]+) s wall", proc.stdout)
    if found is None:
        raise RuntimeError(f"no 'learners: ... s wall' line in the authors' output:\n{proc.stdout[-2000:]}")
    return {"compute_s": float(found.group(1)), "command_s": command}


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
    runs: dict[str, list[dict[str, float]]] = {"torchpref": []}
    if args.authors is not None:
        runs["authors"] = []
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover

        def tqdm(x, **_):
            return x

    for _ in tqdm(range(args.repeats), desc="repeats"):
        runs["torchpref"].append(run_ours(args.trials, args.queries))
        if args.authors is not None:
            runs["authors"].append(run_authors(args.authors, args.script, args.trials, args.python))
    med = {
        name: {k: statistics.median(r[k] for r in rs) for k in ("compute_s", "command_s")} for name, rs in runs.items()
    }
    result = {
        "trials": args.trials,
        "queries": args.queries,
        "repeats": args.repeats,
        "median": med,
        "runs": runs,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
    }
    if "authors" in med:
        result["speedup"] = {k: med["authors"][k] / med["torchpref"][k] for k in ("compute_s", "command_s")}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "speed_wave.json").write_text(json.dumps(result, indent=2))
    with open(args.out / "speed_wave.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["program", "repeat", "compute_s", "command_s"])
        for name, rs in runs.items():
            for i, r in enumerate(rs):
                w.writerow([name, i, f"{r['compute_s']:.2f}", f"{r['command_s']:.2f}"])
    for name, m in med.items():
        print(f"{name:10s} compute {m['compute_s']:6.1f} s   whole command {m['command_s']:6.1f} s")
    if "speedup" in result:
        s = result["speedup"]
        print(f"speed-up   compute {s['compute_s']:.2f}x   whole command {s['command_s']:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
