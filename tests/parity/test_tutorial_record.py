"""The BoTorch tutorial scripts resume a long run from their record only on the code that measured its
rows: a results file stamped with today's code never summarises rows that older code measured."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _common():
    spec = importlib.util.spec_from_file_location(
        "tutorials_common", ROOT / "benchmarks/parity/botorch_tutorials_common.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_record_resumes_its_own_codes_rows_only(tmp_path, monkeypatch):
    common = _common()
    path = tmp_path / "run.jsonl"
    first = common.Record(path, {"batches": 3})
    first.add({"seed": 0, "model": "PreferenceGP", "regret": 0.1})
    assert common.Record(path, {"batches": 3}).done(0, "PreferenceGP")  # same code, same settings
    assert not common.Record(path, {"batches": 4}).done(0, "PreferenceGP")  # other settings
    monkeypatch.setattr(common, "code_fingerprint", lambda: "other code")
    later = common.Record(path, {"batches": 3})
    assert not later.done(0, "PreferenceGP") and later.rows == []
    assert len(path.read_text().splitlines()) == 1  # the older row stays in the file
