"""Time the lake scenario (400 paths, both planners), report its ratings and draw Figs. 7-8.

Run: ``.venv/bin/python benchmarks/paper/lake_scenario.py [--seeds 0 1 2]``
"""

import argparse
import time
from pathlib import Path

import torch

from torchpref.lake import LakeOperator, make_scenario
from torchpref.lake.plotting import plot_field, plot_objectives

RESULTS = Path(__file__).resolve().parents[1] / "results"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    op = LakeOperator()
    for seed in args.seeds:
        start = time.perf_counter()
        sc = make_scenario(seed, progress=True)
        elapsed = time.perf_counter() - start
        for name, X in (("train", sc.train_X), ("test", sc.test_X)):
            share = float((op.level(X) == 5).double().mean())
            print(
                f"seed {seed} {name}: {elapsed:.1f} s, rated 5: {100 * share:.1f} %, "
                f"distance {float(X[:, 0].min()):.0f}-{float(X[:, 0].max()):.0f}, "
                f"information {float(X[:, 1].min()):.0f}-{float(X[:, 1].max()):.0f}, "
                f"levels {torch.bincount(op.level(X), minlength=6)[1:].tolist()}"
            )
        if seed == args.seeds[0]:
            plot_field(sc, RESULTS / "lake_field.png")
            plot_objectives(sc, RESULTS / "lake_objectives.png")


if __name__ == "__main__":
    main()
