r"""Conditioning a :class:`~torchpref.PreferenceGP` on batches of observations, and fantasies.

BoTorch's look-ahead acquisition functions (``qKnowledgeGradient``,
``qNegIntegratedPosteriorVariance``) ask a model for *fantasy models*: the model conditioned on
sampled answers at candidate points, one problem per sample and candidate batch. Here a fantasy
model is a :class:`~torchpref.PreferenceGP` of batch shape ``sample_shape x batch_shape``
whose problems share the old items and observations and each add the candidates ``X`` with
their own sampled answers (:meth:`~torchpref.inference.padding.PaddedData.append`); the batch-first
Laplace solver finds all their modes at once, warm-started from the old mode and the old
posterior mean at ``X``.
"""

from __future__ import annotations

import copy
from typing import Protocol, TypeVar

import torch
from botorch.posteriors.gpytorch import GPyTorchPosterior
from botorch.sampling.base import MCSampler
from botorch.sampling.pairwise_samplers import PairwiseMCSampler
from torch import Tensor

from torchpref.data.preference_data import PreferenceData, prepare_levels, prepare_ratings
from torchpref.inference.padding import PaddedData
from torchpref.inference.solver import PosteriorState
from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood
from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood


class RatingLikelihoods(Protocol):
    """The model's likelihoods as fantasies use them: the rating likelihood (a Protocol:
    :class:`~torchpref.models.defaults.PreferenceLikelihood`'s module imports this one, through
    ``pairwise_interface``)."""

    @property
    def rating(self) -> BetaRatingLikelihood | OrdinalRatingLikelihood:
        """The likelihood of a rating: Beta on ``[0, 1]``, or ordinal for levels."""


class FantasyModel(Protocol):
    """What conditioning and fantasies use of a :class:`~torchpref.PreferenceGP` (a Protocol:
    ``preference_gp`` imports this module)."""

    _cache: PosteriorState | None

    @property
    def train_X(self) -> Tensor:
        """The items (``batch x n x d``, untransformed)."""

    @property
    def batch_shape(self) -> torch.Size:
        """The batch of problems."""

    @property
    def rating_levels(self) -> int | None:
        """``K`` where ratings are levels ``1..K``, else ``None``."""

    @property
    def rating_eps(self) -> float:
        """How far ratings are kept from 0 and 1."""

    @property
    def likelihood(self) -> RatingLikelihoods:
        """The model's likelihoods (``model.likelihood``)."""

    def posterior(self, X: Tensor, *, observation_noise: bool = False) -> GPyTorchPosterior:
        """The posterior at ``X`` (with the comparison noise where ``observation_noise``)."""

    def replace_data(
        self, data: PreferenceData | PaddedData, warm_f: Tensor | None = None, *, lazy: bool = False
    ) -> object:
        """Swap in new observations (``lazy``: solved at the next prediction)."""

    def _padded(self) -> PaddedData: ...

    def _state(self) -> PosteriorState: ...

    def _predict(self, X: Tensor) -> tuple[Tensor, Tensor]: ...

    def _prediction_inputs(self, X: Tensor) -> Tensor: ...


#: the model conditioned (the result is a new one of its class)
ModelT = TypeVar("ModelT", bound=FantasyModel)


def _check_indices(name: str, index: Tensor, m: int) -> Tensor:
    index = torch.as_tensor(index)
    if index.is_floating_point() or (index.numel() and ((index < 0) | (index >= m)).any()):
        raise ValueError(
            f"{name} must hold integer indices into the {m} rows of X, got {index.flatten()[:6].tolist()}."
        )
    return index.long()


def batch_shape_of(
    X: Tensor, comparisons: Tensor | None, ratings: Tensor | None, model_batch: torch.Size = torch.Size()
) -> torch.Size:
    r"""The batch shape that ``batch_X x m x d`` items, ``batch_C x k x 2`` comparisons,
    ``batch_R x r`` ratings and a model of batch shape ``model_batch`` broadcast to.

    Raises:
        ValueError: the shapes do not broadcast, naming them.
    """
    shapes = {"X": X.shape[:-2], "the model": model_batch}
    if comparisons is not None:
        shapes["comparisons"] = comparisons.shape[:-2]
    if ratings is not None:
        shapes["ratings"] = torch.as_tensor(ratings).shape[:-1]
    try:
        return torch.broadcast_shapes(*shapes.values())
    except RuntimeError:
        named = ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
        raise ValueError(f"the batch shapes do not broadcast: {named}.") from None


