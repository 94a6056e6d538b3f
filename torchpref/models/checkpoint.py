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
default is loaded by passing one of the same structure (``load_model(path, covar_module=...)``);
so is a prior mean (``mean_module=...``): a checkpoint of a model with a mean is refused, naming
the mean's keys, unless one is passed.

A file that cannot be a checkpoint (truncated by a crash, damaged, another kind of file, a pickle
holding code) or one whose contents are not a checkpoint's raises :class:`CheckpointError`, a
``ValueError`` naming the file and what is wrong; nothing is half-loaded.
"""

from __future__ import annotations

import errno
import io
import numbers
import os
import pickle
import stat
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, cast

import torch
from botorch.models.transforms.input import InputTransform
from gpytorch.kernels import Kernel
from gpytorch.means import Mean

from torchpref.data.preference_data import DEFAULT_RATING_EPS, PreferenceData
from torchpref.models.preference_gp import PreferenceGP

FORMAT = "torchpref.PreferenceGP"
VERSION = 1
DATA_KEYS = ("train_X", "comparisons", "ratings", "rating_index", "ties")
SETTINGS_KEYS = ("rating_eps", "max_newton_iter", "learn_likelihood", "rating_levels", "ties_offered", "laplace_dtype")
#: The data tensors' ranks and kinds of values ("float": real floating, "int": integer).
DATA_LAYOUT = {
    "train_X": (2, "float"),
    "comparisons": (2, "int"),
    "ratings": (1, "float"),
    "rating_index": (1, "int"),
    "ties": (2, "int"),
}
#: :func:`load_model`'s default bound on the number of items: the kernel matrix of 100,000 items
#: takes 80 GB in float64.
MAX_ITEMS = 100_000


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
    assert isinstance(d, PreferenceData)  # one problem: checked above
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
    at ``path`` as it was (:func:`save_atomically`)."""
    save_atomically(lambda: model_checkpoint(model), path, "save_model")


