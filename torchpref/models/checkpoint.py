r"""Saving a :class:`~torchpref.PreferenceGP` with its data, loadable with ``torch.load``'s safe
``weights_only=True``.

A model's ``state_dict`` holds its hyperparameters only (as in GPyTorch); the person's answers
are the data. A checkpoint is a plain dictionary of tensors, numbers and strings:

* ``"data"``: ``train_X``, ``comparisons``, ``ratings``, ``rating_index``, ``ties``;
* ``"state_dict"``: the model's ``state_dict`` (kernel, likelihoods, input transform);
* ``"settings"``: ``rating_eps``, ``max_newton_iter``, ``learn_likelihood``, ``rating_levels``,
  ``ties_offered``, ``laplace_dtype`` (``None`` or a ``torch.dtype``).

The loaded model solves its mode afresh: its posterior is the saved one's to the Newton
tolerance (``1e-11`` in log-posterior units in float64, about ``1e-6`` in the posterior mean).

The kernel and input transform are modules, not data: a model with a kernel other than the
default is loaded by passing one of the same structure (``load_model(path, covar_module=...)``).

A file that cannot be a checkpoint (truncated by a crash, damaged, another kind of file, a pickle
holding code) or one whose contents are not a checkpoint's raises :class:`CheckpointError`, a
``ValueError`` naming the file and what is wrong; nothing is half-loaded.
"""

from __future__ import annotations

import os
import pickle
import tempfile
from pathlib import Path
from typing import Any

import torch
from botorch.models.transforms.input import InputTransform
from gpytorch.kernels import Kernel

from torchpref.data.preference_data import DEFAULT_RATING_EPS, PreferenceData
from torchpref.models.preference_gp import PreferenceGP

FORMAT = "torchpref.PreferenceGP"
VERSION = 1
DATA_KEYS = ("train_X", "comparisons", "ratings", "rating_index", "ties")
SETTINGS_KEYS = ("rating_eps", "max_newton_iter", "learn_likelihood", "rating_levels", "ties_offered", "laplace_dtype")


class CheckpointError(ValueError):
    """A file or dictionary that is not a usable torchpref model checkpoint."""


def model_checkpoint(model: PreferenceGP) -> dict[str, Any]:
    """The model's data, hyperparameters and settings as a dictionary of tensors and plain
    values (see the module docstring)."""
    if model.batch_shape:
        raise ValueError(
            f"save_model saves a model of one problem; this one has batch_shape {tuple(model.batch_shape)}."
        )
    d = model.data
    learn = bool(model.likelihood.comparison.raw_comparison_noise.requires_grad)
    return {
        "format": FORMAT,
        "version": VERSION,
        "data": {
            "train_X": d.train_X,
            "comparisons": d.comparisons,
            "ratings": d.ratings,
            "rating_index": d.rating_index,
            "ties": d.ties,
        },
        "state_dict": model.state_dict(),
        "settings": {
            "rating_eps": float(model.rating_eps),
            "max_newton_iter": int(model.max_newton_iter),
            "learn_likelihood": learn,
            "rating_levels": model.rating_levels,
            "ties_offered": bool(model.ties_offered),
            "laplace_dtype": model._laplace_dtype,
        },
    }


