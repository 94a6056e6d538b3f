"""Ax's and BoFire's own tests of their preference paths, run unmodified, counting the models each
test builds (the plugin ``tests/parity/ax_swap_plugin.py``; docs/ax.md).

* Ax (ax-platform 1.3.1 ships its tests): the tests of ``AX_FILES`` whose names select the
  preference path (``AX_SELECT``, both in :mod:`torchpref.testing.upstream`), run as a user of
  docs/ax.md runs Ax: ``import torchpref.integrations.ax`` and ``use_preference_gp()`` before the
  tests, nothing of BoTorch's rebound. Every test that fits a preference model by Ax's defaults
  must build ``PreferenceGP``; ``PairwiseGP`` is built only where a test names it itself
  (:data:`AX_NAMES_PAIRWISE`).
* BoFire 0.5.0 (its tests are in its sdist: ``make upstream-tests`` unpacks them into
  ``.cache/upstream/``, or set ``TORCHPREF_BOFIRE_TESTS``): ``tests/bofire/surrogates/test_pairwise_gp.py``
  with its names ``PairwiseGP``, ``PairwiseGPSurrogate`` and ``PairwiseProbitLikelihood`` bound to
  ``PreferenceGP``, :class:`torchpref.integrations.bofire.PreferenceGPSurrogate` and the model's
  likelihood class (a harness: BoFire has no registry for its surrogate's model).

Each is skipped, with the reason, where the library (or BoFire's test file) is absent. They take
minutes: ``make test-integrations`` runs them. ``benchmarks/parity/ax_upstream_tests.py`` writes
the counts, with Ax's ``PairwiseGP`` baseline, to ``benchmarks/results/ax/upstream_tests.json``.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

from torchpref.testing.upstream import AX_FILES, AX_MODES, AX_SELECT, ax_site, count, run_with_plugin

ROOT = Path(__file__).resolve().parents[2]
#: Ax tests that fail through the documented path, and why.
AX_KNOWN = {
    "test_fitting_auxiliary_experiment_dataset": "asserts isinstance(model, PairwiseGP) of the preference model "
    "Ax builds by default, which use_preference_gp() makes a PreferenceGP",
    # they fit no preference model; an analysis card errors in some runs, without torchpref too
    **{
        name: "an analysis card errors intermittently, with PairwiseGP too"
        for name in ("test_offline_experiments", "test_online_experiments")
    },
}
#: Ax tests that build BoTorch's PairwiseGP themselves (not by an Ax default), and how.
AX_NAMES_PAIRWISE = {
    "test_eubo_construction_pbo_and_bope_modes": "constructs PairwiseGP(...) directly",
    "test_fitting_auxiliary_experiment_dataset": "one of its specs names ModelConfig(botorch_model_class=PairwiseGP)",
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


def _run(tmp_path: Path, rootdir: Path, files: list[str], env: dict[str, str], select: str | None) -> dict:
    return run_with_plugin(rootdir, files, env, select, tmp_path / "report.json", Path(__file__).resolve().parent)


def _failures(results: dict, known: dict[str, str]) -> dict[str, str]:
    """The failed tests not in ``known`` nor failing for the environment (:data:`ENVIRONMENT`)."""
    failed = {k.split("::")[-1]: v.get("error", "")[-800:] for k, v in results.items() if v.get("outcome") == "failed"}
    return {k: e for k, e in failed.items() if k not in known and not any(p in e for p in ENVIRONMENT)}


def test_ax_preference_tests_through_the_documented_path(tmp_path):
    site = ax_site()
    if site is None:
        pytest.skip("Ax is not installed (pip install 'torchpref[ax]'): Ax's own tests were not run")
    files = [f for f in AX_FILES if (site / f).is_file()]
    if not files:
        pytest.skip(f"this Ax ships none of its test files {AX_FILES[:2]}...")
    results = _run(tmp_path, site, files, AX_MODES["documented"], AX_SELECT)
    unexpected = _failures(results, AX_KNOWN)
    assert not unexpected, "failed through the documented path:\n" + "\n\n".join(
        f"{k}: {e}" for k, e in unexpected.items()
    )
    c = count(results)
    pairwise = [k.split("::")[-1] for k in c["built_pairwise_gp_only"] + c["built_both"]]
    assert set(pairwise) <= set(AX_NAMES_PAIRWISE), f"built BoTorch's PairwiseGP by an Ax default: {pairwise}"
    built = len(c["built_preference_gp_only"]) + len(c["built_both"])
    print(
        f"{c['ran']} ran, {c['fit_a_preference_model']} fit a preference model, {built} built PreferenceGP; failed {c['failed']}"
    )
    assert c["ran"] >= 50 and built >= 10  # Ax 1.3.1: 55 selected, 11 fit a preference model (docs/ax.md)


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
    results = _run(tmp_path, root, [BOFIRE_FILE], {**env, "TORCHPREF_SWAP_NAMES": BOFIRE_NAMES}, None)
    assert not _failures(results, BOFIRE_KNOWN)
    c = count(results)
    assert not c["built_pairwise_gp_only"] and not c["built_both"], "BoFire's tests still built BoTorch's PairwiseGP"
    failed = [k for k, v in results.items() if v.get("outcome") == "failed"]
    assert all("likelihood='logit' is not supported" in results[k]["error"] for k in failed)
    assert c["ran"] >= 13 and len(c["built_preference_gp_only"]) >= 6
