"""Property-based tests (hypothesis) over the public API (issue #26, item 5): generated items,
comparisons, ratings, shapes, dtypes and hyperparameters, and invariants that hold for all of them.

* posteriors are finite, with variances >= 0, in float64 and float32;
* predictive probabilities lie in [0, 1], and P(a > b) + P(b > a) = 1 for forced choices;
* a call that fails (bad indices, bad ratings) leaves the model as it was;
* save -> load gives the same posterior;
* a batched model equals its members;
* the cache follows edits: after changing a hyperparameter, the posterior is a fresh model's.

The default profile (``torchpref``: derandomised, few examples, no deadline) keeps the default
test run under a minute; ``TORCHPREF_HYPOTHESIS_PROFILE=long`` (``benchmarks/test_properties_long.py``)
runs many more examples.
"""

import copy
import os
import warnings

import pytest
import torch

hypothesis = pytest.importorskip("hypothesis", reason="the property-based tests need the test extra: hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import torchpref  # noqa: E402
from torchpref import BatchedPreferenceGP, PreferenceGP  # noqa: E402
from torchpref.models.checkpoint import model_checkpoint  # noqa: E402

_COMMON = dict(deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("torchpref", max_examples=12, derandomize=True, **_COMMON)
settings.register_profile("long", max_examples=300, **_COMMON)
PROFILE = os.environ.get("TORCHPREF_HYPOTHESIS_PROFILE", "torchpref")
if PROFILE not in ("torchpref", "long"):
    raise ValueError(f"TORCHPREF_HYPOTHESIS_PROFILE must be 'torchpref' or 'long', got {PROFILE!r}.")
SETTINGS = settings.get_profile(PROFILE)

F64 = torch.float64
unit = st.floats(0.0, 1.0, allow_nan=False, allow_infinity=False)
log_scale = st.floats(-2.0, 2.0, allow_nan=False).map(lambda e: 10.0**e)


@st.composite
def problems(draw, max_n=8, max_d=3, dtypes=(torch.float64, torch.float32)):
    """Items in the unit cube (duplicates and edges included), comparisons between distinct items,
    ratings in [0, 1] (0 and 1 included), hyperparameters over four decades."""
    n = draw(st.integers(2, max_n))
    d = draw(st.integers(1, max_d))
    dtype = draw(st.sampled_from(dtypes))
    X = torch.tensor(draw(st.lists(st.lists(unit, min_size=d, max_size=d), min_size=n, max_size=n)), dtype=dtype)
    pairs = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=2 * n))
    pairs = [p for p in pairs if p[0] != p[1]]
    rated = draw(st.lists(st.integers(0, n - 1), max_size=n))
    if not pairs and not rated:
        pairs = [(0, 1)]
    return dict(
        X=X,
        comparisons=torch.tensor(pairs, dtype=torch.long).reshape(-1, 2) if pairs else None,
        ratings=torch.tensor(draw(st.lists(unit, min_size=len(rated), max_size=len(rated))), dtype=dtype)
        if rated
        else None,
        rating_index=torch.tensor(rated, dtype=torch.long) if rated else None,
        lengthscale=draw(log_scale),
        outputscale=draw(log_scale),
        comparison_noise=draw(log_scale) / 10,
        ties_offered=draw(st.booleans()),
    )


