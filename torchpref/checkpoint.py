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
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import torch
from botorch.models.transforms.input import InputTransform
from gpytorch.kernels import Kernel

from torchpref.data import PreferenceData
from torchpref.models import PreferenceGP

FORMAT = "torchpref.PreferenceGP"
VERSION = 1


def model_checkpoint(model: PreferenceGP) -> dict[str, Any]:
    """The model's data, hyperparameters and settings as a dictionary of tensors and plain
    values (see the module docstring)."""
    if model.batch_shape:
        raise ValueError(f"save_model saves a model of one problem; this one has batch_shape {tuple(model.batch_shape)}.")
    d = model.data
    learn = bool(model.likelihood.comparison.raw_comparison_noise.requires_grad)
    return {
        "format": FORMAT,
        "version": VERSION,
        "data": {"train_X": d.train_X, "comparisons": d.comparisons, "ratings": d.ratings,
                 "rating_index": d.rating_index, "ties": d.ties},
        "state_dict": model.state_dict(),
        "settings": {"rating_eps": float(model.rating_eps), "max_newton_iter": int(model.max_newton_iter),
                     "learn_likelihood": learn, "rating_levels": model.rating_levels,
                     "ties_offered": bool(model.ties_offered), "laplace_dtype": model._laplace_dtype},
    }


def save_model(model: PreferenceGP, path: str | os.PathLike) -> None:
    """Write :func:`model_checkpoint` to ``path`` atomically: a failed save leaves any old file
    at ``path`` as it was."""
    path = Path(path)
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
        ValueError: if ``source`` is not a torchpref model checkpoint, or its hyperparameters do
            not fit the kernel / input transform given (naming the keys).
    """
    if isinstance(source, dict):
        ck = source
    else:
        ck = torch.load(source, map_location=map_location, weights_only=True)
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise ValueError(f"{source if not isinstance(source, dict) else 'the dictionary'} is not a {FORMAT} checkpoint.")
    if ck.get("version") != VERSION:
        raise ValueError(f"checkpoint version {ck.get('version')!r} is not supported (this torchpref reads {VERSION}).")
    data = PreferenceData.create(**ck["data"], rating_eps=ck["settings"]["rating_eps"],
                                 rating_levels=ck["settings"].get("rating_levels"))
    model = PreferenceGP(data.train_X, data.comparisons, data.ratings, data.rating_index, ties=data.ties,
                         covar_module=covar_module, input_transform=input_transform, **ck["settings"])
    missing, unexpected = _key_mismatch(model, ck["state_dict"])
    if missing or unexpected:
        raise ValueError(f"the saved hyperparameters do not fit this kernel / input transform: missing {missing}, "
                         f"unexpected {unexpected}; pass covar_module / input_transform like the saved ones.")
    model.load_state_dict(ck["state_dict"])
    return model


def _key_mismatch(model: PreferenceGP, state_dict: dict[str, Any]) -> tuple[list[str], list[str]]:
    keys = set(model.state_dict())
    return sorted(keys - set(state_dict)), sorted(set(state_dict) - keys)
