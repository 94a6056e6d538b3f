"""The SUSHI replay (issue 50) on a small synthetic file in the release's format, written here: the
loader, the replay's answers and scores, the effort model's prices, the command line."""

from __future__ import annotations

import json
import math
import warnings

import pytest
import torch

from torchpref.data.effort import EffortModel
from torchpref.experiments import sushi
from torchpref.experiments.sushi_data import FEATURES, SushiDataMissing, load_sushi, write_synthetic


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return load_sushi(write_synthetic(tmp_path_factory.mktemp("sushi"), 40, seed=3))


def test_loader_reads_the_release_format(data, tmp_path):
    assert data.X.shape == (100, len(FEATURES)) and len(data.people) == 40
    assert float(data.X.min()) == 0.0 and float(data.X.max()) == 1.0
    p = data.people[0]
    assert len(set(p.items)) == 10 and all(0 <= v <= 4 for v in p.levels)
    # the release's own file names, any number of people
    folder = write_synthetic(tmp_path / "five", 5, seed=0)
    order = folder / "sushi3b.5.10.order"
    order.rename(folder / "sushi3b.5000.10.order")
    (folder / "sushi3b.5.10.score").rename(folder / "sushi3b.5000.10.score")
    assert len(load_sushi(folder).people) == 5


def test_loader_says_where_to_get_the_data(tmp_path):
    with pytest.raises(SushiDataMissing, match="kamishima"):
        load_sushi(tmp_path)
    folder = write_synthetic(tmp_path / "s", 3)
    (folder / "sushi3.idata").unlink()
    with pytest.raises(SushiDataMissing, match="sushi3.idata"):
        load_sushi(folder)


def test_loader_refuses_a_damaged_file(tmp_path):
    folder = write_synthetic(tmp_path, 3)
    score = folder / "sushi3b.3.10.score"
    lines = score.read_text().splitlines()
    score.write_text("\n".join(lines[:2]) + "\n")
    with pytest.raises(ValueError, match="3 people but"):
        load_sushi(folder)
    lines[0] = lines[0].replace("-1", "7", 1)
    score.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match="ratings in -1..4"):
        load_sushi(folder)


def test_split_and_person_data(data):
    s = sushi.split(data, data.people[1], 1, 0)
    assert sorted(s.askable.tolist() + s.held.tolist()) == list(range(10)) and len(s.askable) == sushi.ASKABLE
    again = sushi.split(data, data.people[1], 1, 0)  # seeded
    assert all(torch.equal(getattr(s, f), getattr(again, f)) for f in ("X", "position", "levels", "askable", "held"))
    d = sushi.person_data(s, s.askable)
    # the ranking of the 6 as successive best-of-m: every pair, the better ranked first
    assert d.comparisons.shape == (15, 2)
    assert bool((s.position[d.comparisons[:, 0]] < s.position[d.comparisons[:, 1]]).all())
    assert torch.allclose(d.ratings, (s.levels[s.askable].double() + 0.5) / 5)


def test_concordance_brute_force():
    mean = torch.tensor([[3.0, 1.0, 2.0, 2.0]])
    pairs = torch.tensor([[[0, 1], [1, 2], [2, 3], [3, 0]]])
    # right, wrong, tie (1/2), wrong
    assert float(sushi.concordance(mean, pairs)) == pytest.approx(1.5 / 4)
    mask = torch.tensor([[True, True, False, False]])
    assert float(sushi.concordance(mean, pairs, mask)) == pytest.approx(0.5)


def test_at_budgets():
    curve = [0.5, 0.6, 0.7, 0.8]
    assert sushi.at_budgets(curve, [3.4, 4.3, 3.4], (3.0, 3.4, 7.7, 100)) == [0.5, 0.6, 0.7, 0.8]


def test_replay_answers_from_the_record(data):
    splits = [sushi.split(data, p, k, 0) for k, p in enumerate(data.people[:6])]
    for policy in ("default", "random best-of-3", "default (ratings only)"):
        out = sushi.replay(splits, policy, None, 4, 0)
        effort = EffortModel.plain()
        for rec in out:
            assert len(rec["ranking"]) == len(rec["ratings"]) == 5
            assert all(0.0 <= v <= 1.0 for v in rec["ranking"] + rec["ratings"])
            assert len(rec["kinds"]) == 4 and all(
                s in (effort.rating(), *map(effort.ranking, (2, 3, 4, 5))) for s in rec["seconds"]
            )
        if policy == "random best-of-3":
            assert all(k == "ranking" for rec in out for k in rec["kinds"])
            assert all(s == effort.ranking(3) for rec in out for s in rec["seconds"])
        if policy == "default (ratings only)":
            assert all(k == "rating" for rec in out for k in rec["kinds"])


