r"""The simulated lake-monitoring operator of the paper (Sec. IV.B).

Likert level ``u`` of a path with objectives ``[distance, information]``:

.. math::
    u = 1 \text{ if information} < 125, \quad u = 2 \text{ if } 125 \le \text{information} < 150,
    \quad u = \mathrm{clip}(\lceil 5 - (\text{distance} - 450) / 50 \rceil, 1, 5) \text{ otherwise},

so a path with at least 150 information is rated 5 below distance 500, 4 below 550, 3 below
600, 2 below 650, and 1 from there on (at 500 exactly the formula gives 4). (The paper leaves ``information == 125`` open; here it is 2.)
"""

from __future__ import annotations

from typing import Protocol

import torch
from torch import Tensor

from torchpref.data.preference_data import likert_to_unit

__all__ = ["LakeOperator", "RealisticLakeOperator"]


class Operator(Protocol):
    """Who :class:`RealisticLakeOperator` wraps: a rating in ``[0, 1]`` of one path, the best of
    several (:class:`LakeOperator`, the experiment's normalised operator)."""

    def rate(self, x: Tensor, /) -> float: ...

    def choose(self, X: Tensor, /) -> int: ...


class LakeOperator:
    r"""A simulated operator who wants at least ``info_good`` information, then short paths.

    As a user of the active-learning loop it answers rating queries with :meth:`rate` and
    best-of-``m`` ranking queries with :meth:`choose`, both noise-free.

    Args:
        info_poor: below this information a path is rated 1 (paper: 125).
        info_good: below this (and at least ``info_poor``) a path is rated 2 (paper: 150).
        distance_best: distance up to which the level formula gives 5 or more (paper: 450).
        distance_scale: distance per Likert level (paper: 50).
        num_levels: levels on the scale (paper: 5).
    """

    def __init__(
        self,
        *,
        info_poor: float = 125.0,
        info_good: float = 150.0,
        distance_best: float = 450.0,
        distance_scale: float = 50.0,
        num_levels: int = 5,
    ) -> None:
        if not info_poor <= info_good:
            raise ValueError(f"need info_poor <= info_good, got {info_poor} and {info_good}.")
        if not distance_scale > 0:
            raise ValueError(f"distance_scale must be positive, got {distance_scale}.")
        if num_levels < 3:
            raise ValueError(f"num_levels must be at least 3, got {num_levels}.")
        self.info_poor, self.info_good = float(info_poor), float(info_good)
        self.distance_best, self.distance_scale = float(distance_best), float(distance_scale)
        self.num_levels = int(num_levels)

    @staticmethod
    def _check(X) -> Tensor:
        X = torch.as_tensor(X, dtype=torch.float64)
        if X.dim() < 1 or X.shape[-1] != 2:
            raise ValueError(
                f"objective vectors must be ... x 2 ([distance, information]), got shape {tuple(X.shape)}."
            )
        if not torch.isfinite(X).all():
            raise ValueError(f"objective vectors must be finite, got {X.flatten().tolist()[:6]}.")
        return X

    def level(self, X: Tensor) -> Tensor:
        r"""Likert levels of objective vectors.

        Args:
            X: ``... x 2`` rows ``[distance, information]``.

        Returns:
            A long tensor of shape ``...`` with levels in ``1..num_levels``.
        """
        X = self._check(X)
        distance, info = X[..., 0], X[..., 1]
        by_distance = torch.ceil(self.num_levels - (distance - self.distance_best) / self.distance_scale)
        by_distance = by_distance.clamp(1, self.num_levels)
        u = torch.where(info < self.info_good, torch.full_like(info, 2.0), by_distance)
        u = torch.where(info < self.info_poor, torch.ones_like(info), u)
        return u.long()

    def utility(self, X: Tensor) -> Tensor:
        r"""A score that orders paths as the levels do and breaks ties within a level:
        ``10^7 level + information`` below ``info_good`` (more is better) and
        ``10^7 level + 10^6 - distance`` from there on (enough information first, then the
        shorter path). Shape ``...``."""
        X = self._check(X)
        lv = self.level(X).to(X.dtype)
        tie = torch.where(X[..., 1] < self.info_good, X[..., 1], 1e6 - X[..., 0])
        return lv * 1e7 + tie

    def rate(self, x: Tensor) -> float:
        r"""A rating query: the level of one path mapped to ``[0, 1]`` by
        :func:`torchpref.data.preference_data.likert_to_unit` (level ``k`` -> ``(k - 1/2) / 5``).

        Args:
            x: ``2`` objective vector ``[distance, information]``.
        """
        x = self._check(x)
        if x.shape != (2,):
            raise ValueError(f"rate takes one objective vector of shape (2,), got {tuple(x.shape)}.")
        return float(likert_to_unit(self.level(x), num_levels=self.num_levels))

    def choose(self, X: Tensor) -> int:
        r"""A ranking query: the index of the preferred row of ``X`` (``m x 2``).

        The best level wins; among rows of the best level a path with at least ``info_good``
        information beats one without, then the shorter path wins, and among paths below
        ``info_good`` more information wins (:meth:`utility`); an exact tie goes to the
        lowest index.
        """
        X = self._check(X)
        if X.dim() != 2 or X.shape[0] < 1:
            raise ValueError(f"choose takes an m x 2 tensor with m >= 1, got shape {tuple(X.shape)}.")
        return int(self.utility(X).argmax())


