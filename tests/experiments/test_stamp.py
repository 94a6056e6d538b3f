"""Stamped results (issue 36): a stamp names its sources by hash, and a result goes stale when one changes."""

import json
from pathlib import Path

import pytest

from torchpref.experiments.results import write_json
from torchpref.experiments.stamp import ROOT, make_stamp, status


def test_a_stamp_records_what_was_measured_and_on_what(tmp_path):
    src = tmp_path / "bench.py"
    src.write_text("print(1)\n")
    s = make_stamp("harness: a test", sources=[src], root=tmp_path, note="x")
    assert s["sources"] == {"bench.py": pytest.approx(s["sources"]["bench.py"])} and len(s["sources"]["bench.py"]) == 64
    assert s["path"] == "harness: a test" and s["note"] == "x"
    assert set(s["versions"]) >= {"python", "torch", "gpytorch", "botorch", "numpy", "torchpref"}
    assert len(s["load_avg"]) == 3 and s["cpu_count"] >= 1 and s["wall_s"] > 0 and s["cpu_s"] > 0


def test_a_result_goes_stale_when_a_source_changes_or_goes(tmp_path):
    src = tmp_path / "bench.py"
    src.write_text("print(1)\n")
    out = tmp_path / "r.json"
    out.write_text(json.dumps({"value": 1, "stamp": make_stamp(sources=[src], root=tmp_path)}))
    assert status(out, tmp_path)[0] == "fresh"
    src.write_text("print(2)\n")
    state, reason = status(out, tmp_path)
    assert state == "stale" and "bench.py" in reason
    src.unlink()
    assert status(out, tmp_path) == ("stale", "changed since the stamp: bench.py (gone)")


def test_unstamped_and_unreadable_files_say_so(tmp_path):
    (tmp_path / "a.json").write_text('{"value": 1}')
    (tmp_path / "b.json").write_text("not json")
    assert status(tmp_path / "a.json", tmp_path) == ("unstamped", "no stamp")
    assert status(tmp_path / "b.json", tmp_path)[0] == "unstamped"


def test_the_measured_path_is_the_user_path_or_a_named_harness():
    with pytest.raises(ValueError, match="harness"):
        make_stamp("the plugin")


def test_write_json_stamps_a_dictionary_with_the_loaded_package_modules(tmp_path):
    path = write_json(tmp_path / "r.json", {"value": 2}, measured="harness: unit test")
    data = json.loads(path.read_text())
    assert data["value"] == 2 and data["stamp"]["path"] == "harness: unit test"
    assert "torchpref/experiments/stamp.py" in data["stamp"]["sources"]  # the code that ran
    assert status(path, ROOT)[0] == "fresh"
    assert json.loads(write_json(tmp_path / "l.json", [1, 2]).read_text()) == [1, 2]  # lists as they are


def test_code_digest_ignores_docstrings_comments_and_layout(tmp_path):
    from torchpref.experiments.stamp import code_digest

    a, b, c = tmp_path / "a.py", tmp_path / "b.py", tmp_path / "c.py"
    a.write_text('"""Module."""\n\ndef f(x):\n    """Twice x."""\n    return 2 * x  # double\n')
    b.write_text('"""Another text."""\ndef f(x):\n    # a comment\n    return 2*x\n')
    c.write_text('def f(x):\n    return 3 * x\n')
    assert code_digest(a) == code_digest(b) != code_digest(c)
    data = tmp_path / "d.csv"
    data.write_text("1,2\n")
    before = code_digest(data)
    data.write_text("1,3\n")
    assert code_digest(data) != before


def test_a_stamp_is_stale_only_when_code_changed(tmp_path):
    import json

    from torchpref.experiments.stamp import make_stamp, status

    src = tmp_path / "m.py"
    src.write_text('def f():\n    """Doc."""\n    return 1\n')
    out = tmp_path / "r.json"
    out.write_text(json.dumps({"x": 1, "stamp": make_stamp(sources=[src], root=tmp_path)}))
    assert status(out, tmp_path)[0] == "fresh"
    src.write_text('def f():\n    """Another doc."""\n    # why\n    return 1\n')
    assert status(out, tmp_path)[0] == "fresh"
    src.write_text("def f():\n    return 2\n")
    assert status(out, tmp_path) == ("stale", "changed since the stamp: m.py")


def test_a_stamp_hashes_what_its_subprocesses_ran(tmp_path):
    import subprocess
    import sys

    from torchpref.experiments.stamp import make_stamp, recording_subprocesses

    with recording_subprocesses():
        subprocess.run([sys.executable, "-c", "import torchpref.study.folder"], check=True)
        stamp = make_stamp()
    assert "torchpref/study/folder.py" in stamp["sources"] and "torchpref/study/folder.py" in stamp["code"]
    assert "torchpref/study/folder.py" not in make_stamp()["sources"] or "torchpref.study.folder" in sys.modules


def test_every_benchmark_that_starts_processes_stamps_their_code():
    """A measurement that starts processes (a server, workers, a pytest run) hashes what they ran:
    its script runs under recording_subprocesses() (issue 53)."""
    import re

    root = Path(__file__).resolve().parents[2]
    starts = re.compile(r"subprocess\.(run|Popen)|ProcessPoolExecutor|multiprocessing|testing\.serve import")
    missing = [
        p.relative_to(root).as_posix()
        for p in sorted((root / "benchmarks").rglob("*.py"))
        if starts.search(p.read_text())
        and "recording_subprocesses" not in p.read_text()
        and "__main__" in p.read_text()
    ]
    assert not missing, f"start processes without recording_subprocesses(): {missing}"
