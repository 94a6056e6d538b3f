r"""Saving a :class:`~torchpref.population.model.Population`, loadable with ``torch.load``'s safe
``weights_only=True``, validated as model checkpoints are (:mod:`torchpref.models.checkpoint`).

A population file is a plain dictionary: ``format``, ``version``, ``tensors`` (``U``, ``alpha``,
``L_U``, ``S_chol``), the kernels' ``state_dict`` (``k_m``, ``k_g``), ``settings`` (the
likelihoods'), ``space`` (``dim``, and the feature ``names`` if the population was given them),
``stats``, and ``digest``: a SHA-256 of everything else. The whole file is checked (format,
version, digest, every tensor's kind, shape and finiteness, the factors' positive diagonals,
settings' types, the kernels' keys and shapes) before any module is built from it: a damaged
file raises :class:`~torchpref.models.checkpoint.CheckpointError` naming the file and the fault.
A population from another objective space (another ``d``, or other feature names) is refused by
name (:func:`load_population`'s ``dim`` / ``names``, and :meth:`Population.person_model`).
"""

from __future__ import annotations

import hashlib
import io
import os
from typing import Any

import torch
from gpytorch.kernels import Kernel

from torchpref.models.checkpoint import CheckpointError, _read, save_atomically
from torchpref.models.defaults import default_covar_module
from torchpref.population.model import Population

FORMAT = "torchpref.Population"
VERSION = 1
SETTINGS: dict[str, type | tuple[type, ...]] = {
    "comparison_noise": float,
    "rating_scale": float,
    "rating_precision": float,
    "rating_levels": (int, type(None)),
}


def _digest(ck: dict[str, Any]) -> str:
    body = {k: v for k, v in ck.items() if k != "digest"}
    buf = io.BytesIO()
    torch.save(body, buf)
    return hashlib.sha256(buf.getvalue()).hexdigest()


def population_checkpoint(pop: Population) -> dict[str, Any]:
    """The population as a dictionary of tensors and plain values (module docstring)."""
    ck: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "tensors": {"U": pop.U, "alpha": pop.alpha, "L_U": pop.L_U, "S_chol": pop.S_chol},
        "k_m": pop.k_m.state_dict(),
        "k_g": pop.k_g.state_dict(),
        "settings": dict(pop.settings),
        "space": {"dim": pop.dim, "names": None if pop.names is None else list(pop.names)},
        "stats": {k: v for k, v in pop.stats.items() if isinstance(v, (int, float, str))},
    }
    ck["digest"] = _digest(ck)
    return ck


def save_population(pop: Population, path: str | os.PathLike) -> None:
    """Write :func:`population_checkpoint` to ``path`` atomically, as :func:`~torchpref.save_model`
    writes a model (a temporary file, flushed, renamed; a symbolic link written through)."""
    save_atomically(lambda: population_checkpoint(pop), path, "save_population")


def _check_tensors(t: Any, where: str) -> None:
    if not isinstance(t, dict) or set(t) != {"U", "alpha", "L_U", "S_chol"}:
        raise CheckpointError(f"{where}: tensors must be U, alpha, L_U and S_chol.")
    for name, v in t.items():
        if not isinstance(v, torch.Tensor) or not v.is_floating_point() or v.layout != torch.strided:
            raise CheckpointError(f"{where}: {name} must be a dense real tensor, got {type(v).__name__}.")
        if not bool(torch.isfinite(v).all()):
            raise CheckpointError(f"{where}: {name} is not finite.")
    U = t["U"]
    if U.dim() != 2 or U.shape[0] < 1:
        raise CheckpointError(f"{where}: U must be N x d with N >= 1, got shape {tuple(U.shape)}.")
    N = U.shape[0]
    if tuple(t["alpha"].shape) != (N,):
        raise CheckpointError(f"{where}: alpha must have shape ({N},), got {tuple(t['alpha'].shape)}.")
    for name in ("L_U", "S_chol"):
        L = t[name]
        if tuple(L.shape) != (N, N):
            raise CheckpointError(f"{where}: {name} must be {N} x {N}, got {tuple(L.shape)}.")
        if not bool((torch.diagonal(L) > 0).all()) or bool(torch.triu(L, 1).abs().max() > 0):
            raise CheckpointError(f"{where}: {name} is not a Cholesky factor (lower, positive diagonal).")


