r"""A population file checked before anything is built from it (:func:`torchpref.load_population`).

In this order, each refusal a :class:`~torchpref.models.checkpoint.CheckpointError` (a
``ValueError``) naming the file and what it is:

1. the path: a missing file is a ``FileNotFoundError`` naming it; a directory, a FIFO or any
   other file that is not a regular one is refused without reading it (opened non-blocking);
2. the archive, before ``torch.load`` reads it: a file that is not a zip archive is not a
   population file; one whose directory cannot be read is a damaged population file; every
   record must be stored uncompressed and no larger than the file (so nothing ``torch.load``
   allocates can exceed the file's size, as a compressed record could);
3. the contents, before any tensor is computed with: the entries' kinds; every tensor dense, real
   and within its own storage (:func:`torchpref.models.checkpoint._check_tensor`, the check
   :func:`~torchpref.load_model` makes: no expanded view that grows when copied), all tensors
   together no larger than the file, and their shapes; then the digest, finiteness, the factors'
   structure, the settings (finite and positive), the space, and the kernels' hyperparameters
   (finite; once loaded, within their constraints with finite prior densities:
   :func:`torchpref.models.checkpoint._check_loaded_values`).
"""

from __future__ import annotations

import io
import math
import os
from typing import IO, Any, cast

import torch
from gpytorch.kernels import Kernel

from torchpref.models.checkpoint import FORMAT as MODEL_FORMAT
from torchpref.models.checkpoint import CheckpointError, _check_loaded_values, _check_tensor
from torchpref.models.checkpoint import check_archive as archive_check
from torchpref.models.checkpoint import open_regular as archive_open

FORMAT = "torchpref.Population"
VERSIONS = (1, 2)
TENSORS = {1: ("U", "alpha", "L_U", "S_chol"), 2: ("U", "alpha", "L_U", "S_chol", "A")}
SETTINGS: dict[str, type | tuple[type, ...]] = {
    "comparison_noise": float,
    "rating_scale": float,
    "rating_precision": float,
    "rating_levels": (int, type(None)),
}
MORE_SETTINGS: dict[str, type | tuple[type, ...]] = {
    "lengthscale": float,
    "outputscale": float,
    "rating_eps": float,
    "tie_threshold": float,
    "ties_offered": bool,
}
"""Settings a population file records since the person model's recipe (absent from older files)."""


def open_regular(path: str | os.PathLike) -> tuple[IO[bytes], int]:
    """``path`` opened for reading, with its size, if it is a regular file
    (:func:`torchpref.models.checkpoint.open_regular`, in a population file's words)."""
    return archive_open(path, "population file", "save_population")


def check_archive(fh: IO[bytes], size: int, where: str) -> None:
    """The file is a zip archive (``torch.save``'s) whose records are stored, none larger than the
    file (:func:`torchpref.models.checkpoint.check_archive`, in a population file's words)."""
    archive_check(fh, size, where, "population file", "save_population")


def read(fh: IO[bytes], where: str) -> Any:
    """``torch.load(weights_only=True)`` of the archive, its failures named as a damaged population file's."""
    try:
        return torch.load(cast(io.BufferedReader, fh), map_location="cpu", weights_only=True)
    except Exception as err:  # torch.load raises many kinds for a damaged archive
        first = str(err).splitlines()[0] if str(err) else ""
        raise CheckpointError(
            f"{where} is a damaged population file (or holds something other than tensors and plain values): "
            f"{type(err).__name__}: {first}; not loaded."
        ) from err


def check_kind(ck: object, where: str) -> int:
    """The file's format and version (returned)."""
    if isinstance(ck, dict) and ck.get("format") == MODEL_FORMAT:
        raise CheckpointError(
            f"{where} is a torchpref.PreferenceGP checkpoint, not a population file: load it with load_model."
        )
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise CheckpointError(f"{where} is not a {FORMAT} file.")
    version = ck.get("version")
    if type(version) is not int or version not in VERSIONS:
        raise CheckpointError(
            f"{where}: population file version {version!r} is not supported (this torchpref reads {VERSIONS})."
        )
    return version


def check_tensor_shapes(t: object, version: int, where: str, size: int) -> None:
    """The tensors' kinds, storage and shapes, before any is computed with."""
    names = TENSORS[version]
    if not isinstance(t, dict) or set(t) != set(names):
        raise CheckpointError(f"{where}: tensors must be {', '.join(names)} (version {version}).")
    for name, v in t.items():
        if not isinstance(v, torch.Tensor) or not v.is_floating_point():
            raise CheckpointError(f"{where}: {name} must be a real floating tensor, got {type(v).__name__}.")
        _check_tensor(name, v, where)
    total = sum(v.numel() * v.element_size() for v in t.values())
    if total > size:
        raise CheckpointError(f"{where}: its tensors take {total} bytes, more than the file's {size}; not loaded.")
    U = t["U"]
    if U.dim() != 2 or U.shape[0] < 1 or U.shape[1] < 1:
        raise CheckpointError(f"{where}: U must be M x d with M, d >= 1, got shape {tuple(U.shape)}.")
    M = U.shape[0]
    if tuple(t["alpha"].shape) != (M,):
        raise CheckpointError(f"{where}: alpha must have shape ({M},), got {tuple(t['alpha'].shape)}.")
    for name in names[2:]:
        if tuple(t[name].shape) != (M, M):
            raise CheckpointError(f"{where}: {name} must be {M} x {M}, got {tuple(t[name].shape)}.")


