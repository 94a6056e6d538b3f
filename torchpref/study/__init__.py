r"""A preference study run end to end (``torchpref study``, docs/study.md).

Participants answer in the browser exactly as with ``torchpref serve``; everything is kept in one
study folder (:mod:`~torchpref.study.folder`); when a participant finishes, the population is
refitted on every finished participant in a separate process (:mod:`~torchpref.study.refit`) and
the next participant starts from it; the experimenter has a page of their own
(:mod:`~torchpref.study.page`), exports (:mod:`~torchpref.study.export`) and a report
(:mod:`~torchpref.study.report`).
"""

from __future__ import annotations

from torchpref.study.create import create_study
from torchpref.study.folder import StudyFolder

__all__ = ["StudyFolder", "create_study"]