def save_model(model: PreferenceGP, path: str | os.PathLike) -> None:
    """Write :func:`model_checkpoint` to ``path`` atomically: a failed save leaves any old file
    at ``path`` as it was."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a directory; give save_model a file name.")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot save to {path}: the folder {path.parent} does not exist.")
    ck = model_checkpoint(model)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(ck, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_model(
    source: str | os.PathLike | dict[str, Any],
    covar_module: Kernel | None = None,
    input_transform: InputTransform | None = None,
    map_location: str | torch.device | None = None,
) -> PreferenceGP:
    """The model saved by :func:`save_model` (a path, read with ``weights_only=True``) or given as
    a :func:`model_checkpoint` dictionary.

    Args:
        source: the file, or the checkpoint itself.
        covar_module: a kernel of the saved one's structure (default: the default kernel).
        input_transform: an input transform of the saved one's structure, if it had one.
        map_location: passed to ``torch.load``.

    Raises:
        CheckpointError: (a ``ValueError``) if ``source`` is not a readable torchpref model
            checkpoint (truncated, damaged, another kind of file, entries missing or of the
            wrong kind, non-finite hyperparameters), or its hyperparameters do not fit the
            kernel / input transform given (naming the keys). ``ValueError``: data that fail
            validation, as for :class:`~torchpref.models.preference_gp.PreferenceGP`.
        FileNotFoundError, IsADirectoryError, PermissionError: as ``open`` raises them.
    """
    where = "the dictionary" if isinstance(source, dict) else str(source)
    ck = source if isinstance(source, dict) else _read(source, map_location)
    _check_contents(ck, where)
    settings = ck["settings"]
    if ck["data"]["train_X"].shape[-1] == 0:  # a prior-only PreferenceGP(None, None): no items, d unknown
        model = PreferenceGP(None, None, covar_module=covar_module, input_transform=input_transform, **settings)
        model.to(ck["data"]["train_X"].dtype)
    else:
        data = PreferenceData.create(
            **ck["data"],
            rating_eps=settings.get("rating_eps", DEFAULT_RATING_EPS),
            rating_levels=settings.get("rating_levels"),
        )
        model = PreferenceGP(
            data.train_X,
            data.comparisons,
            data.ratings,
            data.rating_index,
            ties=data.ties,
            covar_module=covar_module,
            input_transform=input_transform,
            **settings,
        )
    missing, unexpected = _key_mismatch(model, ck["state_dict"])
    if missing or unexpected:
        raise CheckpointError(
            f"the saved hyperparameters do not fit this kernel / input transform: missing {missing}, "
            f"unexpected {unexpected}; pass covar_module / input_transform like the saved ones."
        )
    try:
        model.load_state_dict(ck["state_dict"], strict=True)
    except RuntimeError as err:  # a shape that does not fit
        raise CheckpointError(
            f"{where}: the saved hyperparameters do not fit this kernel / input transform: {' '.join(str(err).split())}"
        ) from err
    return model


def _read(path: str | os.PathLike, map_location) -> Any:
    """``torch.load(path, weights_only=True)``, its many failure types for a file that is no
    checkpoint turned into one :class:`CheckpointError`."""
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except (FileNotFoundError, IsADirectoryError, PermissionError):
        raise
    except pickle.UnpicklingError as err:
        raise CheckpointError(
            f"{path} is not a {FORMAT} checkpoint: it holds something other than tensors and "
            "plain values, or is not a file written by torch.save; not loaded."
        ) from err
    except Exception as err:
        raise CheckpointError(
            f"{path} is not a readable {FORMAT} checkpoint (truncated, damaged or another kind "
            f"of file): {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
        ) from err


def _check_contents(ck: Any, where: str) -> None:
    """The checkpoint's entries are there and of the right kinds, its hyperparameters finite."""
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise CheckpointError(f"{where} is not a {FORMAT} checkpoint.")
    if ck.get("version") != VERSION:
        raise CheckpointError(
            f"checkpoint version {ck.get('version')!r} is not supported (this torchpref reads {VERSION})."
        )
    for key, allowed in (("data", DATA_KEYS), ("settings", SETTINGS_KEYS), ("state_dict", None)):
        entry = ck.get(key)
        if not isinstance(entry, dict):
            raise CheckpointError(f"{where}: the checkpoint's {key!r} is missing or not a dictionary.")
        unknown = sorted(map(str, set(entry) - set(allowed))) if allowed is not None else []
        if unknown:
            raise CheckpointError(f"{where}: unknown {key} entries {unknown}; expected some of {list(allowed)}.")
    if not isinstance(ck["data"].get("train_X"), torch.Tensor):
        raise CheckpointError(f"{where}: the checkpoint's data has no train_X tensor.")
    for name, value in ck["data"].items():
        if value is not None and not isinstance(value, torch.Tensor):
            raise CheckpointError(f"{where}: data {name!r} must be a tensor or None, got {type(value).__name__}.")
    for name, value in ck["state_dict"].items():
        if not isinstance(value, torch.Tensor):
            raise CheckpointError(f"{where}: hyperparameter {name!r} must be a tensor, got {type(value).__name__}.")
        bad = value.isnan() if "constraint" in name else ~value.isfinite()  # a bound may be infinite
        if value.is_floating_point() and bad.any():
            raise CheckpointError(f"{where}: hyperparameter {name!r} is not finite: {value.tolist()}.")


def _key_mismatch(model: PreferenceGP, state_dict: dict[str, Any]) -> tuple[list[str], list[str]]:
    keys = set(model.state_dict())
    return sorted(keys - set(state_dict)), sorted(set(state_dict) - keys)
