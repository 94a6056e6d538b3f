"""BoTorch's preference acquisition, objective, active-learning and input-constructor checks
(``test/acquisition/test_preference.py``, ``test_objective.py``'s ``LearnedObjective``,
``test_active_learning.py``'s ``PairwiseMCPosteriorVariance``, ``test_input_constructors.py``'s
EUBO part), rewritten and run against ``PreferenceGP`` and ``PairwiseGP`` alike, with the other
BoTorch acquisitions a preference model is used with (tests/parity/botorch_port.py explains the counting)."""

import warnings

import pytest
import torch
from botorch.acquisition import (
    LearnedObjective,
    PosteriorMean,
    UpperConfidenceBound,
    qKnowledgeGradient,
    qUpperConfidenceBound,
)
from botorch.acquisition.active_learning import PairwiseMCPosteriorVariance, qNegIntegratedPosteriorVariance
from botorch.acquisition.input_constructors import get_acqf_input_constructor
from botorch.acquisition.logei import qLogNoisyExpectedImprovement
from botorch.acquisition.max_value_entropy_search import qMaxValueEntropy
from botorch.acquisition.objective import GenericMCObjective
from botorch.acquisition.preference import (
    AnalyticExpectedUtilityOfBestOption,
    PairwiseBayesianActiveLearningByDisagreement,
    qExpectedUtilityOfBestOption,
)
from botorch.exceptions.errors import UnsupportedError
from botorch.exceptions.warnings import InputDataWarning
from botorch.models import ModelListGP, SingleTaskGP
from botorch.models.deterministic import FixedSingleSampleModel, PosteriorMeanModel
from botorch.models.transforms.input import Normalize
from botorch.optim import optimize_acqf
from botorch.sampling.pairwise_samplers import PairwiseSobolQMCNormalSampler
from botorch_port import _seeded, impl, make_model, model_class, small_problem  # noqa: F401

F64 = {"dtype": torch.float64}
X_DIM, Y_DIM = 3, 2


@pytest.fixture
def setting(impl):
    """An outcome model on ``X``, preference models on ``X`` and on ``Y`` from one comparison."""
    X, Y = torch.rand(2, X_DIM, **F64), torch.rand(2, Y_DIM, **F64)
    comps = torch.tensor([[1, 0]])
    outcome = SingleTaskGP(X, Y)
    return {
        "on_X": make_model(impl, X, comps),
        "on_Y": make_model(impl, Y, comps),
        "outcome": FixedSingleSampleModel(model=outcome),
        "outcome_gp": outcome,
    }


def _pref_model(setting, outcome_model):
    return setting["on_X"] if outcome_model is None else setting["on_Y"]


# --------------------------------------------------------------------------- test_preference.py
@pytest.mark.parametrize("with_outcome", [False, True])
@pytest.mark.parametrize(
    "acqf_class", [AnalyticExpectedUtilityOfBestOption, PairwiseBayesianActiveLearningByDisagreement]
)
def test_pairs_only(impl, setting, with_outcome, acqf_class):
    outcome = setting["outcome"] if with_outcome else None
    acqf = acqf_class(pref_model=_pref_model(setting, outcome), outcome_model=outcome)
    assert acqf(torch.rand(2, X_DIM, **F64)).shape == (1,)
    for q in (1, 3):
        with pytest.raises((UnsupportedError, AssertionError)):
            acqf(torch.rand(q, X_DIM, **F64))


@pytest.mark.parametrize("with_outcome", [False, True])
def test_eubo_previous_winner(impl, setting, with_outcome):
    outcome = setting["outcome"] if with_outcome else None
    winner = torch.rand(1, Y_DIM if with_outcome else X_DIM, **F64)
    acqf = AnalyticExpectedUtilityOfBestOption(
        pref_model=_pref_model(setting, outcome), outcome_model=outcome, previous_winner=winner
    )
    assert acqf(torch.rand(1, X_DIM, **F64)).shape == (1,)
    for q in (2, 3):
        with pytest.raises((UnsupportedError, AssertionError)):
            acqf(torch.rand(q, X_DIM, **F64))


@pytest.mark.parametrize("with_outcome", [False, True])
def test_qeubo_shapes(impl, setting, with_outcome):
    outcome = setting["outcome"] if with_outcome else None
    acqf = qExpectedUtilityOfBestOption(pref_model=_pref_model(setting, outcome), outcome_model=outcome)
    for q in (1, 2, 3):
        assert acqf(torch.rand(q, X_DIM, **F64)).shape == (1,)