def test_a_rating_is_not_asked_twice(data):
    """As a session does, a rating of an item already rated is replaced by a question among the unrated."""
    splits = [sushi.split(data, p, k, 0) for k, p in enumerate(data.people[:4])]
    out = sushi.replay(splits, "random ratings", None, 6, 1)
    assert sum(rec["redirected"] for rec in out) > 0


def test_references_combine(data):
    splits = [sushi.split(data, p, k, 0) for k, p in enumerate(data.people[:10])]
    refs = sushi.references(splits, None)
    assert set(refs) == {"all ratings", "the ranking", "both"}
    assert all(len(v) == 10 for v in refs.values())


def test_reproduce_sushi_end_to_end(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    from torchpref.cli import main

    folder = write_synthetic(tmp_path / "data", 30, seed=1)
    out = tmp_path / "out"
    args = ["reproduce", "sushi", "--data", str(folder), "--people", "6", "--train", "8", "--calibration", "4"]
    args += ["--seeds", "1", "--queries", "2", "--policies", "default", "random best-of-3", "random ratings"]
    assert main([*args, "--out", str(out)]) == 0
    summary = json.loads((out / "sushi.json").read_text())
    assert "stamp" in summary and set(summary["summary"]["conditions"]) == {"none", "population"}
    for c in summary["summary"]["conditions"].values():
        assert set(c["policies"]) == {"default", "random best-of-3", "random ratings"}
        assert len(c["tests"]["default_vs_best_single_kind"]["ranking"]) == len(sushi.BUDGETS)
    table = json.loads((out / "rating_model.json").read_text())["rows"]
    assert [r["precision"] for r in table] == [1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 80.0]
    assert (out / "sushi.png").stat().st_size > 0 and (out / "sushi_curves.csv").is_file()


def test_reproduce_sushi_without_data_says_where_to_get_it(tmp_path, monkeypatch, capsys):
    from torchpref.cli import main

    monkeypatch.delenv("TORCHPREF_SUSHI_DATA", raising=False)
    try:
        code = main(["reproduce", "sushi", "--out", str(tmp_path / "o")])
        text = ""
    except (FileNotFoundError, SystemExit) as err:
        code, text = 1, str(err)
    out = capsys.readouterr()
    assert code != 0 and "kamishima" in text + out.out + out.err


def test_learned_rating_precision_stays_finite():
    """10 ratings a GP fits exactly drove the learned precision to ~1e6 without a prior (issue 50)."""
    from botorch.fit import fit_gpytorch_mll

    import torchpref
    from torchpref.inference.laplace import LaplaceConvergenceWarning

    g = torch.Generator().manual_seed(0)
    X = torch.rand(10, 2, generator=g, dtype=torch.float64)
    r = torchpref.likert_to_unit((1 + 4 * torch.rand(10, generator=g, dtype=torch.float64)).round(), num_levels=5)
    model = torchpref.PreferenceGP(X, ratings=r, rating_index=torch.arange(10), learn_likelihood=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LaplaceConvergenceWarning)
        fit_gpytorch_mll(torchpref.LaplaceMarginalLogLikelihood(model))
    nu = float(model.likelihood.rating.rating_precision.detach())
    assert math.isfinite(nu) and 1.0 < nu < 1000.0


def test_person_models_share_the_calibrated_precision():
    """A session's model, a population's people and the PreferenceGP default (the paper's 80)."""
    import torchpref
    from torchpref.data.preference_data import PreferenceData
    from torchpref.models.defaults import PERSON_RATING_PRECISION
    from torchpref.models.recipe import DEFAULT_MODEL
    from torchpref.population.fit import fit_population
    from torchpref.sessions.settings import default_session_model

    X = torch.rand(5, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert DEFAULT_MODEL.rating_precision == PERSON_RATING_PRECISION
    m = default_session_model(X)
    assert float(m.likelihood.rating.rating_precision) == pytest.approx(PERSON_RATING_PRECISION)
    people = [
        PreferenceData.create(X, torch.tensor([[0, 1]]), ratings=torch.tensor([0.7]), rating_index=torch.tensor([2]))
        for _ in range(2)
    ]
    pop = fit_population(people, fit=False)
    person = pop.person_model(X)
    assert float(person.likelihood.rating.rating_precision) == pytest.approx(PERSON_RATING_PRECISION)
    assert float(torchpref.PreferenceGP(X).likelihood.rating.rating_precision) == pytest.approx(80.0)
