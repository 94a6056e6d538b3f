r"""The model's prediction strategy: one object holding what prediction and the evidence need.

:class:`PosteriorState` plays the part of GPyTorch's ``prediction_strategy``: built lazily by
:meth:`~torchpref.PreferenceGP._state` for one data object and one set of hyperparameter values
and one module structure (:func:`cache_key`, computed once per call of ``_state``: the values of
all parameters and buffers, the modules' classes, their non-tensor settings such as a Matérn
kernel's ``nu`` or the model's ``ties_offered``, and their tensors' dtypes), and replaced when any
of them changes, or when the model switches between train and eval
mode (as GPyTorch resets ``prediction_strategy``). Building it solves the Laplace modes of all the
model's problems (:func:`~torchpref.inference.laplace.find_mode`), warm-started from the previous
state's modes.
"""

from __future__ import annotations

import types
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
from gpytorch.module import Module
from torch import Tensor

from torchpref.inference.laplace import ModeResult, Observations, PredictiveCache, find_mode, predict, predicted_mode
from torchpref.inference.numerics import NotPSDError, batched_cholesky, cholesky_jittered
from torchpref.inference.padding import PaddedData

if TYPE_CHECKING:
    from torchpref.models.preference_gp import PreferenceGP

#: Up to this many test points (all blocks together) one kernel call on ``[train_X; X]`` gives both
#: the cross-covariances and the test blocks (a few wasted entries cost less than a second call).
JOINT_KERNEL_MAX_POINTS = 64


def submodules(module: torch.nn.Module) -> list[torch.nn.Module]:
    """``module`` and all modules below it, breadth first (a shared module once per parent),
    without the generators of ``Module.modules()``."""
    modules, i = [module], 0
    while i < len(modules):
        modules.extend([c for c in modules[i]._modules.values() if c is not None])
        i += 1
    return modules


#: Types of the plain values in a module's ``__dict__`` that :func:`cache_key` records: settings
#: such as a Matérn kernel's ``nu``, the model's ``ties_offered``, a constraint's transform function.
_PLAIN = frozenset(
    {bool, int, float, complex, str, type(None), torch.dtype, torch.device, torch.Size}
    | {types.FunctionType, types.BuiltinFunctionType, types.BuiltinMethodType}
)  # not bound methods: ``setattr(m, "f", m.f)`` (a monkeypatch undone) changes nothing
#: Attributes that do not change the posterior: the train / eval flag (its transitions reset the
#: model's cache explicitly) and the model's once-only scaling warning,
#: warm start and cache itself.
_NOT_STRUCTURE = frozenset({"training", "_scaling_warned", "_warm_f", "_cache"})


def _setting(value: object) -> bool:
    if type(value) in _PLAIN:
        return True
    return type(value) is tuple and all(_setting(v) for v in value)


def cache_key(module: Module) -> tuple[Tensor, tuple]:
    """What the posterior of ``module``'s data depends on, in one pass over ``module`` and every
    module below it (:func:`submodules`' order, each module once):

    * the *fingerprint*: the values of all parameters and buffers, concatenated (each tensor
      once; integer and boolean buffers such as a kernel's ``active_dims`` as floating values);
    * the *structure*: each module's class, its plain settings (numbers, strings, flags, dtypes,
      functions and tuples of them in its ``__dict__``: a Matérn kernel's ``nu``, the model's
      ``ties_offered``, a constraint's transform), and the name and dtype of each of its
      parameters and buffers.

    Equal keys mean the same posterior for the same data. Tensors held as plain attributes
    (neither parameter nor buffer) are not looked into."""
    key, vals, seen = [], [], set()
    for m in dict.fromkeys(submodules(module)):  # a module shared by several parents once
        key.append(type(m))
        key.extend(
            [
                (k, v)
                for k, v in m.__dict__.items()
                if (type(v) in _PLAIN or (type(v) is tuple and _setting(v))) and k not in _NOT_STRUCTURE
            ]
        )
        for tensors in (m._parameters, m._buffers):
            for k, t in tensors.items():
                if t is not None:
                    key.append((k, t.dtype))
                    if id(t) not in seen:
                        seen.add(id(t))
                        vals.append(t)
    if not vals:
        return torch.zeros(0), tuple(key)
    like = next((v.dtype for v in vals if v.is_floating_point()), torch.float64)
    vals = [v if v.is_floating_point() or v.is_complex() else v.to(like) for v in vals]
    with torch.no_grad():  # one call: torch.cat of the flattened values (which promotes the dtypes)
        return torch._utils._flatten_dense_tensors(vals), tuple(key)


