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

from torchpref.acquisition import QueryUCB, choice_probabilities, rating_bin_probabilities, sample_information
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

    From ``num_samples`` joint posterior samples of the utility over the ``N`` candidates it
    values each query by the mutual information between its answer and a target
    (:func:`~torchpref.acquisition.sample_information`):

    * ``target="maximizer"`` (default): which candidate is the maximiser, the discrete entropy
      search of Hennig & Schuler (2012) / Villemonteix et al. (2009), so information is bought
      where the utility is high;
    * ``target="utility"``: the utility itself (the answer's ``I(y; f)``, as
      :class:`~torchpref.acquisition.QueryInformation`).

    A rating of each of the ``num_plausible`` candidates most likely to be the maximiser (ties by
    eq. 12's UCB) is valued with its binned Beta answer; a best-of-``m`` ranking is built
    greedily among them (start at the likeliest maximiser, add the item that most increases the
    ranking's information). The query of largest information / cost is asked.

    Args:
        m: items per ranking query.
        rating_cost: effort of one rating.
        ranking_cost: effort of one best-of-``m`` choice (default ``1 + (m - 1) / 4``: 2 for
            ``m = 5``, twice a rating; see ``docs/wave.md``).
        gamma: eq. 12's ``gamma``, to order candidates of equal maximiser probability.
        num_samples: joint posterior samples.
        target: ``"maximizer"`` or ``"utility"``.
        num_plausible: candidates considered for ratings and rankings.
        num_bins: bins of a rating's answer.
    """

    name = "info per effort"

    def __init__(self, m: int = 5, rating_cost: float = 1.0, ranking_cost: float | None = None,
                 gamma: float = 3.0, num_samples: int = 128, target: str = "maximizer",
                 num_plausible: int = 10, num_bins: int = 10):
        if ranking_cost is None:
            ranking_cost = 1.0 + (m - 1) / 4
        if not (rating_cost > 0 and ranking_cost > 0):
            raise ValueError(f"costs must be positive, got rating_cost={rating_cost}, ranking_cost={ranking_cost}.")
        if target not in ("maximizer", "utility"):
            raise ValueError(f"target must be 'maximizer' or 'utility', got {target!r}.")
        if num_samples < 2 or num_plausible < 1:
            raise ValueError(f"need num_samples >= 2 and num_plausible >= 1, got {num_samples} and {num_plausible}.")
        self.m, self.rating_cost, self.ranking_cost = m, float(rating_cost), float(ranking_cost)
        self.gamma, self.num_samples, self.target = gamma, num_samples, target
        self.num_plausible, self.num_bins = num_plausible, num_bins

    def _samples(self, model, X: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
        """``S x N`` joint samples, the posterior mean and std at ``X``."""
        mvn = model.posterior(X.unsqueeze(0)).distribution
        mean = mvn.mean.reshape(-1)
        cov = mvn.covariance_matrix.reshape(mean.numel(), mean.numel())
        std = cov.diagonal().clamp_min(0).sqrt()
        jitter = 1e-9 * float(cov.diagonal().mean().clamp_min(1e-12))
        eye = torch.eye(mean.numel(), dtype=mean.dtype, device=mean.device)
        for _ in range(8):
            L, info = torch.linalg.cholesky_ex(cov + jitter * eye)
            if not info:
                break
            jitter *= 10
        else:  # fall back on independent samples
            L = torch.diag(std)
        z = torch.randn(self.num_samples, mean.numel(), generator=generator, dtype=mean.dtype, device=mean.device)
        return mean + z @ L.mT, mean, std

    def select(self, model, X, indices, step, num_steps, generator):
        with torch.no_grad():
            F, mean, std = self._samples(model, X, generator)
            N = X.shape[0]
            ucb = mean + self.gamma * std
            argmax = F.argmax(-1)
            p_max = torch.bincount(argmax, minlength=N).to(mean) / F.shape[0]
            order = torch.argsort(p_max + 1e-9 * torch.sigmoid(ucb - ucb.max()), descending=True)
            cand = order[: min(self.num_plausible, N)]
            Fc = F[:, cand]  # S x K
            labels = None
            if self.target == "maximizer":
                # which plausible candidate is the maximiser (K + 1 labels: K for "another one"),
                # few enough that every label has many samples (a plug-in estimate is biased
                # upwards when labels have few samples each)
                rank = torch.full((N,), cand.numel(), dtype=torch.long, device=X.device)
                rank[cand] = torch.arange(cand.numel(), device=X.device)
                labels = rank[argmax]
            N = cand.numel() + 1
            lik = model.likelihood
            P_rate = rating_bin_probabilities(Fc.mT, lik.rating, self.num_bins)  # K x S x G
            rating_info = sample_information(P_rate, labels, N)
            best_rating = int(rating_info.argmax())
            rating_value = float(rating_info[best_rating]) / self.rating_cost
            K = cand.numel()
            if K < self.m or self.m < 2:
                return _rating(X, indices, int(cand[best_rating]))
            chosen = [0]
            value = 0.0
            noise = lik.comparison.comparison_noise
            for _ in range(self.m - 1):
                rest = torch.tensor([i for i in range(K) if i not in chosen], dtype=torch.long)
                sets = torch.cat([torch.tensor(chosen).expand(rest.numel(), -1), rest.unsqueeze(-1)], dim=-1)
                f_sets = Fc[:, sets].permute(1, 0, 2)  # b x S x q
                vals = sample_information(choice_probabilities(f_sets, noise), labels, N)
                k = int(vals.argmax())
                chosen.append(int(rest[k]))
                value = float(vals[k])
            ranking_value = value / self.ranking_cost
        if ranking_value > rating_value:
            return _ranking(X, indices, cand[torch.tensor(chosen)])
        return _rating(X, indices, int(cand[best_rating]))
