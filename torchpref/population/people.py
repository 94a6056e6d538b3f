r"""The people of a population: their data checked, their distinct items found, and their shards
laid out (:class:`~torchpref.population.shards.ShardData`)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from botorch.exceptions.warnings import InputDataWarning
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.inference.padding import PaddedData
from torchpref.models.defaults import PreferenceLikelihood
from torchpref.population.blocks import Layout
from torchpref.population.shards import ShardData

#: Above this many of a shard's distinct items, its part of ``S`` is never formed through an
#: ``N_s x N_s`` scatter (80 MB at 3,200 items).
MAX_SCATTER_ITEMS = 3200


def check_people(people: object) -> list[PreferenceData]:
    """``people`` as a list of float64 :class:`~torchpref.data.preference_data.PreferenceData`.

    Warns (BoTorch's ``InputDataWarning``, as :class:`~torchpref.PreferenceGP` does) when the
    items leave the unit cube by more than BoTorch's tolerance of 0.01.

    Raises:
        ValueError: naming the problem: not a sequence, empty, an entry that is not a
            ``PreferenceData``, feature dimensions that differ, items that are not finite,
            ratings of different kinds (Beta and levels, or different numbers of levels), or no
            answers at all.
    """
    if isinstance(people, (PreferenceData, str, bytes)) or not isinstance(people, Sequence):
        raise ValueError(f"people must be a sequence of PreferenceData, one per person; got {type(people).__name__}.")
    if len(people) == 0:
        raise ValueError("people is empty: a population needs at least one person's PreferenceData.")
    out = []
    for i, p in enumerate(people):
        if not isinstance(p, PreferenceData):
            raise ValueError(f"people[{i}] must be a PreferenceData, got {type(p).__name__}.")
        X = p.train_X
        if X.dim() != 2 or X.shape[-1] != people[0].train_X.shape[-1]:
            raise ValueError(
                f"people[{i}] has items of shape {tuple(X.shape)}: every person's items must have "
                f"d = {people[0].train_X.shape[-1]} features (people[0]'s)."
            )
        if not bool(torch.isfinite(X).all()):
            bad = X[~torch.isfinite(X)][:3].tolist()
            raise ValueError(f"people[{i}] has items that are not finite (such as {bad}).")
        if p.rating_levels != people[0].rating_levels:
            raise ValueError(
                f"people[{i}] has rating_levels={p.rating_levels}, people[0] {people[0].rating_levels}: "
                "a population's ratings are all Beta (None) or all levels of one scale."
            )
        out.append(p.to(dtype=torch.float64))
    if sum(p.num_observations for p in out) == 0:
        raise ValueError("the population has no answers: fit_population needs comparisons or ratings.")
    return out


def warn_outside_unit_cube(X: Tensor, stacklevel: int = 3) -> None:
    """BoTorch's ``InputDataWarning`` when the items ``X`` (``... x d``) leave the unit cube by
    more than BoTorch's tolerance of 0.01 (the words of :class:`~torchpref.PreferenceGP`'s)."""
    X = X.reshape(-1, X.shape[-1])
    lo, hi = X.min(0).values, X.max(0).values
    out = ((lo < -0.01) | (hi > 1.01)).nonzero().reshape(-1).tolist()
    if out:
        ranges = ", ".join(f"column {i}: [{float(lo[i]):.3g}, {float(hi[i]):.3g}]" for i in out[:5])
        warnings.warn(
            f"the items are not contained in the unit cube ({ranges}); the default kernel's "
            f"lengthscale prior assumes inputs in [0, 1]: scale the people's items to [0, 1] with your "
            "domain's bounds (fit_population takes no input transform).",
            InputDataWarning,
            stacklevel=stacklevel,
        )


@dataclass(frozen=True)
class Items:
    """All people's distinct items ``U`` (``N x d``), each person-item's row of ``U`` (``ids``,
    people's items one after another) and where each person's start (``offsets``, ``P + 1``)."""

    U: Tensor
    ids: Tensor
    offsets: Tensor

    @classmethod
    def of(cls, people: Sequence[PreferenceData]) -> Items:
        """The distinct items of ``people`` and where each person's items are among them."""
        X = torch.cat([p.train_X for p in people])
        U, ids = torch.unique(X, dim=0, return_inverse=True)
        sizes = torch.tensor([0] + [p.n for p in people])
        return cls(U, ids, sizes.cumsum(0))


def shard_bounds(P: int, k: int) -> list[tuple[int, int]]:
    """``k`` runs of consecutive people (at most ``P``), as even as can be."""
    k = max(1, min(k, P))
    edges = [round(i * P / k) for i in range(k + 1)]
    return list(zip(edges[:-1], edges[1:]))


def by_rows(P: int, n: int, N_s: int, M: int) -> bool:
    """Whether a shard forms its part of ``S`` per person's rows (``P n M (M + n)``) rather than
    through an ``N_s x N_s`` scatter (``N_s M (N_s + M)``): the cheaper, the scatter only up to
    :data:`MAX_SCATTER_ITEMS`."""
    return N_s > MAX_SCATTER_ITEMS or P * n * M * (M + n) < N_s * M * (N_s + M) + P * n * n


def shard_data(
    people: Sequence[PreferenceData],
    items: Items,
    bounds: tuple[int, int],
    likelihood: PreferenceLikelihood,
    z_pos: Tensor,
    ties_offered: bool = False,
) -> ShardData:
    """The shard of ``people[start:stop]``: its distinct items, each one's column among the
    mean's items (``z_pos``: ``N``, ``-1`` for none) and its people's padded data (strict choices
    as the tie likelihood's upper category where ``ties_offered``, as a person's model has them)."""
    start, stop = bounds
    part = people[start:stop]
    ids = items.ids[int(items.offsets[start]) : int(items.offsets[stop])]
    own, local = torch.unique(ids, return_inverse=True)
    padded = PaddedData.stack(part)
    P, n = len(part), padded.num_items
    sizes = torch.tensor([p.n for p in part])
    person = torch.repeat_interleave(torch.arange(P), sizes)
    position = torch.arange(len(ids)) - torch.repeat_interleave(sizes.cumsum(0) - sizes, sizes)
    index = torch.zeros(P, n, dtype=torch.long)
    index[person, position] = local
    mask = padded.item_mask if padded.item_mask is not None else torch.ones(P, n, dtype=torch.bool)
    comparison = likelihood.strict if ties_offered else likelihood.comparison
    obs = padded.observations(comparison, likelihood.rating, likelihood.tie)
    layout = Layout(items.U[own], padded.X, index, mask, obs)
    M = int((z_pos >= 0).sum())
    return ShardData(layout, z_pos[own], by_rows(P, n, len(own), M))
