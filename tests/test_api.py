"""The package's front: the lazily exported names, their type-checker imports and ``__all__`` agree."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import torchpref
from torchpref.extras import EXTRAS, MissingExtraError, message, require

INIT = Path(torchpref.__file__)
ROOT = INIT.parents[1]


def _type_checking_imports() -> dict[str, str]:
    """name -> module (relative to torchpref) of each import under ``if TYPE_CHECKING:``."""
    out = {}
    for node in ast.parse(INIT.read_text()).body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for imp in node.body:
                assert isinstance(imp, ast.ImportFrom), ast.dump(imp)
                for alias in imp.names:
                    out[alias.asname or alias.name] = imp.module.removeprefix("torchpref.")
    return out


def test_type_checking_imports_are_the_lazy_exports():
    assert _type_checking_imports() == torchpref._EXPORTS


def test_all_lists_every_export_once():
    assert sorted(torchpref.__all__) == sorted({*torchpref._EXPORTS, "__version__"})
    assert len(torchpref.__all__) == len(set(torchpref.__all__))


def test_every_export_resolves():
    missing = [name for name in torchpref._EXPORTS if getattr(torchpref, name, None) is None]
    assert not missing, missing


# --------------------------------------------------------------------------- missing extras
# A process in which matplotlib (and ipywidgets) cannot be imported, as after a plain ``pip install torchpref``.
BLOCK = """
import sys, importlib.abc
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {"matplotlib", "ipywidgets"}:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Block())
"""


def _run_without_plot(code: str, cwd) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    env.pop("TORCHPREF_DEBUG", None)
    return subprocess.run(
        [sys.executable, "-c", BLOCK + code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )


def _one_line_naming_plot(proc: subprocess.CompletedProcess, what: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 3, (proc.returncode, proc.stderr)
    assert lines == [f'{what} needs matplotlib, which is not installed: pip install "torchpref[plot]"'], proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout


@pytest.mark.parametrize(
    "argv, what",
    [
        (["reproduce", "wave", "--trials", "1"], "torchpref reproduce wave"),
        (["reproduce", "lake", "--trials", "1"], "torchpref reproduce lake"),
        (["reproduce", "suite", "--trials", "1"], "torchpref reproduce suite"),
        (["elicit", "lake", "--no-session"], "torchpref elicit lake"),
    ],
)
def test_a_command_without_the_plot_extra_says_so_before_any_work(tmp_path, argv, what):
    code = (
        f"import sys; from torchpref.cli import main; rc = main({argv!r}); print('torch' in sys.modules); sys.exit(rc)"
    )
    proc = _run_without_plot(code, tmp_path)
    _one_line_naming_plot(proc, what)
    assert proc.stdout == "False\n"  # torch not even loaded
    assert list(tmp_path.iterdir()) == []  # no output folder, no figure, no session file


def test_the_demo_without_the_plot_extra_says_so_before_any_work(tmp_path):
    proc = _run_without_plot("import sys; from torchpref.demo import main; sys.exit(main(['--out', 'demo']))", tmp_path)
    _one_line_naming_plot(proc, "python -m torchpref.demo")
    assert proc.stdout == "" and not (tmp_path / "demo").exists()


def test_a_command_that_draws_nothing_runs_without_the_plot_extra(tmp_path):
    """``elicit --features`` shows a table, no figure: it needs no extra (here it stops at the CSV)."""
    (tmp_path / "items.csv").write_text("id,a\nx,oops\n")
    code = "import sys; from torchpref.cli import main; sys.exit(main(['elicit', '--features', 'items.csv']))"
    proc = _run_without_plot(code, tmp_path)
    assert proc.returncode == 2 and "items.csv" in proc.stderr and "torchpref[" not in proc.stderr, proc.stderr


def test_the_library_raises_a_missing_extra_error_naming_the_extra(tmp_path):
    code = (
        "from torchpref.frontends.widgets import _widgets\n"
        "try:\n    _widgets()\nexcept ImportError as e:\n    print(type(e).__name__, '|', e)\n"
        "from torchpref.lake.plotting import _pyplot\n"
        "try:\n    _pyplot()\nexcept ImportError as e:\n    print(type(e).__name__, '|', e)\n"
    )
    proc = _run_without_plot(code, tmp_path)
    assert proc.stdout.splitlines() == [
        'MissingExtraError | the notebook widget needs ipywidgets, which is not installed: pip install "torchpref[widgets]"',
        'MissingExtraError | drawing the lake needs matplotlib, which is not installed: pip install "torchpref[plot]"',
    ], proc.stdout + proc.stderr


def test_require_names_the_extra_and_the_module():
    with pytest.raises(
        MissingExtraError, match=r'^x needs no_such_mod_7, which is not installed: pip install "torchpref\[plot\]"$'
    ):
        require("no_such_mod_7", "x", extra="plot")
    with pytest.raises(ValueError, match="no_such_mod_7"):
        message("no_such_mod_7", "x")  # no extra installs it: a bug in the caller, said as such
    assert require("json", "x").dumps([1]) == "[1]"


def test_every_extra_named_exists_in_pyproject():
    text = (ROOT / "pyproject.toml").read_text()
    extras = set(re.findall(r"^([a-z]+) = \[", text.split("[project.optional-dependencies]")[1].split("\n[")[0], re.M))
    assert set(EXTRAS.values()) <= extras, extras
    for module, extra in EXTRAS.items():
        line = next(row for row in text.splitlines() if row.startswith(f"{extra} = ["))
        assert f'"{module}' in line, line


# --------------------------------------------------------------------------- annotations
def _unannotated_public_functions() -> list[str]:
    """Public functions and public methods (and ``__init__``) of public classes, in public modules,
    with a parameter or the return (not of ``__init__`` or a property setter) unannotated."""
    out = []
    for f in sorted((ROOT / "torchpref").rglob("*.py")):
        if any(part.startswith("_") and part != "__init__.py" for part in f.relative_to(ROOT).parts):
            continue

        def check(fn: ast.FunctionDef | ast.AsyncFunctionDef, qualname: str) -> None:
            args = fn.args.posonlyargs + fn.args.args + fn.args.kwonlyargs
            missing = [a.arg for a in args if a.annotation is None and a.arg not in ("self", "cls")]
            if fn.returns is None and fn.name != "__init__":
                missing.append("return")
            if missing:
                out.append(f"{f.relative_to(ROOT)}:{fn.lineno} {qualname}: {', '.join(missing)}")

        for node in ast.parse(f.read_text()).body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
                check(node, node.name)
            elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                for m in node.body:
                    if isinstance(m, (ast.FunctionDef, ast.AsyncFunctionDef)) and (
                        not m.name.startswith("_") or m.name == "__init__"
                    ):
                        check(m, f"{node.name}.{m.name}")
    return out


def test_the_public_api_is_fully_annotated():
    missing = _unannotated_public_functions()
    assert not missing, "unannotated parameters or returns:\n" + "\n".join(missing)


# --------------------------------------------------------------------------- the front door
README_TEXT = (ROOT / "README.md").read_text()


def test_readme_is_a_front_door():
    assert len(README_TEXT.splitlines()) <= 150
    assert "make demo" in README_TEXT and "make test" in README_TEXT
    assert 'pip install ".[plot]"' in README_TEXT and "(docs/index.md)" in README_TEXT


def test_every_result_path_in_the_readme_exists():
    """Every figure and every ``benchmarks/results/...`` file the README names is there (globs too)."""
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", README_TEXT)
    named = re.findall(r"`(benchmarks/results/[^`]+)`", README_TEXT)
    assert images and named
    for path in images:
        assert path.startswith("benchmarks/results/") and (ROOT / path).is_file(), path
    for text in named:
        first, *rest = [p.strip() for p in text.split(",")]
        folder = Path(first).parent
        for part in [first, *(str(folder / r) for r in rest)]:
            assert list(ROOT.glob(part.rstrip("/"))), part


def test_every_local_link_in_the_readme_and_docs_resolves():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    broken = []
    for page in pages:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" not in target and not (page.parent / target).exists():
                broken.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not broken, "\n".join(broken)


def test_the_docs_site_picks_up_every_page():
    index = (ROOT / "docs" / "index.md").read_text()
    assert ":glob:" in index and "\n*\n" in index and "notebooks/*" in index
    assert (ROOT / "docs" / "notebooks").resolve() == (ROOT / "notebooks").resolve()


def test_the_package_has_a_license_file():
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert 'license-files = ["LICENSE"]' in (ROOT / "pyproject.toml").read_text()


def test_ci_runs_the_readme_test_command():
    run = (ROOT / ".ci" / "run").read_text()
    assert run.rstrip().endswith("make test") and "CI=true" in run
    make = (ROOT / "Makefile").read_text()
    assert "ifeq ($(CI),true)" in make and "lint types docs wheel-check" in make
