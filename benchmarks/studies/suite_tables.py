r"""Markdown tables of a suite run's verdicts (docs/suite.md): best-or-tied counts per strategy at
equal effort and after a number of queries, per metric, and each family's best strategy at equal
effort, from ``suite_summary.json``.

Run ``python benchmarks/studies/suite_tables.py benchmarks/results/suite_realistic_plain [...]``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

METRICS = ("wrms", "tp", "regret")
SHORT = {
    "UCBC": "UCBC",
    "random ratings": "RRt",
    "random rankings": "RRk",
    "UCB ratings": "UCBr",
    "profile per effort": "PPE",
    "clipped profile": "CPE",
    "profile per second": "PPS",
    "info per effort": "IPE",
    "variance per effort": "VPE",
}


def tables(folder: Path) -> str:
    s = json.loads((folder / "suite_summary.json").read_text())
    v = s["verdicts"]
    strategies = list(next(iter(next(iter(v.values())).values()))["wrms"]["mean"])
    points = list(next(iter(v.values())))
    out = [
        f"### {folder.name}: effort `{s['settings'].get('effort', 'units')}`, {s['trials']} trials, "
        f"{s['wall_time_s']:.0f} s wall, {s['cpu_time_s']:.0f} s of trial CPU\n"
    ]
    head = (
        "| strategy | ratings | "
        + " | ".join(f"{p}: {m}" for p in points for m in ("all",))
        + " | equal effort: WRMS / TP / regret |"
    )
    out += [head, "|" + "---|" * (3 + len(points))]
    cells = {p: len(v) * len(METRICS) for p in points}
    for st in strategies:
        counts = [sum(v[fc][p][m]["status"][st] in ("best", "tied") for fc in v for m in METRICS) for p in points]
        eff = [p for p in points if p.startswith("effort")]
        per_metric = [sum(v[fc][p][m]["status"][st] in ("best", "tied") for fc in v for p in eff) for m in METRICS]
        share = s["fraction_ratings"]
        share = [share[fc][st] for fc in share] if isinstance(share, dict) and st in next(iter(share.values())) else []
        ratings = f"{100 * sum(share) / len(share):.0f} %" if share else ""
        out.append(
            f"| {st} | {ratings} | "
            + " | ".join(f"{c} of {cells[p]}" for c, p in zip(counts, points))
            + f" | {' / '.join(str(x) for x in per_metric)} (of {len(v) * len(eff)} each) |"
        )
    out.append("")
    out.append(
        "| family / condition | "
        + " | ".join(f"{p}: {m}" for p in points if p.startswith("effort") for m in METRICS)
        + " |"
    )
    out.append("|" + "---|" * (1 + len(METRICS) * sum(p.startswith("effort") for p in points)))
    for fc in v:
        row = []
        for p in points:
            if not p.startswith("effort"):
                continue
            for m in METRICS:
                cell = v[fc][p][m]
                tied = [SHORT.get(x, x) for x, st in cell["status"].items() if st == "tied"]
                best = SHORT.get(cell["best"], cell["best"])
                mark = "PPS" in [best] + tied
                row.append(
                    f"{'**' if best == 'PPS' else ''}{best}{'**' if best == 'PPS' else ''}"
                    + (f" (+{','.join(tied)})" if tied else "")
                    + ("" if mark else " ✗")
                )
        out.append(f"| {fc} | " + " | ".join(row) + " |")
    return "\n".join(out)


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        print(tables(Path(arg)))
        print()
