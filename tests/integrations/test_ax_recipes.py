"""The recipes of docs/ax.md, run as written, and the errors of the Ax helpers (issue 32, items 2-3).

Each ``<!-- recipe: NAME -->`` code block of docs/ax.md is executed here as it stands and its
results checked. Skipped, with the reason, where Ax (``pip install 'torchpref[ax]'``) is absent.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

pytest.importorskip("ax", reason="Ax is not installed (pip install 'torchpref[ax]'): the Ax recipes are untested here")

from ax.adapter.registry import Generators
from ax.adapter.torch import TorchAdapter
from ax.generators.torch.botorch_modular import utils as _ax_utils
from ax.generators.torch.botorch_modular.generator import BoTorchGenerator
from ax.generators.torch.botorch_modular.surrogate import SurrogateSpec
from ax.service.utils.best_point import get_trace
from botorch.acquisition.logei import qLogNoisyExpectedImprovement

import torchpref.integrations.ax as tax
import torchpref.integrations.ax_recipes as tar
from torchpref import PreferenceGP

DOC = Path(__file__).resolve().parents[2] / "docs" / "ax.md"
PREF = tar.PREFERENCE_METRIC
_ORIGINAL_CHOOSE = _ax_utils.choose_model_class


def recipe(name: str) -> dict:
    """Run the code block after ``<!-- recipe: name -->`` in docs/ax.md; its namespace."""
    match = re.search(rf"<!-- recipe: {re.escape(name)} -->\s*```python\n(.*?)```", DOC.read_text(), re.S)
    assert match, f"docs/ax.md has no recipe {name!r}"
    namespace: dict = {"__name__": f"recipe_{name}"}
    torch.manual_seed(0)  # BoTorch's acquisition optimiser draws from torch's global generator
    exec(compile(match.group(1), f"docs/ax.md:{name}", "exec"), namespace)
    return namespace


def _models(strategy) -> list:
    model = strategy.adapter.generator.surrogate.model
    return list(getattr(model, "models", [model]))


def test_recipe_pbo():
    ns = recipe("pbo")
    exp, strategy = ns["experiment"], ns["strategy"]
    assert len(exp.trials) == 10 and all(len(t.arms) == 2 for t in exp.trials.values())
    assert [type(m) for m in _models(strategy)] == [PreferenceGP]
    assert _ax_utils.choose_model_class is _ORIGINAL_CHOOSE  # no opt-in left behind
    # the recommendation is among the better compared arms under the hidden utility (optimum (0.3, 0.7))
    u = lambda p: -((p["x1"] - 0.3) ** 2 + (p["x2"] - 0.7) ** 2)  # noqa: E731
    compared = sorted(u(arm.parameters) for arm in exp.arms_by_name.values())
    assert u(ns["best"]) >= compared[len(compared) // 2]
    assert ns["arm_name"] in exp.arms_by_name


def test_recipe_pbo_client():
    ns = recipe("pbo-client")
    assert len(ns["table"]) == 10  # 5 pairs
    assert [type(m) for m in _models(ns["strategy"])] == [PreferenceGP]
    best = ns["best"]
    assert (
        best["x1"] + best["x2"]
        >= max(a.parameters["x1"] + a.parameters["x2"] for a in ns["experiment"].arms_by_name.values()) - 0.5
    )


def test_pbo_client_get_next_trials_gives_one_arm_trials():
    """What docs/ax.md says of PBO through the Client: one-arm trials, then a failure."""
    from ax.api.client import Client

    exp = tar.pbo_experiment({"x1": (0.0, 1.0), "x2": (0.0, 1.0)})
    client = Client()
    client.set_experiment(exp)
    client.set_generation_strategy(tar.pbo_generation_strategy(d=2, initial_pairs=2, seed=0))
    trials = client.get_next_trials(max_trials=2)
    assert [len(exp.trials[i].arms) for i in trials] == [1, 1]


def test_recipe_bope_client():
    ns = recipe("bope-client")
    bo, pe = ns["bo"], ns["pe"]
    assert len(bo.trials) == 7 and len(pe.trials) == 6
    gs = ns["client"]._generation_strategy
    assert tax.is_preference_model_class(type(gs.adapter.generator.surrogate._submodels[(PREF,)]))
    trace, utility = ns["trace"], ns["utility"]
    assert list(trace) == sorted(bo.trials) and max(trace.values()) == pytest.approx(utility)
    assert all(b >= a for a, b in zip(list(trace.values()), list(trace.values())[1:], strict=False))
    # the same trace from Ax's own get_trace differs: it fits PairwiseGP (no opt-in)
    assert _ax_utils.choose_model_class is _ORIGINAL_CHOOSE
    assert get_trace(bo) != pytest.approx(trace)
    with tax.use_preference_gp():
        assert get_trace(bo) == pytest.approx(trace)
    assert ns["arm_name"] in bo.arms_by_name and ns["trial_index"] in bo.trials


def test_recipe_ratings_with_comparisons():
    ns = recipe("ratings-with-comparisons")
    (model,) = [m for m in _models(ns["strategy"]) if isinstance(m, PreferenceGP)]
    assert sorted(model.ratings.tolist()) == pytest.approx([0.1, 0.9])
    rated = model.train_X[model.rating_index]
    with torch.no_grad():
        mean = model.posterior(rated).mean.reshape(-1)
    assert mean[model.ratings.argmax()] > mean[model.ratings.argmin()]


def test_recipe_ratings_alone():
    ns = recipe("ratings-alone")
    gs = ns["client"]._generation_strategy
    (model,) = _models(gs)
    assert isinstance(model, PreferenceGP) and model.comparisons.numel() == 0
    assert model.ratings.numel() == model.train_X.shape[0] >= 6
    assert bool(((model.ratings > 0) & (model.ratings < 1)).all())


# ---------------------------------------------------------------- errors


def _rated_experiment(values=(0.8, 0.2)):
    exp = tar.pbo_experiment({"x1": (0.0, 1.0), "x2": (0.0, 1.0)})
    for k, (a, b) in enumerate([((0.1, 0.2), (0.7, 0.9)), ((0.5, 0.5), (0.2, 0.8)), ((0.9, 0.1), (0.3, 0.3))]):
        tar.add_comparison(exp, dict(x1=a[0], x2=a[1]), dict(x1=b[0], x2=b[1]), k % 2 == 0)
    for v, x in zip(values, (0.25, 0.75), strict=False):
        tar.add_rating(exp, {"x1": x, "x2": x}, v)
    return exp


def _fit(exp, spec, transforms=None, fit_tracking_metrics=True):
    kw = {} if transforms is None else {"transforms": transforms}
    return TorchAdapter(
        experiment=exp,
        generator=BoTorchGenerator(surrogate_spec=spec),
        fit_tracking_metrics=fit_tracking_metrics,
        **kw,
    )


@pytest.mark.parametrize(
    ("value", "match"),
    [
        ("rating", r"must be a list of metric names, got 'rating': write \['rating'\]"),
        ({"rating"}, "must be a list of metric names"),
        ([1], "must be a list of metric names"),
        (["rating", "rating"], r"names \['rating'\] more than once"),
    ],
)
def test_bad_rating_metrics_option(value, match):
    spec = SurrogateSpec(
        metric_to_model_configs={PREF: [tax.preference_model_config(2, model_options={"rating_metrics": value})]}
    )
    with pytest.raises(ValueError, match=match):
        _fit(_rated_experiment(), spec, transforms=[])


def test_rating_metric_named_in_its_own_model():
    spec = tar.preference_surrogate_spec(2, metric="rating", rating_metrics=["rating"])
    with pytest.raises(
        ValueError, match="'rating' is named in .* of its own model: its values are the model's ratings"
    ):
        _fit(_rated_experiment(), spec, transforms=[])
    spec = tar.preference_surrogate_spec(2, rating_metrics=[PREF])
    with pytest.raises(ValueError, match="it is the preference metric"):
        _fit(_rated_experiment(), spec, transforms=[])


def test_ax_default_transforms_are_refused_by_name():
    """Ax's registry default (Y_trans: StandardizeY, ...) rescales the ratings: refused, naming
    the transforms and the fix; with transforms=[] the same data fits."""
    exp = _rated_experiment()
    spec = tar.preference_surrogate_spec(2, metric="rating")
    with pytest.raises(ValueError, match=r"rating metric 'rating'.*StandardizeY.*transforms=\[\]"):
        Generators.BOTORCH_MODULAR(
            experiment=exp, data=exp.lookup_data(), surrogate_spec=spec, botorch_acqf_class=qLogNoisyExpectedImprovement
        )
    adapter = _fit(exp, spec, transforms=[], fit_tracking_metrics=True)
    model = adapter.generator.surrogate._submodels[("rating",)]
    assert isinstance(model, PreferenceGP) and sorted(model.ratings.tolist()) == pytest.approx([0.2, 0.8])


def test_out_of_range_ratings():
    with pytest.raises(ValueError, match="rating metric 'rating': a rating must be in"):
        tar.add_rating(tar.pbo_experiment({"x1": (0.0, 1.0)}), {"x1": 0.5}, 1.5)
    with pytest.raises(ValueError, match="rating metric 'score': a rating must be in"):
        tar.add_rating(tar.pbo_experiment({"x1": (0.0, 1.0)}), {"x1": 0.5}, float("nan"), metric="score")
    # a value attached past add_rating: refused at the fit, named
    exp = _rated_experiment(values=(0.5,))
    exp.trials[max(exp.trials)].attach_batch_trial_data(
        raw_data={exp.trials[max(exp.trials)].arms[0].name: {"rating": (3.0, 0.0)}}
    )
    with pytest.raises(ValueError, match=r"rating metric 'rating': ratings must be in \[0, 1\], got \[3.0\]"):
        _fit(exp, tar.preference_surrogate_spec(2, rating_metrics=["rating"]), transforms=[])


def test_helper_argument_errors():
    exp = tar.pbo_experiment({"x1": (0.0, 1.0), "x2": (0.0, 1.0)})
    with pytest.raises(ValueError, match="a_preferred must be True or False"):
        tar.add_comparison(exp, {"x1": 0.1, "x2": 0.1}, {"x1": 0.2, "x2": 0.2}, 1)
    with pytest.raises(ValueError, match="lower bound 1.0 must be below upper bound 0.0"):
        tar.pbo_experiment({"x1": (1.0, 0.0)})
    with pytest.raises(ValueError, match="initial_trials must be at least 1"):
        tar.pbo_generation_strategy(2, initial_pairs=0)
    with pytest.raises(ValueError, match="no comparisons yet"):
        tar.pbo_best_point(exp)
    with pytest.raises(ValueError, match="needs a BOPE experiment"):
        tar.bope_best_point(exp)
    trial = exp.new_batch_trial()
    with pytest.raises(ValueError, match="preferred must be 0 or 1"):
        tar.record_preference(trial, True)
