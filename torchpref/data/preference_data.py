r"""Observations: items, comparisons and ratings, with validation.

The model sees three things (paper Sec. III.B.1):

* ``train_X`` (``n x d``): the items, one row per distinct point of the objective space;
* ``comparisons`` (``p x 2`` long): row ``[i, j]`` means item ``i`` was preferred to item
  ``j`` (BoTorch's convention; the paper's label ``d = -1`` for ``x_i > x_j``);
* ``ratings`` (``q``) in ``[0, 1]`` with ``rating_index`` (``q`` long): item rated by each;
  or, for data with ``rating_levels = K``, levels ``1..K`` (the ordinal likelihood's input);
* ``ties`` (``t x 2`` long): row ``[i, j]`` means the person had no preference between ``i``
  and ``j`` (not in the paper; see docs/observations.md).

:class:`PreferenceData` is immutable: adding observations returns a new object, so a failed
update never leaves a half-updated model behind.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TypeAlias

import torch
from torch import Tensor

DEFAULT_RATING_EPS = 1e-3

TensorLike: TypeAlias = "Tensor | Sequence[Any] | float"
"""What ``torch.as_tensor`` takes: a tensor, a (nested) sequence or array of numbers, or a number."""


class RatingBoundaryWarning(UserWarning):
    """A rating at exactly 0 or 1 was moved inside the open interval (docs/decisions.md)."""


def _as_tensor(value, dtype=None, device=None, name: str = "the input", what: str = "numbers") -> Tensor:
    """``value`` as a tensor; text, ``None``, ragged lists and bools (a mask is never data here)
    raise ``ValueError`` naming ``name``."""
    try:
        t = value if isinstance(value, Tensor) else torch.as_tensor(value, device=device)
    except (TypeError, ValueError, RuntimeError) as err:
        raise ValueError(f"{name} must hold {what}, got {type(value).__name__} {value!r:.60} ({err}).") from None
    if t.dtype == torch.bool:
        raise ValueError(
            f"{name} must hold {what}, got a bool tensor {t.flatten()[:5].tolist()} (for a mask, use mask.nonzero())."
        )
    if t.is_complex():
        raise ValueError(f"{name} must hold real {what}, got {t.dtype} values {t.flatten()[:3].tolist()}.")
    if isinstance(value, Tensor):
        return value.to(device=device if device is not None else value.device, dtype=dtype or value.dtype)
    if dtype is not None or t.is_floating_point():
        # python floats become float64, not torch's float32 default; convert from the original values
        # (going through float32 first would round 0.1 to 0.10000000149 and 1 - 1e-9 to exactly 1)
        return torch.as_tensor(value, dtype=dtype or torch.float64, device=device)
    return t


def _check_finite(name: str, t: Tensor) -> None:
    if t.is_floating_point() and not torch.isfinite(t).all():
        bad = t[~torch.isfinite(t)].flatten()[:3].tolist()
        raise ValueError(f"{name} must be finite, got non-finite values such as {bad}.")


def _check_num_levels(num_levels: object) -> None:
    if isinstance(num_levels, bool) or not hasattr(num_levels, "__index__") or num_levels < 2:  # type: ignore[operator]
        raise ValueError(f"num_levels must be an integer of at least 2, got {num_levels!r}.")


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
    _check_num_levels(num_levels)
    lv = _as_tensor(levels, dtype=torch.float64, name="levels")
    _check_finite("levels", lv)
    if (lv != lv.round()).any() or (lv < 1).any() or (lv > num_levels).any():
        raise ValueError(f"Likert levels must be integers in 1..{num_levels}, got {lv.flatten().tolist()[:5]}.")
    if mode == "centre":
        return (lv - 0.5) / num_levels
    if mode == "linear":
        return (lv - 1.0) / (num_levels - 1)
    raise ValueError(f"mode must be 'centre' or 'linear', got {mode!r}.")


def unit_to_likert(values: TensorLike, num_levels: int = 5) -> Tensor:
    """Inverse of :func:`likert_to_unit` in ``"centre"`` mode: the bin each value falls in.

    Raises:
        ValueError: a value outside ``[0, 1]`` or not finite; ``num_levels`` not an integer of at
            least 2.
    """
    _check_num_levels(num_levels)
    v = _as_tensor(values, dtype=torch.float64, name="values")
    _check_finite("values", v)
    if ((v < 0) | (v > 1)).any():
        raise ValueError(f"values must lie in [0, 1], got {v[(v < 0) | (v > 1)][:3].tolist()}.")
    return (v * num_levels).floor().clamp(0, num_levels - 1).long() + 1


def best_of_m(chosen: int, shown: Sequence[int] | Tensor) -> Tensor:
    r"""A best-of-``m`` answer as ``m - 1`` comparisons ``[chosen, other]`` (Sec. III.A).

    Args:
        chosen: index (into ``train_X``) of the item the person picked.
        shown: the ``m`` indices of the items shown, ``chosen`` among them.

    Returns:
        A ``(m - 1) x 2`` long tensor.
    """
    shown_t = _indices("shown", shown)
    if shown_t.numel() < 2:
        raise ValueError(f"a ranking query needs at least 2 items, got {shown_t.tolist()}.")
    if shown_t.unique().numel() != shown_t.numel():
        raise ValueError(f"the items shown must be distinct, got {shown_t.tolist()}.")
    chosen_t = _indices("chosen", chosen)
    if chosen_t.numel() != 1:
        raise ValueError(f"chosen must be one item index, got {chosen_t.tolist()}.")
    chosen = int(chosen_t)
    if chosen not in shown_t.tolist():
        raise ValueError(f"the chosen item {chosen} is not among those shown {shown_t.tolist()}.")
    others = shown_t[shown_t != chosen]
    return torch.stack([torch.full_like(others, chosen), others], dim=-1)


def best_of_m_with_ties(best: Sequence[int] | Tensor, shown: Sequence[int] | Tensor) -> tuple[Tensor, Tensor]:
    r"""A best-of-``m`` answer that names several items as equally best.

    Each of the ``b`` best items is preferred to each of the ``m - b`` others, and each pair of
    best items is a tie ("these two are equally best").

    Args:
        best: indices of the ``b >= 1`` items picked as equally best.
        shown: the ``m`` indices of the items shown, all of ``best`` among them.

    Returns:
        ``(comparisons, ties)``: ``b (m - b) x 2`` rows ``[best, other]`` and ``b (b - 1) / 2 x 2``
        rows ``[best_a, best_b]``. One best item gives :func:`best_of_m`'s comparisons and no tie.
    """
    shown_t = _indices("shown", shown)
    best_t = _indices("best", best)
    if best_t.numel() < 1 or best_t.unique().numel() != best_t.numel():
        raise ValueError(f"the best items must be one or more distinct indices, got {best_t.tolist()}.")
    missing = [b for b in best_t.tolist() if b not in shown_t.tolist()]
    if missing:
        raise ValueError(f"the best item(s) {missing} are not among those shown {shown_t.tolist()}.")
    best_of_m(int(best_t[0]), shown_t)  # the same checks of ``shown``
    others = shown_t[~torch.isin(shown_t, best_t)]
    comparisons = torch.stack([best_t.repeat_interleave(others.numel()), others.repeat(best_t.numel())], dim=-1)
    ties = torch.combinations(best_t, 2) if best_t.numel() > 1 else torch.zeros(0, 2, dtype=torch.long)
    return comparisons, ties


def prepare_levels(
    levels: TensorLike, num_levels: int, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """Validate rating levels: integers in ``1..num_levels`` (kept as values of ``dtype``)."""
    lv = _as_tensor(levels, dtype=dtype, device=device, name="rating levels").flatten()
    _check_finite("rating levels", lv)
    bad = (lv != lv.round()) | (lv < 1) | (lv > num_levels)
    if bad.any():
        raise ValueError(f"rating levels must be integers in 1..{num_levels}, got {lv[bad][:5].tolist()}.")
    return lv


def prepare_ratings(
    ratings: TensorLike,
    eps: float = DEFAULT_RATING_EPS,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Tensor:
    """Validate ratings and move exact 0 and 1 in to ``eps`` and ``1 - eps`` (with a warning)."""
    r = _as_tensor(ratings, dtype=dtype, device=device, name="ratings").flatten()
    _check_finite("ratings", r)
    if ((r < 0) | (r > 1)).any():
        bad = r[(r < 0) | (r > 1)][:3].tolist()
        hint = (
            " Ratings on a scale of levels 1..K (a Likert scale) map into [0, 1] with "
            "torchpref.likert_to_unit(levels, num_levels=K)."
            if (r > 1).any()
            else ""
        )
        raise ValueError(f"ratings must lie in [0, 1], got {bad}.{hint}")
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
        ties: ``t x 2`` long, rows ``[i, j]``: no preference between ``i`` and ``j``.
        rating_levels: ``K`` when ``ratings`` are levels ``1..K`` (ordinal likelihood); ``None``
            for ratings in ``(0, 1)`` (Beta likelihood).
    """

    train_X: Tensor
    comparisons: Tensor
    ratings: Tensor
    rating_index: Tensor
    ties: Tensor = None  # type: ignore[assignment]  # None: no ties (__post_init__ makes it t x 2)
    rating_levels: int | None = None

    def __post_init__(self) -> None:
        if self.ties is None:
            object.__setattr__(self, "ties", torch.zeros(0, 2, dtype=torch.long, device=self.train_X.device))

    @classmethod
    def create(
        cls,
        train_X: TensorLike,
        comparisons: TensorLike | None = None,
        ratings: TensorLike | None = None,
        rating_index: TensorLike | None = None,
        rating_eps: float = DEFAULT_RATING_EPS,
        ties: TensorLike | None = None,
        rating_levels: int | None = None,
    ) -> PreferenceData:
        """Validated data: ``train_X`` (``n x d``; integers become float64), ``comparisons``
        (``p x 2`` rows ``[preferred, other]``), ``ratings`` in ``[0, 1]`` (moved in to ``rating_eps``
        from the bounds; levels ``1..rating_levels`` when that is given) of the rows
        ``rating_index`` (given together with ``ratings``), ``ties`` (``t x 2`` "no preference" pairs).

        Raises:
            ValueError: a bad shape, index or value (naming it).
        """
        if rating_levels is not None and (int(rating_levels) != rating_levels or rating_levels < 2):
            raise ValueError(f"rating_levels must be an integer of at least 2, got {rating_levels}.")
        X = _as_tensor(train_X, name="train_X")
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
        t = _check_comparisons(ties, n, dev, name="ties")
        r, ri = _check_ratings(ratings, rating_index, n, rating_eps, rating_levels, X.dtype, dev)
        # copies: a caller who edits their tensors in place afterwards must not edit the data
        # under a model's cached factorisation (its posterior would be neither model's)
        return cls(
            X.clone(),
            C.clone(),
            r.clone(),
            ri.clone(),
            t.clone(),
            None if rating_levels is None else int(rating_levels),
        )

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
        """Comparisons plus ratings plus ties."""
        return self.comparisons.shape[0] + self.ratings.shape[0] + self.ties.shape[0]

    def index_items(self, X: TensorLike, atol: float = 0.0) -> tuple[PreferenceData, Tensor]:
        r"""Indices of the rows of ``X`` (``m x d``), adding those not already present.

        An item already in ``train_X`` (same coordinates, within ``atol``) reuses its index, and
        so does a row repeated inside ``X``.

        Returns:
            The data with the new items appended, and the ``m`` indices.
        """
        X = _as_tensor(X, dtype=self.train_X.dtype, device=self.train_X.device, name="items")
        if X.dim() == 1:
            X = X.unsqueeze(0)
        if X.dim() != 2 or X.shape[-1] != self.dim:
            raise ValueError(f"items must be m x {self.dim}, got shape {tuple(X.shape)}.")
        _check_finite("items", X)
        allX = self.train_X
        idx = []
        new_rows: list[Tensor] = []
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
            data = PreferenceData(
                torch.cat([allX] + new_rows, dim=0),
                self.comparisons,
                self.ratings,
                self.rating_index,
                self.ties,
                self.rating_levels,
            )
        return data, torch.tensor(idx, dtype=torch.long, device=allX.device)

    def add(
        self,
        X: TensorLike | None = None,
        comparisons: TensorLike | None = None,
        ratings: TensorLike | None = None,
        rating_index: TensorLike | None = None,
        rating_eps: float = DEFAULT_RATING_EPS,
        ties: TensorLike | None = None,
    ) -> PreferenceData:
        """New data with items appended (by coordinates: duplicates reuse their index) and
        observations appended. Indices in ``comparisons`` / ``ties`` / ``rating_index`` refer to
        the rows of ``X`` when ``X`` is given, otherwise to the existing ``train_X``. Ratings are
        levels ``1..K`` when the data has ``rating_levels``."""
        data = self
        if X is not None:
            data, map_idx = self.index_items(X)
        else:
            map_idx = None
        m = map_idx.numel() if map_idx is not None else self.n
        dev = self.train_X.device
        C = _check_comparisons(comparisons, m, dev)
        t = _check_comparisons(ties, m, dev, name="ties")
        r, ri = _check_ratings(ratings, rating_index, m, rating_eps, self.rating_levels, self.train_X.dtype, dev)
        if map_idx is not None:
            C, t, ri = map_idx[C], map_idx[t], map_idx[ri]
            if C.numel() and (C[:, 0] == C[:, 1]).any():
                raise ValueError("a comparison compares an item with itself (two rows of X are the same item).")
            if t.numel() and (t[:, 0] == t[:, 1]).any():
                raise ValueError("a tie pairs an item with itself (two rows of X are the same item).")
        return PreferenceData(
            data.train_X,
            torch.cat([data.comparisons, C], dim=0),
            torch.cat([data.ratings, r], dim=0),
            torch.cat([data.rating_index, ri], dim=0),
            torch.cat([data.ties, t], dim=0),
            self.rating_levels,
        )

    def to(self, *args, **kwargs) -> PreferenceData:
        """A copy with the items and ratings converted as by ``Tensor.to`` (the indices follow the device)."""
        X = self.train_X.to(*args, **kwargs)
        return PreferenceData(
            X,
            self.comparisons.to(X.device),
            self.ratings.to(X),
            self.rating_index.to(X.device),
            self.ties.to(X.device),
            self.rating_levels,
        )


