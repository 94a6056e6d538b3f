"""Ax's own preference tests, run through a pytest plugin that counts the models each test builds
(``tests/parity/ax_swap_plugin.py``): shared by ``tests/parity/test_upstream_suites.py`` and
``benchmarks/parity/ax_upstream_tests.py`` (docs/ax.md).

Three ways to run them (:data:`AX_MODES`):

* ``"documented"``: as a user of docs/ax.md does, ``import torchpref.integrations.ax`` and
  ``use_preference_gp()`` before the tests are collected; nothing of BoTorch's is rebound;
* ``"plain"``: Ax as it is, without torchpref (the ``PairwiseGP`` baseline);
* ``"harness"``: BoTorch's ``PairwiseGP`` name swapped for ``PreferenceGP`` before Ax is imported
  (a test harness, not a user's path).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

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
AX_SELECT = (
    "pairwise or preference or pref or bope or pbo or ranking or learned or utility or plbo or auxiliary "
    "or aux_exp or PE"
)
_INTEGRATION = "torchpref.integrations.ax"
AX_MODES: dict[str, dict[str, str]] = {
    "documented": {
        "TORCHPREF_SWAP_BOTORCH": "0",
        "TORCHPREF_SWAP_IMPORT": _INTEGRATION,
        "TORCHPREF_SWAP_CALL": f"{_INTEGRATION}:use_preference_gp",
    },
    "plain": {"TORCHPREF_SWAP_BOTORCH": "0"},
    "harness": {"TORCHPREF_SWAP_BOTORCH": "1", "TORCHPREF_SWAP_IMPORT": _INTEGRATION},
}


def ax_site() -> Path | None:
    """The folder holding the installed ``ax`` package (its tests ship with it), or ``None``."""
    try:
        import ax
    except ImportError:
        return None
    return Path(ax.__file__).resolve().parent.parent


def run_with_plugin(
    rootdir: Path, files: list[str], env: dict[str, str], select: str | None, report: Path, plugin_dir: Path
) -> dict[str, Any]:
    """Run ``files`` under ``rootdir`` with the counting plugin; its per-test report (outcome, error,
    ``PreferenceGP`` / ``PairwiseGP`` built)."""
    root = Path(__file__).resolve().parents[2]
    full_env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(root), str(plugin_dir)]),
        "TORCHPREF_SWAP_REPORT": str(report),
        **env,
    }
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "ax_swap_plugin"]
    cmd += ["--rootdir", str(rootdir), "-c", os.devnull, "-W", "ignore", *files]
    if select:
        cmd += ["-k", select]
    proc = subprocess.run(cmd, cwd=rootdir, env=full_env, capture_output=True, text=True)
    if not report.is_file():
        raise RuntimeError(f"no report (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return json.loads(report.read_text())


def count(results: dict[str, Any]) -> dict[str, Any]:
    """The counts docs/ax.md states: tests run, passed and failed; of those that fit a preference
    model, how many built ``PreferenceGP`` only, ``PairwiseGP`` only, or both; and the names."""
    ran = {k: v for k, v in results.items() if "outcome" in v}
    fit = {k: v for k, v in ran.items() if v["PreferenceGP"] or v["PairwiseGP"]}

    def names(pred) -> list[str]:
        return sorted(k for k, v in fit.items() if pred(v))

    return {
        "ran": len(ran),
        "passed": sum(v["outcome"] == "passed" for v in ran.values()),
        "failed": sorted(k for k, v in ran.items() if v["outcome"] == "failed"),
        "skipped": sum(v["outcome"] == "skipped" for v in ran.values()),
        "fit_a_preference_model": len(fit),
        "built_preference_gp_only": names(lambda v: v["PreferenceGP"] and not v["PairwiseGP"]),
        "built_pairwise_gp_only": names(lambda v: v["PairwiseGP"] and not v["PreferenceGP"]),
        "built_both": names(lambda v: v["PreferenceGP"] and v["PairwiseGP"]),
        "fit_and_passed": len(names(lambda v: v["outcome"] == "passed")),
    }
