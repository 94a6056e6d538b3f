r"""Kernels of our own: :class:`FixedRBFKernel`, an RBF kernel with fixed hyperparameters.

The model's default kernel is GPyTorch's ``ScaleKernel(RBFKernel())`` with priors
(:func:`torchpref.models.preference_gp.default_covar_module`); a simulation study that never fits the
hyperparameters evaluates thousands of small kernel matrices, where that kernel's constraint
transforms and sub-modules cost most of the time. :func:`fixed_rbf_kernel` builds the fast
equivalent from settings.
"""

from __future__ import annotations

import torch
from gpytorch.kernels import Kernel, RBFKernel, ScaleKernel
from torch import Tensor

__all__ = ["FixedRBFKernel", "fixed_rbf_kernel"]


class FixedRBFKernel(Kernel):
    r"""``outputscale * exp(-|x - x'|^2 / (2 lengthscale^2))`` with fixed (buffer) hyperparameters.

    The values of ``ScaleKernel(RBFKernel())`` with the same lengthscale and outputscale, computed
    by the same operations (GPyTorch's centred quadratic expansion, so the results are the same to
    the last bit), without the constraint transforms, autograd function and sub-modules that cost
    most of a small kernel evaluation's time. For experiments that never fit the hyperparameters;
    ``outputscale`` and ``base_kernel.lengthscale`` read and set the values as on a ``ScaleKernel``.

    **A batch of values.** A ``B`` tensor of lengthscales (and of outputscales, or one) gives
    ``B`` kernels at once: ``k(X1, X2)`` is ``B x n1 x n2`` for inputs ``n x d`` or ``B x n x d``,
    e.g. one isotropic kernel per problem of a batched model whose hyperparameters differ by
    problem (learned per trial in a simulation study).

    Args:
        lengthscale: the lengthscale, a scalar or ``B`` values (isotropic).
        outputscale: the kernel variance ``sigma_f^2``, a scalar or ``B`` values.
    """

    lengthscale_value: Tensor  # buffers
    outputscale_value: Tensor

    def __init__(self, lengthscale: float | Tensor, outputscale: float | Tensor):
        super().__init__()
        ls, os_ = (torch.as_tensor(v) for v in (lengthscale, outputscale))
        dtype = ls.dtype if ls.is_floating_point() else torch.get_default_dtype()
        self.register_buffer("lengthscale_value", _lengthscale_shape(ls.to(dtype)))
        self.register_buffer("outputscale_value", _outputscale_shape(os_.to(dtype)))

    # ``ScaleKernel(RBFKernel())``'s attribute names, so code written for that kernel can read and
    # set the values: ``k.outputscale``, ``k.base_kernel.lengthscale`` (the kernel itself).
    @property
    def base_kernel(self) -> FixedRBFKernel:
        """The kernel itself, so ``kernel.base_kernel.lengthscale`` reads as for ``ScaleKernel(RBFKernel())``."""
        return self

    @property
    def lengthscale(self) -> Tensor:
        """The fixed lengthscale (``1 x 1``)."""
        return self.lengthscale_value

    @lengthscale.setter
    def lengthscale(self, value: float | Tensor) -> None:
        self.lengthscale_value = _lengthscale_shape(torch.as_tensor(value).to(self.lengthscale_value))

    @property
    def outputscale(self) -> Tensor:
        """The fixed kernel variance ``sigma_f^2`` (a scalar)."""
        return self.outputscale_value

    @outputscale.setter
    def outputscale(self, value: float | Tensor) -> None:
        self.outputscale_value = _outputscale_shape(torch.as_tensor(value).to(self.outputscale_value))

    def forward(self, x1: Tensor, x2: Tensor, diag: bool = False, last_dim_is_batch: bool = False, **params) -> Tensor:
        if last_dim_is_batch:
            raise NotImplementedError("FixedRBFKernel does not support last_dim_is_batch.")
        x1 = x1.div(self.lengthscale_value)
        x2 = x2.div(self.lengthscale_value)
        scale = self.outputscale_value.unsqueeze(-1)  # () -> 1, B -> B x 1
        if diag:
            if torch.equal(x1, x2):
                return scale.expand(*x1.shape[:-1]).clone()
            return torch.linalg.norm(x1 - x2, dim=-1).pow(2).div_(-2.0).exp_().mul_(scale)
        same = torch.equal(x1, x2) and not (x1.requires_grad or x2.requires_grad)
        adjustment = x1.mean(-2, keepdim=True)  # gpytorch.kernels.kernel.sq_dist, step by step
        x1 = x1 - adjustment
        x1_norm = x1.pow(2).sum(dim=-1, keepdim=True)
        x1_pad = torch.ones_like(x1_norm)
        if same:
            x2, x2_norm, x2_pad = x1, x1_norm, x1_pad
        else:
            x2 = x2 - adjustment
            x2_norm = x2.pow(2).sum(dim=-1, keepdim=True)
            x2_pad = torch.ones_like(x2_norm)
        res = torch.cat([-2.0 * x1, x1_norm, x1_pad], dim=-1).matmul(torch.cat([x2, x2_pad, x2_norm], dim=-1).mT)
        if same:
            res.diagonal(dim1=-2, dim2=-1).fill_(0)
        return res.clamp_min_(0).div_(-2.0).exp_().mul(scale.unsqueeze(-1))


def _lengthscale_shape(ls: Tensor) -> Tensor:
    """A scalar as ``1 x 1``, ``B`` values as ``B x 1 x 1`` (they divide ``[B x] n x d`` inputs)."""
    return ls.reshape(1, 1) if ls.numel() == 1 else ls.reshape(-1, 1, 1)


def _outputscale_shape(os_: Tensor) -> Tensor:
    """A scalar as ``()``, ``B`` values as ``B``."""
    return os_.reshape(()) if os_.numel() == 1 else os_.reshape(-1)


def fixed_rbf_kernel(lengthscale: float, outputscale: float, like: Tensor) -> FixedRBFKernel:
    r"""A :class:`FixedRBFKernel` holding the values a ``ScaleKernel(RBFKernel())`` set to
    ``lengthscale`` and ``outputscale`` stores (its constraint round trip included), in the
    dtype and on the device of ``like``: the two kernels give the same matrices to the bit."""
    ref = ScaleKernel(RBFKernel())
    ref.base_kernel.lengthscale = lengthscale
    ref.outputscale = outputscale
    ref = ref.to(like)  # set, then cast (the float32 round trip of the defaults included)
    with torch.no_grad():
        return FixedRBFKernel(ref.base_kernel.lengthscale.detach().clone(), ref.outputscale.detach().clone()).to(like)
