r"""The items a ``torchpref serve`` page shows: objective values, labels and one picture per item.

:class:`ServeItems` holds the pool (``N x d`` objective values, their names, the items' labels)
and how an item's picture is made: from an image file named in a features CSV (read only from
one directory, checked when the CSV is read), from the lake world's map (each path drawn with
:func:`torchpref.frontends.elicit.plot_paths`), or from a render function written in Python.
Pictures are made once per item and kept (a bounded cache); making them is serialised, as
matplotlib's state is shared by threads.
"""

from __future__ import annotations

import hashlib
import io
import os
import sys
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from torchpref.data.features import FeaturesError, printable, read_features_csv
from torchpref.version import __version__

__all__ = ["IMAGE_TYPES", "PLOT_LOCK", "ServeItems", "items_from_csv", "lake_items", "picture_bytes"]

IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".gif": "image/gif"}
"""The image files a features CSV may name (no SVG: it can hold scripts), by suffix."""

_MAGIC = ((b"\x89PNG\r\n\x1a\n", "image/png"), (b"\xff\xd8\xff", "image/jpeg"), (b"GIF8", "image/gif"))
CACHE_SIZE = 512
PROGRESS_ROWS = 20_000
"""Checking more image files than this shows a progress bar on standard error (about a second)."""
PLOT_LOCK = threading.RLock()
"""Held while a picture or plot is made: matplotlib's state is shared by the server's threads."""


def picture_bytes(picture: object) -> tuple[bytes, str] | None:
    """``(bytes, media type)`` of what a render function returned: PNG/JPEG/GIF ``bytes``, a
    matplotlib ``Figure`` (drawn to PNG and closed), a :class:`~pathlib.Path` to such a file, or
    ``None`` (no picture).

    Raises:
        TypeError: anything else, or bytes that are not a PNG, JPEG or GIF image (naming it).
    """
    if picture is None:
        return None
    if hasattr(picture, "savefig"):
        buf = io.BytesIO()
        picture.savefig(buf, format="png", dpi=getattr(picture, "dpi", 100))
        import sys

        if "matplotlib.pyplot" in sys.modules:
            sys.modules["matplotlib.pyplot"].close(picture)
        return buf.getvalue(), "image/png"
    if isinstance(picture, Path):
        picture = picture.read_bytes()
    if isinstance(picture, (bytes, bytearray)):
        kind = next((t for magic, t in _MAGIC if bytes(picture[:8]).startswith(magic)), None)
        if kind is None:
            raise TypeError(f"a picture's bytes must be a PNG, JPEG or GIF image, got {bytes(picture[:8])!r}.")
        return bytes(picture), kind
    raise TypeError(
        f"a render function must return PNG/JPEG/GIF bytes, a matplotlib Figure, a Path or None, "
        f"got {type(picture).__name__}."
    )


