"""Ax 1.3.1's own preference tests as a user gets them (issue 32, docs/ax.md).

Runs the tests of ``torchpref.testing.upstream.AX_FILES`` selected by ``AX_SELECT`` (Ax ships
them) with the counting plugin ``tests/parity/ax_swap_plugin.py``, in each mode asked for:
``documented`` (``import torchpref.integrations.ax`` and ``use_preference_gp()`` before the tests,
nothing of BoTorch's rebound), ``plain`` (Ax without torchpref: the PairwiseGP baseline) and,
labelled as a harness, ``harness`` (BoTorch's ``PairwiseGP`` name swapped). One pytest process per
mode, one after the other, one thread; writes ``benchmarks/results/ax/upstream_tests.json``
(stamped, the counts and every test's outcome and models), rewritten as each mode finishes.

    .venv-ax/bin/python benchmarks/parity/ax_upstream_tests.py --modes documented plain
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from torchpref.experiments.results import write_json
from torchpref.testing.upstream import AX_FILES, AX_MODES, AX_SELECT, ax_site, count, run_with_plugin

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "benchmarks" / "results" / "ax" / "upstream_tests.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--modes", nargs="+", default=["documented", "plain"], choices=sorted(AX_MODES))
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    site = ax_site()
    if site is None:
        raise SystemExit("Ax is not installed: pip install 'torchpref[ax]' (make test-integrations makes .venv-ax)")
    import ax

    files = [f for f in AX_FILES if (site / f).is_file()]
    summary: dict = {
        "ax_version": ax.__version__,
        "files": files,
        "select": AX_SELECT,
        "cpu_count": os.cpu_count(),
        "modes": {},
    }
    env = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    for i, mode in enumerate(args.modes, 1):
        print(f"[{i}/{len(args.modes)}] {mode}: {len(files)} files ...", flush=True)
        start, load = time.time(), os.getloadavg()[0]
        with tempfile.TemporaryDirectory() as tmp:
            results = run_with_plugin(
                site, files, {**env, **AX_MODES[mode]}, AX_SELECT, Path(tmp) / "r.json", ROOT / "tests" / "parity"
            )
        summary["modes"][mode] = {
            "measured": "harness: BoTorch's PairwiseGP name swapped" if mode == "harness" else "user",
            "env": AX_MODES[mode],
            "counts": count(results),
            "tests": results,
            "wall_s": round(time.time() - start, 1),
            "load_average_at_start": round(load, 2),
        }
        write_json(args.out, summary, measured="user", sources=[__file__])
        c = summary["modes"][mode]["counts"]
        print(
            f"  {c['ran']} ran, {c['passed']} passed, {len(c['failed'])} failed; {c['fit_a_preference_model']} fit a "
            f"preference model: PreferenceGP only {len(c['built_preference_gp_only'])}, PairwiseGP only "
            f"{len(c['built_pairwise_gp_only'])}, both {len(c['built_both'])}",
            flush=True,
        )


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of the pytest processes it starts too
        main()
