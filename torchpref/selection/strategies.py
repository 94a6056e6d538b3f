r"""Query selectors: given a model and candidate items, return the next query.

Every selector has ``select(model, X, indices, step, num_steps, generator) -> Query`` with
``X`` the ``N x d`` candidates (``indices`` their pool rows, or ``None``), ``step`` the
zero-based query number out of ``num_steps``. Baselines (paper Sec. IV.A): random ratings,
random rankings, UCB ratings, random mixed. The paper's combined strategy is :class:`UCBC`;
:class:`InformationPerEffort` is ours.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from torchpref.acquisition.choice_sets import greedy_choice_sets
from torchpref.acquisition.functions import (
    item_ucb,
    membership_information,
    rating_bin_probabilities,
    sample_information,
    top_set_membership,
)
from torchpref.data.effort import EffortModel
from torchpref.data.queries import Query, ranking_query, rating_query
from torchpref.models.defaults import preference_likelihood
from torchpref.selection.choosing import (  # importable from here too
    QueryRows,
    _ranking_size,
    choose_by_scores,
    effort_model,
    query_items,
    ranking_cost,
    shown,
    uniform_among,
)
from torchpref.selection.samples import (  # importable from here too
    SelectorModel,
    joint_posterior,
    joint_samples,
    sample_scorers,
)


def _check_m(m: int, X: Tensor) -> None:
    if m < 2:
        raise ValueError(f"a ranking query needs m >= 2 items, got m={m}.")
    if X.shape[0] < m:
        raise ValueError(f"need at least m={m} candidates for a ranking query, got {X.shape[0]}.")


class Selector:
    r"""Base class; ``name`` labels results.

    Subclasses implement :meth:`select_batch`, which picks one query for each of ``T``
    independent trials at the same step (``X``: ``T x N x d``; ``model`` a
    :class:`~torchpref.models.batch.BatchedPreferenceGP`, or a :class:`~torchpref.PreferenceGP` when
    ``T = 1``); :meth:`select` is its single-trial case, so both run the same code and consume
    each trial's generator identically. A custom selector may override :meth:`select` alone
    (it then runs in :func:`~torchpref.selection.active.run_active_learning` only).
    """

    name = "selector"

    def select(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Tensor | None,
        step: int,
        num_steps: int,
        generator: torch.Generator,
    ) -> Query:
        """The next query for ``model`` among the candidates ``X`` (``N x d``)."""
        return self.select_batch(model, X.unsqueeze(0), [indices], step, num_steps, [generator])[0]

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        """One query per trial: ``X`` is ``T x N x d``, ``indices`` and ``generators`` one per trial."""
        raise NotImplementedError(f"{type(self).__name__} implements no select_batch: it runs one trial at a time.")

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """The index of the query to ask next among ``queries`` (:class:`~torchpref.RatingQuery` /
        :class:`~torchpref.RankingQuery`, items in the model's coordinates), valued as this
        selector values the queries it builds (:mod:`torchpref.selection.choosing`)."""
        raise NotImplementedError(f"{type(self).__name__} implements no choose.")


class PerEffortSelector(Selector):
    r"""A selector that values each trial's best rating and best ranking per unit of effort
    (:meth:`values`) and asks the larger (the rating where they are equal)."""

    rating_cost: float
    ranking_cost: float
    m: int
    #: the seconds of every question where set (:class:`~torchpref.data.effort.EffortModel`): a
    #: best-of-``q`` of any size priced by it; else ``rating_cost`` / ``ranking_cost`` in the
    #: selector's own units
    effort: EffortModel | dict[str, float] | None = None

    def values(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
        r"""``(rating rows T, rating values T, ranking rows T x m or None, ranking values T)``,
        values per unit of effort."""
        raise NotImplementedError

    def scorers(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Callable[[Tensor], Tensor], Callable[[Tensor], Tensor]]:
        r"""The value (not per effort) of a rating of each of the rows ``T x R`` and of a ranking of
        each ``T x R x q`` set of rows of the candidates ``X`` (``T x N x d``): two functions to
        ``T x R``, on the samples and target that :meth:`values` uses."""
        raise NotImplementedError

    def query_cost(self, q: int) -> float:
        """The effort of a rating (``q = 1``) or of a best-of-``q``."""
        if self.effort is not None:
            effort = EffortModel.of(self.effort)
            return effort.rating() if q == 1 else effort.ranking(q)
        rating, ranking = self.rating_cost, self.ranking_cost
        return rating if q == 1 else ranking_cost(rating, ranking, self.m, q)

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        qr = query_items(queries)
        with torch.no_grad():
            rating_fn, ranking_fn = self.scorers(model, qr.X.unsqueeze(0), [generator])
            return choose_by_scores(qr, rating_fn, ranking_fn, self.query_cost)

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        with torch.no_grad():
            rating_row, rating_value, ranking_rows, ranking_value = self.values(model, X, generators)
        return [
            ranking_query(X[b], indices[b], shown(ranking_rows[b]))
            if ranking_rows is not None and bool(ranking_value[b] > rating_value[b])
            else rating_query(X[b], indices[b], int(rating_row[b]))
            for b in range(X.shape[0])
        ]


class RandomRatings(Selector):
    """Rate a uniformly random candidate."""

    name = "random ratings"

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        return [
            rating_query(X[b], indices[b], int(torch.randint(X.shape[1], (1,), generator=g)))
            for b, g in enumerate(generators)
        ]

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """A uniformly random rating query (any query if there is none)."""
        return uniform_among(query_items(queries), "rating", generator)


class RandomRankings(Selector):
    """Best of ``m`` uniformly random distinct candidates."""

    name = "random rankings"

    def __init__(self, m: int = 5):
        self.m = _ranking_size(m)

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        _check_m(self.m, X[0])
        return [
            ranking_query(X[b], indices[b], torch.randperm(X.shape[1], generator=g)[: self.m])
            for b, g in enumerate(generators)
        ]

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """A uniformly random ranking query (any query if there is none)."""
        return uniform_among(query_items(queries), "ranking", generator)


class RandomMixed(Selector):
    """A random rating or a random ranking, with probability ``p_ranking`` of a ranking."""

    name = "random mixed"

    def __init__(self, m: int = 5, p_ranking: float = 0.5):
        self.m, self.p_ranking = _ranking_size(m), p_ranking

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        out = []
        for b, g in enumerate(generators):
            coin = float(torch.rand((), generator=g, dtype=torch.float64))
            sel = RandomRankings(self.m) if coin < self.p_ranking else RandomRatings()
            out += sel.select_batch(model, X[b : b + 1], indices[b : b + 1], step, num_steps, [g])
        return out

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """A ranking with probability ``p_ranking``, else a rating, uniformly among the queries of
        that kind (any query if there is none)."""
        qr = query_items(queries)
        coin = float(torch.rand((), generator=generator, dtype=torch.float64))
        return uniform_among(qr, "ranking" if coin < self.p_ranking else "rating", generator)


def _ucb(model, X: Tensor, gamma: float) -> Tensor:
    """Eq. 12's UCB at ``X`` (``T x N x d``): ``T x N`` (:func:`~torchpref.acquisition.functions.item_ucb`)."""
    with torch.no_grad():
        return item_ucb(model, X, gamma)[0]


class UCBRatings(Selector):
    """Rate the candidate of largest UCB (eq. 12)."""

    name = "UCB ratings"

    def __init__(self, gamma: float = 3.0):
        self.gamma = gamma

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        best = _ucb(model, X, self.gamma).argmax(-1).tolist()
        return [rating_query(X[b], indices[b], i) for b, i in enumerate(best)]

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """The rating query of largest UCB (without one: the ranking of largest item UCB)."""
        qr = query_items(queries)
        ucb = _ucb(model, qr.X.unsqueeze(0), self.gamma)[0]
        return _best_by_ucb(qr, ucb, "rating" if qr.of_kind("rating") else "ranking")


class UCBC(Selector):
    r"""The paper's combined strategy (Sec. III.C), as the authors' code ran it.

    At zero-based query ``t`` of ``T`` it asks for a ranking with probability
    ``max(0, (T - t) / T)`` (so early queries are rankings, later ones ratings), else a rating.
    Rating: the candidate of largest UCB. Ranking: ``m`` distinct candidates drawn by a softmax
    ``exp(UCB / T)``, with temperature ``T = temperatures[0]`` for the first and
    ``temperatures[1]`` after (with the authors' 5 and 25 and UCBs of a few units, close to
    uniform: the ranking branch explores). The authors' code zeroed a drawn candidate's UCB and
    could draw it again; here the ``m`` candidates are distinct.

    Args:
        gamma: eq. 12's ``gamma`` (the paper's text: 3; the authors' code: 2).
        m: items per ranking query.
        temperatures: softmax temperatures (the authors': 5 then 25).
    """

    name = "UCBC"

    def __init__(self, gamma: float = 3.0, m: int = 5, temperatures: tuple[float, float] = (5.0, 25.0)):
        self.gamma, self.m, self.temperatures = gamma, _ranking_size(m), temperatures

    def ranking_probability(self, step: int, num_steps: int) -> float:
        """The probability ``max(0, (T - t) / T)`` of a ranking at zero-based query ``step`` of ``num_steps``."""
        return max(0.0, (num_steps - step) / num_steps)

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        ucb = _ucb(model, X, self.gamma)
        out: list[Query] = []
        for b, g in enumerate(generators):
            coin = float(torch.rand((), generator=g, dtype=torch.float64))
            if coin >= self.ranking_probability(step, num_steps):
                out.append(rating_query(X[b], indices[b], int(ucb[b].argmax())))
                continue
            _check_m(self.m, X[b])
            logits = ucb[b].clone()
            rows = []
            for k in range(self.m):
                temp = self.temperatures[0] if k == 0 else self.temperatures[1]
                p = torch.softmax((logits - logits.max()) / temp, dim=0)  # drawn rows: logit -inf
                r = int(torch.multinomial(p, 1, generator=g))
                rows.append(r)
                logits[r] = -math.inf
            out.append(ranking_query(X[b], indices[b], torch.tensor(rows)))
        return out

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        r"""The coin of :meth:`select`, then, for a rating, the rating query of largest UCB; for a
        ranking, a ranking query drawn with probability proportional to ``exp(max UCB / T_0 + sum
        of the other items' UCB / T_1)`` (the softmax draw of :meth:`select`, first item at
        ``T_0``, the rest at ``T_1``, as weights of whole sets). Without queries of the coin's
        kind, the other kind's rule."""
        qr = query_items(queries)
        ucb = _ucb(model, qr.X.unsqueeze(0), self.gamma)[0]
        coin = float(torch.rand((), generator=generator, dtype=torch.float64))
        ranking = coin < self.ranking_probability(step, num_steps)
        if not qr.of_kind("rating" if not ranking else "ranking"):
            ranking = not ranking
        if not ranking:
            return _best_by_ucb(qr, ucb, "rating")
        idx = qr.of_kind("ranking")
        logits = []
        for i in idx:
            u = ucb[qr.rows[i]]
            logits.append(u.max() / self.temperatures[0] + (u.sum() - u.max()) / self.temperatures[1])
        z = torch.stack(logits)
        return idx[int(torch.multinomial(torch.softmax(z - z.max(), 0), 1, generator=generator))]


def _best_by_ucb(qr: QueryRows, ucb: Tensor, kind: str) -> int:
    """The query of ``kind`` whose largest item UCB is largest (ties to the first)."""
    idx = qr.of_kind(kind)
    vals = torch.stack([ucb[qr.rows[i]].max() for i in idx])
    return idx[int(vals.argmax())]


class InformationPerEffort(Selector):
    r"""Ask the query whose answer is expected to carry the most information per unit of effort.

    From ``num_samples`` joint posterior samples of the utility over the ``N`` candidates it
    values each query by the mutual information between its answer and a target:

    * ``target="top"`` (default): which candidates are in the top set, the ``k =
      round(top_fraction * N)`` largest utilities of each sample. The value is the summed
      information about each candidate's membership,
      ``sum_i I(y; 1[f(x_i) in top k])`` (:func:`~torchpref.acquisition.functions.membership_information`),
      the expected reduction of the summed membership entropies, with the estimator's
      finite-sample bias removed (without the correction, summed over ~100 items, the bias is
      as large as the information itself and favours ratings over rankings). It buys
      information on the whole upper region and on its boundary (which item is in, which is
      just out), not only on the single best item;
    * ``target="top+levels"``: the same, and each candidate's rating level: the labels
      ``1[mu(f(x_i)) > e]`` for the rating-scale edges ``e`` of ``level_edges`` (by default the
      bin edges of a 1-5 Likert scale), summed with the memberships in the same estimator. A
      ranking tells only which item is better, so it informs memberships (relative) but not
      levels (absolute); a rating informs both. The target is what the metrics score: which
      items are best (true positives, regret) and what each would be rated (WRMS);
    * ``target="maximizer"``: which candidate is the maximiser, the discrete entropy search of
      Hennig & Schuler (2012) / Villemonteix et al. (2009)
      (:func:`~torchpref.acquisition.functions.sample_information`);
    * ``target="utility"``: the utility itself (the answer's ``I(y; f)``, as
      :class:`~torchpref.acquisition.functions.QueryInformation`).

    The ``num_plausible`` candidates whose target is most uncertain (``"top"``: membership
    probability nearest 1/2; otherwise: likeliest maximisers; ties by eq. 12's UCB) are
    considered: a rating of each is valued with its binned Beta answer, a best-of-``m`` ranking
    is built greedily among them (:func:`~torchpref.acquisition.functions.greedy_choice_set`: start at the
    most uncertain one, add the item that adds most information). The query of largest
    information / cost is asked. All answers are valued under the model's own likelihoods
    (its ``sigma_R``, ``nu``, ``sigma_B``).

    ``top_fraction = 0.2``, ``num_plausible = 15`` and ``min_count = 8`` were chosen on the wave
    experiment's development seeds 1-3 (``docs/wave.md``), not on its reported seed. One call
    costs about 10 ms for 100 candidates (128 joint samples of their utilities, one Cholesky of the
    candidates' covariance).

    Args:
        m: items per ranking query.
        rating_cost: effort of one rating.
        ranking_cost: effort of one best-of-``m`` choice (default ``1 + (m - 1) / 4``: 2 for
            ``m = 5``, twice a rating; see ``docs/wave.md``).
        gamma: eq. 12's ``gamma``, to order candidates of equal uncertainty.
        num_samples: joint posterior samples.
        target: ``"top"``, ``"top+levels"``, ``"maximizer"`` or ``"utility"``.
        top_fraction: the top set's share of the candidates (``target="top"``).
        num_plausible: candidates considered for ratings and rankings.
        num_bins: bins of a rating's answer.
        min_count: ``target="top"``: an item counts only if both its labels have at least this
            many samples (membership probability in ``[min_count / S, 1 - min_count / S]``;
            see :func:`~torchpref.acquisition.functions.membership_information`).
        bias_correction: ``target="top"``: correct the information estimates' finite-sample
            bias (:func:`~torchpref.acquisition.functions.membership_information`).
        level_edges: ``target="top+levels"``: the rating-scale edges of the levels.
        effort: an :class:`~torchpref.data.effort.EffortModel` pricing every question in seconds
            (instead of ``rating_cost`` and ``ranking_cost``).
    """

    name = "info per effort"

    def __init__(
        self,
        m: int = 5,
        rating_cost: float = 1.0,
        ranking_cost: float | None = None,
        gamma: float = 3.0,
        num_samples: int = 128,
        target: str = "top",
        top_fraction: float = 0.2,
        num_plausible: int = 15,
        num_bins: int = 10,
        min_count: int = 8,
        bias_correction: bool = True,
        level_edges: tuple[float, ...] = (0.2, 0.4, 0.6, 0.8),
        *,
        effort: EffortModel | dict[str, float] | None = None,
    ):
        m, rating_cost, ranking_cost = effort_model(m, rating_cost, ranking_cost, effort)
        self.effort = None if effort is None else EffortModel.of(effort).as_dict()
        if target not in ("top", "top+levels", "maximizer", "utility"):
            raise ValueError(f"target must be 'top', 'top+levels', 'maximizer' or 'utility', got {target!r}.")
        if not all(0 < e < 1 for e in level_edges):
            raise ValueError(f"level_edges must lie in (0, 1), got {level_edges}.")
        if num_samples < 2 or num_plausible < 1:
            raise ValueError(f"need num_samples >= 2 and num_plausible >= 1, got {num_samples} and {num_plausible}.")
        if not 0 < top_fraction < 1:
            raise ValueError(f"top_fraction must be in (0, 1), got {top_fraction}.")
        self.m, self.rating_cost, self.ranking_cost = m, rating_cost, ranking_cost
        self.gamma, self.num_samples, self.target = gamma, num_samples, target
        self.top_fraction, self.num_plausible, self.num_bins = top_fraction, num_plausible, num_bins
        self.min_count, self.bias_correction = min_count, bias_correction
        self.level_edges = tuple(float(e) for e in level_edges)

    def _levels(self, F: Tensor, rating_likelihood) -> Tensor:
        """``T x S x L x N``: is each sample's rating mean ``Phi(f / (sqrt 2 sigma_B))`` above
        each of :attr:`level_edges` (the latent thresholds ``sqrt 2 sigma_B Phi^-1(edge)``)."""
        edges = torch.tensor(self.level_edges, dtype=F.dtype, device=F.device)
        c = math.sqrt(2) * rating_likelihood.rating_scale.to(F) * torch.special.ndtri(edges)
        return F.unsqueeze(-2) > c.reshape(-1, 1)

    def _prepare(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Tensor, Tensor, Callable[[Tensor], Tensor], Any]:
        """Joint samples ``F`` (``T x S x N``), the candidates by uncertainty of the target (``T x
        N``), the information function of answer probabilities and the model's likelihood."""
        mean, cov = joint_posterior(model, X)
        F, std = joint_samples(mean, cov, generators, self.num_samples)  # T x S x N
        T, S, N = F.shape
        lik = preference_likelihood(model)
        ucb = mean + self.gamma * std
        tie = 1e-9 * torch.sigmoid(ucb - ucb.max(-1, keepdim=True).values)
        if self.target in ("top", "top+levels"):
            Z = top_set_membership(F, max(1, min(N, round(self.top_fraction * N))))
            if self.target == "top+levels":  # and each item's rating level: N x L more labels
                Z = torch.cat([Z, self._levels(F, lik.rating).flatten(-2)], dim=-1)
            p = Z.to(F).mean(-2)
            order = torch.argsort((p * (1 - p)).reshape(T, -1, N).sum(1) + tie, dim=-1, descending=True)

            def info(P: Tensor) -> Tensor:  # T x R x S x Y -> T x R
                return membership_information(P, Z, self.min_count, self.bias_correction)

            return F, order, info, lik
        argmax = F.argmax(-1)  # T x S
        p_max = torch.zeros_like(mean).scatter_add_(1, argmax, torch.ones_like(F[..., 0])) / S
        order = torch.argsort(p_max + tie, dim=-1, descending=True)
        if self.target == "maximizer":
            # which plausible candidate is the maximiser (K + 1 labels: K for "another one"), few
            # enough that every label has many samples (a plug-in estimate is biased upwards when
            # labels have few samples each)
            K = min(self.num_plausible, N)
            rank = torch.full((T, N), K, dtype=torch.long, device=F.device)
            rank.scatter_(1, order[:, :K], torch.arange(K, device=F.device).expand(T, K))
            labels = rank.gather(1, argmax)  # T x S

            def info(P: Tensor) -> Tensor:
                return torch.stack([sample_information(P[b], labels[b], K + 1) for b in range(T)])

            return F, order, info, lik
        return F, order, sample_information, lik

    def scorers(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Callable[[Tensor], Tensor], Callable[[Tensor], Tensor]]:
        """The information of a rating of rows ``T x R`` and of a ranking of rows ``T x R x q`` (not
        per effort; :meth:`PerEffortSelector.scorers`)."""
        F, _, info, lik = self._prepare(model, X, generators)
        return sample_scorers(F, info, lik, self.num_bins)

    query_cost = PerEffortSelector.query_cost
    choose = PerEffortSelector.choose

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        with torch.no_grad():
            F, order, info, lik = self._prepare(model, X, generators)
            T, S, N = F.shape
            cand = order[:, : min(self.num_plausible, N)]  # T x K
            Fc = F.gather(2, cand.unsqueeze(1).expand(T, S, cand.shape[1]))  # T x S x K
            rating_info = info(rating_bin_probabilities(Fc.mT, lik.rating, self.num_bins))  # T x K x S x G -> T x K
            best_rating = cand.gather(1, rating_info.argmax(-1, keepdim=True)).squeeze(-1).tolist()
            rating_value = rating_info.max(-1).values / self.rating_cost
            if cand.shape[1] < self.m or self.m < 2:
                return [rating_query(X[b], indices[b], best_rating[b]) for b in range(T)]
            chosen, value = greedy_choice_sets(Fc, lik.comparison, self.m, info, start=0)
            ranking = (value / self.ranking_cost > rating_value).tolist()
            rows = cand.gather(1, chosen)  # T x m
        return [
            ranking_query(X[b], indices[b], rows[b]) if ranking[b] else rating_query(X[b], indices[b], best_rating[b])
            for b in range(T)
        ]
