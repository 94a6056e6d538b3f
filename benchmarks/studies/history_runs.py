r"""Re-run the earlier selector studies that docs/suite.md and docs/results.md quote, with the
settings each recorded (issue 53: every results file stamped with the code it ran).

Each sub-command writes one folder of ``benchmarks/results/`` (stamped by the experiment's own
writer; the suite's ``suite.json`` and ``suite_trials.json`` are the stamped summary's companions,
``benchmarks/results_status.py``):

* ``lakes10-selector``: the suite's selectors on 10 lakes x 20 trials (``lakes10_selector/``), and
  the clipped profile alone with the same trial seeds (``lakes10_selector_clipped/``);
* ``lake-operator --operator paper|realistic``: the paper's lake under each operator
  (``lake_operator_<operator>/``, one worker);
* ``wave-selector``: the suite's selectors on the paper's wave experiment (``wave_selector/``);
* ``realistic --effort plain|trajectories``: issue 24's realistic-rater suite, fixed condition
  (``suite_realistic_<effort>/``);
* ``select30 --effort plain|trajectories``: issue 30's candidates on the realistic families
  (``suite_select30_<effort>/``, one worker).

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python benchmarks/studies/history_runs.py realistic --effort plain
"""

from __future__ import annotations

import argparse
from pathlib import Path

from torchpref.experiments.families import REALISTIC_FAMILIES
from torchpref.experiments.lake import run_lake_experiment
from torchpref.experiments.stamp import recording_subprocesses
from torchpref.experiments.suite import run_suite
from torchpref.experiments.wave import run_wave_experiment

RESULTS = Path(__file__).resolve().parents[1] / "results"
LAKE_SELECTORS = [
    "UCBC",
    "random ratings",
    "UCB ratings",
    "info per effort",
    "variance per effort",
    "profile per effort",
]
OPERATOR_SELECTORS = ["UCBC", "UCB ratings", "clipped profile", "profile per second"]
WAVE_SELECTORS = [
    "UCBC", "random ratings", "random rankings", "UCB ratings", "info per effort",
    "variance per effort", "profile per effort", "clipped profile",
]  # fmt: skip
REALISTIC_SELECTORS = [
    "UCBC",
    "random ratings",
    "random rankings",
    "UCB ratings",
    "clipped profile",
    "profile per second",
]
SELECT30 = ["UCBC", "clipped profile", "utility info"]


def lakes10_selector(workers: int | None) -> None:
    common = dict(trials=20, queries=14, seed=10, lakes=10, workers=workers, plan_trials=20)
    run_lake_experiment(out=RESULTS / "lakes10_selector", strategies=LAKE_SELECTORS, plan=["UCBC"], **common)
    run_lake_experiment(out=RESULTS / "lakes10_selector_clipped", strategies=["clipped profile"], plan=[], **common)


def lake_operator(operator: str) -> None:
    run_lake_experiment(
        trials=20, queries=14, seed=10, workers=1, strategies=OPERATOR_SELECTORS, plan=[], plan_trials=20,
        operator=operator, out=RESULTS / f"lake_operator_{operator}",
    )  # fmt: skip


def wave_selector(workers: int | None) -> None:
    run_wave_experiment(
        trials=100, queries=20, seed=10, workers=workers, strategies=WAVE_SELECTORS, out=RESULTS / "wave_selector"
    )


def realistic(effort: str, workers: int | None) -> None:
    run_suite(
        families=[*REALISTIC_FAMILIES, "waves", "two-bumps"], trials=30, queries=20, seed=24, conditions=["fixed"],
        strategies=REALISTIC_SELECTORS, effort=effort, workers=workers, out=RESULTS / f"suite_realistic_{effort}",
    )  # fmt: skip


def select30(effort: str) -> None:
    run_suite(
        families=["realistic"], trials=30, queries=20, seed=24, strategies=SELECT30, effort=effort, workers=1,
        out=RESULTS / f"suite_select30_{effort}",
    )  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", choices=["lakes10-selector", "lake-operator", "wave-selector", "realistic", "select30"])
    ap.add_argument("--effort", choices=["plain", "trajectories"], default="plain")
    ap.add_argument("--operator", choices=["paper", "realistic"], default="paper")
    ap.add_argument("--workers", type=int, default=None, help="worker processes (default: CPU count)")
    args = ap.parse_args(argv)
    if args.run == "lakes10-selector":
        lakes10_selector(args.workers)
    elif args.run == "lake-operator":
        lake_operator(args.operator)
    elif args.run == "wave-selector":
        wave_selector(args.workers)
    elif args.run == "realistic":
        realistic(args.effort, args.workers)
    else:
        select30(args.effort)


if __name__ == "__main__":
    with recording_subprocesses():
        main()
