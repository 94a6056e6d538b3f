r"""Replay real people's recorded choices (electricity suppliers, Dutch rail) and ask whether a
selector predicts their held-out choices sooner than revealing answers at random (issue 30).

The method: :mod:`torchpref.experiments.replay`. Data and its sources: ``benchmarks/studies/data/README.md``.

Run ``nice -n 10 python benchmarks/studies/replay.py [--people 80] [--splits 3]`` (one process, one
thread; about 15 minutes on one core); writes ``benchmarks/results/replay/`` (``replay.json``: areas,
paired Wilcoxon tests against random, load average and CPU count; ``replay.csv``: the curves;
``replay_rows.jsonl``: every (data set, person, split, selector) curve; ``replay.png``). The same as
``torchpref reproduce replay --out benchmarks/results/replay``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from torchpref.cli import main

if __name__ == "__main__":
    out = Path(__file__).resolve().parents[1] / "results" / "replay"
    sys.exit(main(["reproduce", "replay", "--out", str(out), *sys.argv[1:]]))
