r"""Rankings by expected information, ratings by the clipped profile, under one value per second.

The two selectors that won somewhere (docs/suite.md) win on different answers: the expected
information about the utility, ``I(y; f)`` (:class:`~torchpref.selection.strategies.InformationPerEffort`,
``target="utility"``), is the one selector that beats random on real people's rankings; the
clipped profile (:class:`~torchpref.selection.top_profile.ProfileVariancePerEffort`,
``clipped=True``) wins the realistic families, where it asks ratings. :class:`InformationAndProfile`
builds its best ranking as the first does (a best-of-``m`` built greedily for ``I(y; f)`` among the
likeliest maximisers) and its best rating as the second does (the item whose rating most reduces
the clipped profile's variance), then asks the one of larger value per second under **one** value,
``decide``:

* ``"information"`` (default): both valued by ``I(y; f)`` per second;
* ``"profile"``: both valued by the clipped profile's expected variance reduction per second;
* ``"sum"``: every query valued by both at once, ``I / I* + D / D*`` per second (``D`` the clipped
  profile's reduction; ``I*``, ``D*`` the largest of each among the candidates' ratings, so that
  the two count equally with no weight to choose), the rating and the ranking both picked by it;
* ``"order"``: every query valued by the information its answer carries about the **order** of the
  ``num_plausible`` likeliest maximisers: ``sum I(y; 1[f_i > f_j])`` over their pairs
  (:func:`~torchpref.acquisition.information.membership_information`, pairs whose order is nearly
  known left out). A rating tells the order only through where it puts one item among the others:
  what it says about the person's overall level (a shift of every ``f``) counts for nothing, as it
  orders nothing. A ranking is all order.

All on the same joint posterior samples (common random numbers from the trial's generator), under
the model's own likelihoods; seconds default to the plain effort model's
(:class:`~torchpref.simulation.raters.EffortModel`: a rating 3.4 s, a best-of-5 6.1 s).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from torchpref.acquisition.choice_sets import greedy_choice_steps
from torchpref.acquisition.functions import rating_bin_probabilities
from torchpref.acquisition.information import membership_information, sample_information
from torchpref.data.effort import EffortModel
from torchpref.data.queries import Query
from torchpref.models.defaults import preference_likelihood
from torchpref.selection.choosing import query_items
from torchpref.selection.samples import SelectorModel, joint_posterior, joint_samples
from torchpref.selection.strategies import PerEffortSelector, effort_model
from torchpref.selection.top_profile import _Moments, _reduction, top_profile

__all__ = ["InformationAndProfile"]

DECIDE = ("information", "profile", "sum", "order")
#: the fewest samples of each order of a pair for the pair to count (``decide="order"``)
ORDER_MIN_COUNT = 8
Value = Callable[[Tensor], Tensor]


class InformationAndProfile(PerEffortSelector):
    r"""Rankings by ``I(y; f)``, ratings by the clipped profile, one value per second (module notes).

    Args:
        m: items per ranking query.
        rating_cost: seconds of a rating (default the plain effort model's, 3.4).
        ranking_cost: seconds of a best-of-``m`` (default: the plain effort model's where
            ``rating_cost`` is not given either, else ``1 + (m - 1) / 4`` as every per-effort selector).
        decide: ``"information"``, ``"profile"``, ``"sum"`` or ``"order"``: the one value both are
            compared by.
        num_samples: joint posterior samples.
        top_fraction: the clipped profile's top share.
        num_plausible: candidates considered for ratings (largest profile variance) and rankings
            (likeliest maximisers).
        num_bins: bins of a rating's answer.
        gamma: eq. 12's ``gamma``, to order candidates of equal probability of being the maximiser.
        effort: the :class:`~torchpref.data.effort.EffortModel` that prices every question in
            seconds (default: the plain effort model where no cost is given; given costs keep the
            selector's own units).
        choose_size: ask the best-of-``q``, ``2 <= q <= m``, of largest value per second: the
            first ``q`` items of a set built greedily from the most valuable pair (a small pool whose
            best is known gains more from a pair than from showing the same five again);
            ``False``: always ``m``, built from the likeliest maximiser.

    Raises:
        ValueError: an unknown ``decide``, or the checks of the selectors it combines.
    """

    name = "information & clipped profile"

    def __init__(
        self,
        m: int = 5,
        rating_cost: float | None = None,
        ranking_cost: float | None = None,
        decide: str = "information",
        num_samples: int = 256,
        top_fraction: float = 0.2,
        num_plausible: int = 15,
        num_bins: int = 10,
        gamma: float = 3.0,
        *,
        effort: EffortModel | dict[str, float] | None = None,
        choose_size: bool = False,
    ):
        if effort is None and rating_cost is None and ranking_cost is None:
            effort = EffortModel.plain()
        elif rating_cost is None:  # the plain effort model's seconds of a rating, the ranking's as given
            rating_cost = EffortModel.plain().rating()
        m, rating_cost, ranking_cost = effort_model(
            m, 1.0 if rating_cost is None else rating_cost, ranking_cost, effort
        )
        self.effort = None if effort is None else EffortModel.of(effort).as_dict()
        self.choose_size = bool(choose_size)
        if decide not in DECIDE:
            raise ValueError(f"decide must be one of {DECIDE}, got {decide!r}.")
        if num_samples < 2 or num_plausible < 1 or num_bins < 2 or not 0 < top_fraction < 1:
            raise ValueError(
                f"need num_samples >= 2, num_plausible >= 1, num_bins >= 2 and 0 < top_fraction < 1, got "
                f"{num_samples}, {num_plausible}, {num_bins} and {top_fraction}."
            )
        self.m, self.rating_cost, self.ranking_cost, self.decide = m, rating_cost, ranking_cost, decide
        self.num_samples, self.top_fraction, self.num_plausible = num_samples, top_fraction, num_plausible
        self.num_bins, self.gamma = num_bins, gamma

    def _prepare(self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]) -> dict[str, Any]:
        """Samples ``F``, the profile's order and value, the maximisers' order, the likelihood."""
        mean, cov = joint_posterior(model, X)
        F, std = joint_samples(mean, cov, generators, self.num_samples)
        T, S, N = F.shape
        lik = preference_likelihood(model)
        p_max = torch.zeros_like(mean).scatter_add_(1, F.argmax(-1), torch.ones_like(F[..., 0])) / S
        ucb = mean + self.gamma * std
        tie = 1e-9 * torch.sigmoid(ucb - ucb.max(-1, keepdim=True).values)

        by_max = torch.argsort(p_max + tie, dim=-1, descending=True)
        prep = dict(F=F, lik=lik, by_max=by_max)
        if self.decide != "order":  # the clipped profile (decide="order" values by the order alone)
            V = top_profile(F, max(1, min(N, round(self.top_fraction * N))), lik.rating, True)
            var = V.var(-2)
            by_profile = var.argsort(-1, descending=True)
            n = max(1, int((var > 0).sum(-1).max()))
            mom = _Moments.of(V.gather(2, by_profile[:, :n].unsqueeze(1).expand(T, S, n)))

            def profile(P: Tensor) -> Tensor:  # T x R x S x Y -> T x R
                return _reduction(P, mom, True)

            prep.update(profile=profile, by_profile=by_profile)
        if self.decide == "sum":
            self._scaled_sum(prep)
        if self.decide == "order":
            K = min(self.num_plausible, N)
            top = F.gather(2, by_max[:, :K].unsqueeze(1).expand(T, S, K))
            iu = torch.triu_indices(K, K, 1, device=F.device)
            Z = top[..., iu[0]] > top[..., iu[1]]  # T x S x K(K-1)/2: the order of each pair

            def order(P: Tensor) -> Tensor:  # T x R x S x Y -> T x R
                return membership_information(P, Z, ORDER_MIN_COUNT, True)

            prep.update(order=order)
        return prep

    def _scaled_sum(self, prep: dict[str, Any]) -> None:
        """``decide="sum"``: the value ``I / I* + D / D*`` (``D`` the clipped profile's reduction),
        each over its largest value among the candidates' ratings, and those ratings' values."""
        F, lik, profile = prep["F"], prep["lik"], prep["profile"]
        T, S, N = F.shape
        K = min(self.num_plausible, N)
        cand = torch.cat([prep["by_profile"][:, :K], prep["by_max"][:, :K]], -1)  # T x 2K (repeats harmless)
        P = rating_bin_probabilities(F.gather(2, cand.unsqueeze(1).expand(T, S, 2 * K)).mT, lik.rating, self.num_bins)
        info, prof = sample_information(P), profile(P)  # T x 2K
        tiny = torch.finfo(F.dtype).tiny
        s_info, s_prof = info.amax(-1, keepdim=True).clamp_min(tiny), prof.amax(-1, keepdim=True).clamp_min(tiny)

        def total(Q: Tensor) -> Tensor:  # T x R x S x Y -> T x R
            return sample_information(Q) / s_info + profile(Q) / s_prof

        prep.update(sum=total, rating_cand=cand, rating_sum=info / s_info + prof / s_prof)

    def _judge(self, prep: dict[str, Any]) -> Value:
        return sample_information if self.decide == "information" else prep[self.decide]

    def scorers(self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]) -> tuple[Value, Value]:
        """The ``decide`` value (not per second) of a rating of rows ``T x R`` and of a ranking of
        rows ``T x R x q``."""
        prep = self._prepare(model, X, generators)
        return self._scorers(prep, self._judge(prep), self._judge(prep))

    def _scorers(self, prep: dict[str, Any], rating_value: Value, ranking_value: Value) -> tuple[Value, Value]:
        F, lik = prep["F"], prep["lik"]
        T, S, _ = F.shape

        def rating_fn(rows: Tensor) -> Tensor:
            Fr = F.gather(2, rows.unsqueeze(1).expand(T, S, rows.shape[1]))
            return rating_value(rating_bin_probabilities(Fr.mT, lik.rating, self.num_bins))

        def ranking_fn(rows: Tensor) -> Tensor:
            R, q = rows.shape[1:]
            Fr = F.gather(2, rows.reshape(T, 1, R * q).expand(T, S, R * q)).reshape(T, S, R, q).transpose(1, 2)
            return ranking_value(lik.comparison.choice_probabilities(Fr))

        return rating_fn, ranking_fn

    def values(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
        r"""``(rating rows T, rating values T, ranking rows T x m or None, ranking values T)``: the
        rating of largest clipped-profile reduction and the ranking of largest ``I(y; f)``, each
        valued by ``decide`` per second."""
        prep = self._prepare(model, X, generators)
        F, lik = prep["F"], prep["lik"]
        T, S, N = F.shape
        K = min(self.num_plausible, N)
        if self.decide == "sum":  # the rating of largest summed value
            cand, by_value = prep["rating_cand"], prep["rating_sum"]
        elif self.decide == "order":  # the likeliest maximiser whose rating orders most
            cand = prep["by_max"][:, :K]
            Fc = F.gather(2, cand.unsqueeze(1).expand(T, S, K))
            by_value = prep["order"](rating_bin_probabilities(Fc.mT, lik.rating, self.num_bins))
        else:
            cand = prep["by_profile"][:, :K]
            Fc = F.gather(2, cand.unsqueeze(1).expand(T, S, K))
            by_value = prep["profile"](rating_bin_probabilities(Fc.mT, lik.rating, self.num_bins))  # T x K
        rating_row = cand.gather(1, by_value.argmax(-1, keepdim=True))  # T x 1
        rate, rank = self._scorers(prep, self._judge(prep), self._judge(prep))
        if self.decide in ("sum", "order"):  # the rating was picked by the judge's own value
            rating_value = by_value.amax(-1) / self.query_cost(1)
        else:
            rating_value = rate(rating_row).squeeze(-1) / self.query_cost(1)
        if K < max(self.m, 2):
            return rating_row.squeeze(-1), rating_value, None, torch.full_like(rating_value, -torch.inf)
        cand = prep["by_max"][:, :K]
        Fc = F.gather(2, cand.unsqueeze(1).expand(T, S, K))
        builder = prep[self.decide] if self.decide in ("sum", "order") else sample_information
        # from the likeliest maximiser, or with choose_size from the most valuable pair (a small
        # pool's top, once known, would otherwise be in every set, and its answer foretold)
        chosen, steps = greedy_choice_steps(Fc, lik.comparison, self.m, builder, start=None if self.choose_size else 0)
        rows = cand.gather(1, chosen)  # T x m
        ranking_value = self._prefix_value(rank, rows, steps, self.m)
        if self.choose_size:  # the greedy set's prefix of largest value per second; the rest -1
            size = torch.full_like(ranking_value, self.m, dtype=torch.long)
            for q in range(2, self.m):
                v = self._prefix_value(rank, rows, steps, q)
                better = v > ranking_value
                ranking_value, size = torch.where(better, v, ranking_value), torch.where(better, q, size)
            rows = torch.where(torch.arange(self.m, device=rows.device) < size.unsqueeze(-1), rows, -1)
        return rating_row.squeeze(-1), rating_value, rows, ranking_value

    def _prefix_value(self, rank: Value, rows: Tensor, steps: Tensor, q: int) -> Tensor:
        """The judge's value per second of the first ``q`` of the greedy sets ``rows`` (``T x m``):
        the search's own value where the search valued the sets by the judge (every ``decide`` but
        ``"profile"``; a pair's where it searched pairs, in closed form), else valued anew."""
        if self.decide != "profile" and (q >= 3 or self.choose_size):
            return steps[:, q - 2] / self.query_cost(q)
        return rank(rows[:, :q].unsqueeze(1)).squeeze(-1) / self.query_cost(q)

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """Among given queries: the rating of largest clipped-profile reduction and the ranking of
        largest ``I(y; f)``, the one of larger ``decide`` value per second asked (ties to the first)."""
        qr = query_items(queries)
        with torch.no_grad():
            prep = self._prepare(model, qr.X.unsqueeze(0), [generator])
            if self.decide in ("sum", "order"):
                pickers = (prep[self.decide], prep[self.decide])
            else:
                pickers = (prep["profile"], sample_information)
            by_profile, by_info = self._scorers(prep, *pickers)
            judge_rate, judge_rank = self._scorers(prep, self._judge(prep), self._judge(prep))
            best: tuple[float, int] | None = None
            for q, idx in qr.groups().items():
                rows = torch.stack([qr.rows[i] for i in idx]).unsqueeze(0)  # 1 x R x q
                pick = (by_profile(rows[..., 0]) if q == 1 else by_info(rows))[0].argmax()
                one = rows[:, int(pick)].unsqueeze(1)
                v = float((judge_rate(one[..., 0]) if q == 1 else judge_rank(one))[0, 0]) / self.query_cost(q)
                if best is None or v > best[0] or (v == best[0] and idx[int(pick)] < best[1]):
                    best = (v, idx[int(pick)])
        assert best is not None
        return best[1]
