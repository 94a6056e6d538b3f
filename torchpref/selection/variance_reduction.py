r"""Expected reduction of the top region's rating-scale variance per unit of effort.

Notation (one trial; the code is batched over ``T`` trials): ``N`` candidates with Laplace
posterior ``f ~ N(m, Sigma)``; ``S`` joint posterior samples ``f^(s)``.

**What a query buys.** Laplace inference adds an answer's negative log-likelihood Hessian to the
posterior precision, ``Sigma' = (Sigma^-1 + H)^-1``. For a query on items ``Q`` with ``H`` zero
outside ``Q`` (Woodbury)

.. math::

    \Sigma - \Sigma' = \Sigma_{:Q} (I + H \Sigma_{QQ})^{-1} H \Sigma_{Q:} .

``H`` is the answer's *expected* Hessian, averaged over the posterior and the answer:

* a rating of item ``i``: ``H = E_f[I(f_i)]``, the rating likelihood's Fisher information
  (``likelihood.fisher``; Beta: ``nu^2 (psi'(a) + psi'(b)) mu'^2``);
* a best-of-``m`` choice: the answer "``j`` is best" adds the comparisons ``j > k``, ``k != j``
  (eq. 3), each ``kappa(f_j - f_k) (e_j - e_k)(e_j - e_k)^T`` with ``kappa`` the probit's
  negative second derivative; ``H = E_f[sum_j P(j | f) sum_{k != j} kappa(f_j - f_k) (e_j -
  e_k)(e_j - e_k)^T]``, a weighted graph Laplacian: it informs differences only.

A rating informs an item's absolute level; a ranking only the differences between its items.

**What it is worth.** The loss is the posterior variance of the rating-scale utility
``u_i = Phi(f_i / (sqrt 2 sigma_B))`` (eq. 7's mean) summed over the candidates with weights
``w_i = P(f_i in the top k)`` (from the samples): ``L = sum_i w_i Var(u_i) ~ sum_i w_i g_i^2
Sigma_ii`` with ``g_i`` the slope of the expected rating ``Phi(m_i / sqrt(2 sigma_B^2 +
Sigma_ii))`` in ``m_i`` (delta method). A query's value is ``L - L'``, its expected reduction,
divided by its effort. The top region's levels are what the rating error (WRMS) weighs most
and its order what true positives and regret score; both are variances of the same ``u`` here,
so a rating (the level) and a ranking (the order) are valued on one scale.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from gpytorch.likelihoods import Likelihood
from torch import Tensor

from torchpref.acquisition.functions import choice_probabilities
from torchpref.acquisition.information import top_set_membership
from torchpref.models.defaults import preference_likelihood
from torchpref.selection.samples import SelectorModel, joint_posterior, joint_samples
from torchpref.selection.strategies import PerEffortSelector, effort_model


def rating_hessian(F: Tensor, rating_likelihood: Likelihood) -> Tensor:
    r"""Expected Hessian of one rating of each item: ``E_f[I(f_i)]`` over samples.

    Args:
        F: ``... x S x N`` joint posterior samples.
        rating_likelihood: has ``fisher(f)`` (the Fisher information of a rating at ``f``).

    Returns:
        ``... x N``.
    """
    return rating_likelihood.fisher(F).mean(-2)


def choice_answer_probabilities(F: Tensor, comparison: Likelihood | Tensor, num_quadrature: int = 6) -> Tensor:
    r"""Predictive probability that each of ``q`` items is chosen as the best, ``... x q``, the
    mean over ``S`` posterior samples ``F`` (``... x S x q``) of the comparison likelihood's
    :meth:`~torchpref.likelihoods.pairwise_beta.PairwiseProbitLikelihood.choice_probabilities`
    (lapses included); a bare ``sigma_R`` tensor gives eq. 3's Thurstone choice without lapses."""
    if isinstance(comparison, Tensor):
        return choice_probabilities(F, comparison, num_quadrature).mean(-2)
    return comparison.choice_probabilities(F, num_quadrature).mean(-2)


