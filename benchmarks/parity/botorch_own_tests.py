"""Run BoTorch's own preference tests, unmodified, on ``PairwiseGP`` and on ``PreferenceGP``.

The test files are taken from a checkout of BoTorch's repository (``--botorch-src``; the
installed package has no tests) and run twice in a temporary folder: once as they are (on
``PairwiseGP``: the baseline, which also shows failures that come from a test file being newer
or older than the installed BoTorch), and once with a ``conftest.py`` that puts ``PreferenceGP``
in ``PairwiseGP``'s place, with ``PairwiseGP``'s constructor signature (``datapoints,
comparisons, likelihood, covar_module, input_transform``; its likelihood argument is ignored,
``PreferenceGP``'s comparison likelihood being the probit) and
``LaplaceMarginalLogLikelihood`` in ``PairwiseLaplaceMarginalLogLikelihood``'s. A test method
stops at its first failed assertion, so a failure can hide later checks: docs/botorch.md
reports what a deeper reading (each ``PairwiseGP``-internal assertion taken out) found.

Usage: ``python benchmarks/parity/botorch_own_tests.py --botorch-src PATH [--out benchmarks/results]``
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

from torchpref.experiments.results import write_json

FILES = (
    "test/models/test_pairwise_gp.py",
    "test/acquisition/test_preference.py",
    "test/acquisition/test_objective.py",
    "test/acquisition/test_active_learning.py",
    "test/sampling/test_pairwise_sampler.py",
)

SHIM = '''
"""PreferenceGP in PairwiseGP's place when TP_SHIM=1 (written by benchmarks/parity/botorch_own_tests.py)."""
import os

if os.environ.get("TP_SHIM") == "1":
    import botorch.models as bm
    import botorch.models.pairwise_gp as pg

    from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP

    class PairwiseGP(PreferenceGP):
        def __init__(self, datapoints, comparisons, likelihood=None, covar_module=None, input_transform=None,
                     **kwargs):
            for key in ("jitter", "xtol", "consolidate_rtol", "consolidate_atol", "maxfev"):
                kwargs.pop(key, None)
            super().__init__(datapoints, comparisons, covar_module=covar_module, input_transform=input_transform,
                             **kwargs)

    class PairwiseLaplaceMarginalLogLikelihood(LaplaceMarginalLogLikelihood):
        def __init__(self, likelihood, model):
            super().__init__(model)

    for module in (pg, bm):
        module.PairwiseGP = PairwiseGP
        module.PairwiseLaplaceMarginalLogLikelihood = PairwiseLaplaceMarginalLogLikelihood
'''


def run(folder: Path, shim: bool) -> dict[str, str]:
    """``{test id: "passed" | "failed: first line of the message"}`` for one run."""
    xml = folder / f"report{int(shim)}.xml"
    env = dict(os.environ, TP_SHIM="1" if shim else "0", OMP_NUM_THREADS="1")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:randomly",
            "-p",
            "no:cacheprovider",
            "-W",
            "ignore",
            f"--junitxml={xml}",
            "-o",
            "junit_family=xunit2",
            *FILES,
        ],
        cwd=folder,
        env=env,
        check=False,
        capture_output=True,
    )
    out = {}
    for case in ET.parse(xml).getroot().iter("testcase"):
        bad = case.find("failure") if case.find("failure") is not None else case.find("error")
        name = f"{case.get('classname').split('.')[-1]}::{case.get('name')}"
        if case.find("skipped") is not None:
            out[name] = "skipped"
        elif bad is None:
            out[name] = "passed"
        else:
            out[name] = "failed: " + (bad.get("message") or "").splitlines()[0][:200]
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--botorch-src", required=True, type=Path, help="a checkout of github.com/pytorch/botorch")
    parser.add_argument("--out", type=Path, default=None, help="folder for botorch_own_tests.json")
    args = parser.parse_args(argv)
    import botorch

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in FILES:
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(args.botorch_src / name, folder / name)
        (folder / "conftest.py").write_text(SHIM)
        baseline, ours = run(folder, shim=False), run(folder, shim=True)
    tests = sorted(set(baseline) | set(ours))
    commit = subprocess.run(
        ["git", "-C", str(args.botorch_src), "rev-parse", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    result = {
        "botorch_installed": botorch.__version__,
        "botorch_tests_commit": commit or None,
        "tests": {t: {"PairwiseGP": baseline.get(t, "absent"), "PreferenceGP": ours.get(t, "absent")} for t in tests},
        "summary": {
            m: sum(r.get(t) == "passed" for t in tests) for m, r in (("PairwiseGP", baseline), ("PreferenceGP", ours))
        },
        "total": len(tests),
    }
    for t in tests:
        b, o = baseline.get(t, "absent"), ours.get(t, "absent")
        print(f"{t:70s} PairwiseGP {b[:40]:40s} PreferenceGP {o[:90]}")
    print(
        f"passed: PairwiseGP {result['summary']['PairwiseGP']} of {len(tests)}, "
        f"PreferenceGP {result['summary']['PreferenceGP']} of {len(tests)}"
    )
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        write_json(
            (args.out / "botorch_own_tests.json"),
            result,
            measured="harness: BoTorch's own test files with PreferenceGP put in PairwiseGP's place",
        )


if __name__ == "__main__":
    from torchpref.experiments.stamp import recording_subprocesses

    with recording_subprocesses():  # the stamp hashes the code of every process it starts too
        main()
