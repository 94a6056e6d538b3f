r"""A study's items as its participants see them (:func:`study_items`: the copy of the features CSV
in the folder, or the lake) and as the models see them (:class:`StudySpace`: the unit cube of the
sessions' bounds), for the exports, the report and the page."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchpref.frontends.serve.items import ServeItems, items_from_csv, lake_items
from torchpref.sessions.contents import read_session
from torchpref.sessions.settings import SessionSettings
from torchpref.study.folder import StudyFolder

__all__ = ["StudySpace", "study_items", "study_space"]


def study_items(folder: StudyFolder) -> ServeItems:
    """The study's items, from its settings: its copy of the features CSV, or the lake."""
    settings = folder.settings()
    if settings.get("world") == "lake":
        return lake_items(int(settings.get("seed", 0)))
    return items_from_csv(
        str(folder.path / "items.csv"),
        settings.get("id_column"),
        settings.get("image_column"),
        settings.get("image_dir"),
    )


@dataclass(frozen=True)
class StudySpace:
    """The study's items in raw units (``X``, ``N x d``), in the unit cube the models see
    (``unit``), their labels and the features' names."""

    X: Tensor
    unit: Tensor
    labels: list[str]
    names: list[str]

    def label(self, row: int | None, item: tuple[float, ...] = ()) -> str:
        """Item ``row``'s label (an item outside the pool: its values)."""
        return self.labels[row] if row is not None and 0 <= row < len(self.labels) else str(list(item))


def study_space(folder: StudyFolder, items: ServeItems | None = None) -> StudySpace:
    """The study's :class:`StudySpace`: the unit cube is a session file's (the first that reads),
    else the one a new session of these items gets (:class:`~torchpref.sessions.settings.SessionSettings`)."""
    items = items if items is not None else study_items(folder)
    X = torch.as_tensor(items.X, dtype=torch.float64)
    unit = None
    for f in sorted(folder.sessions.glob("*.session.jsonl")):
        try:
            unit = read_session(f).transform(X)
            break
        except (OSError, ValueError):
            continue
    if unit is None:  # no session yet: the cube a new session of these items gets
        unit = SessionSettings.validated(X, None, 0, 1, None, None).transform(X)
    labels = list(items.labels) if items.labels is not None else [f"#{i + 1}" for i in range(X.shape[0])]
    return StudySpace(X, unit, labels, list(items.names))
