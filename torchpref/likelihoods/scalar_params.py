r"""Positive scalar hyperparameters of the likelihoods (``sigma_R``, ``sigma_B``, ``nu``, ``tau``, ...):
a raw parameter, a GPyTorch constraint and an optional prior each (``_ScalarParamsMixin``); the
default constraints, of which the model's likelihoods share one float64 instance
(:func:`shared_constraint`); and :func:`weak_load_hook`, which keeps GPyTorch modules free of
reference cycles."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from gpytorch.constraints import Interval, Positive
from gpytorch.module import Module as GModule
from torch import Tensor


def scalar_parameter(name: str, doc: str) -> property:
    """A property reading and setting the positive scalar hyperparameter ``name`` of a
    :class:`_ScalarParamsMixin` (stored raw, through its constraint)."""

    def get(self) -> Tensor:
        return self._get(name)

    def set_(self, value) -> None:
        self._set(name, value)

    return property(get, set_, doc=doc)


def weak_load_hook(module: GModule) -> None:
    """Hold ``module`` weakly in GPyTorch's ``load_state_dict`` pre-hook.

    GPyTorch's ``Module`` registers its bound method ``_load_state_hook_ignore_shapes`` as a hook,
    which makes every module a reference cycle: a model dropped (and its mode's matrices) is then
    freed only at a pass of Python's cyclic garbage collector, and a loop that builds a model per
    step leaves them to pile up and to make those passes more frequent. The same function is
    registered instead with the module passed in by torch (held weakly)."""
    hooks = module._load_state_dict_pre_hooks
    register = module.register_load_state_dict_pre_hook
    for key, wrapped in list(hooks.items()):
        hook = getattr(wrapped, "hook", None)
        if getattr(hook, "__self__", None) is module and getattr(hook, "__func__", None) is _IGNORE_SHAPES:
            del hooks[key]
            register(_IGNORE_SHAPES)


_IGNORE_SHAPES = GModule._load_state_hook_ignore_shapes


#: The default constraints of the scalar hyperparameters, by name.
DEFAULT_CONSTRAINTS = {"positive": Positive, "precision": lambda: Interval(1e-2, 1e6)}
# The model's likelihoods share one float64 instance of each default constraint (shared_constraint);
# a likelihood swaps in a private copy before anything could change one (_apply, _load_from_state_dict).
_SHARED_CONSTRAINTS: dict[str, Interval] = {}
# The raw value of a parameter under a shared constraint, by (constraint name, value): computed once,
# as a fresh constraint gives it, whose bounds are in GPyTorch's default dtype (float32).
_SHARED_RAW_VALUES: dict[tuple[str, float], Tensor] = {}


def shared_constraint(kind: str) -> Interval:
    """One instance, shared by all the likelihoods of models, of the default constraint ``kind`` of
    :data:`DEFAULT_CONSTRAINTS`, its bounds in float64 (what a float64 model's ``to`` makes of a
    fresh one), so that building a float64 model makes no constraint and needs no ``to``. A
    parameter registered with it gets the raw value a fresh constraint gives: with float32 bounds an
    Interval's width rounds (``nu = 80`` is stored as 79.9999992 in a model), and every result with
    ratings depends on it to 1e-8."""
    constraint = _SHARED_CONSTRAINTS.get(kind)
    if constraint is None:
        # normal tensors even when first made inside torch.inference_mode (a model built in a
        # simulation's inference block): an inference tensor could not be loaded into later
        with torch.inference_mode(False):
            constraint = DEFAULT_CONSTRAINTS[kind]()
            for key, bound in constraint.named_buffers(recurse=False):
                setattr(constraint, key, bound.to(torch.float64))
        constraint._torchpref_shared = kind
        _SHARED_CONSTRAINTS[kind] = constraint
    return constraint


def _raw_value(name: str, value, constraint: Interval, like: Tensor) -> Tensor:
    """The raw value (dtype and device of ``like``) of the positive hyperparameter ``name`` at
    ``value``, through ``constraint``; a ``ValueError`` for a value that is not positive and finite
    or not inside the constraint."""
    value = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if not torch.isfinite(value).all() or (value <= 0).any():
        raise ValueError(f"{name} must be positive and finite, got {value.tolist()}.")
    raw_value = constraint.inverse_transform(value)
    if not bool(torch.isfinite(raw_value).all()):  # at or beyond a bound of an interval constraint
        raise ValueError(f"{name} must lie inside its constraint {constraint}, got {value.tolist()}.")
    return raw_value


if TYPE_CHECKING:  # the mixin is only ever mixed into a GPyTorch Module

    class _MixinBase(GModule): ...

else:
    _MixinBase = object


class _ScalarParamsMixin(_MixinBase):
    """Positive scalar hyperparameters kept as raw parameters with a constraint and an optional prior."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        weak_load_hook(self)

    def _register(
        self, name: str, value: float, constraint: Interval | None, prior, learn: bool, default: str = "positive"
    ) -> None:
        """Register ``raw_{name}`` at ``value`` with ``constraint`` (a new default constraint
        ``default`` of :data:`DEFAULT_CONSTRAINTS` if ``None``) and ``prior``."""
        constraint = DEFAULT_CONSTRAINTS[default]() if constraint is None else constraint
        kind, raw_value = getattr(constraint, "_torchpref_shared", False), None
        if isinstance(kind, str) and isinstance(value, (int, float)) and not isinstance(value, bool):
            key = (kind, float(value))
            if key not in _SHARED_RAW_VALUES:
                with torch.inference_mode(False):  # a normal tensor, as for the shared constraint
                    _SHARED_RAW_VALUES[key] = _raw_value(
                        name, value, DEFAULT_CONSTRAINTS[kind](), torch.zeros((), dtype=torch.float64)
                    )
            raw_value = _SHARED_RAW_VALUES[key]
        raw = torch.nn.Parameter(
            torch.zeros((), dtype=torch.float64) if raw_value is None else raw_value.clone(), requires_grad=learn
        )
        self.register_parameter(f"raw_{name}", raw)
        self.register_constraint(f"raw_{name}", constraint)
        if prior is not None:
            self.register_prior(
                f"{name}_prior", prior, lambda m, n=name: getattr(m, n), lambda m, v, n=name: m._set(n, v)
            )
        if raw_value is None:
            self._set(name, value)

    def _own_constraints(self, changes: Callable[[str, Interval], bool]) -> None:
        """Private copies of the shared default constraints that ``changes(name, constraint)`` would change."""
        for key, constraint in list(self._constraints.items()):
            if getattr(constraint, "_torchpref_shared", False) and changes(key, constraint):
                private = copy.deepcopy(constraint)
                private._torchpref_shared = False
                self._constraints[key] = private
                self._modules[key] = private

    def _apply(self, fn, *args, **kwargs):
        # e.g. ``to``: a shared constraint whose bounds ``fn`` converts is replaced by a private copy first
        self._own_constraints(lambda key, c: any(fn(b) is not b for b in c._buffers.values() if b is not None))
        return super()._apply(fn, *args, **kwargs)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, *args, **kwargs):
        def changes(key: str, constraint: Interval) -> bool:  # other bounds, or tensors to be assigned
            if local_metadata.get("assign_to_params_buffers", False):
                return True
            loaded = ((b, state_dict.get(f"{prefix}{key}.{name}")) for name, b in constraint._buffers.items())
            return any(
                v is not None and not (isinstance(v, Tensor) and v.shape == b.shape and torch.equal(v.to(b), b))
                for b, v in loaded
            )

        self._own_constraints(changes)
        return super()._load_from_state_dict(state_dict, prefix, local_metadata, *args, **kwargs)

    def _set(self, name: str, value) -> None:
        raw = getattr(self, f"raw_{name}")
        raw_value = _raw_value(name, value, getattr(self, f"raw_{name}_constraint"), raw)
        with torch.no_grad():  # what ``initialize`` does, without its per-call overhead
            raw.copy_(raw_value.expand_as(raw))

    def _get(self, name: str) -> Tensor:
        return getattr(self, f"raw_{name}_constraint").transform(getattr(self, f"raw_{name}"))
