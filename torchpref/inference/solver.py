r"""The Laplace solver's state: what prediction and the evidence need for one data object and one
set of hyperparameter values, built from tensors and observations only.

:class:`PosteriorState` plays the part of GPyTorch's ``prediction_strategy`` (and of tinygp's
solver objects): :meth:`PosteriorState.solve` takes the problems (``padded``, items already
transformed), their prior covariance ``K``, the observations, a warm start and the previous state,
and solves the Laplace modes of all problems (:func:`~torchpref.inference.laplace.find_mode`). It
never sees a model: the model decides *when* a state is stale (its
:class:`SolveKey`: the data object, the hyperparameter values, the modules' structure, the
likelihood) and keeps the current one.

Shapes (``b`` the number of problems of a batch, flattened; ``n`` items per problem, padded):
``K``: ``(..., n, n)``; ``L``: ``(b, n, n)``, the prior factor ``L L^T = K + jitter I``; the mode
``f``: ``(b, n)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchpref.inference.laplace import ModeResult, PredictiveCache, find_mode, predict, predicted_mode
from torchpref.inference.numerics import NotPSDError, batched_cholesky, cholesky_jittered
from torchpref.inference.observations import Observations
from torchpref.inference.padding import PaddedData

#: Up to this many test points (all blocks together) one kernel call on ``[train_X; X]`` gives both
#: the cross-covariances and the test blocks (a few wasted entries cost less than a second call).
JOINT_KERNEL_MAX_POINTS = 64

#: ``kernel(X1, X2=None, diag=False)``: the prior covariance, densely.
KernelFn = Callable[..., Tensor]


def prior_factor(K: Tensor, jitter: float | None) -> tuple[Tensor, float | Tensor]:
    """``L`` (``b x n x n``) with ``L L^T = K + jitter I`` for ``K`` (``... x n x n``), and the
    jitter used: one problem starts from the jitter that worked last time."""
    n = K.shape[-1]
    if K.shape[:-2].numel() == 1:
        L, j = cholesky_jittered(K.reshape(n, n), jitter=jitter, name="kernel matrix")
        return L.reshape(1, n, n), j
    return batched_cholesky(K.reshape(-1, n, n), name="kernel matrix")


def carries_gradients(padded: PaddedData) -> bool:
    """Whether the items or the ratings of ``padded`` require gradients."""
    return any(t is not None and t.requires_grad for t in (padded.X, padded.ratings))


@dataclass(frozen=True)
class SolveKey:
    """What a state was computed for: the data object (compared by identity), the hyperparameter
    values (``fingerprint``), the modules' classes and settings (``structure``) and the likelihood
    module the observations refer to (by identity)."""

    data: object
    fingerprint: Tensor
    structure: tuple
    likelihood: object

    def matches(self, other: SolveKey) -> bool:
        """The same data, hyperparameter values, structure and likelihood."""
        fp, fo = self.fingerprint, other.fingerprint
        return self.same_observations(other) and fp.dtype == fo.dtype and fp.device == fo.device and torch.equal(fp, fo)

    def same_observations(self, other: SolveKey) -> bool:
        """The observations' index structure is the same: it depends on the data and the modules'
        structure (the likelihoods, ties offered, dtypes) only, not on the hyperparameter values."""
        return self.data is other.data and self.likelihood is other.likelihood and self.structure == other.structure


@dataclass(frozen=True)
class PosteriorState:
    """Everything prediction and the evidence need, for one :class:`SolveKey`."""

    key: SolveKey
    padded: PaddedData  # the problems, items transformed by the input transform
    jitter: float | Tensor  # diagonal jitter of L (one per problem for a batch)
    obs: Observations
    mode: ModeResult  # b problems
    pred: PredictiveCache

    @classmethod
    def solve(
        cls,
        key: SolveKey,
        padded: PaddedData,
        K: Tensor,
        observations: Callable[[], Observations],
        *,
        previous: PosteriorState | None = None,
        warm_f: Tensor | None = None,
        max_iter: int = 100,
        mean: Tensor | None = None,
    ) -> PosteriorState:
        """Solve the modes of the problems ``padded`` with prior covariance ``K``.

        ``observations()`` builds the observations (called only when ``previous`` was computed for
        other data or structure: otherwise its observations are reused). The start: ``previous``'s
        modes moved to first order in the new hyperparameters where its data and sizes match, its
        modes where only the sizes match, else ``warm_f`` (``b x n`` or ``None``: zeros); from
        zeros if the warm-started solve fails (a start predicted for hyperparameters far from the
        previous ones can be far from the new mode).

        ``mean``: the prior mean of the items (``b x n``; ``None``: zero), the one seam of a prior
        mean: it enters the observations as offsets (:meth:`Observations.shifted`) and the mode,
        its factors and ``alpha`` are those of the deviation ``g = f - mean ~ GP(0, K)``."""
        with torch.no_grad():
            padded = padded.with_items(padded.X.detach())  # gradients in the items: see ``traced``
            prev_jitter = previous.jitter if (previous is not None and isinstance(previous.jitter, float)) else None
            L, jitter = prior_factor(K.detach(), prev_jitter)
            same_size = previous is not None and previous.mode.f.shape == L.shape[:-1]
            same_data = previous is not None and previous.key.same_observations(key)
            obs = (previous.obs if (previous is not None and same_data) else observations()).shifted(
                None if mean is None else mean.detach().reshape(L.shape[:-1])
            )
            warm: Tensor | tuple[Tensor, Tensor] | None
            if previous is not None and same_data and same_size:
                warm = (previous.mode.f, predicted_mode(previous.mode.f, previous.pred, L))
            else:
                warm = previous.mode.f if (previous is not None and same_size) else warm_f
            try:
                mode = find_mode(L, obs, f0=warm, max_iter=max_iter)
            except NotPSDError:  # LaplaceNumericalError too: from a start far from the new mode
                if warm is None:
                    raise
                mode = find_mode(L, obs, f0=None, max_iter=max_iter)  # a cold start
            pred = PredictiveCache.from_mode(L, mode)
        return cls(key, padded, jitter, obs, mode, pred)

    def traced(self, padded: PaddedData, K: Tensor, obs: Observations) -> PosteriorState:
        """This state with a prediction cache traced through the mode
        (:meth:`~torchpref.inference.laplace.PredictiveCache.traced`), for the problems ``padded`` whose
        items or ratings carry gradients, their prior covariance ``K`` and observations ``obs``
        (built with autograd on): built afresh for each prediction, so that each has its own
        autograd graph."""
        return replace(self, padded=padded, obs=obs, pred=PredictiveCache.traced(K, self.jitter, obs, self.mode))

    def moments(self, kernel: Callable[..., Tensor], X: Tensor, diag: bool = False) -> tuple[Tensor, Tensor]:
        r"""Posterior mean ``... x q`` and covariance ``... x q x q`` (eqs. 9-10) at transformed
        ``X`` (``... x q x d``, its batch dimensions ending in, or broadcasting to, the problems'
        ``batch_shape``); with ``diag``, the variances ``... x q`` instead of the covariance.
        ``kernel(X1, X2=None, diag=False)`` evaluates the prior covariance densely."""
        padded = self.padded
        S = padded.batch_shape
        q, d = X.shape[-2:]
        shape = torch.broadcast_shapes(X.shape[:-2], S) if S else X.shape[:-2]
        E = shape[: len(shape) - len(S)].numel()
        Xe = X.expand(*shape, q, d).reshape(E, *S, q, d)  # test blocks first, then the problems
        N, K_xs = padded.num_items, None
        if not S and not diag and N and E * q <= JOINT_KERNEL_MAX_POINTS:
            # one problem, a few test points: one kernel call gives K_X* and the test blocks
            Xf = Xe.reshape(E * q, d)
            K = kernel(torch.cat([padded.X, Xf]), Xf)  # (N + E q) x E q
            K_xs = K[:N].reshape(1, N, E, q)
            k_ss = K[N:].reshape(E, q, E, q).diagonal(dim1=0, dim2=2).permute(2, 0, 1)  # E x q x q
        else:
            k_ss = kernel(Xe, diag=diag)  # E x S x q (x q)
        tail = k_ss.shape[len(S) + 2 :]  # () for variances, (q,) for covariances
        if N == 0:  # no items yet: the prior
            return k_ss.new_zeros(shape + (q,)), k_ss.reshape(*shape, q, *tail)
        if not S:  # one problem: one kernel call for all test points
            if K_xs is None:
                K_xs = kernel(padded.X, Xe.reshape(E * q, d)).reshape(1, -1, E, q)
        else:
            K_xs = kernel(padded.X.expand(E, *padded.X.shape), Xe)  # E x S x N x q
            K_xs = padded.cross_covariance(K_xs).movedim(0, -2).reshape(S.numel(), -1, E, q)
        mean, cov = predict(self.pred, K_xs, k_ss.movedim(0, len(S)).reshape(S.numel(), E, q, *tail))
        mean = mean.reshape(*S, E, q).movedim(len(S), 0)
        cov = cov.reshape(*S, E, q, *tail).movedim(len(S), 0)
        return mean.reshape(*shape, q), cov.reshape(*shape, q, *tail)