def build(p, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # float32, jitter: expected for some draws
        model = PreferenceGP(
            p["X"],
            p["comparisons"],
            p["ratings"],
            p["rating_index"],
            comparison_noise=p["comparison_noise"],
            ties_offered=p["ties_offered"],
            **kw,
        )
        model.covar_module.base_kernel.lengthscale = p["lengthscale"]
        model.covar_module.outputscale = p["outputscale"]
    return model


def queries(p, m=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = p["X"]
    return torch.cat([torch.rand(m, X.shape[-1], generator=g, dtype=F64).to(X.dtype), X[:2]])


def moments(model, X):
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        post = model.posterior(X)
        return post.mean.squeeze(-1), post.variance.squeeze(-1)


@SETTINGS
@given(problems())
def test_posteriors_are_finite_with_nonnegative_variance(p):
    model = build(p)
    mean, var = moments(model, queries(p))
    assert torch.isfinite(mean).all() and torch.isfinite(var).all()
    assert (var >= -1e-6 * p["outputscale"]).all(), var.min()
    assert mean.dtype == p["X"].dtype
    with torch.no_grad():
        joint = model.posterior(queries(p)).distribution.covariance_matrix
    assert torch.linalg.eigvalsh(joint.double()).min() >= -1e-5 * p["outputscale"]


@SETTINGS
@given(problems())
def test_predictive_probabilities_are_probabilities(p):
    model = build(p)
    Xq = queries(p)
    with torch.no_grad():
        r = model.expected_rating(Xq)
        ab = model.preference_probability(Xq[:-1], Xq[1:])
        ba = model.preference_probability(Xq[1:], Xq[:-1])
        tie = model.tie_probability(Xq[:-1], Xq[1:])
    for v in (r, ab, ba, tie):
        assert torch.isfinite(v).all() and (v >= 0).all() and (v <= 1).all()
    if not p["ties_offered"]:  # forced choice: one of the two orders
        torch.testing.assert_close(ab + ba, torch.ones_like(ab), atol=1e-5, rtol=0)
    else:  # strict preference either way, or a tie
        assert (ab + ba + tie <= 1 + 1e-5).all()


@SETTINGS
@given(problems(), st.data())
def test_a_failed_update_leaves_the_model_as_it_was(p, data):
    model = build(p)
    Xq = queries(p)
    before, data_before = moments(model, Xq), model.data
    n = p["X"].shape[0]
    bad = data.draw(
        st.sampled_from(
            [
                dict(comparisons=torch.tensor([[0, n]])),  # out of range
                dict(comparisons=torch.tensor([[0, -n - 1]])),
                dict(ratings=torch.tensor([1.5], dtype=F64), rating_index=torch.tensor([0])),
                dict(ratings=torch.tensor([float("nan")], dtype=F64), rating_index=torch.tensor([0])),
                dict(ratings=torch.tensor([0.5], dtype=F64), rating_index=torch.tensor([n])),
                dict(ratings=torch.tensor([0.5, 0.5], dtype=F64), rating_index=torch.tensor([0])),
            ]
        )
    )
    with pytest.raises(ValueError):
        model.add_observations(**bad)
    assert model.data is data_before
    after = moments(model, Xq)
    assert torch.equal(before[0], after[0]) and torch.equal(before[1], after[1])


@SETTINGS
@given(problems(dtypes=(torch.float64,)))
def test_save_then_load_gives_the_same_posterior(p):
    model = build(p, learn_likelihood=True)
    ck = copy.deepcopy(model_checkpoint(model))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loaded = torchpref.load_model(ck)
    Xq = queries(p)
    (m0, v0), (m1, v1) = moments(model, Xq), moments(loaded, Xq)
    scale = p["outputscale"]
    torch.testing.assert_close(m1, m0, atol=1e-5 * max(scale, 1.0), rtol=1e-5)
    torch.testing.assert_close(v1, v0, atol=1e-5 * max(scale, 1.0), rtol=1e-5)
    assert loaded.ties_offered is model.ties_offered


@SETTINGS
@given(st.lists(problems(max_n=6, max_d=2, dtypes=(torch.float64,)), min_size=2, max_size=3), st.integers(1, 2))
def test_a_batched_model_equals_its_members(ps, d):
    ps = [dict(q, X=q["X"][:, :1].expand(-1, d).clone() if q["X"].shape[-1] != d else q["X"]) for q in ps]
    shared = ps[0]
    members = [
        build(
            dict(
                q,
                lengthscale=shared["lengthscale"],
                outputscale=shared["outputscale"],
                comparison_noise=shared["comparison_noise"],
                ties_offered=False,
            )
        )
        for q in ps
    ]
    batched = BatchedPreferenceGP.from_models(members)
    Xq = torch.rand(len(ps), 4, d, generator=torch.Generator().manual_seed(1), dtype=F64)
    with torch.no_grad():
        mean, var = batched.marginals(Xq)
        for t, member in enumerate(members):
            m_t, v_t = member.marginals(Xq[t])
            torch.testing.assert_close(mean[t], m_t, atol=1e-7 * max(shared["outputscale"], 1.0), rtol=1e-6)
            torch.testing.assert_close(var[t], v_t, atol=1e-7 * max(shared["outputscale"], 1.0), rtol=1e-6)


@SETTINGS
@given(problems(dtypes=(torch.float64,)), log_scale, log_scale)
def test_the_cache_follows_hyperparameter_and_setting_edits(p, lengthscale, noise):
    model = build(p)
    Xq = queries(p)
    moments(model, Xq)  # fill the cache
    model.covar_module.base_kernel.lengthscale = lengthscale
    model.comparison_likelihood.comparison_noise = noise / 10
    model.ties_offered = not p["ties_offered"]
    fresh = build(dict(p, lengthscale=lengthscale, comparison_noise=noise / 10, ties_offered=not p["ties_offered"]))
    (m0, v0), (m1, v1) = moments(model, Xq), moments(fresh, Xq)
    scale = max(p["outputscale"], 1.0)
    torch.testing.assert_close(m0, m1, atol=1e-5 * scale, rtol=1e-5)
    torch.testing.assert_close(v0, v1, atol=1e-5 * scale, rtol=1e-5)
