"""Every results file under ``benchmarks/results/``: fresh, stale or unstamped (``make results-status``).

A file is *fresh* when every source file its stamp hashed (the script that wrote it and the
``torchpref`` modules it ran) is unchanged, *stale* when one changed or is gone (the reason names
them), *unstamped* when it has no stamp (written before stamps, or not JSON: CSV and PNG files
are judged by the JSON beside them). ``--fail-on-stale`` exits 1 when a file is stale or unstamped
and not listed in ``benchmarks/results/KEPT_STALE.txt`` (one ``path: reason`` a line).

A *companion* is a file its writer leaves unstamped on purpose because the stamped summary beside it
covers the run (the suite's ``suite_trials.json``, every trial's record, and ``suite.json``, the
curves: ``torchpref.experiments.suite``). It takes its summary's state only when the summary is
shown to come from it: the summary's verdicts, best-or-tied counts and shares of ratings, and
``suite.json``'s curves, are recomputed from ``suite_trials.json`` (``suite_report.summarise``) and
must be equal. Otherwise it stays unstamped.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from pathlib import Path

from torchpref.experiments.stamp import ROOT, status

RESULTS = Path(__file__).resolve().parent / "results"


#: files written unstamped beside the stamped summary that covers them (file name: summary name)
COMPANIONS = {"suite.json": "suite_summary.json", "suite_trials.json": "suite_summary.json"}


def _equal(a: object, b: object, tol: float = 1e-9) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=tol, abs_tol=tol) or (math.isnan(a) and math.isnan(float(b)))
    return a == b


@functools.cache
def suite_companions_disagree(folder: Path) -> str:
    """Why ``folder``'s ``suite_summary.json`` (and ``suite.json``) are not what ``suite_trials.json``
    recomputes to, or ``""`` when they are."""
    from torchpref.experiments.suite import CHECKPOINTS, METRICS, effort_budgets
    from torchpref.experiments.suite_report import summarise

    try:
        by_cell = json.loads((folder / "suite_trials.json").read_text())
        summary = json.loads((folder / "suite_summary.json").read_text())
        trials = {tuple(cell.split("/", 1)): records for cell, records in by_cell.items()}
        strategies = list(next(iter(trials.values()))[0])
        queries = int(summary["queries"])
        checkpoints = sorted({q for q in CHECKPOINTS if q <= queries} | {queries})
        budgets = effort_budgets(summary["settings"].get("effort", "units"))
        again = json.loads(json.dumps(summarise(trials, strategies, METRICS, budgets, checkpoints)))
    except (OSError, ValueError, KeyError, IndexError, StopIteration, TypeError) as err:
        return f"cannot recompute the summary from suite_trials.json ({type(err).__name__}: {err})"
    wrong = [k for k in ("verdicts", "best_or_tied", "fraction_ratings") if not _equal(again[k], summary.get(k))]
    curves = folder / "suite.json"
    if curves.is_file() and not _equal(again["curves"], json.loads(curves.read_text())):
        wrong.append("suite.json's curves")
    return "" if not wrong else "recomputed from suite_trials.json, these differ: " + ", ".join(wrong)


def file_status(f: Path) -> tuple[str, str]:
    """``status`` of a results file, a companion (:data:`COMPANIONS`) taking its summary's."""
    state, reason = status(f, ROOT)
    summary = f.parent / COMPANIONS.get(f.name, "")
    if state != "unstamped" or f.name not in COMPANIONS or not summary.is_file():
        return state, reason
    summary_state, summary_reason = status(summary, ROOT)
    if summary_state == "unstamped":
        return state, reason
    disagree = suite_companions_disagree(f.parent)
    if disagree:
        return state, f"no stamp; a companion of {summary.name}, but {disagree}"
    return summary_state, f"a companion of {summary.name} (which recomputes from it): {summary_reason}"


def kept_stale(folder: Path, complain=print) -> dict[str, str]:
    """``{path: reason}`` of the stale files kept on purpose (``KEPT_STALE.txt``); a line that is not
    ``path: reason`` (no colon, or no reason) keeps nothing and is named through ``complain``."""
    f = folder / "KEPT_STALE.txt"
    if not f.is_file():
        return {}
    kept = {}
    for n, line in enumerate(f.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        path, colon, reason = line.partition(":")
        if not colon or not reason.strip() or not path.strip():
            complain(f"KEPT_STALE.txt line {n} is not 'path: reason' and keeps nothing: {line.strip()[:80]!r}")
            continue
        kept[path.strip()] = reason.strip()
    return kept


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?", type=Path, default=RESULTS)
    ap.add_argument("--fail-on-stale", action="store_true")
    args = ap.parse_args(argv)
    kept = kept_stale(args.folder)
    counts = {"fresh": 0, "stale": 0, "unstamped": 0}
    unexplained = []
    for f in sorted(args.folder.rglob("*.json")):
        state, reason = file_status(f)
        rel = f.relative_to(args.folder).as_posix()
        counts[state] += 1
        note = f"  [kept: {kept[rel]}]" if rel in kept else ""
        if state != "fresh" and rel not in kept:
            unexplained.append(rel)
        print(f"{state:9s} {rel}: {reason}{note}")
    total = sum(counts.values())
    stamped = counts["fresh"] + counts["stale"]
    print(f"{counts['fresh']} fresh, {counts['stale']} stale, {counts['unstamped']} unstamped")
    if total:
        print(
            f"{stamped} of {total} stamped ({100 * stamped / total:.0f} %); {len(unexplained)} not fresh without a reason"
        )
    return 1 if args.fail_on_stale and unexplained else 0


if __name__ == "__main__":
    sys.exit(main())
