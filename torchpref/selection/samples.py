r"""Joint posterior samples at a selector's candidates, shared by the selectors that value
answers on them: the joint posterior of one model or ``T`` trials, ``T x S x N`` samples from each
trial's own generator, and the value of a rating or a ranking of given rows under those samples."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from botorch.models.model import Model
from botorch.posteriors import GPyTorchPosterior
from torch import Tensor

from torchpref.acquisition.functions import rating_bin_probabilities
from torchpref.inference.numerics import cholesky_batch
from torchpref.models.batch import BatchedPreferenceGP

__all__ = ["SelectorModel", "joint_posterior", "joint_samples", "sample_scorers"]

SelectorModel = Model | BatchedPreferenceGP
"""What a selector is given: a BoTorch ``Model`` (one person), or a
:class:`~torchpref.models.batch.BatchedPreferenceGP` (``T`` simulated trials at once)."""


def joint_posterior(model: SelectorModel, X: Tensor) -> tuple[Tensor, Tensor]:
    """Joint posterior mean ``T x N`` and covariance ``T x N x N`` at ``X`` (``T x N x d``): a
    :class:`~torchpref.models.batch.BatchedPreferenceGP`'s ``joint``, else (``T = 1``) ``model.posterior``."""
    if isinstance(model, BatchedPreferenceGP):
        return model.joint(X)
    post = model.posterior(X)
    if not isinstance(post, GPyTorchPosterior):
        raise ValueError(f"this selector needs a Gaussian posterior, got a {type(post).__name__}.")
    mvn = post.distribution
    T, N = X.shape[:2]
    return mvn.mean.reshape(T, N), mvn.covariance_matrix.reshape(T, N, N)


def joint_samples(
    mean: Tensor, cov: Tensor, generators: Sequence[torch.Generator], num_samples: int
) -> tuple[Tensor, Tensor]:
    """``T x S x N`` joint samples of ``N(mean, cov)`` (``T x N``, ``T x N x N``; ``S =
    num_samples``, one ``randn`` draw from each trial's generator) and the std (``T x N``)."""
    T, N = mean.shape
    std = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
    jitters = [1e-9 * cov.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)]  # relative, then tenfold
    for _ in range(7):
        jitters.append(10 * jitters[-1])
    L, _, failed = cholesky_batch(cov, torch.stack(jitters))
    if bool(failed.any()):  # fall back on independent samples
        L[failed] = torch.diag_embed(std[failed])
    z = torch.stack(
        [torch.randn(num_samples, N, generator=g, dtype=mean.dtype, device=mean.device) for g in generators]
    )
    return mean.unsqueeze(-2) + z @ L.mT, std


def sample_scorers(
    F: Tensor, value: Callable[[Tensor], Tensor], likelihood: Any, num_bins: int
) -> tuple[Callable[[Tensor], Tensor], Callable[[Tensor], Tensor]]:
    """:meth:`~torchpref.selection.strategies.PerEffortSelector.scorers` of a value of answer probabilities (``T x R x S x Y -> T
    x R``) under joint samples ``F`` (``T x S x N``): a rating's binned answer
    (:func:`rating_bin_probabilities`), a ranking's choice (the comparison likelihood's
    ``choice_probabilities``, lapses included)."""
    T, S, _ = F.shape

    def rating_fn(rows: Tensor) -> Tensor:  # T x R
        Fr = F.gather(2, rows.unsqueeze(1).expand(T, S, rows.shape[1]))  # T x S x R
        return value(rating_bin_probabilities(Fr.mT, likelihood.rating, num_bins))

    def ranking_fn(rows: Tensor) -> Tensor:  # T x R x q
        R, q = rows.shape[1:]
        Fr = F.gather(2, rows.reshape(T, 1, R * q).expand(T, S, R * q)).reshape(T, S, R, q).transpose(1, 2)
        return value(likelihood.comparison.choice_probabilities(Fr))

    return rating_fn, ranking_fn
