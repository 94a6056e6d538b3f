r"""The checks of :class:`~torchpref.models.preference_gp.PreferenceGP`'s constructor arguments that
are not the data's: each argument's type (a kernel, an input transform, a number, a flag) and
range, as a ``ValueError`` naming the argument and the value, before anything is built from it.
The likelihoods' own setters check their parameters' ranges (positive and finite)."""

from __future__ import annotations

import math
import numbers

import torch
from botorch.models.transforms.input import InputTransform
from gpytorch.kernels import Kernel
from gpytorch.means import Mean


def _is_flag(value: object) -> bool:
    kind = type(value)
    return isinstance(value, bool) or (kind.__module__ == "numpy" and kind.__name__ in ("bool", "bool_"))


def _is_real(value: object) -> bool:
    if isinstance(value, torch.Tensor):
        return value.numel() == 1 and value.is_floating_point()
    return isinstance(value, numbers.Real) and not _is_flag(value)


def check_flag(name: str, value: object) -> bool:
    """``value`` as a ``bool``, or a ``ValueError``: a string such as ``'no'`` is not a flag."""
    if not _is_flag(value):
        raise ValueError(f"{name} must be True or False, got {value!r} ({type(value).__name__}).")
    return bool(value)


def check_rating_eps(value: object) -> float:
    """``rating_eps`` as a float in ``(0, 0.5)``, or a ``ValueError``."""
    if not _is_real(value) or not (0.0 < float(value) < 0.5):  # type: ignore[arg-type]
        raise ValueError(f"rating_eps must be a number in (0, 0.5), got {value!r}.")
    return float(value)  # type: ignore[arg-type]


def check_model_arguments(
    covar_module: object = None,
    input_transform: object = None,
    reals: dict[str, object] | None = None,
    flags: dict[str, object] | None = None,
    rating_eps: object = 0.01,
    mean_module: object = None,
) -> None:
    """``covar_module`` a GPyTorch ``Kernel`` or ``None``; ``input_transform`` a BoTorch
    ``InputTransform`` or ``None``; each of ``reals`` (name -> value) a real number (or a
    one-element floating tensor) or ``None``; each of ``flags`` a ``bool``; ``rating_eps`` in
    ``(0, 0.5)``; ``mean_module`` a GPyTorch ``Mean`` or ``None``.

    Raises:
        ValueError: naming the first argument of the wrong type or range.
    """
    if covar_module is not None and not isinstance(covar_module, Kernel):
        raise ValueError(
            f"covar_module must be a gpytorch Kernel (e.g. ScaleKernel(RBFKernel())) or None, got "
            f"{covar_module!r:.60} ({type(covar_module).__name__})."
        )
    if input_transform is not None and not isinstance(input_transform, InputTransform):
        raise ValueError(
            f"input_transform must be a BoTorch InputTransform (e.g. Normalize(d)) or None, got "
            f"{input_transform!r:.60} ({type(input_transform).__name__})."
        )
    if mean_module is not None and not isinstance(mean_module, Mean):
        raise ValueError(
            f"mean_module must be a gpytorch Mean (e.g. ConstantMean()) or None, got "
            f"{mean_module!r:.60} ({type(mean_module).__name__})."
        )
    for name, value in (reals or {}).items():
        if value is not None and not _is_real(value):
            raise ValueError(f"{name} must be a real number, got {value!r:.60} ({type(value).__name__}).")
        if value is not None and not math.isfinite(float(value)):  # type: ignore[arg-type]
            raise ValueError(f"{name} must be finite, got {float(value)}.")  # type: ignore[arg-type]
    for name, value in (flags or {}).items():
        check_flag(name, value)
    check_rating_eps(rating_eps)
