r"""The argument aliases, errors and helpers behind ``PreferenceGP``'s BoTorch ``PairwiseGP`` interface.

BoTorch's preference acquisitions, objectives and input constructors were written against its
``PairwiseGP``; they read ``datapoints``, ``comparisons``, ``dim`` and ``utility``, build models
from a ``RankingDataset`` with ``construct_inputs``, start from a prior-only model
``(None, None)``, and condition on comparisons with ``condition_on_observations(X, Y)``.
:class:`~torchpref.models.preference_gp.PreferenceGP` has the same names with the same meanings
(docs/botorch.md; the methods are in its class, in ``preference_gp.py``) and adds ratings where
BoTorch has none; this module holds what those methods share: the ``datapoints=`` / ``likelihood=``
/ ``jitter=`` aliases, the errors, and turning rankings and ``Y`` into comparisons.
"""

from __future__ import annotations

import copy
from typing import Protocol, TypeVar

import torch
from botorch.exceptions.errors import UnsupportedError
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.inference.padding import PaddedData, create_data
from torchpref.models.fantasy import batch_shape_of


class PriorOnlyModel(Protocol):
    """What :func:`_condition_prior_only` uses of a :class:`~torchpref.models.preference_gp.PreferenceGP`
    (a Protocol: that module imports this one)."""

    @property
    def train_X(self) -> Tensor:
        """The items (``0 x 0`` for a prior-only model)."""

    @property
    def rating_eps(self) -> float:
        """How far ratings are kept from 0 and 1."""

    @property
    def rating_levels(self) -> int | None:
        """``K`` where ratings are levels ``1..K``, else ``None``."""

    def set_train_data(
        self,
        train_X: Tensor | None = None,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
    ) -> None:
        """Replace the data (of one problem)."""

    def replace_data(self, data: PreferenceData | PaddedData, warm_f: Tensor | None = None) -> object:
        """Swap in new observations (batched ones as :class:`~torchpref.inference.padding.PaddedData`)."""


#: the prior-only model conditioned (the result is a copy of it)
PriorOnlyT = TypeVar("PriorOnlyT", bound=PriorOnlyModel)


class TrainDataMismatchError(ValueError, RuntimeError):
    """``set_train_data(..., strict=True)`` was given data of another shape, dtype or device, or
    a :class:`~torchpref.models.preference_gp.LaplaceMarginalLogLikelihood` comparisons other than its model's.

    A ``ValueError`` (bad input) that is also the ``RuntimeError`` GPyTorch's and BoTorch's
    models raise in these cases, so code written for either catches it.
    """


class UnsupportedLikelihoodError(ValueError, UnsupportedError):
    """A ``likelihood=`` that :class:`~torchpref.models.preference_gp.PreferenceGP` cannot score
    comparisons with (BoTorch's ``PairwiseLogitLikelihood``, say): a ``ValueError`` that is also
    BoTorch's ``UnsupportedError``."""


def pairwise_alias(train_X: Tensor | None, datapoints: Tensor | None) -> Tensor | None:
    """The items, given as ``train_X`` (first argument) or as ``datapoints=`` (``PairwiseGP``'s name)."""
    if datapoints is None:
        return train_X
    if train_X is not None:
        raise ValueError(
            "give the items once: train_X (the first argument) and datapoints= (PairwiseGP's name for it) "
            "are the same argument; got both."
        )
    return datapoints


def pairwise_likelihood_noise(likelihood: object, comparison_noise: float | None) -> float:
    r"""``comparison_noise`` (``sigma_R``) for ``PairwiseGP``'s ``likelihood=``.

    BoTorch's ``PairwiseProbitLikelihood`` is ``Phi((f_i - f_j) / sqrt 2)``: eq. 3 with
    ``sigma_R = 1``; torchpref's :class:`~torchpref.likelihoods.pairwise_beta.PairwiseProbitLikelihood`
    gives its own ``sigma_R``. ``None`` leaves ``comparison_noise`` (default 1.0).

    Raises:
        UnsupportedLikelihoodError: any other likelihood (``PairwiseLogitLikelihood`` among them:
            the logistic link is not implemented).
        ValueError: a likelihood together with a different ``comparison_noise``.
    """
    from botorch.models.likelihoods.pairwise import PairwiseProbitLikelihood as BoTorchProbit

    from torchpref.likelihoods.pairwise_beta import PairwiseProbitLikelihood

    if likelihood is None:
        return 1.0 if comparison_noise is None else comparison_noise
    if isinstance(likelihood, BoTorchProbit):
        implied = 1.0
    elif isinstance(likelihood, PairwiseProbitLikelihood):
        implied = float(likelihood.comparison_noise.detach().reshape(-1)[0])
    else:
        raise UnsupportedLikelihoodError(
            f"likelihood={type(likelihood).__name__} is not supported by PreferenceGP: comparisons are scored "
            "with the probit of eq. 3 (BoTorch's PairwiseProbitLikelihood, or torchpref.PairwiseProbitLikelihood "
            "for another comparison_noise); a logistic link is not implemented."
        )
    if comparison_noise is not None and float(comparison_noise) != implied:
        raise ValueError(
            f"likelihood={type(likelihood).__name__} means comparison_noise={implied:g}, but comparison_noise="
            f"{comparison_noise!r} was given too: give one of them."
        )
    return implied


