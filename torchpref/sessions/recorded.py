r"""What a session file's header records about the session's model and selector, and how a resumed
session gets them back.

A new file's header holds :func:`describe_model` of the model the session starts from (its class,
kernel and likelihood structure, settings, and every hyperparameter and constraint value, exactly:
JSON round-trips float64) and :func:`describe_selector` of its selector (class and options). A file
written before these were recorded (torchpref 0.1.0) is read as written with that release's
defaults (:func:`legacy_model_description`, :func:`legacy_selector_description`), frozen here.

Resuming a file without a ``model_factory`` or ``selector`` rebuilds the recorded ones
(:func:`recorded_model_factory`, :func:`recorded_selector`), so a newer default does not change a
person's model; what cannot be rebuilt exactly raises :class:`SessionSettingsError` naming it. Given
ones that differ from the record raise it too, unless the session is opened with ``migrate=True``.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchpref.models.preference_gp import PreferenceGP, default_covar_module
from torchpref.selection.strategies import Selector
from torchpref.sessions.errors import (
    SessionSettingsError,
)
from torchpref.sessions.records import SessionHeader

__all__ = [
    "describe_model",
    "describe_selector",
    "legacy_model_description",
    "legacy_selector_description",
    "recorded_model_factory",
    "recorded_selector",
    "resume_settings",
    "same_description",
]

MIGRATE = (
    "To resume under other settings anyway (the answers are replayed under them; the posterior and "
    "the next queries will differ from the recorded session's), open it with migrate=True."
)


ModelFactory = Callable[[Tensor], PreferenceGP]
"""Builds a session's model from its anchor item (``1 x d``)."""


def _tree(module: torch.nn.Module) -> str:
    """A module's class and its children's, priors left out (no prior enters a session's posterior)."""
    kids = [f"{name}={_tree(child)}" for name, child in module.named_children() if "prior" not in name]
    return type(module).__name__ + (f"({', '.join(kids)})" if kids else "")


def _number(x: float) -> float | str:
    return x if math.isfinite(x) else repr(x)  # JSON has no inf or nan: "inf", "-inf", "nan"


#: Tensors of more elements than this (a population prior's items and factors) are recorded by
#: their SHA-256, not their values: the header stays small, and a resumed file still checks them.
RECORDED_VALUES_MAX = 4096


def _encode_tensor(t: torch.Tensor) -> dict:
    head = {"dtype": str(t.dtype).replace("torch.", ""), "shape": list(t.shape)}
    if t.numel() > RECORDED_VALUES_MAX:
        data = t.detach().to("cpu", torch.float64).contiguous().numpy().tobytes()
        return {**head, "sha256": hashlib.sha256(data).hexdigest()}
    return {**head, "values": [_number(float(v)) for v in t.flatten().tolist()]}


def _decode_tensor(spec: dict) -> torch.Tensor:
    values = [float(v) for v in spec["values"]]
    return torch.tensor(values, dtype=getattr(torch, spec["dtype"])).reshape(spec["shape"])


def describe_model(model: PreferenceGP) -> dict[str, Any]:
    """The model's class, structure, settings and hyperparameter values, as JSON values."""
    dtype = getattr(model, "_laplace_dtype", None)
    tf = getattr(model, "input_transform", None)
    return {
        "class": f"{type(model).__module__}.{type(model).__qualname__}",
        "kernel": _tree(model.covar_module),
        "likelihood": _tree(model.likelihood),
        "input_transform": None if tf is None else _tree(tf),
        "settings": {
            "rating_eps": float(model.rating_eps),
            "max_newton_iter": int(model.max_newton_iter),
            "ties_offered": bool(model.ties_offered),
            "rating_levels": model.rating_levels,
            "laplace_dtype": None if dtype is None else str(dtype).replace("torch.", ""),
        },
        "state": {k: _encode_tensor(v) for k, v in model.state_dict().items() if "prior" not in k},
    } | ({} if model.mean_module is None else {"mean": _tree(model.mean_module)})


def _jsonable(value) -> bool:
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError):
        return False
    return True


def describe_selector(selector: object) -> dict[str, Any]:
    """The selector's class and options (its public attributes; those JSON cannot hold are named
    in ``"unrecorded"``: such a selector is not rebuilt from the file)."""
    options, unrecorded = {}, []
    for key, value in sorted(vars(selector).items()):
        if key.startswith("_"):
            continue
        value = list(value) if isinstance(value, tuple) else value
        if _jsonable(value):
            options[key] = value
        else:
            unrecorded.append(key)
    out = {"class": f"{type(selector).__module__}.{type(selector).__qualname__}", "options": options}
    if unrecorded:
        out["unrecorded"] = unrecorded
    return out


