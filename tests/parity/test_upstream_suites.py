"""Ax's and BoFire's own tests of their preference paths, run unmodified with BoTorch's
``PairwiseGP`` swapped for ``PreferenceGP`` (``tests/parity/ax_swap_plugin.py``), counting the models
each test builds: every test that fits a preference model must build ``PreferenceGP`` and none
may build ``PairwiseGP`` (docs/ax.md).

* Ax (ax-platform 1.3.1 ships its tests): the tests of :data:`AX_FILES` whose names select the
  preference path (:data:`AX_SELECT`), with ``PairwiseGP`` / ``PairwiseLaplaceMarginalLogLikelihood``
  swapped in ``botorch.models`` before Ax is imported, and ``import torchpref.integrations.ax``.
* BoFire 0.5.0 (its tests are in its sdist: ``make upstream-tests`` unpacks them into
  ``.cache/upstream/``, or set ``TORCHPREF_BOFIRE_TESTS``): ``tests/bofire/surrogates/test_pairwise_gp.py``
  with its names ``PairwiseGP``, ``PairwiseGPSurrogate`` and ``PairwiseProbitLikelihood`` bound to
  ``PreferenceGP``, :class:`torchpref.integrations.bofire.PreferenceGPSurrogate` and the model's
  likelihood class.

Each is skipped, with the reason, where the library (or BoFire's test file) is absent. They take
minutes: ``make test-integrations`` runs them.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
AX_FILES = [
    "ax/utils/preference/tests/test_preference_utils.py",
    "ax/adapter/tests/test_torch_adapter.py",
    "ax/adapter/tests/test_cross_validation.py",
    "ax/service/tests/test_best_point.py",
    "ax/analysis/plotly/tests/test_utility_ranking.py",
    "ax/analysis/plotly/tests/test_utility_progression.py",
    "ax/analysis/tests/test_results.py",
    "ax/analysis/tests/test_diagnostics.py",
    "ax/generators/torch/tests/test_surrogate.py",
    "ax/generators/torch/tests/test_utils.py",
    "ax/adapter/tests/test_adapter_utils.py",
]
AX_SELECT = "pairwise or preference or pref or bope or pbo or ranking or learned or utility or plbo or auxiliary or aux_exp or PE"
#: Ax tests that fail with PreferenceGP, and why: they fail alike with BoTorch's PairwiseGP here.
AX_KNOWN = {
    name: "an analysis card errors with PairwiseGP too (Ax 1.3.1, Python 3.11, no JAX)"
    for name in ("test_offline_experiments", "test_online_experiments")
}
#: Failures of the environment, not of the model, by a phrase of their error: they fail alike with
#: PairwiseGP (docs/ax.md).
ENVIRONMENT = {
    "require JAX": "BoTorch's fully Bayesian models need botorch[fully_bayesian] (JAX), not installed",
    "has no attribute 'monitoring'": "Ax's per-test time limit was exceeded (a loaded machine) and its "
    "handler needs Python 3.12's sys.monitoring",
}

BOFIRE_FILE = "tests/bofire/surrogates/test_pairwise_gp.py"
BOFIRE_NAMES = (
    "PairwiseGP=torchpref:PreferenceGP,"
    "PairwiseGPSurrogate=torchpref.integrations.bofire:PreferenceGPSurrogate,"
    "PairwiseProbitLikelihood=torchpref.models.defaults:PreferenceLikelihood"
)
#: BoFire tests that fail with PreferenceGP, and why.
BOFIRE_KNOWN = {
    "test_pairwise_gp_likelihood[logit-PairwiseLogitLikelihood]": "likelihood='logit' is refused by name "
    "(the logistic link is not implemented)",
}


def _run_swapped(tmp_path: Path, rootdir: Path, files: list[str], env: dict[str, str], select: str | None) -> dict:
    report = tmp_path / "report.json"
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), str(Path(__file__).resolve().parent)]),
        "TORCHPREF_SWAP_REPORT": str(report),
        **env,
    }
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "ax_swap_plugin"]
    cmd += ["--rootdir", str(rootdir), "-c", os.devnull, "-W", "ignore", *files]
    if select:
        cmd += ["-k", select]
    proc = subprocess.run(cmd, cwd=rootdir, env=env, capture_output=True, text=True)
    assert report.is_file(), f"no report (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return json.loads(report.read_text())


def _check(results: dict, known: dict[str, str]) -> tuple[int, int]:
    """(tests run, tests that built a PreferenceGP); fails on an unexpected failure or any PairwiseGP."""
    ran = {k: v for k, v in results.items() if "outcome" in v}
    failed = {k.split("::")[-1]: v.get("error", "")[-800:] for k, v in ran.items() if v["outcome"] == "failed"}
    env = {k for k, e in failed.items() if any(phrase in e for phrase in ENVIRONMENT)}
    unexpected = {k: e for k, e in failed.items() if k not in known and k not in env}
    assert not unexpected, "failed with PreferenceGP:\n" + "\n\n".join(f"{k}: {e}" for k, e in unexpected.items())
    pairwise = [k for k, v in results.items() if v["PairwiseGP"]]
    assert not pairwise, f"these tests still built BoTorch's PairwiseGP: {pairwise}"
    built = sum(1 for v in ran.values() if v["PreferenceGP"])
    print(f"{len(ran)} tests ran, {built} built PreferenceGP, 0 built PairwiseGP, failed as known: {sorted(failed)}")
    return len(ran), built


def test_ax_preference_tests_with_preference_gp(tmp_path):
    if importlib.util.find_spec("ax") is None:
        pytest.skip("Ax is not installed (pip install 'torchpref[ax]'): Ax's own tests were not run")
    import ax

    site = Path(ax.__file__).resolve().parent.parent
    files = [f for f in AX_FILES if (site / f).is_file()]
    if not files:
        pytest.skip(f"this Ax ({ax.__version__}) ships none of its test files {AX_FILES[:2]}...")
    results = _run_swapped(tmp_path, site, files, {"TORCHPREF_SWAP_IMPORT": "torchpref.integrations.ax"}, AX_SELECT)
    ran, built = _check(results, AX_KNOWN)
    assert ran >= 50 and built >= 10  # Ax 1.3.1: 55 selected, 11 fit a preference model (docs/ax.md)


def _bofire_tests() -> Path | None:
    given = os.environ.get("TORCHPREF_BOFIRE_TESTS")
    candidates = [Path(given)] if given else sorted((ROOT / ".cache" / "upstream").glob("bofire-*"))
    for c in candidates:
        if (c / BOFIRE_FILE).is_file():
            return c
    return None


def test_bofire_pairwise_surrogate_tests_with_preference_gp(tmp_path):
    if importlib.util.find_spec("bofire") is None:
        pytest.skip("BoFire is not installed (pip install 'torchpref[bofire]'): BoFire's own tests were not run")
    root = _bofire_tests()
    if root is None:
        pytest.skip(
            f"BoFire's test file {BOFIRE_FILE} was not found (make upstream-tests unpacks BoFire's sdist into "
            ".cache/upstream/, or set TORCHPREF_BOFIRE_TESTS)"
        )
    env = {"TORCHPREF_SWAP_BOTORCH": "0", "TORCHPREF_SWAP_IMPORT": "torchpref.integrations.bofire"}
    results = _run_swapped(tmp_path, root, [BOFIRE_FILE], {**env, "TORCHPREF_SWAP_NAMES": BOFIRE_NAMES}, None)
    ran, built = _check(results, BOFIRE_KNOWN)
    failed = [k for k, v in results.items() if v.get("outcome") == "failed"]
    assert all("likelihood='logit' is not supported" in results[k]["error"] for k in failed)
    assert ran >= 13 and built >= 6