@dataclass
class ServeItems:
    """A pool of items and their pictures.

    Args:
        X: ``N x d`` objective values.
        names: the ``d`` objectives' names.
        labels: the ``N`` items' labels (default ``#1 .. #N``).
        render: ``render(item, index) -> picture`` (see :func:`picture_bytes`), or ``None``.
        noun: what an item is called on the page ("item", "path").
        metadata: stored in each new session file's header.
        picture_dir: a folder where drawn PNG pictures are kept between runs (``None``: none); its
            name must change whenever the pictures would (the lake's names the scenario and version).
    """

    X: Tensor
    names: list[str]
    labels: list[str] | None = None
    render: Callable[[Tensor, int], Any] | None = None
    noun: str = "item"
    metadata: dict = field(default_factory=dict)
    picture_dir: Path | None = None

    def __post_init__(self) -> None:
        X = torch.as_tensor(self.X, dtype=torch.float64)
        if X.dim() != 2 or X.shape[0] < 2 or not torch.isfinite(X).all():
            raise ValueError(f"items must be an N x d tensor of finite values with N >= 2, got shape {tuple(X.shape)}.")
        if not bool((X != X[0]).any()):  # every row the first one
            raise ValueError("need at least two distinct items to elicit preferences.")
        self.X = X
        self.names = [printable(n) for n in (self.names or [f"x{k + 1}" for k in range(X.shape[1])])]
        if len(self.names) != X.shape[1]:
            raise ValueError(f"{len(self.names)} names for {X.shape[1]} objectives.")
        if self.labels is not None and len(self.labels) != X.shape[0]:
            raise ValueError(f"{len(self.labels)} labels for {X.shape[0]} items.")
        self._cache: OrderedDict[int, tuple[bytes, str] | None] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self.X.shape[0]

    def label(self, i: int) -> str:
        """Item ``i``'s label."""
        return self.labels[i] if self.labels is not None else f"#{i + 1}"

    @property
    def has_pictures(self) -> bool:
        """Whether items have pictures (a render function or image files)."""
        return self.render is not None

    def prerender(self, progress: bool = True) -> None:
        """Make every item's picture (up to the cache's size) now, one at a time, with a progress
        bar on standard error when there is anything to draw: ``serve`` does this before it prints
        its address, so that no participant waits for a picture. Pictures kept in
        :attr:`picture_dir` by an earlier run are read, not drawn."""
        if self.render is None:
            return
        count = min(len(self), CACHE_SIZE)
        todo = [i for i in range(count) if not self._on_disk(i)]
        if todo and progress:
            where = f"; kept in {self.picture_dir} for the next start" if self.picture_dir is not None else ""
            print(f"torchpref serve: drawing {len(todo)} pictures before the page opens{where}", file=sys.stderr)
        bar = tqdm(todo, desc="pictures", unit="pic", file=sys.stderr, disable=not (todo and progress))
        for i in bar:
            try:
                self.picture(i)
            except Exception:  # a bad picture is reported when it is asked for (a 404)
                continue
        for i in range(count):  # those kept on disk, into memory
            try:
                self.picture(i)
            except Exception:
                continue

    def _disk_path(self, i: int) -> Path | None:
        return None if self.picture_dir is None else Path(self.picture_dir) / f"{i}.png"

    def _on_disk(self, i: int) -> bool:
        path = self._disk_path(i)
        return path is not None and path.is_file()

    def _from_disk(self, i: int) -> tuple[bytes, str] | None:
        path = self._disk_path(i)
        try:
            data = path.read_bytes() if path is not None else b""
        except OSError:
            return None
        return (data, "image/png") if data.startswith(b"\x89PNG\r\n\x1a\n") else None

    def _to_disk(self, i: int, value: tuple[bytes, str] | None) -> None:
        path = self._disk_path(i)
        if path is None or value is None or value[1] != "image/png":
            return
        try:  # kept only to start faster next time: a folder that cannot be written is no error
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            tmp.write_bytes(value[0])
            os.replace(tmp, path)
        except OSError:
            pass

    def prerender_in_background(self) -> threading.Event:
        """Make every item's picture (up to the cache's size) in a daemon thread, one at a time,
        so that a question's pictures are ready before it is asked; set the returned event to stop."""
        stop = threading.Event()
        if self.render is None:
            return stop

        def work() -> None:
            for i in range(min(len(self), CACHE_SIZE)):
                if stop.is_set():
                    return
                try:
                    self.picture(i)
                except Exception:  # a bad picture is reported when it is asked for (a 404)
                    continue

        threading.Thread(target=work, name="torchpref-serve-pictures", daemon=True).start()
        return stop

    def picture(self, i: int) -> tuple[bytes, str] | None:
        """Item ``i``'s picture as ``(bytes, media type)``, or ``None``; made once and kept."""
        if not 0 <= i < len(self):
            raise IndexError(f"no item {i} (items 0..{len(self) - 1}).")
        if self.render is None:
            return None
        with self._lock, PLOT_LOCK:
            if i in self._cache:
                self._cache.move_to_end(i)
                return self._cache[i]
            value = self._from_disk(i)
            if value is None:
                value = picture_bytes(self.render(self.X[i], i))
                self._to_disk(i, value)
            self._cache[i] = value
            while len(self._cache) > CACHE_SIZE:
                self._cache.popitem(last=False)
            return value


def _image_files(path: Path, header: list[str], rows: list[dict], column: str, image_dir: Path) -> list[Path]:
    """The image file of every row, each checked to be a file of a known type inside ``image_dir``."""
    root = image_dir.resolve()
    if not root.is_dir():
        raise FeaturesError(f"--image-dir {image_dir}: not a folder.")
    files = []
    bar = tqdm(rows, desc="image files", unit="row", file=sys.stderr, disable=len(rows) < PROGRESS_ROWS, leave=False)
    for i, row in enumerate(bar, start=2):
        name = row[column].strip()
        target = (root / name).resolve()
        where = f"{path}, row {i}, column {printable(column)!r}"
        if not name or not target.is_relative_to(root):
            raise FeaturesError(f"{where}: {printable(name)!r} is not a file inside the image folder {image_dir}.")
        if target.suffix.lower() not in IMAGE_TYPES:
            raise FeaturesError(
                f"{where}: {printable(name)!r} is not a {', '.join(IMAGE_TYPES)} image (by its name's ending)."
            )
        if not target.is_file():
            raise FeaturesError(f"{where}: no image file {printable(name)!r} in {image_dir}.")
        files.append(target)
    return files