def test_eubo_equals_expected_maximum(impl):
    """Analytic EUBO is ``E[max(f(x1), f(x2))]`` under the model's posterior: check it by Monte Carlo."""
    X, C = small_problem()
    model = make_model(impl, X, C)
    pair = torch.rand(1, 2, X_DIM, **F64)
    eubo = AnalyticExpectedUtilityOfBestOption(pref_model=model)(pair)
    samples = model.posterior(pair[0]).rsample(torch.Size([200_000])).squeeze(-1)  # s x 2
    mc = samples.max(-1).values
    assert abs(float(eubo) - float(mc.mean())) < 4 * float(mc.std()) / 200_000**0.5 + 1e-6


def test_eubo_on_prior_model(impl):
    prior = model_class(impl)(None, None).to(**F64)
    value = AnalyticExpectedUtilityOfBestOption(pref_model=prior)(torch.rand(4, 2, X_DIM, **F64))
    assert value.shape == (4,) and torch.isfinite(value).all()


def test_optimize_eubo(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    bounds = torch.stack([torch.zeros(X_DIM), torch.ones(X_DIM)]).to(**F64)
    cand, _ = optimize_acqf(
        AnalyticExpectedUtilityOfBestOption(pref_model=model), bounds=bounds, q=2, num_restarts=2, raw_samples=32
    )
    assert cand.shape == (2, X_DIM) and (cand >= 0).all() and (cand <= 1).all()


# --------------------------------------------------------------------------- LearnedObjective
def _pref_model_2d(impl, dtype=torch.float64, input_transform=None):
    X = torch.rand(2, 2, dtype=dtype)
    return make_model(impl, X, torch.tensor([[0, 1]]), input_transform=input_transform)


def test_learned_objective_default_sampler(impl):
    from botorch.acquisition.objective import DEFAULT_NUM_PREF_SAMPLES

    obj = LearnedObjective(pref_model=_pref_model_2d(impl))
    samples = torch.rand(3, 2, 8, 2, **F64)
    assert obj(samples).shape == (3 * DEFAULT_NUM_PREF_SAMPLES, 2, 8)
    assert obj.sampler.base_samples.shape == (DEFAULT_NUM_PREF_SAMPLES, 3, 1, 8)
    base = obj.sampler.base_samples
    obj(torch.rand_like(samples))
    assert obj.sampler.base_samples is base  # same shape: base samples reused
    with pytest.raises(ValueError, match="at least 3 dimensions"):
        obj(torch.rand(8, 2, **F64))


def test_learned_objective_many_samples(impl):
    obj = LearnedObjective(pref_model=_pref_model_2d(impl), sample_shape=torch.Size([256]))
    assert obj(torch.rand(3, 2, 8, 2, **F64)).shape == (256 * 3, 2, 8)
    large = torch.rand(256, 2, 8, 2, **F64)
    torch.testing.assert_close(obj(large).mean(0), obj(large.flip(0)).mean(0), atol=1e-2, rtol=0)


def test_learned_objective_posterior_mean(impl):
    mean_model = PosteriorMeanModel(model=_pref_model_2d(impl))
    obj = LearnedObjective(pref_model=mean_model)
    large = torch.rand(256, 2, 8, 2, **F64)
    assert obj(large[:3]).shape == (3, 2, 8)
    torch.testing.assert_close(obj(large).mean(0), obj(large.flip(0)).mean(0))
    with pytest.raises((AssertionError, ValueError)):  # BoTorch >= 0.16 raises ValueError
        LearnedObjective(pref_model=mean_model, sample_shape=torch.Size([4]))


@pytest.mark.parametrize(
    "model_dtype,x_dtype",
    [(torch.float64, torch.float64), (torch.float32, torch.float32), (torch.float64, torch.float32)],
)
def test_learned_objective_dtypes(impl, model_dtype, x_dtype):
    obj = LearnedObjective(pref_model=_pref_model_2d(impl, model_dtype, Normalize(d=2)))
    X = torch.rand(3, 2, 8, 2, dtype=x_dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputDataWarning)
        first, second = obj(X), obj(X)
    assert first.dtype == model_dtype and torch.equal(first, second)


def test_learned_objective_mixed_precision_warns(impl):
    obj = LearnedObjective(pref_model=_pref_model_2d(impl, torch.float64, Normalize(d=2)))
    with pytest.warns(InputDataWarning):
        obj(torch.rand(3, 2, 8, 2))


# --------------------------------------------------------------------------- active learning
def test_pairwise_mc_posterior_variance(impl):
    X = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]], **F64)
    model = make_model(impl, X, torch.tensor([[0, 1]]))
    probit = torch.distributions.Normal(0, 1).cdf
    pv = PairwiseMCPosteriorVariance(model=model, objective=GenericMCObjective(lambda Y, X: probit(Y.squeeze(-1))))
    with pytest.raises(RuntimeError):
        pv(torch.rand(8, 3, 3, **F64))
    assert pv(torch.rand(8, 2, 3, **F64)).shape == (8,) and pv(torch.rand(8, 4, 3, **F64)).shape == (8,)