def fingerprint(module: Module) -> Tensor:
    """The values of all parameters and buffers (:func:`cache_key`'s first part): equal
    fingerprints mean equal hyperparameters."""
    return cache_key(module)[0]


def prior_factor(K: Tensor, jitter: float | None) -> tuple[Tensor, float | Tensor]:
    """``L`` (``B x N x N``) with ``L L^T = K + jitter I`` for ``K`` (``... x N x N``), and the
    jitter used: one problem starts from the jitter that worked last time."""
    N = K.shape[-1]
    if K.shape[:-2].numel() == 1:
        L, j = cholesky_jittered(K.reshape(N, N), jitter=jitter, name="kernel matrix")
        return L.reshape(1, N, N), j
    return batched_cholesky(K.reshape(-1, N, N), name="kernel matrix")


def carries_gradients(padded: PaddedData) -> bool:
    """Whether the items or the ratings of ``padded`` require gradients."""
    return any(t is not None and t.requires_grad for t in (padded.X, padded.ratings))


@dataclass(frozen=True)
class PosteriorState:
    """Everything prediction and the evidence need, for one data object and one set of
    hyperparameter values."""

    data: object  # the model's data object it was computed for (compared by identity)
    fingerprint: Tensor  # the hyperparameter values it was computed for
    structure: tuple  # the modules' classes and settings it was computed for (:func:`cache_key`)
    padded: PaddedData  # the problems, items transformed by the input transform
    jitter: float | Tensor  # diagonal jitter of L (one per problem for a batch)
    likelihood: Module  # the likelihood module ``obs`` refers to
    obs: Observations
    mode: ModeResult  # batched: B = number of problems
    pred: PredictiveCache

    def is_current(self, data: object, fingerprint: Tensor, structure: tuple) -> bool:
        """Whether this state was computed for ``data`` with the hyperparameters ``fingerprint``
        and the modules ``structure``."""
        return (
            self.data is data
            and self.structure == structure
            and self.fingerprint.dtype == fingerprint.dtype
            and self.fingerprint.device == fingerprint.device
            and torch.equal(self.fingerprint, fingerprint)
        )

    @classmethod
    def build(
        cls,
        model: PreferenceGP,
        fp: Tensor,
        key: tuple,
        previous: PosteriorState | None,
        prior: tuple[PaddedData, Tensor] | None = None,
    ) -> PosteriorState:
        """Solve the modes of ``model``'s problems, warm-started from ``previous`` where sizes match
        (and from zeros if the warm-started solve fails: a start predicted for hyperparameters far
        from the previous ones can be far from the new mode). ``prior``: the model's
        :meth:`~torchpref.PreferenceGP._prior` if already computed."""
        with torch.no_grad():
            padded, K = model._prior() if prior is None else prior
            padded = padded.with_items(padded.X.detach())  # gradients in the items: see ``traced``
            prev_jitter = previous.jitter if (previous is not None and isinstance(previous.jitter, float)) else None
            L, jitter = prior_factor(K.detach(), prev_jitter)
            same_size = previous is not None and previous.mode.f.shape == L.shape[:-1]
            # the observations' index structure depends on the data and the modules' structure
            # (the likelihoods, ties_offered, dtypes) only: kept across hyperparameter values
            same_data = (
                previous is not None
                and previous.data is model.data
                and previous.likelihood is model.likelihood
                and previous.structure == key
            )
            obs = previous.obs if same_data else model._observations()
            if same_data and same_size:  # new hyperparameters: the old modes moved to first order
                warm = (previous.mode.f, predicted_mode(previous.mode.f, previous.pred, L))
            else:
                warm = previous.mode.f if same_size else model._warm_f
            try:
                mode = find_mode(L, obs, f0=warm, max_iter=model.max_newton_iter)
            except NotPSDError:  # LaplaceNumericalError too: from a start far from the new mode
                if warm is None:
                    raise
                mode = find_mode(L, obs, f0=None, max_iter=model.max_newton_iter)  # a cold start
            pred = PredictiveCache.from_mode(L, mode)
        return cls(model.data, fp, key, padded, jitter, model.likelihood, obs, mode, pred)

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
