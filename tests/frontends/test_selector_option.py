"""``--selector NAME`` of ``torchpref elicit`` and ``serve``: the named selectors, what a new
session records, and that a resumed session keeps its file's selector when none is named."""

import io
import json

import pytest
import torch

from torchpref.cli import build_parser
from torchpref.frontends.elicit import FeaturesWorld, _open_session
from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.defaults import SELECTOR_NAMES, default_ranking_size, named_selector
from torchpref.selection.strategies import UCBC, InformationPerEffort, RandomMixed


def test_every_name_builds_its_selector_and_the_command_line_offers_exactly_those():
    kinds = {"default": InformationAndProfile, "ucbc": UCBC, "information": InformationPerEffort, "random": RandomMixed}
    assert set(SELECTOR_NAMES) == set(kinds)
    for name, cls in kinds.items():
        for n in (3, 30, None):
            sel = named_selector(name, n)
            assert type(sel) is cls and sel.m == default_ranking_size(n), (name, n)
    with pytest.raises(ValueError, match="'nope'.*ucbc"):
        named_selector("nope", 10)
    parser = build_parser()
    for command in (["elicit", "lake"], ["serve", "lake"]):
        for name in SELECTOR_NAMES:
            assert parser.parse_args([*command, "--selector", name]).selector == name
        assert parser.parse_args(command).selector is None
        with pytest.raises(SystemExit):
            parser.parse_args([*command, "--selector", "nope"])


def _elicit_session(tmp_path, selector):
    X = torch.rand(12, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    world = FeaturesWorld(X, ["a", "b"], None)
    args = build_parser().parse_args(["elicit", "--features", "x.csv", "--queries", "6"])
    args.selector = selector
    return _open_session(world, args, tmp_path / "s.jsonl", 0, io.StringIO(), io.StringIO())


def test_elicit_records_the_named_selector_and_a_resume_keeps_it(tmp_path):
    s = _elicit_session(tmp_path, "ucbc")
    assert isinstance(s.selector, UCBC)
    q = s.ask()
    s.tell(q, 3 if q.kind == "rating" else 0)
    s.close()
    header = json.loads((tmp_path / "s.jsonl").read_text().splitlines()[0])
    assert header["selector"]["class"].endswith(".UCBC")
    resumed = _elicit_session(tmp_path, None)  # no --selector: the file's
    assert isinstance(resumed.selector, UCBC) and resumed.step == 1
    resumed.close()
    (tmp_path / "s.jsonl").unlink()
    fresh = _elicit_session(tmp_path, None)  # no --selector, no file: the default
    assert isinstance(fresh.selector, InformationAndProfile) and fresh.selector.decide == "order"
    fresh.close()


def test_serve_command_line_gives_new_sessions_the_named_selector(tmp_path, monkeypatch):
    pytest.importorskip("starlette")
    from torchpref.frontends.serve import app
    from torchpref.testing.serve import write_items

    items = write_items(tmp_path, n=8, d=2, pictures=False)
    seen = {}
    monkeypatch.setattr(app, "serve", lambda items, **kw: seen.update(kw))
    for name, cls in (("ucbc", UCBC), (None, type(None))):
        argv = ["serve", "--features", str(items), "--port", "0"] + (["--selector", name] if name else [])
        app.run(build_parser().parse_args(argv))
        assert type(seen["new"].selector) is cls  # None: each new session's own default
