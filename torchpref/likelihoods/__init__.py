"""GPyTorch likelihoods of the answers: comparisons, bounded ratings, ordinal levels and ties."""

from __future__ import annotations

from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood, StrictPreferenceLikelihood, TieLikelihood
from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.likelihoods.person import LapseProbitLikelihood, PersonRatingLikelihood

__all__ = [
    'BetaRatingLikelihood',
    'LapseProbitLikelihood',
    'OrdinalRatingLikelihood',
    'PairwiseProbitLikelihood',
    'PersonRatingLikelihood',
    'StrictPreferenceLikelihood',
    'TieLikelihood',
]
