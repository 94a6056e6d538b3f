r"""Query selectors: given a model and candidate items, return the next query.

Every selector has ``select(model, X, indices, step, num_steps, generator) -> Query`` with
``X`` the ``N x d`` candidates (``indices`` their pool rows, or ``None``), ``step`` the
zero-based query number out of ``num_steps``. Baselines (paper Sec. IV.A): random ratings,
random rankings, UCB ratings, random mixed. The paper's combined strategy is :class:`UCBC`;
:class:`InformationPerEffort` is ours.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchpref.acquisition import QueryInformation, QueryUCB
from torchpref.queries import Query, RankingQuery, RatingQuery


def _rating(X: Tensor, indices: Tensor | None, i: int) -> RatingQuery:
    return RatingQuery(X[i], None if indices is None else int(indices[i]))


def _ranking(X: Tensor, indices: Tensor | None, rows: Tensor) -> RankingQuery:
    rows = rows.reshape(-1)
    return RankingQuery(X[rows], None if indices is None else tuple(int(indices[r]) for r in rows))


def _check_m(m: int, X: Tensor) -> None:
    if m < 2:
        raise ValueError(f"a ranking query needs m >= 2 items, got m={m}.")
    if X.shape[0] < m:
        raise ValueError(f"need at least m={m} candidates for a ranking query, got {X.shape[0]}.")


class Selector:
    """Base class; ``name`` labels results."""

    name = "selector"

    def select(self, model, X: Tensor, indices: Tensor | None, step: int, num_steps: int,
               generator: torch.Generator) -> Query:
        raise NotImplementedError


class RandomRatings(Selector):
    """Rate a uniformly random candidate."""

    name = "random ratings"

    def select(self, model, X, indices, step, num_steps, generator):
        return _rating(X, indices, int(torch.randint(X.shape[0], (1,), generator=generator)))


class RandomRankings(Selector):
    """Best of ``m`` uniformly random distinct candidates."""

    name = "random rankings"

    def __init__(self, m: int = 5):
        self.m = m

    def select(self, model, X, indices, step, num_steps, generator):
        _check_m(self.m, X)
        return _ranking(X, indices, torch.randperm(X.shape[0], generator=generator)[: self.m])


class RandomMixed(Selector):
    """A random rating or a random ranking, with probability ``p_ranking`` of a ranking."""

    name = "random mixed"

    def __init__(self, m: int = 5, p_ranking: float = 0.5):
        self.m, self.p_ranking = m, p_ranking

    def select(self, model, X, indices, step, num_steps, generator):
        if float(torch.rand((), generator=generator, dtype=torch.float64)) < self.p_ranking:
            return RandomRankings(self.m).select(model, X, indices, step, num_steps, generator)
        return RandomRatings().select(model, X, indices, step, num_steps, generator)


def _ucb(model, X: Tensor, gamma: float) -> Tensor:
    with torch.no_grad():
        return QueryUCB(model, gamma)(X.unsqueeze(-2))


class UCBRatings(Selector):
    """Rate the candidate of largest UCB (eq. 12)."""

    name = "UCB ratings"

    def __init__(self, gamma: float = 3.0):
        self.gamma = gamma

    def select(self, model, X, indices, step, num_steps, generator):
        return _rating(X, indices, int(_ucb(model, X, self.gamma).argmax()))


class UCBC(Selector):
    r"""The paper's combined strategy (Sec. III.C), as the authors' code ran it.

    At zero-based query ``t`` of ``T`` it asks for a ranking with probability
    ``max(0, (T - t) / T)`` (so early queries are rankings, later ones ratings), else a rating.
    Rating: the candidate of largest UCB. Ranking: ``m`` distinct candidates drawn by a softmax
    over UCB, with temperature ``temperatures[0]`` for the first and ``temperatures[1]`` after.

    Args:
        gamma: eq. 12's ``gamma`` (the paper's text: 3; the authors' code: 2).
        m: items per ranking query.
        temperatures: softmax temperatures (the authors': 5 then 25).
    """

    name = "UCBC"

    def __init__(self, gamma: float = 3.0, m: int = 5, temperatures: tuple[float, float] = (5.0, 25.0)):
        self.gamma, self.m, self.temperatures = gamma, m, temperatures

    def ranking_probability(self, step: int, num_steps: int) -> float:
        return max(0.0, (num_steps - step) / num_steps)

    def select(self, model, X, indices, step, num_steps, generator):
        ucb = _ucb(model, X, self.gamma)
        coin = float(torch.rand((), generator=generator, dtype=torch.float64))
        if coin >= self.ranking_probability(step, num_steps):
            return _rating(X, indices, int(ucb.argmax()))
        _check_m(self.m, X)
        logits = ucb.clone()
        rows = []
        for k in range(self.m):
            temp = self.temperatures[0] if k == 0 else self.temperatures[1]
            p = torch.softmax(temp * (logits - logits.max()), dim=0)
            if rows:
                p[torch.tensor(rows)] = 0.0
            r = int(torch.multinomial(p, 1, generator=generator))
            rows.append(r)
        return _ranking(X, indices, torch.tensor(rows))


class InformationPerEffort(Selector):
    r"""Ask the query whose answer is expected to carry the most information per unit of effort.

    Candidates are restricted to the plausible maximisers, ``{x : UCB(x) >= max LCB}`` (with
    eq. 12's ``gamma``), so the information bought is about where the utility is high. Among
    them it values a rating of each item and a best-of-``m`` ranking built greedily (start at
    the largest UCB, add the item that most increases the ranking's information), each by
    :class:`~torchpref.acquisition.QueryInformation`, divided by the query's cost.

    Args:
        m: items per ranking query.
        rating_cost: effort of one rating.
        ranking_cost: effort of one best-of-``m`` choice.
        gamma: width of the confidence band that defines the plausible maximisers.
        num_samples: posterior samples for the ranking information.
    """

    name = "info per effort"

    def __init__(self, m: int = 5, rating_cost: float = 1.0, ranking_cost: float = 1.0, gamma: float = 3.0,
                 num_samples: int = 128):
        if rating_cost <= 0 or ranking_cost <= 0:
            raise ValueError(f"costs must be positive, got rating_cost={rating_cost}, ranking_cost={ranking_cost}.")
        self.m, self.rating_cost, self.ranking_cost = m, rating_cost, ranking_cost
        self.gamma, self.num_samples = gamma, num_samples

    def select(self, model, X, indices, step, num_steps, generator):
        with torch.no_grad():
            post = model.posterior(X.unsqueeze(-2))
            mean = post.mean.reshape(-1)
            std = post.variance.reshape(-1).clamp_min(0).sqrt()
            ucb, lcb = mean + self.gamma * std, mean - self.gamma * std
            plausible = (ucb >= lcb.max()).nonzero().reshape(-1)
            if plausible.numel() < self.m:
                plausible = ucb.argsort(descending=True)[: max(self.m, plausible.numel())]
            info = QueryInformation(model, num_samples=self.num_samples, generator=generator)
            Xp = X[plausible]
            rating_info = info(Xp.unsqueeze(-2))
            best_rating = int(rating_info.argmax())
            rating_value = float(rating_info[best_rating]) / self.rating_cost
            if Xp.shape[0] < self.m:
                return _rating(X, indices, int(plausible[best_rating]))
            chosen = [int(ucb[plausible].argmax())]
            value = 0.0
            for _ in range(self.m - 1):
                rest = torch.tensor([i for i in range(Xp.shape[0]) if i not in chosen], dtype=torch.long)
                sets = torch.cat([Xp[chosen].expand(rest.numel(), -1, -1), Xp[rest].unsqueeze(-2)], dim=-2)
                vals = info(sets)
                k = int(vals.argmax())
                chosen.append(int(rest[k]))
                value = float(vals[k])
            ranking_value = value / self.ranking_cost
        if ranking_value > rating_value:
            return _ranking(X, indices, plausible[torch.tensor(chosen)])
        return _rating(X, indices, int(plausible[best_rating]))
