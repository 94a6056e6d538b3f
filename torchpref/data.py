r"""Observations: items, comparisons and ratings, with validation.

The model sees three things (paper Sec. III.B.1):

* ``train_X`` (``n x d``): the items, one row per distinct point of the objective space;
* ``comparisons`` (``p x 2`` long): row ``[i, j]`` means item ``i`` was preferred to item
  ``j`` (BoTorch's convention; the paper's label ``d = -1`` for ``x_i > x_j``);
* ``ratings`` (``q``) in ``[0, 1]`` with ``rating_index`` (``q`` long): item rated by each.

:class:`PreferenceData` is immutable: adding observations returns a new object, so a failed
update never leaves a half-updated model behind.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor

DEFAULT_RATING_EPS = 1e-3

TensorLike = Tensor | Sequence[Any] | float
"""What ``torch.as_tensor`` takes: a tensor, a (nested) sequence or array of numbers, or a number."""


class RatingBoundaryWarning(UserWarning):
    """A rating at exactly 0 or 1 was moved inside the open interval (docs/decisions.md)."""


def _as_tensor(value, dtype=None, device=None) -> Tensor:
    if isinstance(value, Tensor):
        return value.to(device=device if device is not None else value.device, dtype=dtype or value.dtype)
    if dtype is not None:
        return torch.as_tensor(value, dtype=dtype, device=device)
    t = torch.as_tensor(value, device=device)
    # python floats become float64, not torch's float32 default; convert from the original values
    # (going through float32 first would round 0.1 to 0.10000000149 and 1 - 1e-9 to exactly 1)
    return torch.as_tensor(value, dtype=torch.float64, device=device) if t.is_floating_point() else t


def _check_finite(name: str, t: Tensor) -> None:
    if t.is_floating_point() and not torch.isfinite(t).all():
        bad = t[~torch.isfinite(t)].flatten()[:3].tolist()
        raise ValueError(f"{name} must be finite, got non-finite values such as {bad}.")


def likert_to_unit(levels: TensorLike, num_levels: int = 5, mode: str = "centre") -> Tensor:
    r"""Map Likert levels ``1..K`` to ratings in ``[0, 1]``.

    Args:
        levels: integer levels in ``1..num_levels`` (a number or a tensor).
        num_levels: ``K``, the number of levels on the scale.
        mode: ``"centre"`` (default) maps level ``k`` to the centre of its bin,
            ``(k - 1/2) / K`` (1..5 -> 0.1, 0.3, 0.5, 0.7, 0.9), which keeps every rating
            inside the Beta likelihood's support; ``"linear"`` is the paper's map
            ``(k - 1) / (K - 1)`` (1..5 -> 0, 0.25, ..., 1), whose end points are then moved in
            by :func:`prepare_ratings`.

    Returns:
        A float64 tensor of the shape of ``levels``.
    """
    if num_levels < 2:
        raise ValueError(f"num_levels must be at least 2, got {num_levels}.")
    lv = _as_tensor(levels, dtype=torch.float64)
    _check_finite("levels", lv)
    if (lv != lv.round()).any() or (lv < 1).any() or (lv > num_levels).any():
        raise ValueError(f"Likert levels must be integers in 1..{num_levels}, got {lv.flatten().tolist()[:5]}.")
    if mode == "centre":
        return (lv - 0.5) / num_levels
    if mode == "linear":
        return (lv - 1.0) / (num_levels - 1)
    raise ValueError(f"mode must be 'centre' or 'linear', got {mode!r}.")


def unit_to_likert(values: TensorLike, num_levels: int = 5) -> Tensor:
    """Inverse of :func:`likert_to_unit` in ``"centre"`` mode: the bin each value falls in."""
    v = _as_tensor(values, dtype=torch.float64)
    return (v * num_levels).floor().clamp(0, num_levels - 1).long() + 1


def best_of_m(chosen: int, shown: Sequence[int] | Tensor) -> Tensor:
    r"""A best-of-``m`` answer as ``m - 1`` comparisons ``[chosen, other]`` (Sec. III.A).

    Args:
        chosen: index (into ``train_X``) of the item the person picked.
        shown: the ``m`` indices of the items shown, ``chosen`` among them.

    Returns:
        A ``(m - 1) x 2`` long tensor.
    """
    shown_t = _as_tensor(shown, dtype=torch.long).flatten()
    if shown_t.numel() < 2:
        raise ValueError(f"a ranking query needs at least 2 items, got {shown_t.tolist()}.")
    if shown_t.unique().numel() != shown_t.numel():
        raise ValueError(f"the items shown must be distinct, got {shown_t.tolist()}.")
    chosen = int(chosen)
    if chosen not in shown_t.tolist():
        raise ValueError(f"the chosen item {chosen} is not among those shown {shown_t.tolist()}.")
    others = shown_t[shown_t != chosen]
    return torch.stack([torch.full_like(others, chosen), others], dim=-1)


def prepare_ratings(ratings: TensorLike, eps: float = DEFAULT_RATING_EPS, dtype: torch.dtype = torch.float64,
                    device: torch.device | str | None = None) -> Tensor:
    """Validate ratings and move exact 0 and 1 in to ``eps`` and ``1 - eps`` (with a warning)."""
    r = _as_tensor(ratings, dtype=dtype, device=device).flatten()
    _check_finite("ratings", r)
    if ((r < 0) | (r > 1)).any():
        bad = r[(r < 0) | (r > 1)][:3].tolist()
        raise ValueError(f"ratings must lie in [0, 1], got {bad}.")
    if not 0 < eps < 0.5:
        raise ValueError(f"rating_eps must lie in (0, 0.5), got {eps}.")
    at_edge = (r == 0) | (r == 1)
    if at_edge.any():
        warnings.warn(
            f"{int(at_edge.sum())} rating(s) at exactly 0 or 1 moved in to {eps} / {1 - eps}: the Beta "
            "likelihood has no density there (set rating_eps to change this).",
            RatingBoundaryWarning,
            stacklevel=3,
        )
        r = r.clamp(eps, 1 - eps)
    return r


@dataclass(frozen=True)
class PreferenceData:
    r"""Validated, immutable observations.

    Attributes:
        train_X: ``n x d`` items.
        comparisons: ``p x 2`` long, rows ``[preferred, other]``.
        ratings: ``q`` values in ``(0, 1)``.
        rating_index: ``q`` long indices into ``train_X``.
    """

    train_X: Tensor
    comparisons: Tensor
    ratings: Tensor
    rating_index: Tensor

    @classmethod
    def create(
        cls,
        train_X: TensorLike,
        comparisons: TensorLike | None = None,
        ratings: TensorLike | None = None,
        rating_index: TensorLike | None = None,
        rating_eps: float = DEFAULT_RATING_EPS,
    ) -> "PreferenceData":
        """Validated data: ``train_X`` (``n x d``; integers become float64), ``comparisons``
        (``p x 2`` rows ``[preferred, other]``), ``ratings`` in ``[0, 1]`` (moved in to ``rating_eps``
        from the bounds) of the rows ``rating_index`` (given together with ``ratings``).

        Raises:
            ValueError: a bad shape, index or value (naming it).
        """
        X = _as_tensor(train_X)
        if not X.is_floating_point():
            X = X.to(torch.float64)
        if X.dim() != 2:
            raise ValueError(f"train_X must be n x d (2-D), got shape {tuple(X.shape)}.")
        if X.shape[-1] < 1:
            raise ValueError(f"train_X must have at least one column, got shape {tuple(X.shape)}.")
        _check_finite("train_X", X)
        n = X.shape[0]
        dev = X.device
        C = _check_comparisons(comparisons, n, dev)
        if (ratings is None) != (rating_index is None):
            raise ValueError("ratings and rating_index must be given together.")
        if ratings is None:
            r = torch.zeros(0, dtype=X.dtype, device=dev)
            ri = torch.zeros(0, dtype=torch.long, device=dev)
        else:
            r = prepare_ratings(ratings, rating_eps, dtype=X.dtype, device=dev)
            ri = _check_index("rating_index", rating_index, n, dev)
            if ri.numel() != r.numel():
                raise ValueError(
                    f"ratings and rating_index must have the same length, got {r.numel()} and {ri.numel()}."
                )
        return cls(X, C, r, ri)

    @property
    def n(self) -> int:
        """The number of items ``n``."""
        return self.train_X.shape[0]

    @property
    def dim(self) -> int:
        """The items' dimension ``d``."""
        return self.train_X.shape[-1]

    @property
    def num_observations(self) -> int:
        """Comparisons plus ratings."""
        return self.comparisons.shape[0] + self.ratings.shape[0]

    def index_items(self, X: TensorLike, atol: float = 0.0) -> tuple["PreferenceData", Tensor]:
        r"""Indices of the rows of ``X`` (``m x d``), adding those not already present.

        An item already in ``train_X`` (same coordinates, within ``atol``) reuses its index, and
        so does a row repeated inside ``X``.

        Returns:
            The data with the new items appended, and the ``m`` indices.
        """
        X = _as_tensor(X, dtype=self.train_X.dtype, device=self.train_X.device)
        if X.dim() == 1:
            X = X.unsqueeze(0)
        if X.dim() != 2 or X.shape[-1] != self.dim:
            raise ValueError(f"items must be m x {self.dim}, got shape {tuple(X.shape)}.")
        _check_finite("items", X)
        allX = self.train_X
        idx = []
        new_rows = []
        for row in X:
            pool = torch.cat([allX] + new_rows, dim=0) if new_rows else allX
            hit = ((pool - row).abs() <= atol).all(dim=-1).nonzero()
            if hit.numel():
                idx.append(int(hit[0]))
            else:
                idx.append(pool.shape[0])
                new_rows.append(row.unsqueeze(0))
        data = self
        if new_rows:
            data = PreferenceData(torch.cat([allX] + new_rows, dim=0), self.comparisons, self.ratings, self.rating_index)
        return data, torch.tensor(idx, dtype=torch.long, device=allX.device)

    def add(
        self,
        X: TensorLike | None = None,
        comparisons: TensorLike | None = None,
        ratings: TensorLike | None = None,
        rating_index: TensorLike | None = None,
        rating_eps: float = DEFAULT_RATING_EPS,
    ) -> "PreferenceData":
        """New data with items appended (by coordinates: duplicates reuse their index) and
        observations appended. Indices in ``comparisons`` / ``rating_index`` refer to the rows
        of ``X`` when ``X`` is given, otherwise to the existing ``train_X``."""
        data = self
        if X is not None:
            data, map_idx = self.index_items(X)
        else:
            map_idx = None
        m = map_idx.numel() if map_idx is not None else self.n
        dev = self.train_X.device
        C = _check_comparisons(comparisons, m, dev)
        if (ratings is None) != (rating_index is None):
            raise ValueError("ratings and rating_index must be given together.")
        if ratings is None:
            r = torch.zeros(0, dtype=self.train_X.dtype, device=dev)
            ri = torch.zeros(0, dtype=torch.long, device=dev)
        else:
            r = prepare_ratings(ratings, rating_eps, dtype=self.train_X.dtype, device=dev)
            ri = _check_index("rating_index", rating_index, m, dev)
            if ri.numel() != r.numel():
                raise ValueError(
                    f"ratings and rating_index must have the same length, got {r.numel()} and {ri.numel()}."
                )
        if map_idx is not None:
            C = map_idx[C]
            ri = map_idx[ri]
            if C.numel() and (C[:, 0] == C[:, 1]).any():
                raise ValueError("a comparison compares an item with itself (two rows of X are the same item).")
        return PreferenceData(
            data.train_X,
            torch.cat([data.comparisons, C], dim=0),
            torch.cat([data.ratings, r], dim=0),
            torch.cat([data.rating_index, ri], dim=0),
        )

    def to(self, *args, **kwargs) -> "PreferenceData":
        """A copy with the items and ratings converted as by ``Tensor.to`` (the indices follow the device)."""
        X = self.train_X.to(*args, **kwargs)
        return PreferenceData(X, self.comparisons.to(X.device), self.ratings.to(X), self.rating_index.to(X.device))


