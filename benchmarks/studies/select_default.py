r"""Choose the default selector on all the evidence (issue 41).

Sub-commands (each writes stamped files under ``benchmarks/results/``; run them one at a time with
``OMP_NUM_THREADS=1 nice -n 10 python benchmarks/studies/select_default.py ...``):

* ``families --effort plain|trajectories``: the new candidates on the five realistic families
  (fixed and learned hyperparameters, 30 paired trials, 20 queries, seed 24: the trials of
  ``suite_select30_<effort>/``), written to ``select41_<effort>/``, then merged with the stored
  trials of UCBC, the clipped profile and utility information of ``suite_select30_<effort>/`` (the
  same trial seeds; the stored curves are reproduced exactly by today's code) into
  ``select41_<effort>/merged_summary.json``: verdicts among all the candidates.
* ``idealised [--trials 20]``: every strategy of the suite and the new candidates on the nine
  idealised families (effort units, both conditions), ``select41_idealised/``.
* ``decide``: reads the twins (``twins/twins.json``), the population replay
  (``replay_population/replay.json``), the families above, and writes ``default_choice.json``:
  per candidate, each criterion of issue 41 and whether it is met.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from torchpref.experiments import suite
from torchpref.experiments.results import write_json
from torchpref.experiments.suite_report import summarise

RESULTS = Path(__file__).resolve().parents[1] / "results"
#: the candidates (suite registry names) and the earlier runs they are merged with
STORED = ("UCBC", "clipped profile", "utility info")
NEW = ("combination", "qEUBO")
#: candidates added after the first runs: the sum of both values (twins, docs/selection.md)
LATER = ("information + profile",)
CANDIDATES = STORED + NEW + LATER
#: the candidate the default is built as (``default_selector``: its plain seconds whatever the effort model)
SHIPPED = "information + profile"
#: the replay's and the twins' names of the candidates
REPLAY_NAME = {"UCBC": "UCBC", "clipped profile": "clipped profile", "utility info": "information"}
REPLAY_NAME.update({"combination": "combination", "qEUBO": "qEUBO", "information + profile": "information + profile"})


def families(effort: str, strategies: tuple[str, ...] = NEW, trials: int = 30, out: Path | None = None) -> None:
    """Run ``strategies`` (into ``select41_<effort>/``, or for others than :data:`NEW`
    ``select41_<effort>_<names>/``), then merge every run of ``effort``."""
    if out is None:
        tail = (
            ""
            if tuple(strategies) == NEW
            else "_" + "_".join(s.replace(" ", "").replace("+", "plus") for s in strategies)
        )
        out = RESULTS / f"select41_{effort}{tail}"
    suite.run_suite(
        families=["realistic"], trials=trials, queries=20, seed=24, out=out, workers=1,
        strategies=list(strategies), effort=effort,
    )  # fmt: skip
    merge(effort)


def merge(effort: str, out: Path | None = None) -> dict:
    """The stored and new trials of the realistic families under ``effort`` (every
    ``select41_<effort>*/`` run, or ``out``'s), verdicts among all (the runs' trials are the first
    ones of the stored run's: the same seeds); written to ``select41_<effort>/merged_summary.json``."""
    runs = [out] if out is not None else sorted(RESULTS.glob(f"select41_{effort}*"))
    out = runs[0] if out is not None else RESULTS / f"select41_{effort}"
    results = {}
    for key, trials in json.loads((RESULTS / f"suite_select30_{effort}" / "suite_trials.json").read_text()).items():
        results[tuple(key.split("/"))] = trials
    for run in runs:
        for key, trials in json.loads((run / "suite_trials.json").read_text()).items():
            have = results[tuple(key.split("/"))]
            results[tuple(key.split("/"))] = [{**a, **b} for a, b in zip(have, trials)]
    have = next(iter(results.values()))[0]
    strategies = [s for s in CANDIDATES if s in have]
    summary = summarise(results, strategies, suite.METRICS, suite.effort_budgets(effort), [10, 20])
    counts = {s: _count(summary["verdicts"], s, "effort") for s in strategies}
    merged = {"effort": effort, "strategies": strategies, "equal_seconds_best_or_tied": counts}
    merged.update(verdicts=summary["verdicts"], fraction_ratings=summary["fraction_ratings"])
    if "default" in have:  # the default as shipped (plain seconds) in the place of its registry twin
        shipped = [s if s != SHIPPED else "default" for s in strategies]
        other = summarise(results, shipped, suite.METRICS, suite.effort_budgets(effort), [10, 20])
        merged["shipped_default"] = {"equal_seconds_best_or_tied": _count(other["verdicts"], "default", "effort")}
    write_json(out / "merged_summary.json", merged)
    print(effort, {s: f"{n}/{t}" for s, (n, t) in counts.items()})
    return merged


def _count(verdicts: dict, strategy: str, axis: str) -> tuple[int, int]:
    cells = [
        v["status"][strategy]
        for per_point in verdicts.values()
        for point, per_metric in per_point.items()
        if point.startswith(axis)
        for v in per_metric.values()
    ]
    return sum(c != "worse" for c in cells), len(cells)


def idealised(trials: int) -> None:
    strategies = list(dict.fromkeys([*suite.STRATEGIES, *CANDIDATES]))
    suite.run_suite(
        families=["idealised"], trials=trials, queries=20, seed=10, out=RESULTS / "select41_idealised", workers=1,
        strategies=strategies, effort="units",
    )  # fmt: skip


def _idealised_worse() -> dict[str, dict[str, int]]:
    """Per candidate and idealised family: the cells (condition, checkpoint, metric) where it is
    significantly worse than that cell's best strategy."""
    s = json.loads((RESULTS / "select41_idealised" / "suite_summary.json").read_text())
    out: dict[str, dict[str, int]] = {}
    for key, per_point in s["verdicts"].items():
        fam = key.split("/")[0]
        for per_metric in per_point.values():
            for v in per_metric.values():
                for cand in CANDIDATES:
                    if cand in v["status"]:
                        row = out.setdefault(cand, {})
                        row[fam] = row.get(fam, 0) + (v["status"][cand] == "worse")
    return out


def _twins(cand: str) -> dict:
    s = json.loads((RESULTS / "twins" / "twins.json").read_text())["summary"]["plain"]["cells"]
    out = {}
    for cell, e in s.items():
        v = e["strategies"].get(cand)
        if v is None:
            continue
        c = v["concordance"]
        ok = c["mean_diff"] > 0 and c["p_wilcoxon"] < 0.05 and v["reach"]["median"] <= 14
        out[cell] = dict(diff=c["mean_diff"], p=c["p_wilcoxon"], reach=v["reach"]["median"], met=ok)
    return out


def _replay(cand: str) -> dict:
    s = json.loads((RESULTS / "replay_population" / "replay.json").read_text())["summary"]
    out = {}
    for ds, per in s.items():
        e = per.get(REPLAY_NAME[cand])
        if e is None:
            continue
        worse = [m for m in ("accuracy", "top1") if e[m]["diff"] < 0 and e[m]["p"] < 0.05]
        worse += ["log_loss"] if e["log_loss"]["diff"] > 0 and e["log_loss"]["p"] < 0.05 else []
        out[ds] = dict(accuracy=e["accuracy"]["diff"], p=e["accuracy"]["p"], worse_on=worse, met=not worse)
    return out


def decide() -> None:
    table = {}
    worse = _idealised_worse() if (RESULTS / "select41_idealised" / "suite_summary.json").is_file() else {}
    for cand in CANDIDATES:
        row: dict = {"twins": _twins(cand), "replay": _replay(cand)}
        for effort in ("plain", "trajectories"):
            m = json.loads((RESULTS / f"select41_{effort}" / "merged_summary.json").read_text())
            n, t = m["equal_seconds_best_or_tied"].get(cand, (0, 0))
            row[f"families_{effort}"] = dict(best_or_tied=n, cells=t, met=n >= 50)
        row["idealised_worse_cells"] = worse.get(cand, {})
        row["idealised_worse_total"] = sum(row["idealised_worse_cells"].values())
        crit = [v["met"] for v in row["twins"].values()] + [v["met"] for v in row["replay"].values()]
        crit += [row["families_plain"]["met"], row["families_trajectories"]["met"]]
        crit += [n == 0 for n in row["idealised_worse_cells"].values()]
        row["criteria_met"], row["criteria"] = sum(crit), len(crit)
        table[cand] = row
    rank = sorted(table, key=lambda c: (-table[c]["criteria_met"], -_families(table[c])))
    write_json(RESULTS / "default_choice.json", {"candidates": table, "ranking": rank, "chosen": rank[0]})
    for c in rank:
        print(f"{c:18s} {table[c]['criteria_met']}/{table[c]['criteria']} criteria; families {_families(table[c])}")


def _families(row: dict) -> int:
    return row["families_plain"]["best_or_tied"] + row["families_trajectories"]["best_or_tied"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    fam = sub.add_parser("families")
    fam.add_argument("--effort", choices=["plain", "trajectories"], required=True)
    fam.add_argument("--strategies", nargs="+", default=list(NEW))
    fam.add_argument("--trials", type=int, default=30)
    fam.add_argument("--out", type=Path, default=None)
    sub.add_parser("merge").add_argument("--effort", choices=["plain", "trajectories"], required=True)
    sub.add_parser("idealised").add_argument("--trials", type=int, default=20)
    sub.add_parser("decide")
    args = ap.parse_args()
    if args.what == "families":
        families(args.effort, tuple(args.strategies), args.trials, args.out)
    elif args.what == "merge":
        merge(args.effort)
    elif args.what == "idealised":
        idealised(args.trials)
    else:
        decide()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