def _indices(name: str, index, device=None) -> Tensor:
    """``index`` as a flat long tensor; bools (a mask would be read as the indices 0 and 1),
    fractions, text and non-finite values raise ``ValueError`` naming ``name``."""
    t = _as_tensor(index, device=device, name=name, what="integer indices")
    if t.is_floating_point():
        if not torch.isfinite(t).all() or (t != t.round()).any():
            raise ValueError(f"{name} must hold integer indices, got {t.flatten()[:5].tolist()}.")
        if t.numel() and t.abs().max() > 2**62:
            raise ValueError(
                f"{name} must hold integer indices, got {t.flatten()[t.flatten().abs() > 2**62][:5].tolist()}."
            )
    return t.long().flatten()


def _check_index(name: str, index, n: int, device) -> Tensor:
    t = _indices(name, index, device)
    if t.numel() and ((t < 0) | (t >= n)).any():
        bad = t[(t < 0) | (t >= n)][:5].tolist()
        raise ValueError(f"{name} out of range for {n} items (valid 0..{n - 1}), got {bad}.")
    return t


def _check_ratings(
    ratings, rating_index, n: int, eps: float, levels: int | None, dtype, device
) -> tuple[Tensor, Tensor]:
    """Validated ``(ratings, rating_index)``: values in ``[0, 1]`` (or levels ``1..levels``)."""
    if (ratings is None) != (rating_index is None):
        raise ValueError("ratings and rating_index must be given together.")
    if ratings is None:
        return torch.zeros(0, dtype=dtype, device=device), torch.zeros(0, dtype=torch.long, device=device)
    if levels is None:
        r = prepare_ratings(ratings, eps, dtype=dtype, device=device)
    else:
        r = prepare_levels(ratings, levels, dtype=dtype, device=device)
    ri = _check_index("rating_index", rating_index, n, device)
    if ri.numel() != r.numel():
        raise ValueError(f"ratings and rating_index must have the same length, got {r.numel()} and {ri.numel()}.")
    return r, ri


def _check_comparisons(comparisons, n: int, device, name: str = "comparisons") -> Tensor:
    """Validated ``p x 2`` index pairs (``comparisons`` or ``ties``): in range, no item paired with itself."""
    if comparisons is None:
        return torch.zeros(0, 2, dtype=torch.long, device=device)
    C = _as_tensor(comparisons, device=device, name=name, what="integer indices")
    if C.numel() == 0:
        return torch.zeros(0, 2, dtype=torch.long, device=device)
    if C.dim() != 2 or C.shape[-1] != 2:
        rows = "[preferred, other]" if name == "comparisons" else "[i, j]"
        raise ValueError(f"{name} must be p x 2 (rows {rows}), got shape {tuple(C.shape)}.")
    C = _check_index(name, C, n, device).view(-1, 2)
    same = C[:, 0] == C[:, 1]
    if same.any():
        what = (
            "an item is compared with itself in comparison"
            if name == "comparisons"
            else "an item is tied with itself in tie"
        )
        raise ValueError(f"{what} row(s) {same.nonzero().flatten()[:5].tolist()}.")
    return C
