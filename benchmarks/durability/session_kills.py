r"""Kill session processes (SIGKILL) at random points, mid-write, mid-rollback and mid-header, many
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

import argparse
import csv
import json
import os
import sys
import tempfile
import time
from pathlib import Path

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
    (args.out / "session_kills.json").write_text(
        json.dumps({k: v for k, v in summary.items() if k != "runs"}, indent=1)
    )
    brief = {k: v for k, v in summary.items() if k not in ("runs", "files")}
    print(json.dumps(brief, indent=1))
    ok = not (summary["lost"] or summary["doubled"] or summary["undos_lost"] or summary["open_failures"])
    sys.exit(0 if ok and summary["all_sequences_ok"] else 1)


if __name__ == "__main__":
    main()
