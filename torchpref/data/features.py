r"""Items from a features CSV (``torchpref elicit --features``): one row per item, a header row
of column names, the objectives' values as numbers, and optionally a column naming the items.

The separator (comma, semicolon, tab or ``|``) is detected from the file; the label column is the
one named by ``id_column``, or else a first column named ``id``, ``name``, ``label``, ``item`` or
``key`` (numbers or not), or a first column holding any text. Every other column is an
objective. Text from the file (names, labels) is made safe to print: control characters, such as
a terminal's escape sequences, are replaced.
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import torch
from torch import Tensor

__all__ = ["FeaturesError", "ID_NAMES", "printable", "read_features_csv"]

ID_NAMES = ("id", "name", "label", "item", "key")
"""Header names of a first column that is taken as the items' labels even if it holds numbers."""

SEPARATORS = ",;\t|"


class FeaturesError(ValueError):
    """A features CSV that cannot be read (the message names the file, row and column)."""


def printable(text: str, width: int = 40) -> str:
    """``text`` safe to print on a terminal: control and other non-printable characters (escape
    sequences, newlines, bidirectional overrides) replaced by ``?``, at most ``width`` characters."""
    clean = "".join(c if c.isprintable() else "?" for c in str(text)).strip()
    return clean if len(clean) <= width else clean[: width - 1] + "…"


def _separator(text: str) -> str:
    try:
        return csv.Sniffer().sniff("\n".join(text.splitlines()[:50]), delimiters=SEPARATORS).delimiter
    except csv.Error:
        return ","


def _number(s: str) -> float | None:
    try:
        return float(s)
    except ValueError:
        return None


def _rows(path: Path) -> tuple[list[list[str]], str]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FeaturesError(f"{path}: not UTF-8 text (byte {exc.start}); save it as a UTF-8 CSV.") from None
    sep = _separator(text)
    rows = [r for r in csv.reader(text.splitlines(), delimiter=sep) if any(c.strip() for c in r)]
    if len(rows) < 3:
        raise FeaturesError(f"{path}: need a header row and at least two items, got {max(0, len(rows) - 1)} item(s).")
    if len(rows[0]) == 1 and any(other in rows[0][0] for other in SEPARATORS):
        raise FeaturesError(
            f"{path}: could not tell the columns apart (one column {printable(rows[0][0])!r}); "
            "separate the values with commas, semicolons, tabs or |, the same on every row."
        )
    named = {",": "comma", ";": "semicolon", "\t": "tab", "|": "|"}[sep]
    if sep != "," and any(re.fullmatch(r"[-+]?\d+,\d+", c.strip()) for r in rows[1:] for c in r):
        raise FeaturesError(
            f"{path}: numbers with a decimal comma (separator: {named}); write them with a point (1.5, not 1,5)."
        )
    for i, r in enumerate(rows[1:], start=2):
        if len(r) != len(rows[0]):
            raise FeaturesError(
                f"{path}, row {i}: {len(r)} values, but the header has {len(rows[0])} columns (separator: {named})."
            )
    return rows, sep


def _label_column(path: Path, header: list[str], body: list[list[str]], id_column: str | None) -> int | None:
    if id_column is not None:
        if id_column not in header:
            raise FeaturesError(
                f"{path}: no column {printable(id_column)!r} for --id; the columns are "
                f"{', '.join(repr(printable(h)) for h in header)}."
            )
        return header.index(id_column)
    if len(header) > 1 and (header[0].lower() in ID_NAMES or any(_number(r[0]) is None for r in body)):
        return 0
    return None


_IMAGE_ENDINGS = (".png", ".jpg", ".jpeg", ".gif", ".webp", ".svg", ".bmp")


def _hint(value: str, column: str, label_column: int | None) -> str:
    """What a cell that is not a number may be: an image file's name, or the items' names."""
    if value.strip().lower().endswith(_IMAGE_ENDINGS):
        return (
            f" (a column of image files? torchpref serve shows them with --image-column {printable(column)}, "
            "and reads the CSV without that column)"
        )
    return " (a column that names the items: --id COLUMN)" if label_column is None else ""


def read_features_csv(path: str | Path, id_column: str | None = None) -> tuple[Tensor, list[str], list[str] | None]:
    """Items from a CSV: a header row of column names, then one row per item.

    Args:
        path: the file.
        id_column: the header name of the column that names the items (default: see the module).

    Returns:
        ``(X, names, labels)``: ``N x d`` float64 objective values, the ``d`` objectives' names and
        the ``N`` labels (or ``None``), names and labels made printable (:func:`printable`).

    Raises:
        FeaturesError: not UTF-8, columns that cannot be told apart, a ragged row, a value that is
            not a finite number (naming the row and column), no objective, fewer than two items.
        OSError: the file cannot be read.
    """
    path = Path(path)
    rows, _ = _rows(path)
    header, body = [c.strip() for c in rows[0]], rows[1:]
    lab = _label_column(path, header, body, id_column)
    labels = None if lab is None else [printable(r[lab]) for r in body]
    cols = [j for j in range(len(header)) if j != lab]
    if not cols:  # the one column is the labels' (lab is not None)
        raise FeaturesError(f"{path}: no objective columns besides the labels {printable(header[lab or 0])!r}.")
    values = []
    for i, r in enumerate(body, start=2):
        row = []
        for j in cols:
            v = _number(r[j])
            if v is None or not math.isfinite(v):
                raise FeaturesError(
                    f"{path}, row {i}, column {printable(header[j])!r}: {printable(r[j])!r} is not a "
                    "finite number" + _hint(r[j], header[j], lab) + "."
                )
            row.append(v)
        values.append(row)
    return torch.tensor(values, dtype=torch.float64), [printable(header[j]) for j in cols], labels
