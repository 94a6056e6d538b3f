"""One home for an answer's probability: the comparison likelihoods' ``choice_probabilities``
against SciPy quadrature and brute-force simulation, lapses included; the selectors and
``QueryInformation`` value a lapsing person's rankings through it."""

import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from torchpref import PreferenceGP
from torchpref.acquisition.functions import QueryInformation, choice_probabilities
from torchpref.likelihoods.pairwise_beta import PairwiseProbitLikelihood
from torchpref.likelihoods.person import LapseProbitLikelihood
from torchpref.models.calibration import calibrate_person
from torchpref.selection.variance_reduction import VariancePerEffort

D = torch.float64


def _quad(f: np.ndarray, sigma: float) -> np.ndarray:
    """P(j best) = int phi(e) prod_{k != j} Phi((f_j + sigma e - f_k) / sigma) de, by SciPy."""
    out = []
    for j in range(len(f)):
        others = np.delete(f, j)

        def integrand(e, j=j, others=others):
            return stats.norm.pdf(e) * np.prod(stats.norm.cdf((f[j] + sigma * e - others) / sigma))

        out.append(integrate.quad(integrand, -12, 12, epsabs=1e-13)[0])
    return np.array(out)


@pytest.mark.parametrize("q", [2, 3, 5])
@pytest.mark.parametrize("sigma", [0.2, 1.0])
def test_choice_probabilities_against_scipy_quadrature(q, sigma):
    g = torch.Generator().manual_seed(q)
    f = 0.6 * torch.randn(4, q, generator=g, dtype=D)
    lik = PairwiseProbitLikelihood(sigma).to(D)
    P = lik.choice_probabilities(f, num_quadrature=24)
    for b in range(4):
        np.testing.assert_allclose(P[b].detach().numpy(), _quad(f[b].numpy(), sigma), atol=1e-6)
    if q == 2:  # eq. 3 exactly
        ref = stats.norm.cdf((f[:, 0] - f[:, 1]).numpy() / (math.sqrt(2) * sigma))
        np.testing.assert_allclose(P[:, 0].detach().numpy(), ref, rtol=1e-12)
    torch.testing.assert_close(choice_probabilities(f, sigma, 24), P.detach())  # the function without lapses


@pytest.mark.parametrize("eps", [0.05, 0.3])
def test_lapses_against_brute_force_simulation(eps):
    """A person who lapses with probability eps picks uniformly, else the noisiest-best item."""
    f = torch.tensor([0.4, 0.0, -0.3, 0.1], dtype=D)
    sigma, n = 0.3, 400_000
    lik = LapseProbitLikelihood(sigma, eps).to(D)
    P = lik.choice_probabilities(f, num_quadrature=24).detach()
    g = torch.Generator().manual_seed(1)
    noisy = (f + sigma * torch.randn(n, 4, generator=g, dtype=D)).argmax(-1)
    lapse = torch.rand(n, generator=g, dtype=D) < eps
    chosen = torch.where(lapse, torch.randint(4, (n,), generator=g), noisy)
    freq = torch.bincount(chosen, minlength=4).to(D) / n
    torch.testing.assert_close(freq, P, atol=4e-3, rtol=0)  # ~5 binomial SDs
    # a pair's answer is the likelihood's own forward (eq. 3 with lapses)
    pair = lik.choice_probabilities(f[:2].unsqueeze(0))[0, 0]
    fwd = lik(f[:2], torch.tensor([[0, 1]])).probs[0]
    torch.testing.assert_close(pair, fwd)
    # and the plain probit's are the lapse-free ones
    plain = PairwiseProbitLikelihood(sigma).to(D).choice_probabilities(f, num_quadrature=24).detach()
    torch.testing.assert_close(P, eps / 4 + (1 - eps) * plain)


def _ratings_model(seed=3):
    """A model with ratings only: its posterior does not depend on the lapse rate."""
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(8, 2, generator=g, dtype=D)
    model = PreferenceGP(X, ratings=torch.tensor([0.8, 0.3, 0.6], dtype=D), rating_index=torch.tensor([0, 3, 5]))
    return model, X


def test_query_information_values_a_lapsing_persons_rankings_less():
    """Fails on the old QueryInformation, which valued rankings without the lapse rate."""
    model, X = _ratings_model()
    calibrate_person(model, lapse_rate=1e-5)
    ranking, rating = X[[1, 2, 4]].unsqueeze(0), X[[6]].unsqueeze(0)
    acq = QueryInformation(model, generator=torch.Generator().manual_seed(0))
    reliable, reliable_rating = float(acq(ranking).detach()), float(acq(rating).detach())
    model.likelihood.comparison.lapse_rate = 0.3
    acq = QueryInformation(model, generator=torch.Generator().manual_seed(0))
    lapsing, lapsing_rating = float(acq(ranking).detach()), float(acq(rating).detach())
    assert lapsing < 0.8 * reliable
    assert lapsing_rating == pytest.approx(reliable_rating, rel=1e-9)  # ratings untouched: same posterior


def test_variance_selector_values_a_lapsing_persons_rankings_less():
    model, X = _ratings_model()
    calibrate_person(model, lapse_rate=1e-5)
    sel = VariancePerEffort(m=3, rating_cost=1.0, ranking_cost=1.0)
    Xc = X.unsqueeze(0)
    _, rating0, _, ranking0 = sel.values(model, Xc, [torch.Generator().manual_seed(0)])
    model.likelihood.comparison.lapse_rate = 0.3
    _, rating1, _, ranking1 = sel.values(model, Xc, [torch.Generator().manual_seed(0)])
    assert float(ranking1) < float(ranking0)
    torch.testing.assert_close(rating1, rating0)
