"""Ordinal ratings where ratings are used: query information, information-per-effort's binned
answers, the active-learning loop."""

import math

import numpy as np
import torch
from scipy import stats

from torchpref.acquisition.functions import QueryInformation, rating_bin_probabilities
from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood
from torchpref.models.preference_gp import PreferenceGP
from torchpref.testing import rand


def level_model(seed: int = 0) -> PreferenceGP:
    g = torch.Generator().manual_seed(seed)
    X = rand(8, 1, generator=g)
    return PreferenceGP(
        X, torch.tensor([[0, 1], [2, 3]]), torch.tensor([1.0, 5.0, 3.0]), torch.tensor([4, 5, 6]), rating_levels=5
    )


def test_rating_information_of_a_level_vs_quadrature():
    """``I(k; f)`` for ``f ~ N(m, v)`` against SciPy: 150-point Gauss-Hermite over ``f`` of the
    ordered probit's level probabilities."""
    model = level_model()
    Xq = torch.linspace(0, 1, 5, dtype=torch.float64).reshape(5, 1, 1)
    got = QueryInformation(model)(Xq)
    mean, var = (t.detach() for t in model.marginals(Xq.reshape(5, 1)))
    lik = model.likelihood.rating
    c = np.concatenate([[-np.inf], lik.cut_points.detach().numpy(), [np.inf]])
    sig = float(lik.level_noise)
    x, w = np.polynomial.hermite.hermgauss(150)
    w = w / math.sqrt(math.pi)
    ent = lambda P: -(P * np.log(np.clip(P, 1e-300, None))).sum(-1)  # noqa: E731
    for i in range(5):
        f = float(mean[i]) + math.sqrt(2 * float(var[i])) * x
        P = stats.norm.cdf((c[None, 1:] - f[:, None]) / sig) - stats.norm.cdf((c[None, :-1] - f[:, None]) / sig)
        ref = ent(w @ P) - w @ ent(P)
        assert abs(float(got[i].detach()) - ref) < 2e-3 * max(ref, 0.05), (i, float(got[i].detach()), ref)


def test_bins_of_an_ordinal_rating_are_its_levels():
    lik = OrdinalRatingLikelihood(4)
    f = torch.randn(3, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    P = rating_bin_probabilities(f, lik, num_bins=10)
    assert P.shape == (3, 2, 4)
    torch.testing.assert_close(P, lik(f).probs)


def test_active_learning_with_levels_and_information_per_effort():
    """The loop runs with an ordinal model and a rating answer in [0, 1] becomes its level."""
    from torchpref.data.queries import BoxCandidates
    from torchpref.selection.active import run_active_learning
    from torchpref.selection.strategies import InformationPerEffort, RandomRatings
    from torchpref.simulation.users import SimulatedUser

    user = SimulatedUser(lambda X: torch.sin(6 * X[:, 0]), 0.05, 0.8, 80.0, generator=torch.Generator().manual_seed(3))
    box = BoxCandidates(torch.tensor([[0.0], [1.0]], dtype=torch.float64), 30)
    for selector in (RandomRatings(), InformationPerEffort(m=3, num_samples=64)):
        model = level_model(2)
        n0, p0 = model.ratings.numel(), model.comparisons.shape[0]
        hist = run_active_learning(model, user, box, selector, 4, generator=torch.Generator().manual_seed(4))
        new = model.ratings[n0:]
        assert new.numel() == sum(r.query.kind == "rating" for r in hist.records)
        assert ((new >= 1) & (new <= 5) & (new == new.round())).all()
        assert new.numel() + model.comparisons.shape[0] - p0 >= 4
    assert isinstance(selector, InformationPerEffort)
