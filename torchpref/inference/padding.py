r"""The data of a batch of independent preference problems, padded to common sizes.

:class:`PaddedData` holds ``batch_shape`` problems as tensors with leading dimensions
``batch_shape``: items ``... x N x d`` and observations ``... x P x 2`` / ``... x Q``, each with
a mask that is false on padding. It is what the model's posterior core and the batch-first
Laplace solver (:mod:`torchpref.inference.laplace`) read; a single :class:`~torchpref.data.preference_data.PreferenceData`
is the batch of shape ``()``.

Padding is exact (see :mod:`torchpref.inference.laplace`): a padded item gets prior variance 1 and no
correlation (:meth:`PaddedData.prior_covariance`) and no observation; a padded observation has
mask false and holds index 0 (and rating 0.5, or level 1), values every likelihood can evaluate.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import torch
from torch import Tensor

from torchpref.data.preference_data import DEFAULT_RATING_EPS, PreferenceData
from torchpref.inference.observations import ItemLikelihood, Observations, PairLikelihood

PAD_RATING = 0.5


def _pad(tensors: Sequence[Tensor], length: int, fill) -> Tensor:
    """Stack tensors along a new first dim, padding their first dim to ``length`` with ``fill``."""
    out = tensors[0].new_full((len(tensors), length, *tensors[0].shape[1:]), fill)
    for b, t in enumerate(tensors):
        out[b, : t.shape[0]] = t
    return out


def _lengths_mask(lengths: Sequence[int], size: int, device) -> Tensor:
    return torch.arange(size, device=device).unsqueeze(0) < torch.tensor(list(lengths), device=device).unsqueeze(1)


@dataclass(frozen=True)
class PaddedData:
    """Items and observations of ``batch_shape`` problems (masks ``None``: no padding)."""

    X: Tensor  # ... x N x d
    comparisons: Tensor  # ... x P x 2 long
    ratings: Tensor  # ... x Q
    rating_index: Tensor  # ... x Q long
    item_mask: Tensor | None = None  # ... x N bool
    comparison_mask: Tensor | None = None  # ... x P bool
    rating_mask: Tensor | None = None  # ... x Q bool
    ties: Tensor | None = None  # ... x T x 2 long ("no preference" pairs); None: none
    tie_mask: Tensor | None = None  # ... x T bool

    @classmethod
    def single(cls, data: PreferenceData) -> PaddedData:
        """One problem: batch shape ``()``, nothing padded."""
        return cls(data.train_X, data.comparisons, data.ratings, data.rating_index, ties=data.ties)

    @classmethod
    def create(
        cls,
        train_X: Tensor,
        comparisons: Tensor | Sequence[Tensor] | None = None,
        ratings: Tensor | Sequence[Tensor] | None = None,
        rating_index: Tensor | Sequence[Tensor] | None = None,
        rating_eps: float = DEFAULT_RATING_EPS,
        ties: Tensor | Sequence[Tensor] | None = None,
        rating_levels: int | None = None,
    ) -> PaddedData:
        """Batched training data, validated per problem: items ``b x n x d``, ``comparisons`` /
        ``ties`` ``b x p x 2`` and ``ratings`` / ``rating_index`` ``b x q`` (or sequences of ``b``
        per-problem tensors of any lengths); ratings are levels ``1..rating_levels`` when given."""
        b = train_X.shape[0]

        def part(value, k: int):
            if value is None:
                return None
            if len(value) != b:
                raise ValueError(f"batched training data: expected {b} per-problem entries, got {len(value)}.")
            return value[k]

        return cls.stack(
            [
                PreferenceData.create(
                    train_X[k],
                    part(comparisons, k),
                    part(ratings, k),
                    part(rating_index, k),
                    rating_eps=rating_eps,
                    ties=part(ties, k),
                    rating_levels=rating_levels,
                )
                for k in range(b)
            ]
        )

    @classmethod
    def stack(cls, data: Sequence[PreferenceData]) -> PaddedData:
        """``len(data)`` problems of any sizes: batch shape ``(len(data),)``."""
        if not data:
            raise ValueError("need at least one problem.")
        dev = data[0].train_X.device
        n, p, q, t = ([getattr(d, a).shape[0] for d in data] for a in ("train_X", "comparisons", "ratings", "ties"))
        N, P, Q, T = max(n), max(p), max(q), max(t)
        return cls(
            _pad([d.train_X for d in data], N, 0.0),
            _pad([d.comparisons for d in data], P, 0),
            _pad([d.ratings for d in data], Q, PAD_RATING if data[0].rating_levels is None else 1.0),
            _pad([d.rating_index for d in data], Q, 0),
            None if min(n) == N else _lengths_mask(n, N, dev),
            None if min(p) == P else _lengths_mask(p, P, dev),
            None if min(q) == Q else _lengths_mask(q, Q, dev),
            _pad([d.ties for d in data], T, 0),
            None if min(t) == T else _lengths_mask(t, T, dev),
        )

    @property
    def batch_shape(self) -> torch.Size:
        """The problems' batch shape (``X``'s shape without ``n x d``)."""
        return self.X.shape[:-2]

    @property
    def num_problems(self) -> int:
        """The number of problems: the product of :attr:`batch_shape`."""
        return self.batch_shape.numel()

    @property
    def num_items(self) -> int:
        """``N``, the (padded) number of items per problem."""
        return self.X.shape[-2]

    n = num_items

    @property
    def dim(self) -> int:
        """The items' dimension ``d``."""
        return self.X.shape[-1]

    @property
    def num_observations(self) -> int:
        """Observations per problem, padding included."""
        return self.comparisons.shape[-2] + self.ratings.shape[-1]

    def problem(self, b: int) -> PreferenceData:
        """Problem ``b`` (an index into the flattened batch) without its padding."""
        flat = self.flat()

        def keep(t: Tensor, mask: Tensor | None) -> Tensor:
            return t[b] if mask is None else t[b][mask[b]]

        ties = flat.X.new_zeros(0, 2, dtype=torch.long) if flat.ties is None else keep(flat.ties, flat.tie_mask)
        return PreferenceData(
            keep(flat.X, flat.item_mask),
            keep(flat.comparisons, flat.comparison_mask),
            keep(flat.ratings, flat.rating_mask),
            keep(flat.rating_index, flat.rating_mask),
            ties,
        )

    def flat(self) -> PaddedData:
        """The same problems with the batch dimensions flattened into one (``b = prod(batch_shape)``)."""
        b = self.num_problems

        def f(t: Tensor | None, k: int) -> Tensor | None:
            return None if t is None else t.reshape(b, *t.shape[t.dim() - k :])

        def g(t: Tensor, k: int) -> Tensor:
            return t.reshape(b, *t.shape[t.dim() - k :])

        return PaddedData(
            g(self.X, 2),
            g(self.comparisons, 2),
            g(self.ratings, 1),
            g(self.rating_index, 1),
            f(self.item_mask, 1),
            f(self.comparison_mask, 1),
            f(self.rating_mask, 1),
            f(self.ties, 2),
            f(self.tie_mask, 1),
        )

    def map(self, fn: Callable[[Tensor], Tensor]) -> PaddedData:
        """The same problems with ``fn`` applied to every tensor (e.g. a device move)."""
        mapped: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            mapped[f.name] = None if v is None else fn(v)
        return PaddedData(**mapped)

    def with_items(self, X: Tensor) -> PaddedData:
        """The same problems with items ``X`` (e.g. transformed by an input transform)."""
        return replace(self, X=X)

    def observations(
        self,
        comparison_likelihood: PairLikelihood,
        rating_likelihood: ItemLikelihood,
        tie_likelihood: PairLikelihood | None = None,
    ) -> Observations:
        """The observations of the ``b`` flattened problems as likelihood terms."""
        d = self.flat()
        return Observations.from_data(
            d.comparisons,
            d.ratings,
            d.rating_index,
            comparison_likelihood,
            rating_likelihood,
            d.comparison_mask,
            d.rating_mask,
            ties=d.ties,
            tie_likelihood=tie_likelihood,
            tie_mask=d.tie_mask,
        )

    def prior_covariance(self, K: Tensor) -> Tensor:
        """``K`` (``... x N x N``) with padded items made independent with unit variance."""
        if self.item_mask is None:
            return K
        m = self.item_mask
        K = torch.where(m.unsqueeze(-1) & m.unsqueeze(-2), K, 0.0)
        return K + torch.diag_embed((~m).to(K))

    def cross_covariance(self, K_xs: Tensor) -> Tensor:
        """``K_X*`` (``... x N x s``) with the padded items' rows zeroed."""
        return K_xs if self.item_mask is None else torch.where(self.item_mask.unsqueeze(-1), K_xs, 0.0)

    def append(
        self,
        X: Tensor,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
    ) -> PaddedData:
        """New items ``X`` (``... x m x d``, broadcast to the batch) appended to every problem,
        with observations among them (indices into ``X``'s ``m`` rows, ``... x k x 2`` / ``... x r``).
        For unpadded items only (the fantasy batches of :meth:`PreferenceGP.fantasize`)."""
        if self.item_mask is not None:
            raise ValueError("appending items to a batch with padded items is not supported.")
        shape = torch.broadcast_shapes(
            self.batch_shape,
            X.shape[:-2],
            *([] if comparisons is None else [comparisons.shape[:-2]]),
            *([] if ratings is None else [ratings.shape[:-1]]),
        )
        N = self.num_items
        Xn = torch.cat([self.X.expand(*shape, *self.X.shape[-2:]), X.expand(*shape, *X.shape[-2:])], dim=-2)

        def grow(old: Tensor, new: Tensor | None, k: int, offset: bool) -> Tensor:
            old = old.expand(*shape, *old.shape[old.dim() - k :])
            if new is None:
                return old
            new = new.to(old.device) + (N if offset else 0)
            return torch.cat([old, new.expand(*shape, *new.shape[new.dim() - k :]).to(old.dtype)], dim=-k)

        def mask(old: Tensor | None, size_old: int, new: Tensor | None, k: int) -> Tensor | None:
            if old is None:
                return None
            add = 0 if new is None else new.shape[new.dim() - k]
            return torch.cat([old.expand(*shape, size_old), old.new_ones(*shape, add)], dim=-1)

        return PaddedData(
            Xn,
            grow(self.comparisons, comparisons, 2, True),
            grow(self.ratings, ratings, 1, False),
            grow(self.rating_index, rating_index, 1, True),
            None,
            mask(self.comparison_mask, self.comparisons.shape[-2], comparisons, 2),
            mask(self.rating_mask, self.ratings.shape[-1], ratings, 1),
            None if self.ties is None else grow(self.ties, None, 2, False),
            None if self.tie_mask is None else self.tie_mask.expand(*shape, self.tie_mask.shape[-1]),
        )


def create_data(
    train_X: Tensor,
    comparisons: Tensor | None,
    ratings: Tensor | None,
    rating_index: Tensor | None,
    rating_eps: float,
    ties: Tensor | None = None,
    rating_levels: int | None = None,
) -> PreferenceData | PaddedData:
    """Validated data: one problem for ``n x d`` items, one per batch element for ``b x n x d``."""
    if isinstance(train_X, Tensor) and train_X.dim() == 3:
        return PaddedData.create(
            train_X, comparisons, ratings, rating_index, rating_eps=rating_eps, ties=ties, rating_levels=rating_levels
        )
    return PreferenceData.create(
        train_X, comparisons, ratings, rating_index, rating_eps=rating_eps, ties=ties, rating_levels=rating_levels
    )
