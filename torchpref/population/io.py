r"""Saving a :class:`~torchpref.population.model.Population`, loadable with ``torch.load``'s safe
``weights_only=True``, checked whole before anything is built from it
(:mod:`torchpref.population.checks`).

A population file is a plain dictionary: ``format``, ``version`` (2; files of version 1 still
load), ``tensors`` (``U``, the ``M`` items the mean is represented at; ``alpha``; ``L_U``;
``S_chol``; and ``A = I - S^{-1}``, what a person model needs, kept so that loading and each new
person cost no ``M^3``), the kernels' ``state_dict`` (``k_m``, ``k_g``), ``settings`` (the
likelihoods'), ``space`` (``dim``, and the feature ``names`` if the population was given them),
``stats`` (including which mean: ``"exact"`` or ``"inducing"``), and ``digest``: a SHA-256 of
everything else. A population from another objective space (another ``d``, or other feature
names) is refused by name (:func:`load_population`'s ``dim`` / ``names``, and
:meth:`Population.person_model`).
"""

from __future__ import annotations

import hashlib
import io
import os
from typing import Any

import torch
from gpytorch.kernels import Kernel

from torchpref.models.checkpoint import CheckpointError, save_atomically
from torchpref.models.defaults import default_covar_module
from torchpref.population import checks
from torchpref.population.model import Population

FORMAT = checks.FORMAT
VERSION = 2


class NotAPopulation(TypeError, ValueError):
    """Something given where a :class:`~torchpref.Population` is expected (a ``TypeError`` and a
    ``ValueError``, so that either ``except`` catches it)."""


def as_population(obj: object) -> Population:
    """``obj`` if it is a :class:`~torchpref.Population`.

    Raises:
        NotAPopulation: naming what was given, and for a path the call that loads it
            (:func:`load_population`).
    """
    if isinstance(obj, Population):
        return obj
    if isinstance(obj, (str, os.PathLike)):
        raise NotAPopulation(
            f"population must be a torchpref.Population, got the path {str(obj)!r}: load the file first, "
            f"population=torchpref.load_population({str(obj)!r})."
        )
    raise NotAPopulation(
        f"population must be a torchpref.Population (torchpref.fit_population or torchpref.load_population "
        f"make one), got {type(obj).__name__}."
    )


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
        "tensors": {"U": pop.U, "alpha": pop.alpha, "L_U": pop.L_U, "S_chol": pop.S_chol, "A": pop.A},
        "k_m": pop.k_m.state_dict(),
        "k_g": pop.k_g.state_dict(),
        "settings": dict(pop.settings),
        "space": {"dim": pop.dim, "names": None if pop.names is None else list(pop.names)},
        "stats": {k: v for k, v in pop.stats.items() if isinstance(v, (int, float, str)) and not isinstance(v, bool)},
    }
    ck["digest"] = _digest(ck)
    return ck


def save_population(pop: Population, path: str | os.PathLike) -> None:
    """Write :func:`population_checkpoint` to ``path`` atomically, as :func:`~torchpref.save_model`
    writes a model (a temporary file, flushed, renamed; a symbolic link written through)."""
    save_atomically(lambda: population_checkpoint(pop), path, "save_population")


def _read_checked(source: str | os.PathLike, where: str) -> dict[str, Any]:
    """The file's dictionary, checked (:mod:`torchpref.population.checks`, in its order)."""
    fh, size = checks.open_regular(source)
    with fh:
        checks.check_archive(fh, size, where)
        ck = checks.read(fh, where)
    version = checks.check_kind(ck, where)
    checks.check_tensor_shapes(ck.get("tensors"), version, where, size)
    for key in ("k_m", "k_g"):
        checks.check_kernel_state(ck.get(key), key, where)
    if not isinstance(ck.get("digest"), str) or ck["digest"] != _digest(ck):
        raise CheckpointError(
            f"{where}: the contents do not match their digest (a damaged population file); not loaded."
        )
    checks.check_tensor_values(ck["tensors"], where)
    checks.check_settings(ck.get("settings"), where)
    checks.check_space_and_stats(ck, int(ck["tensors"]["U"].shape[-1]), where)
    return ck


def load_population(
    source: str | os.PathLike,
    *,
    dim: int | None = None,
    names: list[str] | tuple[str, ...] | None = None,
    k_m: Kernel | None = None,
    k_g: Kernel | None = None,
) -> Population:
    """The population saved by :func:`save_population`, checked whole before anything is built
    (:mod:`torchpref.population.checks`).

    Args:
        dim, names: the objective space of the items it will be used on: refused when the file
            was fitted on another (another number of features, or other feature names).
        k_m, k_g: kernels of the saved ones' structure (default: the default kernel).

    Raises:
        FileNotFoundError: no file at ``source`` (naming it).
        CheckpointError: (a ``ValueError``) a file that is not a regular one (a FIFO), not a
            population file, a damaged one, or one of another objective space, naming the file
            and the fault.
    """
    where = str(source)
    ck = _read_checked(source, where)
    t = ck["tensors"]
    d = int(t["U"].shape[-1])
    saved_names = ck["space"]["names"]
    if dim is not None and int(dim) != d:
        raise CheckpointError(f"{where}: this population's objective space has d = {d} features, the items {dim}.")
    if names is not None and saved_names is not None and list(names) != list(saved_names):
        raise CheckpointError(
            f"{where}: this population was fitted on the objective space {saved_names}, not {list(names)}."
        )
    km = checks.load_kernel(ck["k_m"], (k_m if k_m is not None else default_covar_module(d)).double(), "k_m", where)
    kg = checks.load_kernel(ck["k_g"], (k_g if k_g is not None else default_covar_module(d)).double(), "k_g", where)
    names_t = None if saved_names is None else tuple(saved_names)
    stats = dict(ck["stats"])
    stats.setdefault("mean", "exact")  # version 1 populations were all exact
    return Population(km, kg, t["U"], t["alpha"], t["L_U"], t["S_chol"], ck["settings"], stats, names_t, t.get("A"))
