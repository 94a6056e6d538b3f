r"""The dtype a model's Laplace problem is solved in, and its kernel evaluated in that dtype.

A float32 :class:`~torchpref.PreferenceGP` solves in float64 by default (mixed precision): its
kernel matrices are evaluated with the parameters and inputs converted to float64, factorised
and solved there, and its posteriors are returned in float32. ``laplace_dtype=torch.float32``
solves natively instead. Why, and what each costs: docs/precision.md.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import chain

import torch
from torch import Tensor
from torch.func import functional_call

#: The dtypes a model and its Laplace solve may be in. float16 and bfloat16 are refused: their
#: 3 and 2 significant digits cannot resolve a Newton decrement, and the kernel's squared
#: distances overflow float16 beyond ``|x|`` of about 0.003 times its lengthscale floor.
SUPPORTED_DTYPES = (torch.float32, torch.float64)


def check_dtype(dtype: torch.dtype, what: str = "train_X") -> None:
    """A ``ValueError`` naming ``dtype`` unless it is one of :data:`SUPPORTED_DTYPES`."""
    if dtype not in SUPPORTED_DTYPES:
        raise ValueError(
            f"{what} is {dtype}; PreferenceGP supports float32 and float64 (float64 recommended): "
            f"convert it, e.g. .to(torch.float64)."
        )


def check_laplace_dtype(value: object) -> torch.dtype | None:
    """``value`` if it is ``None``, ``torch.float32`` or ``torch.float64``, else a ``ValueError``."""
    if value is None or value in SUPPORTED_DTYPES:
        return value
    raise ValueError(f"laplace_dtype must be None, torch.float32 or torch.float64, got {value!r}.")


def solve_dtype(model_dtype: torch.dtype, asked: torch.dtype | None) -> torch.dtype:
    """The dtype of the solve: ``asked`` (default float64), but never less precise than the
    model's own ``model_dtype``."""
    asked = torch.float64 if asked is None else asked
    return asked if torch.finfo(asked).eps <= torch.finfo(model_dtype).eps else model_dtype


class _Evaluate(torch.nn.Module):
    """``fn(*args)`` with ``module`` as a child, so that :func:`torch.func.functional_call` can
    give it converted parameters for one call."""

    def __init__(self, module: torch.nn.Module, fn: Callable[..., Tensor]):
        super().__init__()
        self.module, self.fn = module, fn

    def forward(self, *args: Tensor) -> Tensor:
        return self.fn(*args)


def call_in_dtype(module: torch.nn.Module, dtype: torch.dtype, fn: Callable[..., Tensor], *args: Tensor) -> Tensor:
    """``fn(*args)`` (a method of ``module``, e.g. a kernel's ``forward``) with ``module``'s
    floating parameters and buffers and the tensors ``args`` converted to ``dtype`` for this call
    only; the conversion is differentiable, so gradients reach the parameters in their own dtype."""
    if all(t.dtype == dtype for t in chain(module.parameters(), args)):
        return fn(*args)
    converted = {
        f"module.{name}": t.to(dtype)
        for name, t in chain(module.named_parameters(), module.named_buffers())
        if t.is_floating_point()
    }
    args = tuple(a.to(dtype) if a.is_floating_point() else a for a in args)
    return functional_call(_Evaluate(module, fn), converted, args)