def condition_batch(
    model: ModelT,
    X: Tensor,
    comparisons: Tensor | None = None,
    ratings: Tensor | None = None,
    rating_index: Tensor | None = None,
) -> ModelT:
    r"""A new model with the items ``X`` and observations among them added to every problem.

    Args:
        model: a model without padded items (one problem, batched training data of equal
            sizes, or a fantasy model); unchanged.
        X: ``batch_X x m x d`` new items (untransformed).
        comparisons: ``batch_C x k x 2`` long, rows ``[preferred, other]`` into ``X``'s rows.
        ratings: ``batch_R x r`` values in ``[0, 1]`` of the rows ``rating_index`` (``batch_R x r``).

    Returns:
        A model of batch shape ``broadcast(batch_X, batch_C, batch_R, model.batch_shape)``.
    """
    X = torch.as_tensor(X).to(model.train_X)
    if X.dim() < 2 or X.shape[-1] != model.train_X.shape[-1]:
        raise ValueError(f"X must be ... x m x {model.train_X.shape[-1]}, got shape {tuple(X.shape)}.")
    m = X.shape[-2]
    if comparisons is not None:
        comparisons = _check_indices("comparisons", comparisons, m)
        if comparisons.shape[-1] != 2 or (comparisons[..., 0] == comparisons[..., 1]).any():
            raise ValueError(
                f"comparisons must be ... x k x 2 with two different items per row, got "
                f"shape {tuple(comparisons.shape)}."
            )
    if (ratings is None) != (rating_index is None):
        raise ValueError("ratings and rating_index must be given together.")
    if ratings is not None:
        assert rating_index is not None  # given together: checked above
        rating_index = _check_indices("rating_index", rating_index, m)
        shape = torch.as_tensor(ratings).shape
        levels = getattr(model, "rating_levels", None)
        if levels is not None:  # an ordinal model's ratings are levels
            ratings = prepare_levels(ratings, levels, dtype=X.dtype, device=X.device).reshape(shape)
        else:
            ratings = prepare_ratings(ratings, model.rating_eps, dtype=X.dtype, device=X.device).reshape(shape)
    batch_shape_of(X, comparisons, ratings, model.batch_shape)
    new_data = model._padded().append(X, comparisons, ratings, rating_index)
    with torch.no_grad():  # warm start: the old mode, the old posterior mean at X
        S, N = model.batch_shape, model.train_X.shape[-2]
        f_old = model._state().mode.f.reshape(*S, N)
        f_new = model._predict(model._prediction_inputs(X))[0]
        shape = new_data.batch_shape
        warm = torch.cat([f_old.expand(*shape, N), f_new.expand(*shape, m)], dim=-1)
    cache, model._cache = model._cache, None  # not deep-copied
    try:
        new = copy.deepcopy(model)
    finally:
        model._cache = cache
    new.replace_data(new_data, warm.reshape(-1, N + m), lazy=True)
    return new


def perceived_utility(model: FantasyModel, X: Tensor) -> GPyTorchPosterior:
    r"""The posterior of ``f + eps`` at ``X`` with ``eps ~ N(0, sigma_R^2)`` independent per point:
    the utilities a person compares (eq. 3), so that ``P(f_i + eps_i > f_j + eps_j)`` is the
    probit likelihood of the comparison."""
    return model.posterior(X, observation_noise=True)


def sampled_comparisons(sampler: PairwiseMCSampler, posterior: GPyTorchPosterior) -> Tensor:
    r"""Comparisons ``sample_shape x batch x k x 2`` among the ``q`` points, rows ``[preferred,
    other]``: the pairs the sampler picks, each oriented by the utilities it samples.

    BoTorch's ``PairwiseMCSampler`` (0.18) returns each pair as ``[other, preferred]``
    (``np.choose`` takes the second index when the first sample is larger), the reverse of
    ``PairwiseGP``'s own convention; so the pairs are re-oriented here with the sampler's own
    utility samples (the same base samples: the sampler caches them).
    """
    pairs = sampler(posterior)
    samples = super(PairwiseMCSampler, sampler).forward(posterior).squeeze(-1)  # type: ignore[safe-super]  # sample_shape x batch x q
    first = samples.gather(-1, pairs[..., 0].to(samples.device))
    second = samples.gather(-1, pairs[..., 1].to(samples.device))
    return torch.where((first >= second).unsqueeze(-1), pairs, pairs.flip(-1)).to(samples.device)


def fantasize(model: ModelT, X: Tensor, sampler: MCSampler, kind: str | None = None) -> ModelT:
    r"""A fantasy model: ``model`` conditioned on sampled answers at ``X`` (``batch x q x d``).

    Args:
        kind: ``"comparisons"`` (the default with a ``PairwiseMCSampler``, e.g. BoTorch's
            ``PairwiseSobolQMCNormalSampler``): the sampler draws perceived utilities ``f + eps``
            (eq. 3) at the ``q`` points and turns them into comparisons among them, as for
            ``PairwiseGP``. ``"ratings"`` (the default with any other ``MCSampler``): the sampler
            draws the utility ``f`` and each point gets the rating ``mu(f)`` (eq. 7), the mean of
            its Beta likelihood (whose spread, a standard deviation below ``1 / (2 sqrt(nu + 1))``,
            is left out).

    Returns:
        A model of batch shape ``sampler.sample_shape x broadcast(batch, model.batch_shape)``.
    """
    if not isinstance(sampler, MCSampler):
        raise TypeError(
            f"sampler must be a BoTorch MCSampler (e.g. PairwiseSobolQMCNormalSampler), got {sampler!r:.60}."
        )
    kind = kind or ("comparisons" if isinstance(sampler, PairwiseMCSampler) else "ratings")
    if kind == "comparisons":
        if not isinstance(sampler, PairwiseMCSampler):
            raise ValueError("comparison fantasies need a PairwiseMCSampler (e.g. PairwiseSobolQMCNormalSampler).")
        return condition_batch(model, X, comparisons=sampled_comparisons(sampler, perceived_utility(model, X)))
    if kind == "ratings":
        if isinstance(sampler, PairwiseMCSampler):
            raise ValueError("rating fantasies need a sampler of utilities, not a PairwiseMCSampler.")
        f = sampler(model.posterior(X)).squeeze(-1)  # sample_shape x batch x q
        rating = model.likelihood.rating
        if not isinstance(rating, BetaRatingLikelihood):  # as before: no rating mean for levels
            raise AttributeError(
                f"rating fantasies need a Beta rating likelihood's mean_link; {type(rating).__name__} has none."
            )
        u = rating.mean_link(f)  # differentiable in X, as BoTorch's fantasies are
        index = torch.arange(X.shape[-2], device=u.device).expand(u.shape)
        return condition_batch(model, X, ratings=u, rating_index=index)
    raise ValueError(f"kind must be 'comparisons' or 'ratings', got {kind!r}.")
