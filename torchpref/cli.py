r"""The ``torchpref`` command line.

    torchpref reproduce wave [--trials N] [--queries Q] [--seed S] [--out DIR]
    torchpref reproduce lake [--trials N] [--queries Q] [--seed S] [--out DIR]
    torchpref elicit lake [--session FILE]
    torchpref elicit --features items.csv [--session FILE]

Each subcommand lives in its own module, imported only when it runs.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# subcommand -> module with ``add_arguments(parser)`` and ``run(args) -> int``
REPRODUCE = {"wave": "torchpref.experiments.wave", "lake": "torchpref.lake.experiment"}
ELICIT = "torchpref.elicit"


def _experiment_args(p: argparse.ArgumentParser, trials: int, queries: int) -> None:
    p.add_argument("--trials", type=int, default=trials, help=f"number of trials (default {trials})")
    p.add_argument("--queries", type=int, default=queries, help=f"queries per trial (default {queries})")
    p.add_argument("--seed", type=int, default=10, help="seed of the whole run (default 10)")
    p.add_argument("--out", default="benchmarks/results", help="output folder (default benchmarks/results)")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: CPU count)")


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``torchpref``'s arguments (its help texts are plain text, no markup)."""
    parser = argparse.ArgumentParser(
        prog="torchpref", description="Reproduce the paper's experiments, or learn your preferences in the terminal.")
    sub = parser.add_subparsers(dest="command", required=True)
    rep = sub.add_parser("reproduce", help="reproduce one of the paper's experiments")
    rep_sub = rep.add_subparsers(dest="experiment", required=True)
    _experiment_args(rep_sub.add_parser("wave", help="the 1-D wave-function experiment (Fig. 6)"), 100, 20)
    _experiment_args(rep_sub.add_parser("lake", help="the lake-monitoring experiment (Fig. 9)"), 20, 14)
    el = sub.add_parser("elicit", help="learn your preferences in the terminal")
    el.add_argument("world", nargs="?", choices=["lake"], help="a built-in world to elicit over")
    el.add_argument("--features", help="CSV of items' objective values (one row per item, a header row)")
    el.add_argument("--session", help="session file (JSON Lines) to append to / resume from")
    el.add_argument("--queries", type=int, default=14, help="number of queries (default 14)")
    el.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    el.add_argument("--out", default=".", help="where to write figures (default: current folder)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``torchpref`` with the arguments ``argv`` (default ``sys.argv[1:]``); return the exit status."""
    args = build_parser().parse_args(argv)
    if args.command == "reproduce":
        module = importlib.import_module(REPRODUCE[args.experiment])
    else:
        if (args.world is None) == (args.features is None):
            print("torchpref elicit: give either a world (lake) or --features FILE", file=sys.stderr)
            return 2
        module = importlib.import_module(ELICIT)
    return int(module.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