def same_description(a: dict, b: dict) -> bool:
    """Whether two descriptions are equal (as canonical JSON)."""
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def _differences(recorded: dict, mine: dict, prefix: str = "") -> list[str]:
    out = []
    for key in sorted(set(recorded) | set(mine)):
        a, b = recorded.get(key, "(absent)"), mine.get(key, "(absent)")
        if isinstance(a, dict) and isinstance(b, dict) and "values" not in a:
            out += _differences(a, b, f"{prefix}{key}.")
        elif json.dumps(a, sort_keys=True) != json.dumps(b, sort_keys=True):
            show = lambda v: v["values"] if isinstance(v, dict) and "values" in v else v  # noqa: E731
            out.append(f"{prefix}{key}: recorded {json.dumps(show(a))[:80]}, here {json.dumps(show(b))[:80]}")
    return out


def settings_error(path: object, setting: str, recorded: dict, mine: dict, why: str) -> SessionSettingsError:
    """The error for a resumed file whose recorded ``setting`` this session does not reproduce."""
    diff = "; ".join(_differences(recorded, mine)[:4]) or "(not comparable)"
    return SessionSettingsError(
        f"session file {path} records a {setting} this session does not reproduce ({why}): {diff}. "
        f"Resume it with the recorded {setting} (pass none: it is rebuilt from the file), or pass "
        f"{'model_factory' if setting == 'model' else 'selector'}= one that builds it. {MIGRATE}",
        setting,
        json.dumps(recorded, sort_keys=True)[:200],
        json.dumps(mine, sort_keys=True)[:200],
    )


def recorded_model_factory(desc: dict, dim: int) -> Callable[[Tensor], PreferenceGP] | None:
    """A ``train_X -> PreferenceGP`` that builds the recorded model: this version's
    :class:`~torchpref.PreferenceGP` with the default kernel's structure, the recorded settings
    and every recorded value loaded; ``None`` if this version cannot build it exactly."""
    if desc.get("class") != f"{PreferenceGP.__module__}.{PreferenceGP.__qualname__}" or desc.get("input_transform"):
        return None
    s = desc.get("settings", {})
    dtype = s.get("laplace_dtype")

    def factory(train_X: torch.Tensor) -> PreferenceGP:
        kernel = default_covar_module(dim).to(train_X)
        model = PreferenceGP(
            train_X,
            covar_module=kernel,
            rating_eps=s["rating_eps"],
            max_newton_iter=s["max_newton_iter"],
            ties_offered=s["ties_offered"],
            rating_levels=s["rating_levels"],
            laplace_dtype=None if dtype is None else getattr(torch, dtype),
        )
        state = model.state_dict()
        for key, spec in desc["state"].items():
            state[key] = _decode_tensor(spec)
        model.load_state_dict(state)
        return model

    try:
        model = factory(torch.zeros(1, dim, dtype=torch.float64))
    except (KeyError, RuntimeError, TypeError, ValueError, AttributeError):
        return None
    return factory if same_description(describe_model(model), desc) else None


def recorded_selector(desc: dict) -> Selector | None:
    """The recorded selector, built again from its class and options; ``None`` if this version
    cannot (a class outside torchpref or gone, options it no longer takes or records otherwise)."""
    path = desc.get("class", "")
    if not path.startswith("torchpref.") or desc.get("unrecorded"):
        return None
    module, _, name = path.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name)
        params = inspect.signature(cls).parameters
        if not set(desc["options"]) <= set(params):
            return None
        selector = cls(**desc["options"])
    except (ImportError, AttributeError, TypeError, ValueError):
        return None
    return selector if same_description(describe_selector(selector), desc) else None


# torchpref 0.1.0's session defaults, frozen: what a file without "model" / "selector" was written with.
_LEGACY_STATE = {
    "covar_module.raw_outputscale": 0.5413248546129181,
    "covar_module.base_kernel.raw_lengthscale": -1.5083235746906931,  # 1 x d, every entry
    "covar_module.base_kernel.raw_lengthscale_constraint.lower_bound": 9.999999747378752e-05,
    "covar_module.base_kernel.raw_lengthscale_constraint.upper_bound": math.inf,
    "covar_module.raw_outputscale_constraint.lower_bound": 0.0,
    "covar_module.raw_outputscale_constraint.upper_bound": math.inf,
    "likelihood.comparison.raw_comparison_noise": 0.5413248546129181,
    "likelihood.comparison.raw_comparison_noise_constraint.lower_bound": 0.0,
    "likelihood.comparison.raw_comparison_noise_constraint.upper_bound": math.inf,
    "likelihood.rating.raw_rating_scale": 0.5413248546129181,
    "likelihood.rating.raw_rating_precision": -9.433528937901379,
    "likelihood.rating.raw_rating_scale_constraint.lower_bound": 0.0,
    "likelihood.rating.raw_rating_scale_constraint.upper_bound": math.inf,
    "likelihood.rating.raw_rating_precision_constraint.lower_bound": 0.009999999776482582,
    "likelihood.rating.raw_rating_precision_constraint.upper_bound": 1000000.0,
    "likelihood.tie.raw_tie_threshold": -2.2521684610440906,
    "likelihood.tie.comparison.raw_comparison_noise": 0.5413248546129181,
    "likelihood.tie.comparison.raw_comparison_noise_constraint.lower_bound": 0.0,
    "likelihood.tie.comparison.raw_comparison_noise_constraint.upper_bound": math.inf,
    "likelihood.tie.raw_tie_threshold_constraint.lower_bound": 0.0,
    "likelihood.tie.raw_tie_threshold_constraint.upper_bound": math.inf,
    "likelihood.strict.tie.raw_tie_threshold": -2.2521684610440906,
    "likelihood.strict.tie.comparison.raw_comparison_noise": 0.5413248546129181,
    "likelihood.strict.tie.comparison.raw_comparison_noise_constraint.lower_bound": 0.0,
    "likelihood.strict.tie.comparison.raw_comparison_noise_constraint.upper_bound": math.inf,
    "likelihood.strict.tie.raw_tie_threshold_constraint.lower_bound": 0.0,
    "likelihood.strict.tie.raw_tie_threshold_constraint.upper_bound": math.inf,
}
_SP = "(_transform=Softplus)"
_LEGACY_KERNEL = (
    f"ScaleKernel(base_kernel=RBFKernel(raw_lengthscale_constraint=GreaterThan{_SP}), "
    f"raw_outputscale_constraint=Positive{_SP})"
)
_PROBIT = f"PairwiseProbitLikelihood(raw_comparison_noise_constraint=Positive{_SP})"
_TIE = f"TieLikelihood(comparison={_PROBIT}, raw_tie_threshold_constraint=Positive{_SP})"
_LEGACY_LIKELIHOOD = (
    f"PreferenceLikelihood(comparison={_PROBIT}, rating=BetaRatingLikelihood(raw_rating_scale_constraint="
    f"Positive{_SP}, raw_rating_precision_constraint=Interval), tie={_TIE}, "
    f"strict=StrictPreferenceLikelihood(tie={_TIE}))"
)


