r"""The simulated lake-monitoring operator of the paper (Sec. IV.B).

Likert level ``u`` of a path with objectives ``[distance, information]``:

.. math::
    u = 1 \text{ if information} < 125, \quad u = 2 \text{ if } 125 \le \text{information} < 150,
    \quad u = \mathrm{clip}(\lceil 5 - (\text{distance} - 450) / 50 \rceil, 1, 5) \text{ otherwise},

so a path with at least 150 information is rated 5 below distance 500, 4 below 550, 3 below
600, 2 below 650, and 1 from there on (at 500 exactly the formula gives 4). (The paper leaves ``information == 125`` open; here it is 2.)
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchpref.data.preference_data import likert_to_unit

__all__ = ["LakeOperator"]


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
