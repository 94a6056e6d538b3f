"""The long robustness runs (issue #26): the property-based suite under its ``long`` hypothesis
profile (300 examples a property instead of 12), and 100 hostile-start fits
(``hostile_fits.py``), each written to ``benchmarks/results/``. Run with the benchmarks
(``pytest benchmarks/robustness/test_robustness_long.py --benchmark-only``); each is one timed round."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from torchpref.testing import problems as hf

ROOT = Path(__file__).resolve().parents[2]
RESULTS = Path(__file__).resolve().parents[1] / "results"


def test_properties_long_profile(benchmark):
    env = dict(os.environ, TORCHPREF_HYPOTHESIS_PROFILE="long", PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(ROOT / "tests" / "test_properties.py")]

    def run():
        return subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True)

    result = benchmark.pedantic(run, rounds=1, iterations=1)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "properties_long.txt").write_text(result.stdout[-4000:])
    assert result.returncode == 0, result.stdout[-4000:]


def test_one_hundred_hostile_start_fits(benchmark):
    out = RESULTS / "hostile_fits.json"
    benchmark.pedantic(hf.main, args=(["--fits", "100", "--out", str(out)],), rounds=1, iterations=1)
    summary = json.loads(out.read_text())
    assert summary["fits"] == 100 and summary["other"] == 0, summary["counts"]
