r"""Acquisition functions over queries, in BoTorch's convention (``b x q x d`` -> ``b``).

A batch of ``q = 1`` point is a rating query; ``q = m >= 2`` points are a best-of-``m``
ranking query. So one acquisition function values both query types and a selector
(:mod:`torchpref.selection.strategies`) compares them.

* :func:`latent_ucb`: eq. 12's UCB on the latent utility, BoTorch's own
  ``UpperConfidenceBound`` with ``beta = gamma^2`` (the paper's ``gamma = 3`` is ``beta = 9``).
* :func:`item_ucb`: eq. 12 at each point (with the posterior mean and std), what the UCB
  selectors rank by; :class:`QueryUCB`: the largest UCB among a query's items.
* :class:`QueryInformation`: the mutual information between a query's answer and the latent
  utility, ``I(y; f) = H[y] - E_f H[y | f]``, under the model's own noise: a Beta rating
  (eqs. 4-7) or a best-of-``q`` choice where each item's utility is seen with
  ``N(0, sigma_R^2)`` noise (eq. 3; for ``q = 2`` exactly the probit).
* :func:`choice_probabilities`, :func:`rating_bin_probabilities`: an answer's probabilities
  under each joint posterior sample.
* From :mod:`torchpref.acquisition.information` (and importable from here): :func:`sample_information`, the
  same information or that about a discrete target such as the location of the maximum, from
  those probabilities; :func:`membership_information`, the summed information about each item's
  membership of a set such as each sample's top set (:func:`top_set_membership`). From
  :mod:`torchpref.acquisition.choice_sets`: :func:`greedy_choice_set`, a best-of-``m`` query that maximises
  any such value. What :class:`~torchpref.selection.strategies.InformationPerEffort` uses.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from botorch.acquisition import AcquisitionFunction, UpperConfidenceBound
from botorch.models.model import Model
from botorch.posteriors import GPyTorchPosterior
from botorch.utils.transforms import t_batch_mode_transform
from torch import Tensor
from torch.distributions import Beta

from torchpref.acquisition.choice_sets import greedy_choice_set
from torchpref.acquisition.information import entropy, membership_information, sample_information, top_set_membership
from torchpref.inference.numerics import gauss_hermite
from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood
from torchpref.likelihoods.pairwise_beta import thurstone_choice_probabilities
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.defaults import preference_likelihood
from torchpref.models.preference_gp import PreferenceGP

__all__ = [
    "QueryInformation",
    "QueryUCB",
    "choice_probabilities",
    "greedy_choice_set",
    "item_ucb",
    "latent_ucb",
    "membership_information",
    "rating_bin_probabilities",
    "sample_information",
    "top_set_membership",
]


def latent_ucb(model: Model, gamma: float = 3.0) -> UpperConfidenceBound:
    r"""Eq. 12, ``mean + gamma * std`` of the latent utility, as BoTorch's UCB (``beta = gamma^2``).

    Raises:
        ValueError: ``gamma`` negative (``beta = gamma^2`` would turn it into ``+|gamma|``) or not finite.
    """
    if not math.isfinite(gamma) or gamma < 0:
        raise ValueError(f"gamma must be a finite number >= 0, got {gamma}.")
    return UpperConfidenceBound(model, beta=gamma**2)


def item_ucb(model: Model, X: Tensor, gamma: float = 3.0) -> tuple[Tensor, Tensor, Tensor]:
    r"""Eq. 12's ``mean + gamma * std`` of the latent utility at each point of ``X`` (``... x d``),
    with the posterior mean and std (each ``...``). Uses the marginals of a
    :class:`~torchpref.PreferenceGP` or a :class:`~torchpref.BatchedPreferenceGP` (``T x N x d``
    points), else any BoTorch model's posterior."""
    if isinstance(model, (PreferenceGP, BatchedPreferenceGP)):
        mean, var = model.marginals(X)
    else:
        post: Any = model.posterior(X.unsqueeze(-2))  # any posterior with a mean and a variance
        mean, var = post.mean[..., 0, 0], post.variance[..., 0, 0]
    std = var.clamp_min(0).sqrt()
    return mean + gamma * std, mean, std


class QueryUCB(AcquisitionFunction):
    r"""``max_i mean(x_i) + gamma * std(x_i)`` over a query's ``q`` items (eq. 12 for ``q = 1``;
    :func:`item_ucb`)."""

    def __init__(self, model: Model, gamma: float = 3.0):
        super().__init__(model)
        self.gamma = gamma

    @t_batch_mode_transform()  # type: ignore[arg-type]  # BoTorch types it for the base class only
    def forward(self, X: Tensor) -> Tensor:
        return item_ucb(self.model, X, self.gamma)[0].max(dim=-1).values