def check_jitter(jitter: float | None) -> None:
    """``PairwiseGP``'s ``jitter=``, accepted and not used: a kernel matrix is jittered only when
    its Cholesky factorisation fails, by an amount relative to its diagonal and dtype."""
    if jitter is not None and not (isinstance(jitter, (int, float)) and not isinstance(jitter, bool) and jitter >= 0):
        raise ValueError(f"jitter must be a number >= 0 (it is accepted for PairwiseGP's signature), got {jitter!r}.")


def prior_only_data(dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> PreferenceData:
    """No items, no observations and no known input dimension: BoTorch's prior-only model."""
    empty = torch.zeros(0, dtype=torch.long, device=device)
    return PreferenceData(
        torch.zeros(0, 0, dtype=dtype, device=device),
        empty.view(0, 2),
        torch.zeros(0, dtype=dtype, device=device),
        empty,
    )


def ranking_comparisons(items: Tensor, ranks: Tensor) -> Tensor:
    r"""Comparisons ``[better, worse]`` between the items of adjacent ranks of each query.

    Args:
        items: ``r x m`` long item indices of each query.
        ranks: ``r x m`` ranks (0 = best; tied items share a rank).

    Returns:
        ``p x 2`` long: ``[items[k, i], items[k, j]]`` wherever ``ranks[k, j]`` is the next
        rank worse than ``ranks[k, i]`` (no rank strictly between them).
    """
    ranks = ranks.long().reshape(items.shape)
    ri, rj = ranks.unsqueeze(-1), ranks.unsqueeze(-2)  # r x m x 1, r x 1 x m
    # a rank strictly between those of i and j: r x m x m x m, m is a query's size
    between = (
        (ranks.view(-1, 1, 1, ranks.shape[-1]) > ri.unsqueeze(-1))
        & (ranks.view(-1, 1, 1, ranks.shape[-1]) < rj.unsqueeze(-1))
    ).any(-1)
    k, i, j = ((ri < rj) & ~between).nonzero(as_tuple=True)
    return torch.stack([items[k, i], items[k, j]], dim=-1).long()


def _condition_prior_only(
    model: PriorOnlyT,
    X: Tensor,
    comparisons: Tensor | None,
    ratings: Tensor | None,
    rating_index: Tensor | None,
) -> PriorOnlyT:
    """A copy of a prior-only ``model`` whose data are these; batched ``X`` or observations give
    one problem per batch element, as the constructor builds them (BoTorch's fantasies)."""
    new = copy.deepcopy(model)
    batch = batch_shape_of(X, comparisons, ratings)
    if not batch:
        new.set_train_data(X, comparisons, ratings, rating_index)
        return new
    X = X.to(model.train_X).expand(*batch, *X.shape[-2:])
    if comparisons is not None:
        comparisons = comparisons.expand(*batch, *comparisons.shape[-2:])
    if ratings is not None:
        assert rating_index is not None  # condition_on_observations gives the ratings' index with them
        ratings, rating_index = (
            ratings.expand(*batch, ratings.shape[-1]),
            rating_index.expand(*batch, ratings.shape[-1]),
        )
    new.replace_data(
        create_data(X, comparisons, ratings, rating_index, model.rating_eps, rating_levels=model.rating_levels), None
    )
    return new


def _comparisons_from_Y(Y: Tensor) -> Tensor:
    """``Y`` as ``p x 2`` comparisons, refusing what could be ratings."""
    Y = torch.as_tensor(Y)
    if Y.is_floating_point() or Y.is_complex() or Y.dtype == torch.bool:
        raise ValueError(
            f"Y of dtype {Y.dtype} is ambiguous for a preference model: comparisons are a long tensor of shape "
            "m x 2 (rows [preferred, other] into X); ratings go in by keyword, ratings= (values in [0, 1])."
        )
    if Y.dim() < 2 or Y.shape[-1] != 2:
        raise ValueError(f"comparisons Y must have shape m x 2 (rows [preferred, other]), got {tuple(Y.shape)}.")
    return Y.long()


def _check_strict(old, train_X: Tensor, comparisons, ratings) -> None:
    """Raise :class:`TrainDataMismatchError` where the new data's layout differs from the model
    ``old``'s."""
    pairs = [("train_X", train_X, old.train_X)]
    if comparisons is not None or old.comparisons.shape[0]:
        pairs.append(("comparisons", comparisons, old.comparisons))
    if ratings is not None or old.ratings.shape[0]:
        pairs.append(("ratings", ratings, old.ratings))
    for name, new, cur in pairs:
        if new is None:
            raise TrainDataMismatchError(f"strict: {name} is None but the model holds {tuple(cur.shape)}.")
        new = torch.as_tensor(new)
        for what, a, b in (("shape", new.shape, cur.shape), ("device", new.device, cur.device)):
            if a != b:
                raise TrainDataMismatchError(f"strict: cannot change the {what} of {name} from {b} to {a}.")
        if new.is_floating_point() and new.dtype != cur.dtype:
            raise TrainDataMismatchError(f"strict: cannot change the dtype of {name} from {cur.dtype} to {new.dtype}.")
