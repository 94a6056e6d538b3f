r"""Ask the best-of-``m`` of largest expected utility of its best option (qEUBO; Lin, Astudillo,
Frazier & Bakshy 2022), BoTorch's acquisition for preference exploration, as a selector.

``qEUBO(Q) = E[max_{x in Q} f(x)]`` under the model's posterior: the expected utility of the
option the person would pick if they saw the utilities without noise. It is what BoTorch's
``qExpectedUtilityOfBestOption(pref_model=model)`` computes for a set ``Q`` (no outcome model);
here it is estimated on joint posterior samples of the candidates (common random numbers from the
trial's generator), so that it runs on any selector model: a person model with a population's
prior mean (``pop.person_model(...)``) and the batched model of the suite alike.
``tests/selection/test_eubo.py`` checks the estimate against BoTorch's own class on a person model.

A query is built greedily: the pair of largest ``qEUBO`` among the ``num_plausible`` likeliest
maximisers (ties by eq. 12's UCB), then the item that raises it most, until ``m`` items. qEUBO
asks rankings only (a rating's ``qEUBO`` is the item's posterior mean, never above a set's that
holds it).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchpref.data.queries import Query, ranking_query
from torchpref.selection.choosing import query_items
from torchpref.selection.samples import SelectorModel, joint_posterior, joint_samples
from torchpref.selection.strategies import Selector, _check_m, _ranking_size

__all__ = ["ExpectedBestOption", "expected_best_option"]


def expected_best_option(F: Tensor, rows: Tensor) -> Tensor:
    r"""``qEUBO`` of sets of rows under samples: ``F`` ``T x S x N``, ``rows`` ``T x R x q`` ->
    ``T x R``, ``mean_s max_{i in set} F[s, i]``."""
    T, S, _ = F.shape
    R, q = rows.shape[1:]
    Fr = F.gather(2, rows.reshape(T, 1, R * q).expand(T, S, R * q)).reshape(T, S, R, q)
    return Fr.max(-1).values.mean(1)


class ExpectedBestOption(Selector):
    r"""The best-of-``m`` of largest ``qEUBO`` (module notes).

    Args:
        m: items per ranking query.
        num_samples: joint posterior samples.
        num_plausible: candidates considered (the likeliest maximisers).
        gamma: eq. 12's ``gamma``, to order candidates of equal probability of being the maximiser.

    Raises:
        ValueError: ``num_samples < 2`` or ``num_plausible < 2``.
    """

    name = "qEUBO"

    def __init__(self, m: int = 5, num_samples: int = 256, num_plausible: int = 30, gamma: float = 3.0):
        if num_samples < 2 or num_plausible < 2:
            raise ValueError(f"need num_samples >= 2 and num_plausible >= 2, got {num_samples} and {num_plausible}.")
        self.m, self.num_samples, self.num_plausible, self.gamma = _ranking_size(m), num_samples, num_plausible, gamma

    def _samples(self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]) -> tuple[Tensor, Tensor]:
        """Joint samples ``T x S x N`` and the candidates by probability of being the maximiser
        (ties by UCB), ``T x N``."""
        mean, cov = joint_posterior(model, X)
        F, std = joint_samples(mean, cov, generators, self.num_samples)
        T, S, N = F.shape
        p_max = torch.zeros_like(mean).scatter_add_(1, F.argmax(-1), torch.ones_like(F[..., 0])) / S
        ucb = mean + self.gamma * std
        tie = 1e-9 * torch.sigmoid(ucb - ucb.max(-1, keepdim=True).values)
        return F, torch.argsort(p_max + tie, dim=-1, descending=True)

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
        with torch.no_grad():
            F, order = self._samples(model, X, generators)
            T, S, _ = F.shape
            K = max(self.m, min(self.num_plausible, X.shape[1]))
            cand = order[:, :K]
            Fc = F.gather(2, cand.unsqueeze(1).expand(T, S, K))  # T x S x K
            pair = torch.maximum(Fc.unsqueeze(-1), Fc.unsqueeze(-2)).mean(1)  # T x K x K
            pair = pair.masked_fill(torch.eye(K, dtype=torch.bool), -torch.inf)
            flat = pair.reshape(T, -1).argmax(-1)
            chosen = [torch.stack([flat // K, flat % K], -1)]  # T x 2
            best = torch.maximum(Fc.gather(2, chosen[0][:, :1].unsqueeze(1).expand(T, S, 1)), Fc.gather(2, chosen[0][:, 1:].unsqueeze(1).expand(T, S, 1))).squeeze(-1)  # fmt: skip
            used = torch.zeros(T, K, dtype=torch.bool).scatter_(1, chosen[0], True)
            for _ in range(self.m - 2):
                gain = torch.maximum(best.unsqueeze(-1), Fc).mean(1).masked_fill(used, -torch.inf)  # T x K
                j = gain.argmax(-1, keepdim=True)
                chosen.append(j)
                used.scatter_(1, j, True)
                best = torch.maximum(best, Fc.gather(2, j.unsqueeze(1).expand(T, S, 1)).squeeze(-1))
            rows = cand.gather(1, torch.cat(chosen, -1))
        return [ranking_query(X[b], indices[b], rows[b]) for b in range(T)]

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """The query of largest ``qEUBO`` (a rating's: its item's posterior mean); ties to the first."""
        qr = query_items(queries)
        with torch.no_grad():
            F, _ = self._samples(model, qr.X.unsqueeze(0), [generator])
            values = torch.stack([expected_best_option(F, r.reshape(1, 1, -1))[0, 0] for r in qr.rows])
        return int(values.argmax())
