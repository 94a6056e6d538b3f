"""Items, comparisons, ratings and the questions asked: what an answer becomes."""

from __future__ import annotations

from torchpref.data.features import ID_NAMES, FeaturesError, printable, read_features_csv
from torchpref.data.preference_data import (
    PreferenceData,
    RatingBoundaryWarning,
    best_of_m,
    best_of_m_with_ties,
    likert_to_unit,
    prepare_ratings,
    unit_to_likert,
)
from torchpref.data.queries import BoxCandidates, FinitePool, RankingQuery, RatingQuery

__all__ = [
    'BoxCandidates',
    'FeaturesError',
    'FinitePool',
    'ID_NAMES',
    'PreferenceData',
    'RankingQuery',
    'RatingBoundaryWarning',
    'RatingQuery',
    'best_of_m',
    'best_of_m_with_ties',
    'likert_to_unit',
    'prepare_ratings',
    'printable',
    'read_features_csv',
    'unit_to_likert',
]