def legacy_model_description(dim: int) -> dict[str, Any]:
    """torchpref 0.1.0's default session model for ``dim``-dimensional items (RBF lengthscale 0.2,
    outputscale 1, sigma_R = 1, sigma_B = 1, nu = 80, tau = 0.1, ties offered), described."""
    state = {}
    for key, value in _LEGACY_STATE.items():
        shape = [1, dim] if key.endswith("raw_lengthscale") else []
        count = dim if shape else 1
        state[key] = {"dtype": "float64", "shape": shape, "values": [_number(value)] * count}
    return {
        "class": "torchpref.models.preference_gp.PreferenceGP",
        "kernel": _LEGACY_KERNEL,
        "likelihood": _LEGACY_LIKELIHOOD,
        "input_transform": None,
        "settings": {
            "rating_eps": 0.001,
            "max_newton_iter": 100,
            "ties_offered": True,
            "rating_levels": None,
            "laplace_dtype": None,
        },
        "state": state,
    }


def legacy_selector_description(num_pool_items: int | None) -> dict[str, Any]:
    """torchpref 0.1.0's default session selector: ``UCBC(m=default_ranking_size(N))`` (5 for a box)."""
    m = max(2, min(5, num_pool_items - 1)) if num_pool_items else 5
    return {
        "class": "torchpref.selection.strategies.UCBC",
        "options": {"gamma": 3.0, "m": m, "temperatures": [5.0, 25.0]},
    }


def resume_settings(
    header: SessionHeader,
    *,
    path: Path | None,
    dim: int,
    num_pool_items: int | None,
    current: tuple[Selector, ModelFactory],
    given: tuple[Selector | None, ModelFactory | None],
    new_model: Callable[[], PreferenceGP],
    migrate: bool,
) -> tuple[Selector, ModelFactory]:
    """``(selector, model_factory)`` for a session resuming the file ``path`` with ``header``: the
    recorded ones (or the file's release's defaults where it records none) when none are ``given``,
    else those given, checked to be the same. ``current`` are the session's before the file was
    read, ``new_model()`` builds the session's model of no answers (to compare with the record).

    Raises:
        SessionSettingsError: they differ, or this version cannot build the recorded ones
            (unless ``migrate``: then the given ones, or this version's defaults).
    """
    (chosen_selector, factory), (selector, model_factory) = current, given
    rec_sel = header.selector or legacy_selector_description(num_pool_items)
    rec_model = header.model or legacy_model_description(dim)
    if selector is None:
        rebuilt = recorded_selector(rec_sel)
        if rebuilt is not None:
            chosen_selector = rebuilt
        elif not migrate:
            mine = describe_selector(chosen_selector)
            raise settings_error(path, "selector", rec_sel, mine, "this version cannot build it")
    elif not same_description(describe_selector(selector), rec_sel) and not migrate:
        raise settings_error(path, "selector", rec_sel, describe_selector(selector), "another selector was given")
    mine = describe_model(new_model())
    if same_description(mine, rec_model):
        return chosen_selector, factory
    if model_factory is None:
        rebuilt_factory = recorded_model_factory(rec_model, dim)
        if rebuilt_factory is not None:
            return chosen_selector, rebuilt_factory
    if not migrate:
        why = "another model was given" if model_factory is not None else "this version cannot build it"
        raise settings_error(path, "model", rec_model, mine, why)
    return chosen_selector, factory
