"""Published figures read from their results files (issue 36): the README's figures between markers
equal the files, every figure a page names exists and resolves, and every stale figure is marked."""

import importlib.util
import os
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("docs_figures", ROOT / "docs" / "figures.py")
figures = importlib.util.module_from_spec(_spec)
sys.modules["docs_figures"] = figures  # dataclasses look their module up
_spec.loader.exec_module(figures)
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


@pytest.mark.parametrize("name", sorted(figures.FIGURES))
def test_every_figure_resolves_in_its_file(name):
    text = figures.FIGURES[name].text()
    assert text and "nan" not in text.lower()


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_the_figures_a_page_quotes_equal_their_files(page):
    text = page.read_text()
    wrong = [
        f"{m['name']}: the page says {m['text']!r}, the file {figures.FIGURES[m['name']].text()!r} (make pages)"
        for m in figures.MARKER.finditer(text)
        if m["name"] in figures.FIGURES and figures.without_note(m["text"]) != figures.FIGURES[m["name"]].text()
    ]
    if os.environ.get("CI") == "true":  # under CI the stale notes must be on the page too
        wrong += [
            f"{m['name']}: the page says {m['text']!r}, should be {figures.page_text(m['name'])!r} (make pages)"
            for m in figures.MARKER.finditer(text)
            if m["name"] in figures.FIGURES and m["text"] != figures.page_text(m["name"])
        ]
    unknown = [m["name"] for m in [*figures.MARKER.finditer(text), *figures.SUBSTITUTION.finditer(text)]]
    unknown = [n for n in unknown if n not in figures.FIGURES]
    assert not wrong and not unknown, "\n".join(wrong + [f"no such figure: {n}" for n in unknown])


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_the_tables_a_page_quotes_equal_their_files(page):
    found = list(figures.TABLE_MARKER.finditer(page.read_text()))
    unknown = [m["name"] for m in found if m["name"] not in figures.TABLES]
    strict = os.environ.get("CI") == "true"  # under CI the stale notes must be on the page too
    wrong = [
        f"table {m['name']} differs from its file {figures.TABLES[m['name']].file} (make pages)"
        for m in found
        if m["name"] in figures.TABLES
        and (
            m["text"] != figures.table_text(m["name"])
            if strict
            else figures.without_note(m["text"]) != figures.TABLES[m["name"]].text()
        )
    ]
    assert not wrong and not unknown, "\n".join(wrong + [f"no such table: {n}" for n in unknown])


def test_a_table_is_written_from_its_file(tmp_path, monkeypatch):
    results = tmp_path / "benchmarks" / "results"
    results.mkdir(parents=True)
    (results / "t.csv").write_text("n,task,ratio\n20,fit,1.234\n50,fit,2.5\n20,mode,9\n")
    monkeypatch.setattr(figures, "ROOT", tmp_path)
    monkeypatch.setitem(
        figures.TABLES,
        "t_fit",
        figures.Table("t.csv", (("n", "n", "{}"), ("ratio", "ratio", "{:.1f}×")), (("task", "fit"),)),
    )
    page = tmp_path / "p.md"
    page.write_text("before\n<!-- table:t_fit -->\nold\n<!-- /table -->\nafter\n")
    figures.write_pages([page])
    assert (
        page.read_text()
        == "before\n<!-- table:t_fit -->\n| n | ratio |\n|---|---|\n| 20 | 1.2× |\n| 50 | 2.5× |\n\n"
        + figures.TABLE_UNSTAMPED_NOTE  # no stamped JSON beside the CSV
        + "\n<!-- /table -->\nafter\n"
    )


def test_a_figure_that_disagrees_with_its_file_is_caught(tmp_path):
    name = "wave_wrms_info"
    page = f"WRMS <!-- fig:{name} -->0.9999<!-- /fig -->"
    found = [(m["name"], m["text"]) for m in figures.MARKER.finditer(page)]
    assert found == [(name, "0.9999")] and figures.FIGURES[name].text() != "0.9999"


def test_the_readme_quotes_its_headline_figures_from_files():
    names = {m["name"] for m in figures.MARKER.finditer((ROOT / "README.md").read_text())}
    assert len(names) >= 15, sorted(names)


def test_a_stale_or_unstamped_file_marks_its_figures(monkeypatch):
    stale, unstamped = figures.FIGURES["fuzz_problems"].file, figures.FIGURES["wave_wrms_info"].file
    states = {stale: "stale", unstamped: "unstamped"}
    monkeypatch.setattr(figures, "file_state", lambda file: states.get(file, "fresh"))
    subs = figures.substitutions()
    assert subs["fuzz_problems"].endswith(figures.STALE_NOTE)
    assert subs["wave_wrms_info"].endswith(figures.UNSTAMPED_NOTE)
    assert not any(subs["api_checks_passed"].endswith(n) for n in (figures.STALE_NOTE, figures.UNSTAMPED_NOTE))
    assert re.fullmatch(r"[\d,]+", figures.without_note(subs["fuzz_problems"]))


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_page_shows_a_placeholder(page):
    """Figures are written into the pages (make pages), so a page read as a file shows numbers."""
    assert not figures.SUBSTITUTION.search(page.read_text()), (
        f"{page.name} has a {{{{ name }}}} placeholder: make pages"
    )


@pytest.mark.skipif(
    os.environ.get("CI") != "true", reason="CI refuses a stale headline; a working copy may be mid-change"
)
def test_every_stale_readme_figure_has_a_reason():
    """A README figure whose file is stale (its measured code changed) needs a reason in
    benchmarks/results/KEPT_STALE.txt, or a re-measurement (make results)."""
    spec = importlib.util.spec_from_file_location("results_status", ROOT / "benchmarks" / "results_status.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    kept = mod.kept_stale(ROOT / "benchmarks" / "results", complain=lambda line: None)
    names = {m["name"] for m in figures.MARKER.finditer((ROOT / "README.md").read_text())}
    unexplained = sorted(
        {figures.FIGURES[n].file for n in names if figures.is_stale(n)}
        - {k.replace(".json", ".csv") for k in kept}
        - set(kept)
    )
    assert not unexplained, f"stale README figures without a reason in KEPT_STALE.txt: {unexplained}"


def test_a_key_whose_name_holds_dots_is_read_whole():
    data = {"arms": {"mixed, sigma_R = 0.1": {"fit": [1.5, 2.5]}, "mixed": {"sigma_R = 1": 3}}}
    assert figures.dotted(data, "arms.mixed, sigma_R = 0.1.fit.1") == 2.5
    assert figures.dotted(data, "arms.mixed.sigma_R = 1") == 3
    with pytest.raises(KeyError):
        figures.dotted(data, "arms.mixed, sigma_R = 0.2.fit")


def test_each_figure_has_one_name():
    """Two names for the same file, key and format would be two owners of one figure."""
    seen: dict[tuple, str] = {}
    twins = []
    for name, fig in figures.FIGURES.items():
        spec = (type(fig).__name__, fig.file, fig.key, fig.fmt, getattr(fig, "pick", None))
        if spec in seen:
            twins.append(f"{seen[spec]} and {name}")
        seen.setdefault(spec, name)
    assert not twins, "the same figure under two names: " + "; ".join(twins)
