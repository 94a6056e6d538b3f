"""``make results-status`` (benchmarks/results_status.py) reads KEPT_STALE.txt without crashing on a
malformed line: the line is named and keeps nothing."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torchpref

SCRIPT = Path(torchpref.__file__).resolve().parent.parent / "benchmarks" / "results_status.py"


def _module():
    spec = importlib.util.spec_from_file_location("results_status", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_malformed_kept_stale_line_is_named_not_a_crash(tmp_path):
    (tmp_path / "KEPT_STALE.txt").write_text(
        "# comment\nspeed/a.json: measured on the old machine\nno colon on this line\nwave.json:   \n: no path\n"
    )
    said = []
    kept = _module().kept_stale(tmp_path, complain=said.append)
    assert kept == {"speed/a.json": "measured on the old machine"}
    assert len(said) == 3 and "line 3" in said[0] and "line 4" in said[1] and "line 5" in said[2]


def test_status_runs_over_a_folder_with_a_malformed_line(tmp_path, capsys):
    (tmp_path / "KEPT_STALE.txt").write_text("no colon\n")
    (tmp_path / "r.json").write_text("{}")
    assert _module().main([str(tmp_path), "--fail-on-stale"]) == 1  # the unstamped file is not explained
    out = capsys.readouterr().out
    assert "line 1" in out and "unstamped" in out


def _suite_folder(folder: Path) -> None:
    """A suite run's three files, written as the suite writes them (the summary stamped)."""
    import json

    from torchpref.experiments.results import write_json
    from torchpref.experiments.suite import METRICS, effort_budgets
    from torchpref.experiments.suite_report import summarise

    def record(shift: float) -> dict:
        curve = [1.0 - 0.05 * q + shift for q in range(21)]
        return {
            **{m: curve for m in METRICS},
            "cost": [float(q) for q in range(21)],
            "kinds": ["rating"] * 20,
        }

    trials = {("waves", "fixed"): [{"A": record(0.01 * i), "B": record(0.02 * i - 0.1)} for i in range(6)]}
    summary = summarise(trials, ["A", "B"], METRICS, effort_budgets("units"), [10, 20])
    write_json(folder / "suite_trials.json", {"waves/fixed": trials["waves", "fixed"]}, stamp=False)
    write_json(folder / "suite.json", summary.pop("curves"), stamp=False)
    write_json(folder / "suite_summary.json", {**summary, "queries": 20, "settings": {"effort": "units"}})
    assert "stamp" in json.loads((folder / "suite_summary.json").read_text())


def test_a_suite_runs_companions_take_the_summarys_state(tmp_path):
    _suite_folder(tmp_path)
    mod = _module()
    for name in ("suite.json", "suite_trials.json"):
        state, reason = mod.file_status(tmp_path / name)
        assert state == "fresh" and "companion of suite_summary.json" in reason


def test_a_companion_the_summary_does_not_recompute_from_stays_unstamped(tmp_path):
    import json

    _suite_folder(tmp_path)
    curves = json.loads((tmp_path / "suite.json").read_text())
    curves["waves/fixed"]["queries"]["A"]["wrms_mean"][3] += 0.5  # a curve edited by hand
    (tmp_path / "suite.json").write_text(json.dumps(curves))
    state, reason = _module().file_status(tmp_path / "suite.json")
    assert state == "unstamped" and "suite.json's curves" in reason