def save_atomically(make: Callable[[], Any], path: str | os.PathLike, what: str) -> None:
    """``torch.save`` of ``make()`` to ``path`` atomically (a temporary file beside it, flushed and
    renamed): a failed save leaves any old file at ``path`` as it was. ``what`` names the caller in
    errors.

    A symbolic link at ``path`` is written through: its target is replaced and the link kept. A new
    file gets the permissions ``open`` would give it (``0o666`` less the umask); a file replaced
    keeps its own. The file, and then its folder (on POSIX), are flushed to disk before returning.
    """
    path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))  # the link's final target (which may not exist yet)
    if path.is_dir():
        raise ValueError(f"{path} is a directory; give {what} a file name.")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot save to {path}: the folder {path.parent} does not exist.")
    ck = make()
    mode = _file_mode(path)
    fd, tmp = tempfile.mkstemp(prefix=_temporary_prefix(path.name), suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            if hasattr(os, "fchmod"):
                os.fchmod(fh.fileno(), mode)
            torch.save(ck, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_folder(path.parent)


def _temporary_prefix(name: str) -> str:
    """The temporary file's name start: ``NAME.``, with ``NAME`` cut to 200 bytes so that the
    temporary name (8 random characters and ``.tmp`` added) fits where ``NAME`` itself fits
    (255 bytes on most file systems)."""
    raw = os.fsencode(name)
    return (os.fsdecode(raw[:200]) if len(raw) > 200 else name) + "."


def _umask() -> int:
    """The process's umask, read without changing it where ``/proc`` says it (Linux), else by
    setting and restoring it."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o22)
    os.umask(mask)
    return mask


def _file_mode(path: Path) -> int:
    """The permission bits for the file written at ``path``: the existing file's, or ``0o666``
    less the umask for a new one."""
    try:
        return stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        return 0o666 & ~_umask()


def _fsync_folder(folder: Path) -> None:
    """Flush ``folder``'s entries (the rename) to disk, where the platform can (POSIX)."""
    if os.name != "posix":
        return
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def load_model(
    source: str | os.PathLike | dict[str, Any],
    covar_module: Kernel | None = None,
    input_transform: InputTransform | None = None,
    map_location: str | torch.device | None = None,
    *,
    max_items: int | None = MAX_ITEMS,
    mean_module: Mean | None = None,
) -> PreferenceGP:
    """The model saved by :func:`save_model` (a path, read with ``weights_only=True``) or given as
    a :func:`model_checkpoint` dictionary.

    The checkpoint is checked as the constructor checks its arguments, before anything is built
    from it: every setting's type and range (``ties_offered`` must be a ``bool``, not a string),
    every tensor's kind (complex values refused), shape and memory (a tensor whose elements do not
    fit in its own storage, such as an expanded stride-0 view, is refused before it is copied),
    the number of items (at most ``max_items``), the constraint bounds (those of the modules it
    loads into), and, once loaded, that every constrained hyperparameter lies within its
    constraint and every prior has a finite density there.

    Args:
        source: the file, or the checkpoint itself.
        covar_module: a kernel of the saved one's structure (default: the default kernel).
        input_transform: an input transform of the saved one's structure, if it had one.
        map_location: passed to ``torch.load``.
        mean_module: a prior mean of the saved one's structure, if it had one (its parameters and
            buffers are loaded into it).
        max_items: the most items a checkpoint may hold (default :data:`MAX_ITEMS`, 100,000,
            whose kernel matrix takes 80 GB in float64); ``None``: no bound.

    Raises:
        CheckpointError: (a ``ValueError``) if ``source`` is not a readable torchpref model
            checkpoint (truncated, damaged, another kind of file, not a regular file (a FIFO is
            refused without waiting on it), an archive whose records are compressed or larger
            than the file, entries missing or of the
            wrong kind or range, complex, non-finite or out-of-constraint hyperparameters,
            tensors larger than their storage, more than ``max_items`` items), or its
            hyperparameters do not fit the kernel / input transform given (naming the keys).
            ``ValueError``: data that fail validation, as for
            :class:`~torchpref.models.preference_gp.PreferenceGP`.
        FileNotFoundError, IsADirectoryError, PermissionError: as ``open`` raises them.
    """
    if max_items is not None and (
        isinstance(max_items, bool) or not isinstance(max_items, numbers.Integral) or max_items < 1
    ):
        raise ValueError(f"max_items must be a positive integer or None, got {max_items!r}.")
    where = "the dictionary" if isinstance(source, dict) else str(source)
    ck = _check_contents(source if isinstance(source, dict) else _read(source, map_location), where, max_items)
    settings = ck["settings"]
    if ck["data"]["train_X"].shape[-1] == 0:  # a prior-only PreferenceGP(None, None): no items, d unknown
        model = PreferenceGP(
            None, None, covar_module=covar_module, input_transform=input_transform, mean_module=mean_module, **settings
        )
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
            mean_module=mean_module,
            **settings,
        )
    _check_fits(model, ck["state_dict"], where)
    try:
        model.load_state_dict(ck["state_dict"], strict=True)
    except RuntimeError as err:  # a shape that does not fit
        raise CheckpointError(
            f"{where}: the saved hyperparameters do not fit this kernel / input transform: {' '.join(str(err).split())}"
        ) from err
    _check_loaded_values(model, where)
    return model


def open_regular(path: str | os.PathLike, what: str, writer: str) -> tuple[IO[bytes], int]:
    """``path`` opened for reading, with its size, if it is a regular file (``what``: the kind of
    file expected, ``writer``: the function that writes one, both for the messages).

    Raises:
        FileNotFoundError: no file at ``path`` (naming it).
        IsADirectoryError: a directory.
        CheckpointError: a FIFO, socket or device (refused without reading it: opened non-blocking).
    """
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise FileNotFoundError(
            errno.ENOENT, f"no {what} at this path (torchpref.{writer} writes one)", str(path)
        ) from None
    except IsADirectoryError:  # where a directory cannot be opened for reading
        raise IsADirectoryError(errno.EISDIR, f"a directory, not a {what}", str(path)) from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        if stat.S_ISDIR(info.st_mode):
            raise IsADirectoryError(errno.EISDIR, f"a directory, not a {what}", str(path))
        kind = "a FIFO" if stat.S_ISFIFO(info.st_mode) else "a socket or device"
        raise CheckpointError(f"{path} is not a regular file ({kind}); a {what} is one {writer} wrote.")
    return os.fdopen(fd, "rb"), int(info.st_size)


def check_archive(fh: IO[bytes], size: int, where: str, what: str, writer: str) -> None:
    """The file is a zip archive (``torch.save``'s) whose records are stored uncompressed, none
    larger than the file: nothing ``torch.load`` then allocates can exceed the file's size (a
    compressed record of a few kilobytes could expand to gigabytes). Leaves ``fh`` at its start.

    Raises:
        CheckpointError: not a zip archive, an unreadable one, or a record compressed or larger
            than the file (naming ``where`` and the record).
    """
    if fh.read(4) != b"PK\x03\x04":
        raise CheckpointError(f"{where} is not a {what}: not an archive written by torch.save ({writer} writes one).")
    fh.seek(0)
    try:
        records = zipfile.ZipFile(fh).infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        raise CheckpointError(f"{where} is a damaged {what} (truncated or corrupted: {err}); not loaded.") from err
    for r in records:
        if r.compress_type != zipfile.ZIP_STORED or r.file_size > size:
            raise CheckpointError(
                f"{where} is not a file {writer} wrote: its record {r.filename!r} is compressed or expands "
                f"to {r.file_size} bytes, more than the file's {size}; not loaded."
            )
    fh.seek(0)


def _read(path: str | os.PathLike, map_location) -> Any:
    """``torch.load(path, weights_only=True)`` of a regular file holding ``torch.save``'s archive
    of stored records (:func:`open_regular`, :func:`check_archive`), its many failure types for a
    file that is no checkpoint turned into one :class:`CheckpointError`."""
    what = f"{FORMAT} checkpoint"
    fh, size = open_regular(path, what, "save_model")
    with fh:
        check_archive(fh, size, str(path), what, "save_model")
        try:
            return torch.load(cast(io.BufferedReader, fh), map_location=map_location, weights_only=True)
        except pickle.UnpicklingError as err:
            raise CheckpointError(
                f"{path} is not a {what}: it holds something other than tensors and "
                "plain values, or is not a file written by torch.save; not loaded."
            ) from err
        except Exception as err:
            raise CheckpointError(
                f"{path} is not a readable {what} (truncated, damaged or another kind "
                f"of file): {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
            ) from err


def _check_contents(ck: object, where: str, max_items: int | None = MAX_ITEMS) -> dict[str, Any]:
    """The checkpoint's entries are there and of the right kinds and ranges, its tensors real,
    within their storage and finite (hyperparameters), and it holds at most ``max_items`` items;
    returns it."""
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise CheckpointError(f"{where} is not a {FORMAT} checkpoint.")
    version = ck.get("version")
    if type(version) is not int or version != VERSION:
        raise CheckpointError(f"checkpoint version {version!r} is not supported (this torchpref reads {VERSION}).")
    checks: tuple[tuple[str, tuple[str, ...] | None], ...] = (
        ("data", DATA_KEYS),
        ("settings", SETTINGS_KEYS),
        ("state_dict", None),
    )
    for key, allowed in checks:
        entry = ck.get(key)
        if not isinstance(entry, dict):
            raise CheckpointError(f"{where}: the checkpoint's {key!r} is missing or not a dictionary.")
        unknown = sorted(map(str, set(entry) - set(allowed))) if allowed is not None else []
        if unknown:
            raise CheckpointError(f"{where}: unknown {key} entries {unknown}; expected some of {list(allowed or ())}.")
    if not isinstance(ck["data"].get("train_X"), torch.Tensor):
        raise CheckpointError(f"{where}: the checkpoint's data has no train_X tensor.")
    for name, value in ck["settings"].items():
        _check_setting(name, value, where)
    for name, value in ck["data"].items():
        if value is not None and not isinstance(value, torch.Tensor):
            raise CheckpointError(f"{where}: data {name!r} must be a tensor or None, got {type(value).__name__}.")
        if value is not None:
            _check_tensor(f"data {name!r}", value, where)
            rank, kind = DATA_LAYOUT[name]
            integer = not (value.is_floating_point() or value.dtype == torch.bool)
            if value.dim() != rank or (kind == "float") != value.is_floating_point() or (kind == "int") != integer:
                what = "real floating" if kind == "float" else "integer"
                raise CheckpointError(
                    f"{where}: data {name!r} must be a {rank}-dimensional {what} tensor, got "
                    f"{value.dtype} of shape {tuple(value.shape)}."
                )
    n = ck["data"]["train_X"].shape[0]
    if max_items is not None and n > max_items:
        raise CheckpointError(
            f"{where}: the checkpoint holds {n} items, more than max_items={max_items} (its kernel matrix "
            f"alone would take {n * n * 8 / 1e9:.3g} GB in float64); pass a larger max_items to load it."
        )
    for name, value in ck["state_dict"].items():
        if not isinstance(value, torch.Tensor):
            raise CheckpointError(f"{where}: hyperparameter {name!r} must be a tensor, got {type(value).__name__}.")
        _check_tensor(f"hyperparameter {name!r}", value, where)
        bad = value.isnan() if "constraint" in name else ~value.isfinite()  # a bound may be infinite
        if value.is_floating_point() and bad.any():
            raise CheckpointError(f"{where}: hyperparameter {name!r} is not finite: {value.tolist()}.")
    return ck


def _check_setting(name: str, value: object, where: str) -> None:
    """A setting of the kind the constructor takes: flags are ``bool`` (a string's truthiness is
    no answer), counts integers, ``rating_eps`` a number in ``(0, 0.5)``."""
    count = int(value) if isinstance(value, numbers.Integral) and not isinstance(value, bool) else None
    real = float(value) if isinstance(value, numbers.Real) and not isinstance(value, bool) else None
    if name in ("learn_likelihood", "ties_offered"):
        ok, want = isinstance(value, bool), "True or False"
    elif name == "max_newton_iter":
        ok, want = count is not None and count >= 1, "an integer of at least 1"
    elif name == "rating_levels":
        ok, want = value is None or (count is not None and count >= 2), "None or an integer of at least 2"
    elif name == "rating_eps":
        ok, want = real is not None and 0 < real < 0.5, "a number in (0, 0.5)"
    else:  # laplace_dtype (which dtypes the constructor takes, it checks)
        ok, want = value is None or isinstance(value, torch.dtype), "None or a torch.dtype"
    if not ok:
        raise CheckpointError(f"{where}: setting {name!r} must be {want}, got {value!r} ({type(value).__name__}).")


def _check_tensor(what: str, t: torch.Tensor, where: str) -> None:
    """A dense, real tensor whose elements all have memory of their own in its storage: an
    expanded (stride-0) or overlapping view, which would grow into far more memory when copied
    than the file holds, is refused before anything is copied."""
    if t.layout != torch.strided:
        raise CheckpointError(f"{where}: {what} must be a dense tensor, got layout {t.layout}.")
    if t.is_complex():
        raise CheckpointError(f"{where}: {what} must be real, got {t.dtype} values.")
    available = t.untyped_storage().nbytes() - t.storage_offset() * t.element_size()
    if t.numel() * t.element_size() > available:
        raise CheckpointError(
            f"{where}: {what} of shape {tuple(t.shape)} (strides {t.stride()}) has {t.numel()} elements but "
            f"its storage holds {max(available, 0) // t.element_size()}: an expanded view, not saved data."
        )


def _check_fits(model: PreferenceGP, state_dict: dict[str, Any], where: str) -> None:
    """The saved hyperparameters fit ``model``: the same keys, shapes and kinds of values, and
    the same constraint bounds (a bound is part of the module, as its class is: a lowered bound
    would let a lengthscale go negative)."""
    missing, unexpected = _key_mismatch(model, state_dict)
    if missing or unexpected:
        raise CheckpointError(
            f"the saved hyperparameters do not fit this kernel / input transform / mean: missing {missing}, "
            f"unexpected {unexpected}; pass covar_module / input_transform / mean_module like the saved ones."
        )
    own = model.state_dict()
    for name, value in state_dict.items():
        mine = own[name]
        if value.shape != mine.shape:
            raise CheckpointError(
                f"{where}: the saved hyperparameters do not fit this kernel / input transform: size mismatch "
                f"for {name}: {tuple(value.shape)} saved, {tuple(mine.shape)} in the model."
            )
        if value.is_floating_point() != mine.is_floating_point() or (value.dtype == torch.bool) != (
            mine.dtype == torch.bool
        ):
            raise CheckpointError(f"{where}: hyperparameter {name!r} is {value.dtype}; the model's is {mine.dtype}.")
        if name.endswith(("_constraint.lower_bound", "_constraint.upper_bound")) and not torch.equal(
            value.to(mine), mine
        ):
            raise CheckpointError(
                f"{where}: constraint bound {name!r} is {value.tolist()} in the checkpoint but {mine.tolist()} in "
                "the module it loads into; pass covar_module / input_transform with the saved constraints."
            )


def _check_loaded_values(model: PreferenceGP, where: str) -> None:
    """Every constrained hyperparameter of the loaded ``model`` within its constraint, and every
    prior's log density finite at its value."""
    with torch.no_grad():
        for prefix, module in model.named_modules():
            for cname, constraint in getattr(module, "_constraints", {}).items():
                raw = getattr(module, cname[: -len("_constraint")], None)
                if not isinstance(raw, torch.Tensor):
                    continue
                value = constraint.transform(raw)  # the raw value itself where not enforced (transform=None)
                if not (bool(value.isfinite().all()) and constraint.check(value)):
                    name = f"{prefix}.{cname[: -len('_constraint')]}".lstrip(".")
                    raise CheckpointError(
                        f"{where}: hyperparameter {name!r} is {value.tolist()}, outside its constraint {constraint}."
                    )
        for name, module, prior, closure, _ in model.named_priors():  # type: ignore[operator]
            for arg, support in getattr(prior, "arg_constraints", {}).items():
                value = getattr(prior, arg, None)
                if isinstance(value, torch.Tensor) and not bool(support.check(value).all()):
                    raise CheckpointError(f"{where}: prior {name!r} has {arg} {value.tolist()}, outside {support}.")
            log_p = prior.log_prob(closure(module))
            if not bool(log_p.isfinite().all()):
                raise CheckpointError(
                    f"{where}: prior {name!r} has log density {log_p.tolist()} at the saved value: "
                    "the checkpoint's prior parameters or hyperparameters are not valid."
                )


def _key_mismatch(model: PreferenceGP, state_dict: dict[str, Any]) -> tuple[list[str], list[str]]:
    keys = set(model.state_dict())
    return sorted(keys - set(state_dict)), sorted(set(state_dict) - keys)