def _check_index(name: str, index, n: int, device) -> Tensor:
    t = _as_tensor(index, device=device)
    if t.dtype == torch.bool:  # a mask would be read as the indices 0 and 1
        raise ValueError(f"{name} must hold integer indices, got a bool tensor {t.flatten()[:5].tolist()} "
                         "(for a mask, use mask.nonzero()).")
    if t.is_floating_point():
        if not torch.isfinite(t).all() or (t != t.round()).any():
            raise ValueError(f"{name} must hold integer indices, got {t.flatten()[:5].tolist()}.")
    t = t.long().flatten()
    if t.numel() and ((t < 0) | (t >= n)).any():
        bad = t[(t < 0) | (t >= n)][:5].tolist()
        raise ValueError(f"{name} out of range for {n} items (valid 0..{n - 1}), got {bad}.")
    return t


def _check_comparisons(comparisons, n: int, device) -> Tensor:
    if comparisons is None:
        return torch.zeros(0, 2, dtype=torch.long, device=device)
    C = _as_tensor(comparisons, device=device)
    if C.numel() == 0:
        return torch.zeros(0, 2, dtype=torch.long, device=device)
    if C.dim() != 2 or C.shape[-1] != 2:
        raise ValueError(f"comparisons must be p x 2 (rows [preferred, other]), got shape {tuple(C.shape)}.")
    C = _check_index("comparisons", C, n, device).view(-1, 2)
    same = C[:, 0] == C[:, 1]
    if same.any():
        raise ValueError(f"an item is compared with itself in comparison row(s) {same.nonzero().flatten()[:5].tolist()}.")
    return C
