"""PreferenceWidget without a browser: pictures from the render hook, clicks through session.tell."""

from __future__ import annotations

import json

import pytest
import torch

widgets = pytest.importorskip("ipywidgets")
pytest.importorskip("matplotlib")

from torchpref.frontends.widgets import PreferenceWidget, as_picture, table_picture  # noqa: E402
from torchpref.selection.strategies import RandomRankings, RandomRatings  # noqa: E402
from torchpref.sessions.session import PreferenceSession  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n" + b"\0" * 16


@pytest.fixture
def pool(generator):
    return torch.rand(12, 2, generator=generator, dtype=torch.float64)


def _pictures(w: PreferenceWidget) -> list:
    return [card.children[0] for card in w.options.children]


def test_ranking_click_is_recorded_in_the_session_file(pool, tmp_path):
    f = tmp_path / "s.jsonl"
    s = PreferenceSession(pool, session_file=f, selector=RandomRankings(m=3), names=["cost", "speed"])
    w = PreferenceWidget(s)
    q = w.query
    assert [b.description for b in w.buttons] == ["A is best", "B is best", "C is best", "no preference"]
    # the fallback picture: a table of the option's values, named
    first = _pictures(w)[0].value
    assert "cost" in first and f"{float(q.items[0, 0]):.4g}" in first and f"item #{q.indices[0]}" in first
    w.buttons[1].click()
    rec = [json.loads(line) for line in f.read_text().splitlines()][-1]
    assert rec["kind"] == "choice" and rec["answer"] == 1 and rec["query"]["pool_indices"] == list(q.indices)
    assert s.history[-1].answer == 1 and "1 answer in force" in w.status.value
    assert w.query is s.ask() and w.query is not q  # the next query is shown
    w.buttons[-1].click()  # no preference
    assert s.history[-1].kind == "no_preference"


def test_rating_buttons_are_likert_levels_and_undo(pool):
    s = PreferenceSession(pool, selector=RandomRatings(), num_levels=4)
    w = PreferenceWidget(s, noun="design")
    assert [b.answer for b in w.buttons] == [1, 2, 3, 4]
    assert "rate this design from 1 (bad) to 4" in w.prompt.value
    assert w.undo_button.disabled
    item = w.query.item
    w.buttons[2].click()
    assert s.history[-1].kind == "rating" and s.history[-1].answer == 3
    assert torch.equal(s.history[-1].items[0], item)
    w.undo_button.click()
    assert s.step == 0 and "withdrawn" in w.status.value


def test_unit_ratings_use_a_slider(pool):
    s = PreferenceSession(pool, selector=RandomRatings(), num_levels=None)
    w = PreferenceWidget(s)
    slider, submit = w.options.children[0].children[1].children
    slider.value = 0.8
    submit.click()
    assert s.history[-1].value == pytest.approx(0.8)


def test_invalid_answer_changes_nothing(pool):
    s = PreferenceSession(pool, selector=RandomRankings(m=3))
    w = PreferenceWidget(s)
    q = w.query
    w.answer(7)
    assert s.step == 0 and w.query is q and "not recorded" in w.status.value and "7" in w.status.value
    assert not any(b.disabled for b in w.buttons)


def test_render_hook_gets_item_and_pool_index(pool):
    seen = []

    def render(item, index):
        seen.append((item.clone(), index))
        return PNG

    s = PreferenceSession(pool, selector=RandomRankings(m=3))
    w = PreferenceWidget(s, render)
    assert [i for _, i in seen] == list(w.query.indices)
    assert all(torch.equal(x, pool[i]) for x, i in seen)
    assert all(isinstance(p, widgets.Image) and bytes(p.value) == PNG for p in _pictures(w))


def test_as_picture_kinds(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    img = as_picture(fig)
    assert isinstance(img, widgets.Image) and bytes(img.value).startswith(b"\x89PNG")
    assert not plt.fignum_exists(fig.number)  # closed: not shown twice
    path = tmp_path / "x.png"
    path.write_bytes(PNG)
    assert bytes(as_picture(path).value) == PNG
    assert isinstance(as_picture("<b>hi</b>"), widgets.HTML)
    label = widgets.Label("x")
    assert as_picture(label) is label

    class Svg:
        def _repr_svg_(self):
            return "<svg></svg>"

    assert as_picture(Svg()).value == "<svg></svg>"
    with pytest.raises(TypeError, match="int"):
        as_picture(3)


@pytest.mark.parametrize("render", [lambda item, index: 1 / 0, lambda item, index: 42])
def test_a_broken_render_hook_shows_the_table_and_the_session_goes_on(pool, tmp_path, render):
    f = tmp_path / "s.jsonl"
    s = PreferenceSession(pool, session_file=f, selector=RandomRankings(m=3), names=["cost", "speed"])
    w = PreferenceWidget(s, render)
    note, table = _pictures(w)[0].children
    assert "render hook failed" in note.value and ("ZeroDivisionError" in note.value or "TypeError" in note.value)
    assert "cost" in table.value
    w.buttons[0].click()  # the answer is recorded and the next query shown, its buttons live
    assert s.step == 1 and f.read_text().count("\n") == 2 and not any(b.disabled for b in w.buttons)


def test_bad_arguments(pool):
    with pytest.raises(TypeError, match="PreferenceSession"):
        PreferenceWidget(pool)
    with pytest.raises(TypeError, match="render"):
        PreferenceWidget(PreferenceSession(pool), render="not callable")


def test_table_picture_default_names():
    assert "x2" in table_picture(torch.tensor([1.0, 2.5])) and "2.5" in table_picture(torch.tensor([1.0, 2.5]))
