"""One effort model prices every question (issue 50); a selector restricted to one kind; rankings of
the size worth most per second."""

from __future__ import annotations

import pytest
import torch

import torchpref
from torchpref.data.effort import EffortModel
from torchpref.selection.combined import InformationAndProfile
from torchpref.selection.defaults import SELECTOR_NAMES, named_selector
from torchpref.selection.one_kind import OneKind
from torchpref.selection.strategies import UCBC


def _model(n: int = 8, d: int = 2, seed: int = 0) -> torchpref.PreferenceGP:
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, d, generator=g, dtype=torch.float64)
    return torchpref.PreferenceGP(X, comparisons=torch.tensor([[0, 1], [2, 3]]), covar_module=None)


@pytest.mark.parametrize("name", SELECTOR_NAMES)
def test_every_named_selector_prices_by_the_effort_model(name):
    """The three prices of one question the issue found (3.81 / 4.58 / 5.34 s, 3.4 / 4.3 / 5.2 s, 1 : 2)
    are one: the plain effort model's, for every size of ranking."""
    sel = named_selector(name, 20, 5)
    if not hasattr(sel, "query_cost"):
        assert isinstance(sel, (UCBC, torchpref.RandomMixed))  # no prices: they do not compare kinds by effort
        return
    effort = EffortModel.plain()
    assert [sel.query_cost(q) for q in range(1, 6)] == [effort.rating()] + [effort.ranking(q) for q in (2, 3, 4, 5)]


def test_effort_model_round_trips_as_a_dictionary():
    e = EffortModel.trajectories()
    assert EffortModel.of(e.as_dict()) == e and EffortModel.of(e) is e
    with pytest.raises(ValueError, match="EffortModel"):
        EffortModel.of({"seconds": 3})
    with pytest.raises(ValueError, match="EffortModel"):
        torchpref.InformationPerEffort(effort="fast")


def test_the_old_import_path_of_the_effort_model():
    from torchpref.simulation.raters import EffortModel as Old

    assert Old is EffortModel


@pytest.mark.parametrize("kind", ["rating", "ranking"])
def test_one_kind_asks_only_that_kind(kind):
    model = _model()
    X = model.train_inputs[0] if hasattr(model, "train_inputs") else None
    X = torch.rand(8, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    sel = OneKind(torchpref.default_selector(8), kind)
    for step in range(3):
        q = sel.select(model, X, None, step, 3, torch.Generator().manual_seed(step))
        assert q.kind == kind
    assert "only" in sel.name


def test_one_kind_refuses_what_it_cannot_restrict():
    with pytest.raises(ValueError, match="per-effort"):
        OneKind(UCBC(), "rating")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="kind"):
        OneKind(torchpref.default_selector(), "pair")


def test_choose_size_asks_a_prefix_of_the_greedy_set_priced_by_its_size():
    """With choose_size, the ranking asked is the size of largest value per second, and that value is
    its value (computed alone) over its own price."""
    model = _model(10, seed=2)
    X = torch.rand(10, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64).unsqueeze(0)
    sel = InformationAndProfile(m=5, decide="order", choose_size=True, effort=EffortModel.plain())
    g = [torch.Generator().manual_seed(0)]
    _, _, rows, value = sel.values(model, X, g)
    q = int((rows[0] >= 0).sum())
    assert 2 <= q <= 5 and bool((rows[0, :q] >= 0).all()) and bool((rows[0, q:] < 0).all())
    _, rank = sel.scorers(model, X, [torch.Generator().manual_seed(0)])
    alone = float(rank(rows[:, :q].unsqueeze(1))) / EffortModel.plain().ranking(q)
    assert float(value) == pytest.approx(alone, rel=1e-9)


def test_order_values_a_shift_of_every_utility_at_nothing():
    """decide="order": a ranking's value is the same whatever the person's overall level (a shift of
    every utility orders nothing), checked on a model and the same model with a constant prior mean."""
    from gpytorch.means import ConstantMean

    g = torch.Generator().manual_seed(4)
    X = torch.rand(7, 2, generator=g, dtype=torch.float64)
    C = torch.tensor([[0, 1], [1, 2]])
    plain = torchpref.PreferenceGP(X, comparisons=C)
    mean = ConstantMean().to(torch.float64)
    mean.constant.data.fill_(2.5)
    shifted = torchpref.PreferenceGP(X, comparisons=C, mean_module=mean)
    sel = InformationAndProfile(m=3, decide="order", effort=EffortModel.plain())
    rows = torch.tensor([[[0, 3, 5]]])
    a = sel.scorers(plain, X.unsqueeze(0), [torch.Generator().manual_seed(0)])[1](rows)
    b = sel.scorers(shifted, X.unsqueeze(0), [torch.Generator().manual_seed(0)])[1](rows)
    assert float(a) == pytest.approx(float(b), rel=1e-6, abs=1e-9)