def test_integrated_posterior_variance(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    acqf = qNegIntegratedPosteriorVariance(
        model=model, mc_points=torch.rand(16, X_DIM, **F64), sampler=PairwiseSobolQMCNormalSampler(torch.Size([1]))
    )
    assert acqf(torch.rand(4, 2, X_DIM, **F64)).shape == (4,)


# --------------------------------------------------------------------------- input constructors
@pytest.mark.parametrize("acqf_class", [AnalyticExpectedUtilityOfBestOption, qExpectedUtilityOfBestOption])
def test_eubo_input_constructor(impl, setting, acqf_class):
    build = get_acqf_input_constructor(acqf_class)
    pref = setting["on_Y"]
    kwargs = build(model=pref)  # preferential BO: the preference model alone
    assert kwargs["outcome_model"] is None
    acqf_class(**kwargs)
    kwargs = build(model=setting["outcome_gp"], pref_model=pref)  # BOPE
    assert isinstance(kwargs["outcome_model"], FixedSingleSampleModel) and kwargs["pref_model"] is pref
    acqf_class(**kwargs)(torch.rand(2, X_DIM, **F64))
    big = build(model=setting["outcome_gp"], pref_model=pref, sample_multiplier=1e6)
    assert (big["outcome_model"].w.abs() > 10).all() and big["outcome_model"].w.shape[-1] == pref.dim


def test_eubo_input_constructor_previous_winner(impl, setting):
    build = get_acqf_input_constructor(AnalyticExpectedUtilityOfBestOption)
    winner = torch.randn(setting["on_Y"].dim, **F64)
    kwargs = build(model=setting["outcome_gp"], pref_model=setting["on_Y"], previous_winner=winner)
    assert torch.equal(kwargs["previous_winner"], winner)
    AnalyticExpectedUtilityOfBestOption(**kwargs)


# --------------------------------------------------------------------------- other acquisitions
@pytest.mark.parametrize("name", ["UCB", "qUCB", "PosteriorMean"])
def test_standard_acquisitions(impl, name):
    X, C = small_problem()
    model = make_model(impl, X, C)
    acqf = {
        "UCB": lambda: UpperConfidenceBound(model, beta=4.0),
        "qUCB": lambda: qUpperConfidenceBound(model, beta=4.0),
        "PosteriorMean": lambda: PosteriorMean(model),
    }[name]()
    values = acqf(torch.rand(5, 1, X_DIM, **F64))
    assert values.shape == (5,) and torch.isfinite(values).all()


def test_max_value_entropy(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    acqf = qMaxValueEntropy(model, candidate_set=torch.rand(64, X_DIM, **F64), num_mv_samples=8)
    values = acqf(torch.rand(5, 1, X_DIM, **F64))
    assert values.shape == (5,) and torch.isfinite(values).all()


def test_knowledge_gradient(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    acqf = qKnowledgeGradient(model, num_fantasies=None, sampler=PairwiseSobolQMCNormalSampler(torch.Size([4])))
    X_actual = torch.rand(3, 2, X_DIM, **F64)
    X_fantasies = torch.rand(4, 3, 1, X_DIM, **F64)
    assert acqf(torch.cat([X_actual, X_fantasies.permute(1, 0, 2, 3).reshape(3, 4, X_DIM)], dim=-2)).shape == (3,)


def test_learned_objective_in_qlognei(impl):
    """The BOPE step: qLogNEI on an outcome model through the learned preference objective."""
    X, Y = torch.rand(6, X_DIM, **F64), torch.rand(6, Y_DIM, **F64)
    outcome = SingleTaskGP(X, Y)
    pref = make_model(impl, Y[:4], torch.tensor([[0, 1], [2, 3]]))
    acqf = qLogNoisyExpectedImprovement(outcome, X_baseline=X, objective=LearnedObjective(pref_model=pref))
    values = acqf(torch.rand(3, 1, X_DIM, **F64))
    assert values.shape == (3,) and torch.isfinite(values).all()


def test_model_list(impl):
    X, C = small_problem()
    pref = make_model(impl, X, C)
    other = SingleTaskGP(X, X.sum(-1, keepdim=True))
    post = ModelListGP(pref, other).posterior(torch.rand(4, X_DIM, **F64))
    assert post.mean.shape == (4, 2)
