"""Count BoTorch's API checks passed by PreferenceGP and by PairwiseGP (docs/botorch.md).

Runs ``tests/parity/test_botorch_port_*.py`` (BoTorch's own checks of ``PairwiseGP`` and of its
preference acquisitions, objectives and input constructors, rewritten to run on either model)
and tallies, per model, the checks that passed and those that failed (marked ``xfail`` in
``tests/parity/botorch_port.py``'s ``GAPS``; an ``xfail`` that passes counts as passed).

Usage: ``python benchmarks/parity/botorch_api_counts.py [--out benchmarks/results]``
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path

from torchpref.experiments.results import write_json

ROOT = Path(__file__).resolve().parents[2]
IMPLS = ("PreferenceGP", "PairwiseGP")


def run_checks() -> list[tuple[str, str]]:
    """``(check id, outcome)`` for every check, outcome one of passed / failed."""
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "report.xml"
        files = sorted(str(p) for p in (ROOT / "tests" / "parity").glob("test_botorch_port_*.py"))
        if not files:  # never the whole suite: pytest given no files collects every test
            raise FileNotFoundError("no tests/parity/test_botorch_port_*.py")
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pytest",
                "-q",
                "-p",
                "no:randomly",
                "-W",
                "ignore",
                "-rxX",
                f"--junitxml={xml}",
                "-o",
                "junit_family=xunit2",
                *files,
            ],
            cwd=ROOT,
            check=False,
        )
        out = []
        for case in ET.parse(xml).getroot().iter("testcase"):
            skipped = case.find("skipped")
            failed = case.find("failure") is not None or case.find("error") is not None
            if skipped is not None and skipped.get("type") == "pytest.xfail":
                outcome = "failed"
            elif skipped is not None:
                continue  # a check that does not apply
            else:
                outcome = "failed" if failed else "passed"
            out.append((f"{case.get('classname')}::{case.get('name')}", outcome))
        return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = parser.parse_args()
    results = run_checks()
    counts = {impl: Counter(o for name, o in results if f"[{impl}" in name) for impl in IMPLS}
    summary = {
        impl: {"passed": c["passed"], "failed": c["failed"], "total": c["passed"] + c["failed"]}
        for impl, c in counts.items()
    }
    failed = {
        impl: sorted(name.split("::")[-1] for name, o in results if f"[{impl}" in name and o == "failed")
        for impl in IMPLS
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json((out / "botorch_api_counts.json"), {"summary": summary, "failed": failed}, measured="user")
    for impl in IMPLS:
        s = summary[impl]
        print(f"{impl}: {s['passed']} of {s['total']} checks pass; fails: {', '.join(failed[impl]) or 'none'}")


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
