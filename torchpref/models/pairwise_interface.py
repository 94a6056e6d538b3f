r"""What BoTorch's preference tools read from a preference model, for :class:`PreferenceGP`.

BoTorch's preference acquisitions, objectives and input constructors were written against its
``PairwiseGP``; they read ``datapoints``, ``comparisons``, ``dim`` and ``utility``, build models
from a ``RankingDataset`` with ``construct_inputs``, start from a prior-only model
``(None, None)``, and condition on comparisons with ``condition_on_observations(X, Y)``.
:class:`PairwiseGPInterface` gives :class:`~torchpref.models.preference_gp.PreferenceGP` the same names with
the same meanings (docs/botorch.md), and adds ratings where BoTorch has none.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from botorch.exceptions.errors import UnsupportedError
from botorch.utils.datasets import RankingDataset
from gpytorch.distributions import MultivariateNormal
from linear_operator.operators import DenseLinearOperator
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.models.fantasy import batch_shape_of, condition_batch
from torchpref.models.model_data import create_data


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


def pairwise_likelihood_noise(likelihood: Any, comparison_noise: float | None) -> float:
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


class PairwiseGPInterface:
    r"""The part of BoTorch's ``PairwiseGP`` interface that BoTorch's preference tools use.

    Mixed into :class:`~torchpref.models.preference_gp.PreferenceGP`; relies on its ``_data`` (a
    :class:`~torchpref.data.preference_data.PreferenceData` or, batched, a :class:`~torchpref.inference.padding.PaddedData`),
    ``train_X`` / ``comparisons`` / ``ratings``, ``_set_data``, ``add_observations``, ``mode``
    and ``likelihood``.
    """

    # ------------------------------------------------------------ names read by BoTorch
    @property
    def datapoints(self) -> Tensor:
        r"""``batch_shape x n x d`` items as given (before any input transform):
        ``PairwiseGP.datapoints``. For a prior-only model an empty ``0 x 0`` tensor of the
        model's dtype and device."""
        return self.train_X

    @property
    def dim(self) -> int | None:
        """Number of input columns ``d`` (``None`` for a prior-only model that has seen no
        items yet): ``PairwiseGP.dim``, read by BoTorch's EUBO input constructors."""
        return self._data.dim or None

    @property
    def utility(self) -> Tensor:
        r"""``batch_shape x n`` posterior-mode utilities of the items (``PairwiseGP.utility``), in
        the model's dtype."""
        return self.mode.f.reshape(*self.batch_shape, -1).to(self.train_X.dtype)

    @property
    def has_data(self) -> bool:
        """Whether the model holds any item (a prior-only model does not)."""
        return self.train_X.shape[-2] > 0

    # ---------------------------------------------------------------- construction
    @classmethod
    def construct_inputs(cls, training_data: Any, **kwargs: Any) -> dict[str, Tensor]:
        r"""Constructor keyword arguments from BoTorch's ``RankingDataset``.

        A ranking dataset holds items (``X.values``, ``n x d``), the items of each query
        (``X.indices``, ``r x m``) and the rank of each of them (``Y``, ``r x m``, 0 = best,
        ties share a rank). A query becomes comparisons ``[preferred, other]`` between the items
        of adjacent ranks: for ``m = 2`` exactly ``PairwiseGP``'s comparisons, for a strict
        ranking of ``m`` items ``m - 1`` of them (tied items are not compared).

        Returns:
            ``{"train_X": n x d, "comparisons": p x 2}`` (plus ``kwargs``), for ``cls(**inputs)``.

        Raises:
            UnsupportedError: for any other dataset (as ``PairwiseGP`` does): a
                ``SupervisedDataset``'s ``Y`` could be ratings or utilities; give ratings
                explicitly with ``ratings=`` and ``rating_index=``.
        """
        if not isinstance(training_data, RankingDataset):
            raise UnsupportedError(
                f"PreferenceGP.construct_inputs supports only a RankingDataset, got {type(training_data).__name__}; "
                "pass ratings to the constructor with ratings= and rating_index=."
            )
        comparisons = ranking_comparisons(training_data._X.indices, training_data.Y)
        return {"train_X": training_data._X.values, "comparisons": comparisons, **kwargs}

    def subset_output(self, idcs: list[int]) -> PairwiseGPInterface:
        """A copy of this one-output model for ``idcs == [0]`` (BoTorch's output subsetting).

        Raises:
            ValueError: for any other output index.
        """
        if [int(i) for i in idcs] not in ([0], [-1]):
            raise ValueError(f"PreferenceGP has one output (index 0); got output indices {list(idcs)}.")
        return copy.deepcopy(self)

    def load_state_dict(self, state_dict: dict[str, Any], strict: bool = False, assign: bool = False):
        r"""Load hyperparameters; **non-strict by default**, as ``PairwiseGP.load_state_dict``.

        A state dict holds hyperparameters (kernel, likelihoods, input transform), never the data.
        With ``strict=False`` a key the model does not have is ignored (listed in the result's
        ``unexpected_keys``) and a parameter the dict lacks keeps its current value (listed in
        ``missing_keys``): an empty dict, as BoTorch's and Ax's cross-validation load, changes
        nothing. A value of the wrong shape raises, as in PyTorch. ``strict=True`` (which
        ``PairwiseGP`` refuses) requires exactly the model's keys. The posterior follows the new
        values at the next call (its cache is keyed on every parameter).

        Returns:
            PyTorch's ``_IncompatibleKeys`` (``missing_keys``, ``unexpected_keys``).
        """
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    # ------------------------------------------------------------------ data
    def set_train_data(
        self,
        train_X: Tensor | None = None,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        strict: bool = False,
        update_model: bool = True,
        ties: Tensor | None = None,
    ) -> None:
        r"""Replace all data; validated and the mode solved first, so the model is unchanged on
        error. ``train_X=None`` keeps no items (a prior-only model keeps its unknown ``d``).

        Args:
            train_X: ``n x d`` items, or ``None``.
            comparisons: ``p x 2`` long, rows ``[preferred, other]``.
            ratings: ``q`` values in ``[0, 1]``, with ``rating_index`` (``q`` long).
            strict: as in GPyTorch: the new items, comparisons and ratings must have the shapes,
                dtype and device of the current ones (used when only values change).
            update_model: accepted for ``PairwiseGP``'s signature; the mode is always re-solved.
            ties: ``t x 2`` "no preference" pairs; ratings are levels for a model with ``rating_levels``.

        Raises:
            TrainDataMismatchError: ``strict`` and a shape, dtype or device differs.
        """
        old_X = self.train_X
        if train_X is None:
            if comparisons is not None or ratings is not None:
                raise ValueError("comparisons and ratings need the items they index: train_X is None.")
            train_X = old_X[..., :0, :]
        if strict:
            _check_strict(self, train_X, comparisons, ratings)
        if train_X.dim() != 2:
            raise UnsupportedError(
                f"set_train_data takes n x d items, got shape {tuple(train_X.shape)}; "
                "a batched model is built by the constructor or condition_on_observations."
            )
        if self._data.dim == 0 and train_X.shape[-1] == 0:
            return
        new = PreferenceData.create(
            train_X,
            comparisons,
            ratings,
            rating_index,
            rating_eps=self.rating_eps,
            ties=ties,
            rating_levels=self.rating_levels,
        )
        self._set_data(new.to(device=old_X.device, dtype=old_X.dtype), None)

    def condition_on_observations(
        self,
        X: Tensor,
        Y: Tensor | None = None,
        *,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        **kwargs: Any,
    ) -> PairwiseGPInterface:
        r"""A new model with the items ``X`` and observations among them added (``self`` is
        unchanged), with BoTorch's meaning of ``Y``.

        * ``Y`` of integer dtype and shape ``m x 2`` holds comparisons, rows
          ``[preferred, other]`` indexing the rows of ``X`` (``PairwiseGP``'s meaning and
          what ``PairwiseSobolQMCNormalSampler`` fantasises); so does ``comparisons=``.
        * Ratings go in by keyword only: ``ratings=`` (``q`` values in ``[0, 1]``) with
          ``rating_index=`` (rows of ``X``; by default one rating per row of ``X``).

        Batched ``X`` (``batch x m x d``), batched observations (``batch x m x 2`` comparisons,
        ``batch x q`` ratings) or a batched model give a batched model, one problem per batch
        element (:func:`~torchpref.models.fantasy.condition_batch`): fantasies.

        Args:
            X: ``m x d`` items (a row equal to an existing item reuses its index).
            Y: comparisons as above, or ``None``.

        Raises:
            ValueError: for a floating-point ``Y`` (ratings and comparisons cannot be told
                apart: use ``ratings=`` or a long ``Y``), an integer ``Y`` not of shape
                ``m x 2``, or ``Y`` together with ``comparisons=``.
        """
        if not isinstance(X, Tensor):  # nested lists of numbers, as everywhere else in the API
            X = torch.as_tensor(X, dtype=self.train_X.dtype, device=self.train_X.device)
        if Y is not None:
            if comparisons is not None:
                raise ValueError("give comparisons either as Y or as comparisons=, not both.")
            comparisons = _comparisons_from_Y(Y)
        elif comparisons is not None:
            comparisons = torch.as_tensor(comparisons)
        if ratings is not None:
            ratings = torch.as_tensor(ratings)
            if ratings.dim() > 1 and ratings.shape[-1] == 1:  # BoTorch's m x 1 outcomes
                ratings = ratings.squeeze(-1)
            if rating_index is None:
                rating_index = torch.arange(ratings.shape[-1], device=X.device).expand(ratings.shape)
        if not self.has_data and self._data.dim == 0:  # prior-only: these become the data
            return _condition_prior_only(self, X, comparisons, ratings, rating_index)
        batched = (
            self.batch_shape
            or X.dim() > 2
            or (comparisons is not None and comparisons.dim() > 2)
            or (ratings is not None and ratings.dim() > 1)
        )
        if batched:
            return condition_batch(self, X, comparisons, ratings, rating_index)
        return copy.deepcopy(self).add_observations(X, comparisons, ratings, rating_index)

    # ------------------------------------------------------------ observation noise
    def _add_observation_noise(self, mvn: MultivariateNormal, observation_noise: bool | Tensor) -> MultivariateNormal:
        r"""The posterior of the utility as a person perceives it when comparing: ``f + eps``
        with independent ``eps ~ N(0, sigma_R^2)`` per item (eq. 3), or with the given
        ``batch x q x 1`` (or ``q``) variances when ``observation_noise`` is a tensor."""
        cov = mvn.covariance_matrix
        if isinstance(observation_noise, Tensor):
            noise = observation_noise.to(cov)
            if noise.dim() > 1 and noise.shape[-1] == 1:
                noise = noise.squeeze(-1)
            try:
                noise = noise.expand(cov.shape[:-1])
            except RuntimeError:
                raise ValueError(
                    f"observation_noise must be variances of shape {(*cov.shape[:-1], 1)} (or "
                    f"broadcast to it), got shape {tuple(observation_noise.shape)}."
                ) from None
            ok = (noise.detach() >= 0) & noise.detach().isfinite()
            if not bool(ok.all()):
                raise ValueError(
                    f"observation_noise must be finite variances >= 0, got {noise.detach()[~ok][:3].tolist()}."
                )
        else:
            noise = (self.likelihood.comparison.comparison_noise**2).to(cov).expand(cov.shape[:-1])
        return MultivariateNormal(mvn.mean, DenseLinearOperator(cov + torch.diag_embed(noise)))


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


def _condition_prior_only(model, X: Tensor, comparisons, ratings, rating_index):
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
        ratings, rating_index = (
            ratings.expand(*batch, ratings.shape[-1]),
            rating_index.expand(*batch, ratings.shape[-1]),
        )
    new._set_data(
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
