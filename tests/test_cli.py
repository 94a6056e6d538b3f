"""The command line: no traceback for any bad argument, --version, a fresh output folder by
default, the features CSV (separators, label column, printable labels)."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from torchpref.cli import main, output_folder
from torchpref.data.features import FeaturesError, printable, read_features_csv
from torchpref.version import __version__

REPO = Path(__file__).resolve().parents[1]


def run_main(capsys, *argv) -> tuple[int, str, str]:
    """``main(argv)``'s exit status (argparse's SystemExit included), stdout and stderr."""
    try:
        code = main(list(map(str, argv)))
    except SystemExit as exc:  # argparse's own clean errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def test_version(capsys):
    code, out, _ = run_main(capsys, "--version")
    assert code == 0 and out.strip() == f"torchpref {__version__}"


@pytest.mark.parametrize(
    "argv, match",
    [
        (["reproduce", "wave", "--trials", "0"], "--trials: must be at least 1, got 0"),
        (["reproduce", "wave", "--queries", "0"], "--queries: must be at least 1, got 0"),
        (["reproduce", "lake", "--workers", "0"], "--workers: must be at least 1, got 0"),
        (["reproduce", "wave", "--trials", "abc"], "'abc' is not a whole number"),
        (["reproduce", "wave", "--trials", "-3"], "must be at least 1, got -3"),
        (["elicit", "--queries", "0", "--features", "x.csv"], "--queries: must be at least 1"),
        (["elicit"], "give either a world"),
        (["elicit", "lake", "--features", "x.csv"], "give either a world"),
        (["elicit", "--features", "x.csv", "--session", "s", "--no-session"], "not both"),
        (["elicit", "lake", "--id", "name"], "--id names a column"),
        (["elicit", "--features", "/no/such/file.csv"], "No such file or directory"),
        (["elicit", "lake", "--out", "/proc/no/such/folder"], "--out /proc/no/such/folder: cannot write there"),
        (["elicit", "lake", "--out", __file__], "is a file, not a folder"),  # before the lake is built
    ],
)
@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch's own, when this file runs first and imports it
def test_bad_arguments_are_one_line_errors(capsys, argv, match):
    code, out, err = run_main(capsys, *argv)
    assert code == 2 and match in err and "Traceback" not in err + out
    assert len([line for line in err.splitlines() if line.startswith("torchpref")]) == 1


def test_out_is_checked_before_any_work(capsys, tmp_path, monkeypatch):
    import torchpref.experiments.wave as wave

    ran = []
    monkeypatch.setattr(wave, "run", lambda args: ran.append(args) or 0)
    a_file = tmp_path / "f"
    a_file.write_text("")
    for out, match in ((a_file, "is a file"), (a_file / "sub", "cannot write there"), ("/proc/nope", "cannot write")):
        code, _, err = run_main(capsys, "reproduce", "wave", "--out", out)
        assert code == 2 and match in err and not ran
    monkeypatch.chdir(tmp_path)
    code, out, _ = run_main(capsys, "reproduce", "wave", "--trials", "1")
    assert code == 0 and len(ran) == 1
    used = Path(ran[0].out)
    assert used.parent == Path("torchpref-results") and used.name.startswith("wave-") and used.is_dir()
    assert "one trial has no standard error" in out and "start-up included" in out
    assert output_folder(None, "wave") != used  # a fresh folder every time


def test_a_run_refused_or_failed_before_writing_leaves_no_folder(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_main(capsys, "reproduce", "suite", "--families", "nope")
    assert code == 2 and "unknown family 'nope'" in err
    code, _, err = run_main(capsys, "reproduce", "suite", "--families", "nope", "--out", "mine")
    assert code == 2 and not (tmp_path / "mine").exists()
    (tmp_path / "a_file").write_text("")
    code, _, err = run_main(capsys, "reproduce", "lake", "--cache", tmp_path / "a_file")
    assert code == 2 and "--cache" in err and "is a file" in err  # checked before any lake is built
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]
    (tmp_path / "kept").mkdir()
    code, _, _ = run_main(capsys, "reproduce", "suite", "--families", "nope", "--out", "kept")
    assert code == 2 and (tmp_path / "kept").is_dir()  # a folder that was there stays


def test_reproduce_in_a_fresh_clone_leaves_git_status_clean(tmp_path):
    git = shutil.which("git")
    if git is None or not (REPO / ".git").exists():
        pytest.skip("needs git and a git checkout")
    clone = tmp_path / "clone"
    subprocess.run([git, "clone", "-q", str(REPO), str(clone)], check=True)
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "torchpref.cli",
            "reproduce",
            "wave",
            "--trials",
            "2",
            "--queries",
            "2",
            "--workers",
            "1",
        ],
        cwd=clone,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr and "files in torchpref-results/wave-" in res.stdout
    status = subprocess.run([git, "status", "--porcelain"], cwd=clone, capture_output=True, text=True, check=True)
    assert status.stdout == ""
    assert (
        not (clone / "benchmarks" / "results" / "wave.json").exists()
        or subprocess.run([git, "diff", "--quiet"], cwd=clone).returncode == 0
    )


def test_features_separators_label_column_and_errors(tmp_path):
    p = tmp_path / "a.csv"
    for sep in (",", ";", "\t", "|"):
        p.write_text(
            sep.join(["name", "cost", "comfort"])
            + "\n"
            + sep.join(["car", "30", "8.5"])
            + "\n"
            + sep.join(["bike", "2", "4"])
            + "\n"
        )
        X, names, labels = read_features_csv(p)
        assert names == ["cost", "comfort"] and labels == ["car", "bike"] and X.tolist() == [[30, 8.5], [2, 4]]
    p.write_text("id,cost,comfort\n1,30,8\n2,2,4\n3,5,5\n")  # a numeric id column is not an objective
    X, names, labels = read_features_csv(p)
    assert names == ["cost", "comfort"] and labels == ["1", "2", "3"]
    p.write_text("cost,sku,comfort\n30,11,8\n2,12,4\n")
    X, names, labels = read_features_csv(p, id_column="sku")
    assert names == ["cost", "comfort"] and labels == ["11", "12"]
    with pytest.raises(FeaturesError, match="no column 'code' for --id"):
        read_features_csv(p, id_column="code")
    for text, match in (
        ("a;b\n1,5;2\n3;4\n", "decimal comma"),
        ("a b c\n1 2 3\n4 5 6\n", r"row 2, column 'a b c': '1 2 3' is not a finite number"),
        ("x,y\n1,2\n3,1e999\n", "'1e999' is not a finite number"),
        ("name,x\na,1\nb,2\n", None),
    ):
        p.write_text(text)
        if match is None:
            read_features_csv(p)
            continue
        with pytest.raises(FeaturesError, match=match):
            read_features_csv(p)
    p.write_bytes(b"x,y\n\xff\xfe,1\n2,3\n")
    with pytest.raises(FeaturesError, match="not UTF-8"):
        read_features_csv(p)


def test_labels_and_names_are_printable(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("name,co\x1b[2Jst\n\x1b[31mred\x1b[0m,1\nbell\x07,2\n\u202eevil,3\n")
    X, names, labels = read_features_csv(p)
    assert all(c.isprintable() for text in names + labels for c in text)
    assert labels[0] == "?[31mred?[0m" and names == ["co?[2Jst"]
    assert printable("x" * 100, 10) == "x" * 9 + "…"