class QueryInformation(AcquisitionFunction):
    r"""Expected information (nats) that a query's answer carries about the latent utility.

    ``q = 1``: a rating ``u ~ Beta(nu mu(f), nu (1 - mu(f)))`` with ``f ~ N(m, v)``; computed by
    Gauss-Hermite quadrature over ``f`` (closed-form Beta entropies) and a midpoint grid over
    ``u`` for the predictive entropy. For a model with ordinal ratings (``rating_levels``), the
    level ``k``: ``H[E_f P(k | f)] - E_f H[P(k | f)]`` by the same quadrature over ``f``.

    ``q >= 2``: the index of the best item, with the probabilities of the model's comparison
    likelihood (:meth:`~torchpref.likelihoods.pairwise_beta.PairwiseProbitLikelihood.choice_probabilities`:
    each utility seen with ``N(0, sigma_R^2)`` noise, ``P(j | f) = E_eps prod_{k != j} Phi((f_j +
    eps - f_k) / sigma_R)`` by Gauss-Hermite, and a lapsing person's lapses mixed in),
    and ``I = H[mean_s P(. | f_s)] - mean_s H[P(. | f_s)]`` over ``num_samples`` joint posterior
    samples (common random numbers from ``generator``, so values are comparable across queries).

    Args:
        model: a :class:`~torchpref.PreferenceGP`.
        num_samples: posterior samples for ranking queries.
        generator: seeds those samples.
    """

    def __init__(
        self,
        model: Model,
        num_samples: int = 128,
        generator: torch.Generator | None = None,
        num_quadrature: int = 24,
        num_grid: int = 400,
    ):
        super().__init__(model)
        self.num_samples = num_samples
        self.num_quadrature = num_quadrature
        self.num_grid = num_grid
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        self._seed = int(torch.randint(0, 2**31 - 1, (1,), generator=g))

    @t_batch_mode_transform()  # type: ignore[arg-type]  # BoTorch types it for the base class only
    def forward(self, X: Tensor) -> Tensor:
        post = self.model.posterior(X)
        if not isinstance(post, GPyTorchPosterior):
            raise ValueError(f"QueryInformation needs a Gaussian posterior, got a {type(post).__name__}.")
        if X.shape[-2] == 1:
            return self._rating_information(post.mean[..., 0, 0], post.variance[..., 0, 0])
        mvn = post.distribution
        return self._ranking_information(mvn.mean, mvn.covariance_matrix)

    def _rating_information(self, mean: Tensor, var: Tensor) -> Tensor:
        lik = preference_likelihood(self.model).rating
        x, w = gauss_hermite(self.num_quadrature, mean)
        f = mean.unsqueeze(-1) + torch.sqrt(2 * var.clamp_min(0)).unsqueeze(-1) * x  # b x H
        if isinstance(lik, OrdinalRatingLikelihood):  # a level: H[E_f P(k | f)] - E_f H[P(k | f)]
            P = lik(f).probs  # b x H x K
            return (entropy((w.unsqueeze(-1) * P).sum(-2)) - (w * entropy(P)).sum(-1)).clamp_min(0)
        a, b = lik.beta_parameters(f)
        # far-out quadrature nodes can underflow a Beta shape to 0; its entropy term has weight ~0
        tiny = torch.finfo(f.dtype).tiny
        beta = Beta(a.clamp_min(tiny), b.clamp_min(tiny), validate_args=False)
        cond_entropy = (w * beta.entropy()).sum(-1)
        u = (torch.arange(self.num_grid, dtype=mean.dtype, device=mean.device) + 0.5) / self.num_grid
        logp = lik.log_prob(f.unsqueeze(-1), u)  # b x H x G
        log_mix = torch.logsumexp(logp + torch.log(w).unsqueeze(-1), dim=-2)  # b x G
        h_answer = -(torch.exp(log_mix) * log_mix).sum(-1) / self.num_grid
        return (h_answer - cond_entropy).clamp_min(0)

    def _ranking_information(self, mean: Tensor, cov: Tensor) -> Tensor:
        q = mean.shape[-1]
        g = torch.Generator(device=mean.device).manual_seed(self._seed)
        z = torch.randn(self.num_samples, q, generator=g, dtype=mean.dtype, device=mean.device)
        jitter = 1e-9 * torch.eye(q, dtype=mean.dtype, device=mean.device)
        L = torch.linalg.cholesky_ex(cov + jitter)[0]
        f = mean.unsqueeze(-2) + z @ L.mT  # b x S x q
        p = preference_likelihood(self.model).comparison.choice_probabilities(f, self.num_quadrature)  # lapses included
        return sample_information(p)


def choice_probabilities(f: Tensor, comparison_noise: float | Tensor, num_quadrature: int = 6) -> Tensor:
    r"""``... x q`` utilities -> ``... x q`` probabilities that each item is chosen as the best when
    each utility is seen with ``N(0, sigma_R^2)`` noise (eq. 3), without lapses:
    :func:`~torchpref.likelihoods.pairwise_beta.thurstone_choice_probabilities`. The model's own
    answer probabilities (lapses included) are its comparison likelihood's
    :meth:`~torchpref.likelihoods.pairwise_beta.PairwiseProbitLikelihood.choice_probabilities`."""
    return thurstone_choice_probabilities(f, comparison_noise, num_quadrature)


def rating_bin_probabilities(f: Tensor, rating_likelihood: Any, num_bins: int = 32) -> Tensor:
    r"""``...`` utilities -> ``... x num_bins``: the probability of a rating in each of
    ``num_bins`` equal bins of ``[0, 1]`` (Beta density of eqs. 4-7 at the bins' midpoints,
    normalised). A binned rating carries at most the information of the rating itself. For an
    :class:`~torchpref.likelihoods.ordinal.OrdinalRatingLikelihood` the bins are its ``K`` levels (``... x K``,
    exact; ``num_bins`` is not used)."""
    if isinstance(rating_likelihood, OrdinalRatingLikelihood):
        return rating_likelihood(f).probs
    u = (torch.arange(num_bins, dtype=f.dtype, device=f.device) + 0.5) / num_bins
    # bins first: the softmax then runs over contiguous rows (a short last dimension is slow)
    logp = rating_likelihood.log_prob(f.unsqueeze(0), u.reshape(num_bins, *([1] * f.dim())))
    return torch.softmax(logp, dim=0).movedim(0, -1)