def _check(ck: Any, where: str) -> None:
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise CheckpointError(f"{where} is not a {FORMAT} file.")
    if ck.get("version") != VERSION:
        raise CheckpointError(f"{where}: population version {ck.get('version')!r} is not supported ({VERSION}).")
    if not isinstance(ck.get("digest"), str) or ck["digest"] != _digest(ck):
        raise CheckpointError(f"{where}: the contents do not match their digest (a damaged file); not loaded.")
    _check_tensors(ck.get("tensors"), where)
    settings = ck.get("settings")
    if not isinstance(settings, dict) or set(settings) != set(SETTINGS):
        raise CheckpointError(f"{where}: settings must be {sorted(SETTINGS)}.")
    for name, kind in SETTINGS.items():
        if isinstance(settings[name], bool) or not isinstance(settings[name], kind):
            raise CheckpointError(f"{where}: setting {name!r} is {settings[name]!r}.")
    space = ck.get("space")
    d = ck["tensors"]["U"].shape[-1]
    if not isinstance(space, dict) or space.get("dim") != d:
        raise CheckpointError(f"{where}: the space's dim does not match U's {d} features.")
    names = space.get("names")
    if names is not None and (
        not isinstance(names, list) or len(names) != d or not all(isinstance(n, str) for n in names)
    ):
        raise CheckpointError(f"{where}: the space's names must be {d} strings.")
    for key in ("k_m", "k_g"):
        if not isinstance(ck.get(key), dict) or not all(isinstance(v, torch.Tensor) for v in ck[key].values()):
            raise CheckpointError(f"{where}: {key} must be a kernel's state_dict.")


def _kernel(state: dict, given: Kernel | None, d: int, name: str, where: str) -> Kernel:
    k = (given if given is not None else default_covar_module(d)).double()
    own = k.state_dict()
    if set(own) != set(state) or any(own[n].shape != state[n].shape for n in own):
        raise CheckpointError(f"{where}: the saved {name} does not fit the kernel given (keys or shapes differ).")
    k.load_state_dict(state, strict=True)
    return k


def load_population(
    source: str | os.PathLike,
    *,
    dim: int | None = None,
    names: list[str] | tuple[str, ...] | None = None,
    k_m: Kernel | None = None,
    k_g: Kernel | None = None,
) -> Population:
    """The population saved by :func:`save_population`, checked whole before anything is built.

    Args:
        dim, names: the objective space of the items it will be used on: refused when the file
            was fitted on another (another number of features, or other feature names).
        k_m, k_g: kernels of the saved ones' structure (default: the default kernel).

    Raises:
        CheckpointError: (a ``ValueError``) a damaged or foreign file, naming the fault, or a
            population of another objective space, naming both.
    """
    where = str(source)
    ck = _read(source, "cpu")
    _check(ck, where)
    d = int(ck["tensors"]["U"].shape[-1])
    saved_names = ck["space"]["names"]
    if dim is not None and int(dim) != d:
        raise CheckpointError(f"{where}: this population's objective space has d = {d} features, the items {dim}.")
    if names is not None and saved_names is not None and list(names) != list(saved_names):
        raise CheckpointError(
            f"{where}: this population was fitted on the objective space {saved_names}, not {list(names)}."
        )
    km = _kernel(ck["k_m"], k_m, d, "k_m", where)
    kg = _kernel(ck["k_g"], k_g, d, "k_g", where)
    t = ck["tensors"]
    names_t = None if saved_names is None else tuple(saved_names)
    return Population(km, kg, t["U"], t["alpha"], t["L_U"], t["S_chol"], ck["settings"], ck["stats"], names_t)
