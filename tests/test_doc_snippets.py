"""Every page's Python code runs as written (issue 53, item 3): the blocks of a page run in order in
one namespace, as a reader runs them, in a fresh folder. The README's are tests/test_readme.py.

A block that cannot run here says why on the line before it, ``<!-- snippet: skip: REASON -->``;
``serve`` (which listens until interrupted) is run up to the point where it would listen; the pages
of an extra that is not installed (Ax) are skipped by name, and run by ``make test-integrations``."""

import re
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"(?:<!-- snippet: skip: (?P<why>[^>]+?) -->\n)?```python\n(?P<code>.*?)```", re.S)
NEEDS = {"ax.md": "ax", "sessions.md": "ipywidgets"}  # the import an extra brings, by page
PAGES = sorted(p for p in (ROOT / "docs").glob("*.md") if "```python" in p.read_text())


def blocks(page: Path) -> list[tuple[str, str | None]]:
    """``(code, reason to skip or None)`` for each ``python`` block of the page, in order."""
    return [(m["code"], m["why"]) for m in BLOCK.finditer(page.read_text())]


@pytest.fixture
def no_listening(monkeypatch):
    """``serve`` builds its store and checks its settings, then returns instead of listening."""
    from torchpref.frontends.serve import app

    served = []

    def serve_store(make_store, listen, threads=1, ready=None, **kw):
        served.append((make_store(), listen))

    monkeypatch.setattr(app, "serve_store", serve_store)
    return served


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_the_page_code_runs_as_written(page, tmp_path, monkeypatch, no_listening):
    if page.name in NEEDS:
        pytest.importorskip(NEEDS[page.name], reason=f"{page.name} needs {NEEDS[page.name]} (an extra)")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__snippet__"}
    dtype = torch.get_default_dtype()
    ran = 0
    try:
        for n, (code, why) in enumerate(blocks(page), 1):
            if why:
                continue
            exec(compile(code, f"{page.name}, block {n}", "exec"), namespace)
            ran += 1
    finally:
        torch.set_default_dtype(dtype)  # a page may set it, as BoTorch's tutorials do
    if not ran:
        pytest.skip(f"{page.name}: its one block needs what a test cannot have: {blocks(page)[0][1]}")


def test_every_skipped_block_says_why():
    for page in PAGES:
        for _code, why in blocks(page):
            assert why is None or len(why.strip()) > 10, f"{page.name}: a skipped block needs its reason"
    assert sum(why is not None for page in PAGES for _, why in blocks(page)) <= 2  # skipping stays rare


def test_the_botorch_page_has_a_whole_loop():
    code = "\n".join(c for c, _ in blocks(ROOT / "docs" / "botorch.md"))
    assert "optimize_acqf(" in code and "fit_gpytorch_mll(" in code and "for " in code