def ranking_mode_hessians(mean: Tensor, cov: Tensor, comparison_likelihood: Likelihood, num_iter: int = 12) -> Tensor:
    r"""The Hessian a best-of-``q`` answer adds at the new Laplace mode, for each answer.

    Answer ``j`` (item ``j`` is best) adds the comparisons ``j > k``, ``k != j``: the log
    likelihood ``l_j(f) = sum_{k != j} log Phi((f_j - f_k) / (sqrt 2 sigma_R))``. Its mode under
    the Gaussian ``N(mean, cov)`` of the items' utilities is found by Newton's method, ``f = mean
    + g`` with ``g <- cov (I + W cov)^-1 (W g + grad l_j)`` (backtracking if the objective
    would decrease), and ``W = -grad^2 l_j`` there is returned: a star-graph Laplacian,
    ``sum_{k != j} w_k (e_j - e_k)(e_j - e_k)^T``. Unlike the Fisher information averaged over
    the prior, it is small where the answer, once given, leaves no doubt (a comparison far from
    a tie under the new mode), as the Laplace posterior is.

    Args:
        mean: ``... x q`` posterior mean of the query's items.
        cov: ``... x q x q`` their posterior covariance.
        comparison_likelihood: has ``derivatives(eta)`` (``log p`` and its first two
            derivatives in ``eta = f_preferred - f_other``).
        num_iter: Newton iterations.

    Returns:
        ``... x q x q x q``: for each answer ``j`` (dim ``-3``) the ``q x q`` Hessian.
    """
    q = mean.shape[-1]
    eye = torch.eye(q, dtype=mean.dtype, device=mean.device)
    off = 1.0 - eye  # J x k: the comparisons of answer J
    m = mean.unsqueeze(-2).expand(*mean.shape[:-1], q, q)  # ... x J x q
    C = cov.unsqueeze(-3)  # ... x 1 x q x q

    def parts(g: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        f = m + g
        eta = (f.diagonal(dim1=-2, dim2=-1).unsqueeze(-1) - f) * off  # f_J - f_k, 0 at k = J
        lp, d1, d2 = comparison_likelihood.derivatives(eta)
        lp, d1, w = lp * off, d1 * off, -d2 * off
        grad = eye * d1.sum(-1, keepdim=True) - d1  # d l_J / d f_k
        W = torch.diag_embed(w + eye * w.sum(-1, keepdim=True)) - (
            w.unsqueeze(-1) * eye.unsqueeze(-2) + w.unsqueeze(-2) * eye.unsqueeze(-1)
        )
        return lp.sum(-1), grad, W

    def objective(g: Tensor, lp: Tensor) -> Tensor:
        return lp - 0.5 * (g * torch.linalg.solve(C + 1e-10 * eye, g.unsqueeze(-1)).squeeze(-1)).sum(-1)

    g = torch.zeros_like(m)
    lp, grad, W = parts(g)
    obj = objective(g, lp)
    for _ in range(num_iter):
        rhs = (W @ g.unsqueeze(-1)).squeeze(-1) + grad
        step = (C @ torch.linalg.solve(eye + W @ C, rhs.unsqueeze(-1))).squeeze(-1) - g
        t = torch.ones_like(obj)
        for _ in range(4):  # halve the step where the objective would decrease
            lp_new, grad_new, W_new = parts(g + t.unsqueeze(-1) * step)
            obj_new = objective(g + t.unsqueeze(-1) * step, lp_new)
            t = torch.where(obj_new >= obj - 1e-12, t, 0.5 * t)
        g = g + t.unsqueeze(-1) * step
        lp, grad, W = parts(g)
        obj = objective(g, lp)
    return W


def variance_reduction(cov: Tensor, weights: Tensor, rows: Tensor, H: Tensor, slopes: Tensor | None = None) -> Tensor:
    r"""``sum_i weights_i (Var(v_i) - Var'(v_i))`` for queries on the items ``rows``, ``v_i =
    slopes_i f_i`` (the linearised rating-scale utility; module notes).

    Args:
        cov: ``T x N x N`` posterior covariance ``Sigma``.
        weights: ``T x N``.
        rows: ``T x R x q`` long, the items of ``R`` queries per trial.
        H: ``T x R x q x q`` their Hessians.
        slopes: ``T x N`` (default 1).

    Returns:
        ``T x R``.
    """
    T, R, q = rows.shape
    N = cov.shape[-1]
    cross = cov.gather(1, rows.reshape(T, R * q, 1).expand(T, R * q, N)).reshape(T, R, q, N)  # Sigma_Q:
    block = cross.gather(3, rows.unsqueeze(-2).expand(T, R, q, q))  # Sigma_QQ
    eye = torch.eye(q, dtype=cov.dtype, device=cov.device)
    M = torch.linalg.solve(eye + H @ block, H)  # (I + H Sigma_QQ)^-1 H, symmetric
    w = weights.reshape(T, 1, 1, N)
    if slopes is not None:
        cross = cross * slopes.reshape(T, 1, 1, N)  # Cov(f_Q, v)
    return ((M @ cross) * cross * w).sum((-1, -2))  # sum_i w_i c_i^T M c_i


class VariancePerEffort(PerEffortSelector):
    r"""Ask the query of largest expected reduction of the top region's rating-scale variance per
    unit of effort (:mod:`torchpref.selection.variance_reduction`).

    Weights ``w_i g_i^2``: ``w_i`` the posterior probability that candidate ``i`` is among the
    ``k = round(top_fraction * N)`` best (``num_samples`` joint samples), ``g_i`` the slope of
    its expected rating. Every candidate's rating is valued; a best-of-``m`` ranking is built
    greedily among the ``num_plausible`` candidates of largest weighted variance ``w_i g_i^2
    Sigma_ii`` (start from the best pair, add the item that adds most). The larger of the best
    rating's and the best ranking's value per effort is asked. Answers are valued under the
    model's own likelihoods.

    Args:
        m: items per ranking query.
        rating_cost: effort of one rating.
        ranking_cost: effort of one best-of-``m`` choice (default ``1 + (m - 1) / 4``).
        num_samples: joint posterior samples (the top-set weights).
        num_hessian_samples: the first this many of them average the rankings' expected
            Hessians and the ratings' Fisher informations (smooth averages: fewer suffice; a
            ranking costs ``m^2`` Gauss-Hermite terms per sample).
        top_fraction: the top set's share of the candidates.
        num_plausible: candidates a ranking is built from.
    """

    name = "variance per effort"

    def __init__(
        self,
        m: int = 5,
        rating_cost: float = 1.0,
        ranking_cost: float | None = None,
        num_samples: int = 128,
        top_fraction: float = 0.2,
        num_plausible: int = 15,
        num_hessian_samples: int = 32,
    ):
        m, rating_cost, ranking_cost = effort_model(m, rating_cost, ranking_cost)
        if num_samples < 2 or num_plausible < 2:
            raise ValueError(f"need num_samples >= 2 and num_plausible >= 2, got {num_samples} and {num_plausible}.")
        if not 0 < top_fraction < 1:
            raise ValueError(f"top_fraction must be in (0, 1), got {top_fraction}.")
        self.m, self.rating_cost, self.ranking_cost = m, rating_cost, ranking_cost
        self.num_samples, self.top_fraction, self.num_plausible = num_samples, top_fraction, num_plausible
        self.num_hessian_samples = max(1, min(num_hessian_samples, num_samples))

    def weights(self, F: Tensor, mean: Tensor, var: Tensor, rating_likelihood: Likelihood) -> tuple[Tensor, Tensor]:
        r"""The top-set probabilities ``w`` and rating slopes ``g`` (``T x N`` each) from samples
        ``F`` (``T x S x N``) and the marginals: ``g`` is the derivative of the likelihood's
        ``expected_rating(mean, var)`` in ``mean`` (central difference; Beta ratings:
        ``phi(m / s) / s``, ``s = sqrt(2 sigma_B^2 + v)``)."""
        N = F.shape[-1]
        w = top_set_membership(F, max(1, min(N, round(self.top_fraction * N)))).to(F).mean(-2)
        h = 1e-4
        up, down = rating_likelihood.expected_rating(mean + h, var), rating_likelihood.expected_rating(mean - h, var)
        g = (up - down) / (2 * h)
        return w, g

    def _prepare(self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]) -> tuple[Any, ...]:
        """``(F, w, g, var, rating_fn, ranking_fn)``: samples, weights, slopes, marginal variances
        and the expected reductions of a rating of rows ``T x R`` and of a ranking of rows ``T x R
        x q`` (not per effort)."""
        mean, cov = joint_posterior(model, X)
        F, _ = joint_samples(mean, cov, generators, self.num_samples)
        T, S, N = F.shape
        lik = preference_likelihood(model)
        var = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0)
        w, g = self.weights(F, mean, var, lik.rating)
        Fh = F[:, : self.num_hessian_samples]
        h = rating_hessian(Fh, lik.rating)  # T x N

        def rating_fn(rows: Tensor) -> Tensor:  # T x R
            return variance_reduction(cov, w, rows.unsqueeze(-1), h.gather(1, rows).unsqueeze(-1).unsqueeze(-1), g)

        def ranking_fn(rows: Tensor) -> Tensor:  # T x R x q
            R, q = rows.shape[1:]
            Fs = Fh.gather(2, rows.reshape(T, 1, R * q).expand(T, Fh.shape[1], R * q))
            P = choice_answer_probabilities(Fs.reshape(T, -1, R, q).transpose(1, 2), lik.comparison)  # T x R x q
            block = cov.gather(1, rows.reshape(T, -1, 1).expand(T, R * q, N))
            block = block.reshape(T, R, q, N).gather(3, rows.unsqueeze(-2).expand(T, R, q, q))
            mean_q = mean.gather(1, rows.reshape(T, -1)).reshape(rows.shape)
            H = ranking_mode_hessians(mean_q, block, lik.comparison)  # T x R x J x q x q
            red = variance_reduction(cov, w, rows.repeat_interleave(q, 1), H.reshape(T, R * q, q, q), g)
            return (red.reshape(T, R, q) * P).sum(-1)

        return F, w, g, var, rating_fn, ranking_fn

    def scorers(self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]) -> tuple[Any, Any]:
        """:meth:`~torchpref.selection.strategies.PerEffortSelector.scorers`: expected reductions."""
        return self._prepare(model, X, generators)[4:]

    def values(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
        r"""Each trial's best rating and ranking: ``(rating rows T, rating values T, ranking rows
        T x m, ranking values T)``, values per unit of effort."""
        F, w, g, var, rating_fn, ranking_fn = self._prepare(model, X, generators)
        T, S, N = F.shape
        rating = rating_fn(torch.arange(N, device=F.device).expand(T, N))
        rating_value, rating_row = rating.max(-1)
        K = min(self.num_plausible, N)
        if K < self.m:
            return rating_row, rating_value / self.rating_cost, None, torch.full_like(rating_value, -1.0)
        cand = torch.argsort(w * g * g * var, dim=-1, descending=True)[:, :K]  # T x K
        chosen, value = self._greedy(cand, ranking_fn)
        return rating_row, rating_value / self.rating_cost, cand.gather(1, chosen), value / self.ranking_cost

    def _greedy(self, cand: Tensor, ranking_fn: Any) -> tuple[Tensor, Tensor]:
        """Greedy best-of-``m`` set among the ``K`` plausible items ``cand`` (``T x K``): ``T x m``
        columns, ``T`` values."""
        T, K = cand.shape
        j, k = torch.triu_indices(K, K, 1, device=cand.device)
        sets = torch.stack([j, k], -1).expand(T, -1, 2)  # T x R x 2
        while True:
            q = sets.shape[-1]
            vals = ranking_fn(cand.gather(1, sets.reshape(T, -1)).reshape(sets.shape))  # T x R
            b = vals.argmax(-1)
            best = sets[torch.arange(T), b]  # T x q
            if q == self.m:
                return best, vals[torch.arange(T), b]
            taken = torch.zeros(T, K, dtype=torch.bool, device=cand.device).scatter_(1, best, True)
            rest = (~taken).nonzero()[:, 1].reshape(T, K - q)
            sets = torch.cat([best.unsqueeze(1).expand(T, K - q, q), rest.unsqueeze(-1)], -1)
