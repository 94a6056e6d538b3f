r"""Expected reduction of the top-set rating profile's posterior variance per unit of effort.

Notation (one trial; the code is batched over ``T`` trials): ``N`` candidates, ``S`` joint
posterior samples ``f^(s)`` of their utilities, ``r(f) = E[rating | f]`` the rating
likelihood's mean (Beta: ``Phi(f / (sqrt 2 sigma_B))``, eq. 7), ``k`` the size of the top set.

**The target.** The top-set rating profile ``v_i = r(f_i) 1[f_i in top k of f]``: each
candidate's rating where it is among the ``k`` best, 0 elsewhere. Its summed posterior variance
``L = sum_i Var(v_i)`` is the expected squared error of the posterior-mean estimate of the
profile. For an item whose membership is uncertain (probability ``p``) and whose rating is
nearly known, ``Var(v_i) ~ r_i^2 p (1 - p)``: a membership flip costs the item's rating; for a
sure member, ``Var(v_i) = Var(r(f_i))``, the level's variance; a sure non-member costs nothing.
So which items are best (what a ranking tells) and how they would be rated (what a rating
tells) are valued on one scale, in rating units, with no weight between them.

**What a query buys.** An answer ``y`` with probability ``P_sy = P(y | f^(s))`` under each
sample reweights the samples (importance weights of the exact posterior given ``y``). Since
``E_y E[v | y] = E[v]``, the expected reduction of the variance is the variance of the
conditional mean over the answers:

.. math::

    \Delta = \sum_i \Big( \sum_y \frac{A_{yi}^2}{P_y} - \bar v_i^2 \Big), \qquad
    A_{yi} = \frac1S \sum_s P_{sy} v^{(s)}_i, \quad P_y = \frac1S \sum_s P_{sy} .

**Bias.** Ratios of sample means are biased: the plug-in ``Delta`` is too large by about
``sum_y Var_s(P_sy (v_i - m_yi)) / (S P_y) - Var_s(v_i) / S`` (``m_yi = A_yi / P_y``; the delta
method on ``A^2 / P`` and ``vbar^2``), which grows with the number of answers ``Y`` (a binned
rating has more than a best-of-``m`` choice) and would tilt the comparison between the two.
That first-order bias is subtracted (sample variances, ``S - 1`` in the denominator); an answer
independent of ``f`` is then worth exactly 0.

A query's value is ``Delta`` over its effort. All queries of a trial are valued on the same
samples (common random numbers from the trial's generator), so their differences are far less
noisy than each value.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from gpytorch.likelihoods import Likelihood
from torch import Tensor

from torchpref.acquisition.choice_sets import greedy_choice_sets
from torchpref.acquisition.functions import rating_bin_probabilities
from torchpref.acquisition.information import top_set_membership
from torchpref.data.effort import EffortModel
from torchpref.models.defaults import preference_likelihood
from torchpref.selection.samples import SelectorModel, joint_posterior, joint_samples, sample_scorers
from torchpref.selection.strategies import PerEffortSelector, effort_model

__all__ = ["ProfileVariancePerEffort", "profile_variance_reduction", "top_profile"]


def top_profile(F: Tensor, k: int, rating_likelihood: Likelihood, clipped: bool = False) -> Tensor:
    r"""The top-set rating profile of each sample, ``... x S x N``: ``v = r(f) 1[f in top k]``,
    or with ``clipped`` ``v = max(r(f), tau)``, ``tau`` the sample's ``k``-th largest rating.

    The clipped profile reads every item below the top set as the top set's threshold: a
    membership flip of an item near the threshold costs the rating difference it makes (not
    the whole rating), and the threshold's absolute level is shared by the ``N - k`` items below it.

    Args:
        F: ``... x S x N`` joint posterior samples.
        k: the top set's size.
        rating_likelihood: has ``expected_rating(mean, var)``; ``r(f)`` is its value at ``var = 0``.
        clipped: the clipped profile.
    """
    r = rating_likelihood.expected_rating(F, torch.zeros_like(F))
    if clipped:
        return torch.maximum(r, r.topk(k, dim=-1).values[..., -1:])
    return torch.where(top_set_membership(F, k), r, 0.0)


def profile_variance_reduction(P: Tensor, V: Tensor, bias_correction: bool = True) -> Tensor:
    r"""Expected reduction of ``sum_i Var(v_i)`` by a query's answer (module notes).

    Args:
        P: ``T x B x S x Y`` answer probabilities of ``B`` queries under each of ``S`` samples.
        V: ``T x S x n`` the profile in the same samples (only items of nonzero variance matter).
        bias_correction: subtract the estimator's first-order bias.

    Returns:
        ``T x B`` reductions (may be slightly negative with the correction: no clamp, so that
        ranking the queries stays unbiased).
    """
    if V.dim() != 3 or P.dim() != 4 or V.shape[:2] != (P.shape[0], P.shape[2]):
        raise ValueError(
            f"V must be T x S x n with T, S those of P (T x B x S x Y: {tuple(P.shape)}), got shape {tuple(V.shape)}."
        )
    return _reduction(P, _Moments.of(V), bias_correction)


class _Moments(NamedTuple):
    """What every query of a trial shares: the profile ``V`` (``T x S x n``), ``[V, V^2]``
    (``T x S x 2n``), its mean and its sample variance over the samples (``T x 1 x n`` each)."""

    V: Tensor
    VV: Tensor
    mean: Tensor
    var: Tensor

    @classmethod
    def of(cls, V: Tensor) -> _Moments:
        return cls(V, torch.cat([V, V.square()], -1), V.mean(-2, keepdim=True), V.var(-2, keepdim=True))


def _reduction(P: Tensor, mom: _Moments, bias_correction: bool) -> Tensor:
    """:func:`profile_variance_reduction` with the profile's moments computed once."""
    T, B, S, Y = P.shape
    n = mom.V.shape[-1]
    tiny = torch.finfo(P.dtype).tiny
    Pt = P.transpose(-1, -2).reshape(T, B * Y, S)  # answers before samples: one matmul per trial
    p_y = P.mean(-2).unsqueeze(-1).clamp_min(tiny)  # T x B x Y x 1
    A = (Pt @ mom.V).reshape(T, B, Y, n) / S  # A_yi
    between = (A.square() / p_y).sum(-2) - mom.mean.square()  # T x B x n
    if not bias_correction or S < 2:
        return between.sum(-1)
    m = A / p_y  # m_yi = E[v_i | y]
    P2 = Pt.square()
    q0 = P2.sum(-1).reshape(T, B, Y, 1)
    q1, q2 = (P2 @ mom.VV).reshape(T, B, Y, 2 * n).split(n, -1)  # sums of P^2 v, P^2 v^2
    var_y = (q2 - 2 * m * q1 + m.square() * q0).clamp_min(0) / (S - 1)  # Var_s(P_sy (v_s - m_y))
    bias = (var_y / (S * p_y)).sum(-2) - mom.var / S
    return (between - bias).sum(-1)


