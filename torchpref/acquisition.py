r"""Acquisition functions over queries, in BoTorch's convention (``b x q x d`` -> ``b``).

A batch of ``q = 1`` point is a rating query; ``q = m >= 2`` points are a best-of-``m``
ranking query. So one acquisition function values both query types and a selector
(:mod:`torchpref.strategies`) compares them.

* :func:`latent_ucb`: eq. 12's UCB on the latent utility, BoTorch's own
  ``UpperConfidenceBound`` with ``beta = gamma^2`` (the paper's ``gamma = 3`` is ``beta = 9``).
* :class:`QueryUCB`: the largest UCB among a query's items (eq. 12 for ``q = 1``).
* :class:`QueryInformation`: the mutual information between a query's answer and the latent
  utility, ``I(y; f) = H[y] - E_f H[y | f]``, under the model's own noise: a Beta rating
  (eqs. 4-7) or a best-of-``q`` choice where each item's utility is seen with
  ``N(0, sigma_R^2)`` noise (eq. 3; for ``q = 2`` exactly the probit).
* :func:`sample_information`: the same quantity, or the information about a discrete target
  such as the location of the maximum (entropy search), from joint posterior samples and the
  answer's probabilities under each (:func:`choice_probabilities`,
  :func:`rating_bin_probabilities`); what :class:`~torchpref.strategies.InformationPerEffort`
  uses.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from botorch.acquisition import AcquisitionFunction, UpperConfidenceBound
from botorch.utils.transforms import t_batch_mode_transform
from torch import Tensor
from torch.distributions import Beta

from torchpref.numerics import log_ndtr


def latent_ucb(model, gamma: float = 3.0) -> UpperConfidenceBound:
    r"""Eq. 12, ``mean + gamma * std`` of the latent utility, as BoTorch's UCB (``beta = gamma^2``)."""
    return UpperConfidenceBound(model, beta=gamma**2)


class QueryUCB(AcquisitionFunction):
    r"""``max_i mean(x_i) + gamma * std(x_i)`` over a query's ``q`` items (eq. 12 for ``q = 1``)."""

    def __init__(self, model, gamma: float = 3.0):
        super().__init__(model)
        self.gamma = gamma

    @t_batch_mode_transform()
    def forward(self, X: Tensor) -> Tensor:
        post = self.model.posterior(X)
        ucb = post.mean.squeeze(-1) + self.gamma * post.variance.squeeze(-1).clamp_min(0).sqrt()
        return ucb.max(dim=-1).values


class QueryInformation(AcquisitionFunction):
    r"""Expected information (nats) that a query's answer carries about the latent utility.

    ``q = 1``: a rating ``u ~ Beta(nu mu(f), nu (1 - mu(f)))`` with ``f ~ N(m, v)``; computed by
    Gauss-Hermite quadrature over ``f`` (closed-form Beta entropies) and a midpoint grid over
    ``u`` for the predictive entropy.

    ``q >= 2``: the index of the best item when each utility is seen with ``N(0, sigma_R^2)``
    noise; ``P(j | f) = E_eps prod_{k != j} Phi((f_j + eps - f_k) / sigma_R)`` by Gauss-Hermite,
    and ``I = H[mean_s P(. | f_s)] - mean_s H[P(. | f_s)]`` over ``num_samples`` joint posterior
    samples (common random numbers from ``generator``, so values are comparable across queries).

    Args:
        model: a :class:`~torchpref.PreferenceGP`.
        num_samples: posterior samples for ranking queries.
        generator: seeds those samples.
    """

    def __init__(self, model, num_samples: int = 128, generator: torch.Generator | None = None,
                 num_quadrature: int = 24, num_grid: int = 400):
        super().__init__(model)
        self.num_samples = num_samples
        self.num_quadrature = num_quadrature
        self.num_grid = num_grid
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        self._seed = int(torch.randint(0, 2**31 - 1, (1,), generator=g))

    def _gh(self, like: Tensor) -> tuple[Tensor, Tensor]:
        x, w = np.polynomial.hermite.hermgauss(self.num_quadrature)
        return like.new_tensor(x), like.new_tensor(w) / math.sqrt(math.pi)

    @t_batch_mode_transform()
    def forward(self, X: Tensor) -> Tensor:
        post = self.model.posterior(X)
        if X.shape[-2] == 1:
            return self._rating_information(post.mean[..., 0, 0], post.variance[..., 0, 0])
        mvn = post.distribution
        return self._ranking_information(mvn.mean, mvn.covariance_matrix)

    def _rating_information(self, mean: Tensor, var: Tensor) -> Tensor:
        lik = self.model.likelihood.rating
        x, w = self._gh(mean)
        f = mean.unsqueeze(-1) + torch.sqrt(2 * var.clamp_min(0)).unsqueeze(-1) * x  # b x H
        _, _, nu, a, b = lik._shape(f)
        # far-out quadrature nodes can underflow a Beta shape to 0; its entropy term has weight ~0
        tiny = torch.finfo(f.dtype).tiny
        beta = Beta(a.clamp_min(tiny), b.clamp_min(tiny), validate_args=False)
        cond_entropy = (w * beta.entropy()).sum(-1)
        u = (torch.arange(self.num_grid, dtype=mean.dtype, device=mean.device) + 0.5) / self.num_grid
        logp = lik.log_prob(f.unsqueeze(-1), u)  # b x H x G
        log_mix = torch.logsumexp(logp + torch.log(w).unsqueeze(-1), dim=-2)  # b x G
        entropy = -(torch.exp(log_mix) * log_mix).sum(-1) / self.num_grid
        return (entropy - cond_entropy).clamp_min(0)

    def _choice_probabilities(self, f: Tensor) -> Tensor:
        """``... x q`` utilities -> ``... x q`` probabilities that each is chosen."""
        s = self.model.likelihood.comparison.comparison_noise
        x, w = self._gh(f)
        diff = (f.unsqueeze(-1) - f.unsqueeze(-2)) / s  # ... x j x k
        z = diff.unsqueeze(-1) + math.sqrt(2) * x  # ... x j x k x H
        lp = log_ndtr(z)
        q = f.shape[-1]
        eye = torch.eye(q, dtype=torch.bool, device=f.device).unsqueeze(-1)
        lp = lp.masked_fill(eye, 0.0).sum(-2)  # ... x j x H
        p = (torch.exp(lp) * w).sum(-1)
        return p / p.sum(-1, keepdim=True)

    def _ranking_information(self, mean: Tensor, cov: Tensor) -> Tensor:
        q = mean.shape[-1]
        g = torch.Generator(device=mean.device).manual_seed(self._seed)
        z = torch.randn(self.num_samples, q, generator=g, dtype=mean.dtype, device=mean.device)
        jitter = 1e-9 * torch.eye(q, dtype=mean.dtype, device=mean.device)
        L = torch.linalg.cholesky_ex(cov + jitter)[0]
        f = mean.unsqueeze(-2) + z @ L.mT  # b x S x q
        p = self._choice_probabilities(f)
        ent = lambda P: -(P * torch.log(P.clamp_min(1e-300))).sum(-1)  # noqa: E731
        return (ent(p.mean(-2)) - ent(p).mean(-1)).clamp_min(0)


