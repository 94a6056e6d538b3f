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