def items_from_csv(
    path: str | Path, id_column: str | None = None, image_column: str | None = None, image_dir: str | Path | None = None
) -> ServeItems:
    """Items from a features CSV as ``torchpref elicit`` reads it
    (:func:`~torchpref.data.features.read_features_csv`), optionally with a column naming each
    item's image file (a name relative to ``image_dir``, by default the CSV's folder).

    Every named file must lie inside ``image_dir`` (after resolving links), exist and be a PNG,
    JPEG or GIF by its name; only those files are ever served, by item number.

    Raises:
        FeaturesError: as :func:`~torchpref.data.features.read_features_csv`, or a missing image
            column, a file outside the folder, missing or of another type (naming the row).
    """
    import csv

    path = Path(path)
    if image_column is None:
        X, names, labels = read_features_csv(path, id_column)
        return ServeItems(X, names, labels, metadata={"features": str(path)})
    text = path.read_text(encoding="utf-8-sig")
    # the image column is not an objective: read the CSV without it
    from torchpref.data.features import _separator

    sep = _separator(text)
    table = [r for r in csv.reader(text.splitlines(), delimiter=sep) if any(c.strip() for c in r)]
    header = [c.strip() for c in table[0]] if table else []
    if image_column not in header:
        raise FeaturesError(
            f"{path}: no column {printable(image_column)!r} for --image-column; the columns are "
            f"{', '.join(repr(printable(h)) for h in header)}."
        )
    j = header.index(image_column)
    rows = [dict(zip(header, r, strict=False)) for r in table[1:]]
    folder = Path(image_dir) if image_dir is not None else path.parent
    files, root = _image_files(path, header, rows, image_column, folder), folder.resolve()
    stripped = io.StringIO()
    writer = csv.writer(stripped, delimiter=sep)
    for r in table:
        writer.writerow(r[:j] + r[j + 1 :])
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / path.name
        copy.write_text(stripped.getvalue(), encoding="utf-8")
        try:
            X, names, labels = read_features_csv(copy, id_column)
        except FeaturesError as err:
            raise FeaturesError(str(err).replace(str(copy), str(path))) from None

    def render(item: Tensor, index: int) -> Path:
        target = files[index].resolve()  # checked again: the folder may have changed since
        if not target.is_relative_to(root) or not target.is_file():
            raise FileNotFoundError(f"image of item {index} is gone")
        return target

    return ServeItems(X, names, labels, render=render, metadata={"features": str(path), "images": image_column})


def lake_items(seed: int = 0) -> ServeItems:
    """The lake scenario's training paths (objectives ``[distance, information]``), each drawn on
    its map (:func:`torchpref.lake.plotting.plot_paths`, a wide line at 120 dpi); the scenario is
    cached on disk."""
    from torchpref.lake.plotting import plot_paths
    from torchpref.lake.scenario import cached_scenario, default_cache_dir

    scenario = cached_scenario(seed, progress=True)

    def render(item: Tensor, index: int) -> bytes:
        import tempfile

        title = f"path {index}: distance {float(item[0]):.0f}, information {float(item[1]):.0f}"
        path = [scenario.train_paths[int(index)]]
        with tempfile.TemporaryDirectory() as tmp:  # a wide line and 120 dpi: readable small, sharp enlarged
            out = plot_paths(scenario, path, [""], Path(tmp) / "path.png", title=title, dpi=120, line_width=4.5)
            return out.read_bytes()

    labels = [f"path {i}" for i in range(scenario.train_X.shape[0])]
    digest = hashlib.sha256(scenario.train_X.numpy().tobytes()).hexdigest()[:12]
    return ServeItems(
        scenario.train_X,
        ["distance", "information"],
        labels,
        render=render,
        noun="path",
        metadata={"world": "lake", "lake_seed": seed},
        picture_dir=default_cache_dir() / f"pictures-{seed}-{digest}-{__version__}",
    )