def _entropy(P: Tensor) -> Tensor:
    return -(P * torch.log(P.clamp_min(1e-300))).sum(-1)


def choice_probabilities(f: Tensor, comparison_noise: float | Tensor, num_quadrature: int = 6) -> Tensor:
    r"""``... x q`` utilities -> ``... x q`` probabilities that each item is chosen as the best when
    each utility is seen with ``N(0, sigma_R^2)`` noise (eq. 3):
    ``P(j | f) = E_eps prod_{k != j} Phi((f_j + eps - f_k) / sigma_R)``, Gauss-Hermite over eps."""
    x, w = np.polynomial.hermite.hermgauss(num_quadrature)
    x, w = f.new_tensor(x), f.new_tensor(w) / math.sqrt(math.pi)
    diff = (f.unsqueeze(-1) - f.unsqueeze(-2)) / comparison_noise  # ... x j x k
    lp = log_ndtr(diff.unsqueeze(-1) + math.sqrt(2) * x)  # ... x j x k x H
    q = f.shape[-1]
    eye = torch.eye(q, dtype=torch.bool, device=f.device).unsqueeze(-1)
    p = (torch.exp(lp.masked_fill(eye, 0.0).sum(-2)) * w).sum(-1)
    return p / p.sum(-1, keepdim=True)


def rating_bin_probabilities(f: Tensor, rating_likelihood, num_bins: int = 32) -> Tensor:
    r"""``...`` utilities -> ``... x num_bins``: the probability of a rating in each of
    ``num_bins`` equal bins of ``[0, 1]`` (Beta density of eqs. 4-7 at the bins' midpoints,
    normalised). A binned rating carries at most the information of the rating itself."""
    u = (torch.arange(num_bins, dtype=f.dtype, device=f.device) + 0.5) / num_bins
    logp = rating_likelihood.log_prob(f.unsqueeze(-1), u)
    return torch.softmax(logp, dim=-1)


def sample_information(P: Tensor, labels: Tensor | None = None, num_labels: int | None = None) -> Tensor:
    r"""Mutual information (nats) between a query's answer and a target, from posterior samples.

    ``I(y; T) = H[E_s P(y | f_s)] - E_T H[P(y | T)]`` with ``P(y | T = t)`` the mean of
    ``P(y | f_s)`` over the samples whose target is ``t``.

    Args:
        P: ``batch x S x Y`` answer probabilities under each of ``S`` joint posterior samples.
        labels: ``S`` long, the discrete target of each sample (e.g. the index of its
            maximiser: information about where the maximum is). ``None``: the target is the
            utility itself, ``I(y; f) = H[E_s P] - E_s H[P_s]``.
        num_labels: number of possible labels (default ``labels.max() + 1``).

    Returns:
        ``batch`` informations, clamped at 0.
    """
    h_marginal = _entropy(P.mean(-2))
    if labels is None:
        return (h_marginal - _entropy(P).mean(-1)).clamp_min(0)
    S = P.shape[-2]
    k = int(labels.max()) + 1 if num_labels is None else num_labels
    onehot = torch.nn.functional.one_hot(labels, k).to(P)  # S x k
    counts = onehot.sum(0)  # k
    used = counts > 0
    onehot, counts = onehot[:, used], counts[used]
    P_t = (onehot.mT @ P) / counts.unsqueeze(-1)  # batch x k x Y
    return (h_marginal - (counts / S * _entropy(P_t)).sum(-1)).clamp_min(0)
