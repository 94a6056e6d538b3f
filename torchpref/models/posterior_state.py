r"""What a model's posterior depends on: :func:`cache_key` over its modules.

The model keeps one :class:`~torchpref.inference.solver.PosteriorState` (its prediction strategy),
solved for one data object, one set of hyperparameter values and one module structure (the
:func:`cache_key`, computed once per call of the model's ``_state``: the values of all parameters
and buffers, the modules' classes, their non-tensor settings such as a Matérn kernel's ``nu`` or
the model's ``ties_offered``, and their tensors' dtypes), and replaced when any of them changes, or
when the model switches between train and eval mode (as GPyTorch resets ``prediction_strategy``).
"""

from __future__ import annotations

import types

import torch
from gpytorch.module import Module
from torch import Tensor


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
#: warm start, cache itself and the report of its last fit.
_NOT_STRUCTURE = frozenset({"training", "_scaling_warned", "_warm_f", "_cache", "last_fit"})


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
    key: list[object] = []
    vals: list[Tensor] = []
    seen: set[int] = set()
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
