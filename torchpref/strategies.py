r"""Query selectors: given a model and candidate items, return the next query.

Every selector has ``select(model, X, indices, step, num_steps, generator) -> Query`` with
``X`` the ``N x d`` candidates (``indices`` their pool rows, or ``None``), ``step`` the
zero-based query number out of ``num_steps``. Baselines (paper Sec. IV.A): random ratings,
random rankings, UCB ratings, random mixed. The paper's combined strategy is :class:`UCBC`;
:class:`InformationPerEffort` is ours.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchpref.acquisition import (
    QueryUCB,
    greedy_choice_set,
    membership_information,
    rating_bin_probabilities,
    sample_information,
    top_set_membership,
)
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
            p = torch.softmax((logits - logits.max()) / temp, dim=0)  # drawn rows: logit -inf
            r = int(torch.multinomial(p, 1, generator=generator))
            rows.append(r)
            logits[r] = -math.inf
        return _ranking(X, indices, torch.tensor(rows))


class InformationPerEffort(Selector):
    r"""Ask the query whose answer is expected to carry the most information per unit of effort.

    From ``num_samples`` joint posterior samples of the utility over the ``N`` candidates it
    values each query by the mutual information between its answer and a target:

    * ``target="top"`` (default): which candidates are in the top set, the ``k =
      round(top_fraction * N)`` largest utilities of each sample. The value is the summed
      information about each candidate's membership,
      ``sum_i I(y; 1[f(x_i) in top k])`` (:func:`~torchpref.acquisition.membership_information`),
      the expected reduction of the summed membership entropies, with the estimator's
      finite-sample bias removed (without the correction, summed over ~100 items, the bias is
      as large as the information itself and favours ratings over rankings). It buys
      information on the whole upper region and on its boundary (which item is in, which is
      just out), not only on the single best item;
    * ``target="maximizer"``: which candidate is the maximiser, the discrete entropy search of
      Hennig & Schuler (2012) / Villemonteix et al. (2009)
      (:func:`~torchpref.acquisition.sample_information`);
    * ``target="utility"``: the utility itself (the answer's ``I(y; f)``, as
      :class:`~torchpref.acquisition.QueryInformation`).

    The ``num_plausible`` candidates whose target is most uncertain (``"top"``: membership
    probability nearest 1/2; otherwise: likeliest maximisers; ties by eq. 12's UCB) are
    considered: a rating of each is valued with its binned Beta answer, a best-of-``m`` ranking
    is built greedily among them (:func:`~torchpref.acquisition.greedy_choice_set`: start at the
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
        target: ``"top"``, ``"maximizer"`` or ``"utility"``.
        top_fraction: the top set's share of the candidates (``target="top"``).
        num_plausible: candidates considered for ratings and rankings.
        num_bins: bins of a rating's answer.
        min_count: ``target="top"``: an item counts only if both its labels have at least this
            many samples (membership probability in ``[min_count / S, 1 - min_count / S]``;
            see :func:`~torchpref.acquisition.membership_information`).
        bias_correction: ``target="top"``: correct the information estimates' finite-sample
            bias (:func:`~torchpref.acquisition.membership_information`).
    """

    name = "info per effort"

    def __init__(self, m: int = 5, rating_cost: float = 1.0, ranking_cost: float | None = None,
                 gamma: float = 3.0, num_samples: int = 128, target: str = "top", top_fraction: float = 0.2,
                 num_plausible: int = 15, num_bins: int = 10, min_count: int = 8, bias_correction: bool = True):
        if ranking_cost is None:
            ranking_cost = 1.0 + (m - 1) / 4
        if not (rating_cost > 0 and ranking_cost > 0):
            raise ValueError(f"costs must be positive, got rating_cost={rating_cost}, ranking_cost={ranking_cost}.")
        if target not in ("top", "maximizer", "utility"):
            raise ValueError(f"target must be 'top', 'maximizer' or 'utility', got {target!r}.")
        if num_samples < 2 or num_plausible < 1:
            raise ValueError(f"need num_samples >= 2 and num_plausible >= 1, got {num_samples} and {num_plausible}.")
        if not 0 < top_fraction < 1:
            raise ValueError(f"top_fraction must be in (0, 1), got {top_fraction}.")
        self.m, self.rating_cost, self.ranking_cost = m, float(rating_cost), float(ranking_cost)
        self.gamma, self.num_samples, self.target = gamma, num_samples, target
        self.top_fraction, self.num_plausible, self.num_bins = top_fraction, num_plausible, num_bins
        self.min_count, self.bias_correction = min_count, bias_correction

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
            tie = 1e-9 * torch.sigmoid((mean + self.gamma * std) - (mean + self.gamma * std).max())
            if self.target == "top":
                Z = top_set_membership(F, max(1, min(N, round(self.top_fraction * N))))
                p = Z.to(F).mean(0)
                order = torch.argsort(p * (1 - p) + tie, descending=True)

                def info(P: Tensor) -> Tensor:
                    return membership_information(P, Z, self.min_count, self.bias_correction)
            else:
                argmax = F.argmax(-1)
                p_max = torch.bincount(argmax, minlength=N).to(mean) / F.shape[0]
                order = torch.argsort(p_max + tie, descending=True)
                labels = None
                if self.target == "maximizer":
                    # which plausible candidate is the maximiser (K + 1 labels: K for "another
                    # one"), few enough that every label has many samples (a plug-in estimate is
                    # biased upwards when labels have few samples each)
                    K = min(self.num_plausible, N)
                    rank = torch.full((N,), K, dtype=torch.long, device=X.device)
                    rank[order[:K]] = torch.arange(K, device=X.device)
                    labels = rank[argmax]

                def info(P: Tensor) -> Tensor:
                    return sample_information(P, labels, None if labels is None else K + 1)
            cand = order[: min(self.num_plausible, N)]
            Fc = F[:, cand]  # S x K
            lik = model.likelihood
            rating_info = info(rating_bin_probabilities(Fc.mT, lik.rating, self.num_bins))  # K x S x G -> K
            best_rating = int(cand[int(rating_info.argmax())])
            rating_value = float(rating_info.max()) / self.rating_cost
            if cand.numel() < self.m or self.m < 2:
                return _rating(X, indices, best_rating)
            chosen, value = greedy_choice_set(Fc, lik.comparison.comparison_noise, self.m, info, start=0)
            ranking_value = value / self.ranking_cost
        if ranking_value > rating_value:
            return _ranking(X, indices, cand[torch.tensor(chosen)])
        return _rating(X, indices, best_rating)
