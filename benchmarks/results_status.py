"""Every results file under ``benchmarks/results/``: fresh, stale or unstamped (``make results-status``).

A file is *fresh* when every source file its stamp hashed (the script that wrote it and the
``torchpref`` modules it ran) is unchanged, *stale* when one changed or is gone (the reason names
them), *unstamped* when it has no stamp (written before stamps, or not JSON: CSV and PNG files
are judged by the JSON beside them). ``--fail-on-stale`` exits 1 when a file is stale or unstamped
and not listed in ``benchmarks/results/KEPT_STALE.txt`` (one ``path: reason`` a line).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchpref.experiments.stamp import ROOT, status

RESULTS = Path(__file__).resolve().parent / "results"


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
        state, reason = status(f, ROOT)
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