class RealisticLakeOperator:
    r"""The paper's operator answering as a real person would (not in the paper): a personal offset
    and a drift on the rating scale, rating noise, and lapses in rankings.

    A rating is the operator's level ``k`` (:class:`LakeOperator`) moved by the person's
    ``level_offset`` ``b``, a drift ``d_t`` (a random walk over the answers, step ``drift_sd``) and
    noise ``e ~ N(0, level_noise^2)``, rounded and clipped to ``1..K``: ``round(k + b + d_t + e)``,
    mapped to ``[0, 1]`` as the paper's operator's. A ranking is a uniformly random path with
    probability ``lapse_rate``, else the paper's operator's choice. Default figures in levels of
    the 1-5 scale: offset 0.29 and noise 0.39 are SUREAL's person offset and rating noise on a 1-5
    scale (Li & Bampis 2017, Netflix NFLX data); a lapse rate of 0.15 puts choices' agreement in
    the 72-77 % range measured for people (Stiennon et al. 2020).

    It wraps any user with ``rate`` / ``choose`` (e.g. the experiment's normalised operator).

    Args:
        operator: the deterministic operator (its :meth:`rate` and :meth:`choose` are used).
        generator: the source of randomness.
        level_offset: ``b``, in levels.
        drift_sd: the drift's step per answer, in levels.
        level_noise: the rating noise's standard deviation, in levels.
        lapse_rate: the probability of a random choice.
        num_levels: ``K``.
    """

    def __init__(
        self,
        operator: Operator,
        generator: torch.Generator,
        *,
        level_offset: float = 0.29,
        drift_sd: float = 0.05,
        level_noise: float = 0.39,
        lapse_rate: float = 0.15,
        num_levels: int = 5,
    ) -> None:
        for name, v in (("drift_sd", drift_sd), ("level_noise", level_noise)):
            if not v >= 0:
                raise ValueError(f"{name} must be non-negative, got {v}.")
        if not 0 <= lapse_rate <= 1:
            raise ValueError(f"lapse_rate must be in [0, 1], got {lapse_rate}.")
        self.operator, self.generator = operator, generator
        self.level_offset, self.drift_sd, self.level_noise = float(level_offset), float(drift_sd), float(level_noise)
        self.lapse_rate, self.num_levels = float(lapse_rate), int(num_levels)
        self.drift = 0.0

    def _step(self) -> None:
        if self.drift_sd > 0:
            self.drift += self.drift_sd * float(torch.randn((), generator=self.generator, dtype=torch.float64))

    def rate(self, x: Tensor) -> float:
        """The person's rating of one path (module notes of the class)."""
        K = self.num_levels
        level = round(float(self.operator.rate(x)) * K + 0.5)  # the bin centre back to its level
        noise = self.level_noise * float(torch.randn((), generator=self.generator, dtype=torch.float64))
        k = min(max(round(level + self.level_offset + self.drift + noise), 1), K)
        self._step()
        return float(likert_to_unit(torch.tensor(k), num_levels=K))

    def choose(self, X: Tensor) -> int:
        """The person's choice among ``m`` paths: a lapse with probability ``lapse_rate``."""
        m = torch.as_tensor(X).shape[0]
        lapse = float(torch.rand((), generator=self.generator, dtype=torch.float64)) < self.lapse_rate
        choice = int(torch.randint(0, m, (), generator=self.generator)) if lapse else self.operator.choose(X)
        self._step()
        return choice
