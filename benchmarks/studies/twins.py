r"""Twins of real people (issue 41): every selector on simulated new people of the electricity and
Dutch rail populations, with and without the population prior (:mod:`torchpref.experiments.twins`).

Writes ``benchmarks/results/twins/``: ``twins_rows.jsonl`` (every twin's curves, appended as the runs
finish: a re-run resumes), ``twins.json`` (stamped: areas, paired Wilcoxon tests against random,
questions to reach random's 20-question concordance, verdicts at equal seconds), ``twins.csv`` (the
curves), ``twins.png`` and ``twins_trajectories.png`` (concordance against questions and seconds),
(the fitted populations are kept in ``~/.cache/torchpref/twins``).

Run: ``OMP_NUM_THREADS=1 nice -n 10 python benchmarks/studies/twins.py`` (the arguments of
``torchpref reproduce twins``; ``--fresh`` starts over).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from torchpref.cli import main

OUT = Path(__file__).resolve().parents[1] / "results" / "twins"

if __name__ == "__main__":
    argv = [a for a in sys.argv[1:] if a != "--fresh"]
    if "--fresh" in sys.argv[1:] and OUT.exists():
        shutil.rmtree(OUT)
    if "--out" not in argv:
        argv += ["--out", str(OUT)]
    raise SystemExit(main(["reproduce", "twins", *argv]))
