"""What the docs name exists (issue 36): every repository path (``torchpref/...``, ``benchmarks/...``,
``tests/...``, ``docs/...``, ``notebooks/...``) and every dotted ``torchpref.X`` name in README.md and
docs/*.md, except on docs/architecture.md's maps of old paths; and the extras lists equal pyproject's."""

import importlib
import re
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PATH = re.compile(r"(?<![\w./-])((?:torchpref|benchmarks|tests|docs|notebooks)/[\w./*-]*[\w*])")
NAME = re.compile(r"(?<![\w.])(torchpref(?:\.\w+)+)")
#: Paths written as patterns or as outputs that a run creates, not files in the repository.
MADE_BY_A_RUN = ("torchpref-results/", "docs/_build", "docs/_generated", "benchmarks/results/")
#: Paths in other projects' repositories, named as theirs (BoFire's own test file).
FOREIGN = {"tests/bofire/surrogates/test_pairwise_gp.py"}
#: Placeholders: ``torchpref.X`` stands for any public name.
PLACEHOLDERS = {"torchpref.X"}


def _text(page: Path) -> str:
    text = page.read_text()
    if page.name == "architecture.md":  # its tables map old paths to new ones: the old ones are gone
        text = re.split(r"\n## Where each (?:module|test)", text)[0]
    return text


def _exists(ref: str) -> bool:
    if ref in FOREIGN or any(ref.startswith(p) for p in MADE_BY_A_RUN):
        return True
    return bool(list(ROOT.glob(ref))) if "*" in ref else (ROOT / ref).exists()


def _resolves(dotted: str) -> bool:
    if dotted in PLACEHOLDERS:
        return True
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:  # an optional extra (Ax, BoFire) not installed: the module's file exists
            if (ROOT / Path(*parts[:i])).with_suffix(".py").is_file():
                return True
            continue
        try:
            for attr in parts[i:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return True
    return False


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_path_a_page_names_exists(page):
    missing = sorted({m for m in PATH.findall(_text(page)) if not _exists(m.rstrip("."))})
    assert not missing, f"{page.name} names paths that do not exist: {missing}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_torchpref_name_a_page_names_resolves(page):
    missing = sorted({m for m in NAME.findall(_text(page)) if not _resolves(m)})
    assert not missing, f"{page.name} names what torchpref does not have: {missing}"


def test_the_extras_lists_equal_pyprojects():
    extras = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])
    for page in (ROOT / "README.md", ROOT / "docs" / "install.md"):
        text = page.read_text()
        missing = sorted(e for e in extras if f"`{e}`" not in text)
        assert not missing, f"{page.name} does not list the extras {missing}"