class ProfileVariancePerEffort(PerEffortSelector):
    r"""Ask the query of largest expected reduction of the top-set rating profile's variance per
    unit of effort (:mod:`torchpref.selection.top_profile`).

    From ``num_samples`` joint posterior samples of the candidates' utilities (the trial's
    generator: the same samples value every query), the profile ``v_i = r(f_i) 1[i in top k]``
    with ``k = round(top_fraction * N)``. The ``num_plausible`` candidates of largest
    ``Var(v_i)`` are considered: a rating of each is valued with its binned answer
    (:func:`~torchpref.acquisition.functions.rating_bin_probabilities`), a best-of-``m`` ranking is built
    greedily among them (:func:`~torchpref.acquisition.functions.greedy_choice_set`, from the best pair).
    The larger of the best rating's and the best ranking's value per effort is asked. Answers
    are valued under the model's own likelihoods.

    Args:
        m: items per ranking query.
        rating_cost: effort of one rating.
        ranking_cost: effort of one best-of-``m`` choice (default ``1 + (m - 1) / 4``).
        num_samples: joint posterior samples.
        top_fraction: the top set's share of the candidates.
        num_plausible: candidates considered for ratings and rankings.
        num_bins: bins of a rating's answer.
        clipped: value the clipped profile ``max(r(f_i), tau)`` instead (:func:`top_profile`).
        effort: an :class:`~torchpref.data.effort.EffortModel` pricing every question in seconds
            (instead of ``rating_cost`` and ``ranking_cost``).
    """

    name = "profile per effort"

    def __init__(
        self,
        m: int = 5,
        rating_cost: float = 1.0,
        ranking_cost: float | None = None,
        num_samples: int = 256,
        top_fraction: float = 0.2,
        num_plausible: int = 15,
        num_bins: int = 10,
        clipped: bool = False,
        *,
        effort: EffortModel | dict[str, float] | None = None,
    ):
        m, rating_cost, ranking_cost = effort_model(m, rating_cost, ranking_cost, effort)
        self.effort = None if effort is None else EffortModel.of(effort).as_dict()
        if num_samples < 2 or num_plausible < 1 or num_bins < 2:
            raise ValueError(
                f"need num_samples >= 2, num_plausible >= 1 and num_bins >= 2, got {num_samples}, "
                f"{num_plausible} and {num_bins}."
            )
        if not 0 < top_fraction < 1:
            raise ValueError(f"top_fraction must be in (0, 1), got {top_fraction}.")
        self.m, self.rating_cost, self.ranking_cost = m, rating_cost, ranking_cost
        self.num_samples, self.top_fraction = num_samples, top_fraction
        self.num_plausible, self.num_bins, self.clipped = num_plausible, num_bins, clipped

    def _prepare(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Tensor, Tensor, Any]:
        """Joint samples ``F`` (``T x S x N``), the candidates by profile variance (``T x N``) and the
        value of answer probabilities (``T x R x S x Y -> T x R``)."""
        mean, cov = joint_posterior(model, X)
        F, _ = joint_samples(mean, cov, generators, self.num_samples)
        T, S, N = F.shape
        V = top_profile(
            F, max(1, min(N, round(self.top_fraction * N))), preference_likelihood(model).rating, self.clipped
        )
        var = V.var(-2)  # T x N
        order = var.argsort(-1, descending=True)
        n = max(1, int((var > 0).sum(-1).max()))  # the items that matter (zero columns add nothing)
        mom = _Moments.of(V.gather(2, order[:, :n].unsqueeze(1).expand(T, S, n)))

        def value(P: Tensor) -> Tensor:  # T x R x S x Y -> T x R
            return _reduction(P, mom, True)

        return F, order, value

    def scorers(self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]) -> tuple[Any, Any]:
        """The expected reduction of a rating of rows ``T x R`` and of a ranking of rows ``T x R x
        q`` (not per effort; :meth:`~torchpref.selection.strategies.PerEffortSelector.scorers`)."""
        F, _, value = self._prepare(model, X, generators)
        return sample_scorers(F, value, model.likelihood, self.num_bins)

    def values(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
        r"""Each trial's best rating and ranking: ``(rating rows T, rating values T, ranking rows
        T x m or None, ranking values T)``, values per unit of effort (:meth:`query_cost`)."""
        F, order, value = self._prepare(model, X, generators)
        T, S, N = F.shape
        lik = preference_likelihood(model)
        K = min(self.num_plausible, N)
        cand = order[:, :K]  # T x K
        Fc = F.gather(2, cand.unsqueeze(1).expand(T, S, K))  # T x S x K
        rating = value(rating_bin_probabilities(Fc.mT, lik.rating, self.num_bins))  # T x K
        rating_value, best = rating.max(-1)
        rating_row = cand.gather(1, best.unsqueeze(-1)).squeeze(-1)
        rating_cost, ranking_cost = self.query_cost(1), self.query_cost(self.m)
        if K < max(self.m, 2):
            return rating_row, rating_value / rating_cost, None, torch.full_like(rating_value, -torch.inf)
        chosen, ranking_value = greedy_choice_sets(Fc, lik.comparison, self.m, value)
        return rating_row, rating_value / rating_cost, cand.gather(1, chosen), ranking_value / ranking_cost