def check_tensor_values(t: dict[str, torch.Tensor], where: str) -> None:
    """Finite tensors, Cholesky factors lower with a positive diagonal, ``A`` symmetric."""
    for name, v in t.items():
        if not bool(torch.isfinite(v).all()):
            raise CheckpointError(f"{where}: {name} is not finite.")
    for name in ("L_U", "S_chol"):
        L = t[name]
        if not bool((torch.diagonal(L) > 0).all()) or bool(torch.triu(L, 1).abs().max() > 0):
            raise CheckpointError(f"{where}: {name} is not a Cholesky factor (lower, positive diagonal).")
    if "A" in t and not torch.allclose(t["A"], t["A"].mT, rtol=0, atol=1e-9):
        raise CheckpointError(f"{where}: A is not symmetric.")


def check_settings(settings: object, where: str) -> None:
    """The person model's settings: the known keys (those of :data:`SETTINGS`, and any of
    :data:`MORE_SETTINGS`), finite positive numbers, levels ``None`` or ``>= 2``, a boolean
    ``ties_offered``; then :class:`~torchpref.models.recipe.ModelSettings` must take them."""
    from torchpref.models.recipe import ModelSettings

    known = {**SETTINGS, **MORE_SETTINGS}
    if not isinstance(settings, dict) or not set(SETTINGS) <= set(settings) <= set(known):
        raise CheckpointError(f"{where}: settings must be {sorted(SETTINGS)} and any of {sorted(MORE_SETTINGS)}.")
    for name, value in settings.items():
        kind = known[name]
        ok = isinstance(value, bool) if kind is bool else not isinstance(value, bool) and isinstance(value, kind)
        if ok and isinstance(value, float):
            ok = math.isfinite(value) and value > 0
        if ok and name == "rating_levels" and value is not None:
            ok = value >= 2
        if not ok:
            raise CheckpointError(f"{where}: setting {name!r} is {value!r}, not a finite positive value of its kind.")
    try:
        ModelSettings.from_json(settings)
    except ValueError as err:
        raise CheckpointError(f"{where}: {err}") from None


def check_space_and_stats(ck: dict[str, Any], d: int, where: str) -> None:
    """Check a population file's recorded space (its dimension ``d`` and feature names) and its
    statistics before anything is built from it; ``CheckpointError`` naming ``where`` otherwise."""
    space = ck.get("space")
    if not isinstance(space, dict) or space.get("dim") != d:
        raise CheckpointError(f"{where}: the space's dim does not match U's {d} features.")
    names = space.get("names")
    if names is not None and (
        not isinstance(names, list) or len(names) != d or not all(isinstance(n, str) for n in names)
    ):
        raise CheckpointError(f"{where}: the space's names must be {d} strings.")
    stats = ck.get("stats")
    if not isinstance(stats, dict) or not all(
        isinstance(k, str) and isinstance(v, (int, float, str)) and not isinstance(v, bool) for k, v in stats.items()
    ):
        raise CheckpointError(f"{where}: stats must map names to numbers or strings.")


def check_kernel_state(state: object, name: str, where: str) -> None:
    """A kernel's ``state_dict``: tensors, dense, real, within their storage, finite (a
    constraint's bound may be infinite, not NaN)."""
    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        raise CheckpointError(f"{where}: {name} must be a kernel's state_dict.")
    for key, value in state.items():
        if not isinstance(value, torch.Tensor):
            raise CheckpointError(f"{where}: {name}.{key} must be a tensor, got {type(value).__name__}.")
        _check_tensor(f"{name}.{key}", value, where)
        bad = value.isnan() if "constraint" in key else ~value.isfinite()
        if value.is_floating_point() and bool(bad.any()):
            raise CheckpointError(f"{where}: hyperparameter {name}.{key} is not finite: {value.tolist()}.")


def load_kernel(state: dict[str, torch.Tensor], k: Kernel, name: str, where: str) -> Kernel:
    """``k`` with the saved hyperparameters: the same keys and shapes, the same constraint bounds,
    and once loaded every hyperparameter within its constraint with a finite prior density."""
    own = k.state_dict()
    if set(own) != set(state) or any(own[n].shape != state[n].shape for n in own):
        raise CheckpointError(f"{where}: the saved {name} does not fit the kernel given (keys or shapes differ).")
    for key, value in state.items():
        bound = key.endswith(("_constraint.lower_bound", "_constraint.upper_bound"))
        if bound and not torch.equal(value.to(own[key]), own[key]):
            raise CheckpointError(
                f"{where}: {name}'s constraint bound {key!r} is {value.tolist()} in the file but {own[key].tolist()} "
                "in the kernel it loads into."
            )
    k.load_state_dict(state, strict=True)
    _check_loaded_values(cast(Any, k), f"{where}: {name}")
    return k
