r"""Kill session processes (SIGKILL) at random points, mid-write, mid-rollback and mid-header, many
times, and check that no acknowledged answer is lost or doubled and that every file opens again.
The harness and what it checks: :mod:`torchpref.testing.session_kills` (its docstring).

Writes ``results/sessions/session_kills.json`` (and a CSV of the runs).

Usage::

    .venv/bin/python benchmarks/durability/session_kills.py [--kills 200] [--files 10] [--seed 0]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from torchpref.experiments.results import write_json
from torchpref.testing.session_kills import run_all

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "results" / "sessions"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kills", type=int, default=200)
    ap.add_argument("--files", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0, load = time.time(), os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_all(args.kills, args.files, args.seed, Path(tmp))
    summary.update(seconds=round(time.time() - t0, 1), load_average_before=load, load_average_after=os.getloadavg())
    with open(args.out / "session_kills_runs.csv", "w", newline="") as fh:
        keys = ["run", "file", "mode", "killed_at", "opened", "open_error", "acked", "undone"]
        w = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(summary["runs"])
    write_json(args.out / "session_kills.json", {k: v for k, v in summary.items() if k != "runs"}, measured="user")
    brief = {k: v for k, v in summary.items() if k not in ("runs", "files")}
    print(json.dumps(brief, indent=1))
    ok = not (summary["lost"] or summary["doubled"] or summary["undos_lost"] or summary["open_failures"])
    sys.exit(0 if ok and summary["all_sequences_ok"] else 1)


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
