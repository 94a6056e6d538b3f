r"""The SUSHI preference data (Kamishima 2003), read from a user's own download.

In one survey the same people rated 10 sushi, drawn from 100, on a 0-4 scale (4 = most preferred)
and ranked the same 10: the one public data set where each person gave both kinds of answer about
the same items, with item features. The release (``sushi3-2016``) is free for research but may not
be redistributed, so torchpref ships none of it: :func:`load_sushi` reads the folder a user
downloaded from the authors' page (:data:`SOURCE`), and the tests use :func:`write_synthetic`, a
small made-up file in the same format.

Files read (any number of people, as long as the two per-person files agree):

* ``sushi3b.<N>.10.order``: a header line ``100 1``, then per person ``0 10`` and the 10 item ids
  ranked, most preferred first;
* ``sushi3b.<N>.10.score``: per person, 100 space-separated ratings ``0..4`` (``-1``: not rated);
  exactly the ranked items are rated;
* ``sushi3.idata``: the 100 items, tab-separated (id, name, style, major group, minor group,
  oiliness, how often the person eats it, normalised price, how often it is sold).

Item features, in the unit cube (:data:`FEATURES`): the two binary categories as they are (style:
1 = not maki; major group: 1 = not seafood) and the four numerical features min-max scaled over
the 100 items (oiliness, 1 = lightest; eating frequency; price; how often sold). The 12-way minor
group is left out (a categorical feature the RBF kernel cannot use as it is).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

__all__ = [
    "FEATURES",
    "LEVELS",
    "SOURCE",
    "SushiData",
    "SushiDataMissing",
    "SushiPerson",
    "load_sushi",
    "write_synthetic",
]

#: where a user downloads the release
SOURCE = "https://www.kamishima.net/sushi/ (SUSHI Preference Data Sets, the sushi3-2016 release)"
#: the item features torchpref uses, in this order (module notes)
FEATURES = ("style", "major group", "oiliness", "eating frequency", "price", "sold frequency")
#: levels of a rating: 0..4, 4 = most preferred
LEVELS = 5
ITEMS = 100
PER_PERSON = 10
_ORDER = re.compile(r"^sushi3b\.(\d+)\.10\.order$")


class SushiDataMissing(FileNotFoundError):
    """The folder does not hold the SUSHI release; the message says what is missing and where to get it."""


@dataclass(frozen=True)
class SushiPerson:
    """One respondent: ``items`` (10 item ids, most preferred first) and ``levels`` (their 0-4
    rating of each, in the same order)."""

    items: tuple[int, ...]
    levels: tuple[int, ...]


@dataclass(frozen=True)
class SushiData:
    """The items (``X``: ``100 x 6`` in the unit cube, :data:`FEATURES`; ``names``) and the people."""

    X: Tensor
    names: tuple[str, ...]
    people: tuple[SushiPerson, ...]


def _missing(folder: Path, what: str) -> SushiDataMissing:
    return SushiDataMissing(
        f"{folder} does not hold the SUSHI data ({what}). Download the sushi3-2016 release from {SOURCE}, "
        "unpack it, and pass its folder (it holds sushi3.idata, sushi3b.5000.10.order and sushi3b.5000.10.score)."
    )


def _files(folder: Path) -> tuple[Path, Path, Path]:
    if not folder.is_dir():
        raise _missing(folder, "no such folder")
    orders = sorted(p for p in folder.iterdir() if _ORDER.match(p.name))
    if not orders:
        raise _missing(folder, "no sushi3b.<N>.10.order file")
    if len(orders) > 1:
        raise ValueError(f"{folder} holds several order files ({', '.join(p.name for p in orders)}): keep one.")
    order = orders[0]
    score = order.with_name(order.name[: -len("order")] + "score")
    idata = folder / "sushi3.idata"
    for p in (score, idata):
        if not p.is_file():
            raise _missing(folder, f"no {p.name}")
    return order, score, idata


def _items(path: Path) -> tuple[Tensor, tuple[str, ...]]:
    rows = [
        line.split("\t") for line in path.read_text(encoding="utf-8", errors="replace").splitlines() if line.strip()
    ]
    if len(rows) != ITEMS or any(len(r) < 9 for r in rows):
        raise ValueError(f"{path}: expected {ITEMS} tab-separated rows of 9 fields, got {len(rows)} rows.")
    try:
        ids = [int(r[0]) for r in rows]
        raw = torch.tensor([[float(r[k]) for k in (2, 3, 5, 6, 7, 8)] for r in rows], dtype=torch.float64)
    except ValueError as err:
        raise ValueError(f"{path}: a field is not a number ({err}).") from None
    if ids != list(range(ITEMS)) or not torch.isfinite(raw).all():
        raise ValueError(f"{path}: item ids must be 0..{ITEMS - 1} in order with finite features.")
    raw[:, 2] = -raw[:, 2]  # oiliness: 0 = heavy in the file; 1 = lightest here
    lo, hi = raw.min(0).values, raw.max(0).values
    X = (raw - lo) / torch.where(hi > lo, hi - lo, torch.ones_like(hi))
    return X, tuple(r[1] for r in rows)


def _people(order: Path, score: Path) -> tuple[SushiPerson, ...]:
    olines = order.read_text().split("\n")
    slines = [s for s in score.read_text().split("\n") if s.strip()]
    body = [o for o in olines[1:] if o.strip()]
    if olines[0].split() != [str(ITEMS), "1"]:
        raise ValueError(f"{order}: the first line must be '{ITEMS} 1', got {olines[0][:40]!r}.")
    if len(body) != len(slines):
        raise ValueError(f"{order.name} has {len(body)} people but {score.name} has {len(slines)}: they must agree.")
    people = []
    for k, (o, s) in enumerate(zip(body, slines)):
        try:
            ids = [int(v) for v in o.split()]
            levels = [int(v) for v in s.split()]
        except ValueError:
            raise ValueError(f"person {k}: a value is not an integer.") from None
        ranked = ids[2:]
        if ids[:2] != [0, PER_PERSON] or len(ranked) != PER_PERSON or len(set(ranked)) != PER_PERSON:
            raise ValueError(f"{order.name}, person {k}: expected '0 {PER_PERSON}' and {PER_PERSON} distinct ids.")
        if len(levels) != ITEMS or not all(-1 <= v < LEVELS for v in levels) or not all(0 <= i < ITEMS for i in ranked):
            raise ValueError(f"{score.name}, person {k}: expected {ITEMS} ratings in -1..{LEVELS - 1}.")
        if {i for i, v in enumerate(levels) if v >= 0} != set(ranked):
            raise ValueError(f"person {k}: the rated items are not the ranked ones.")
        people.append(SushiPerson(tuple(ranked), tuple(levels[i] for i in ranked)))
    return tuple(people)


def load_sushi(folder: str | os.PathLike) -> SushiData:
    """The release in ``folder`` (module notes).

    Raises:
        SushiDataMissing: a file is missing (the message says where to download the release).
        ValueError: a file that is not in the release's format, naming the file and the person.
    """
    order, score, idata = _files(Path(folder))
    X, names = _items(idata)
    return SushiData(X, names, _people(order, score))


def write_synthetic(folder: str | os.PathLike, num_people: int, seed: int = 0) -> Path:
    """A made-up data set in the release's format, for tests and demonstrations: 100 random items and
    ``num_people`` people with a random linear taste over the features; each ranks 10 random items by
    taste plus noise and rates them by a coarsened, noisier copy (so ratings and ranking mostly, not
    always, agree, and ties are common). Returns ``folder``."""
    g = torch.Generator().manual_seed(seed)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    feats = torch.rand(ITEMS, 6, generator=g, dtype=torch.float64)
    cats = (feats[:, :2] > 0.5).long()
    lines = []
    for i in range(ITEMS):
        f = feats[i]
        lines.append(
            f"{i}\tsynthetic{i}\t{int(cats[i, 0])}\t{int(cats[i, 1])}\t{i % 12}\t{4 * float(f[2]):.6f}\t"
            f"{3 * float(f[3]):.6f}\t{1 + 3 * float(f[4]):.6f}\t{float(f[5]):.6f}"
        )
    (out / "sushi3.idata").write_text("\n".join(lines) + "\n")
    orders, scores = [f"{ITEMS} 1"], []
    for _ in range(num_people):
        w = torch.randn(6, generator=g, dtype=torch.float64)
        items = torch.randperm(ITEMS, generator=g)[:PER_PERSON]
        u = feats[items] @ w
        ranked = items[
            torch.argsort(u + 0.3 * torch.randn(PER_PERSON, generator=g, dtype=torch.float64), descending=True)
        ]
        noisy = u + 0.5 * torch.randn(PER_PERSON, generator=g, dtype=torch.float64)
        z = (noisy - noisy.mean()) / noisy.std().clamp_min(1e-9)
        level = torch.bucketize(z, torch.tensor([-1.2, -0.4, 0.3, 0.8], dtype=torch.float64))
        row = [-1] * ITEMS
        for i, v in zip(items.tolist(), level.tolist()):
            row[i] = int(v)
        orders.append("0 10 " + " ".join(str(i) for i in ranked.tolist()))
        scores.append(" ".join(str(v) for v in row))
    (out / f"sushi3b.{num_people}.10.order").write_text("\n".join(orders) + "\n")
    (out / f"sushi3b.{num_people}.10.score").write_text("\n".join(scores) + "\n")
    return out
