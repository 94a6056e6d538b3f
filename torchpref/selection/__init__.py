"""Selectors that choose the next question, and the active-learning loop."""

from __future__ import annotations

from torchpref.selection.active import History, QueryRecord, fit_model, run_active_learning, run_active_learning_batch
from torchpref.selection.defaults import default_selector
from torchpref.selection.strategies import (
    UCBC,
    InformationPerEffort,
    RandomMixed,
    RandomRankings,
    RandomRatings,
    UCBRatings,
)
from torchpref.selection.top_profile import ProfileVariancePerEffort, profile_variance_reduction, top_profile
from torchpref.selection.variance_reduction import VariancePerEffort

__all__ = [
    'History',
    'InformationPerEffort',
    'ProfileVariancePerEffort',
    'QueryRecord',
    'RandomMixed',
    'RandomRankings',
    'RandomRatings',
    'UCBC',
    'UCBRatings',
    'VariancePerEffort',
    'default_selector',
    'fit_model',
    'profile_variance_reduction',
    'run_active_learning',
    'run_active_learning_batch',
    'top_profile',
]
