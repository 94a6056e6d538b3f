"""GPyTorch likelihoods of the answers: comparisons, bounded ratings, ordinal levels and ties."""

from __future__ import annotations

from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood, StrictPreferenceLikelihood, TieLikelihood

__all__ = [
    'BetaRatingLikelihood',
    'OrdinalRatingLikelihood',
    'PairwiseProbitLikelihood',
    'StrictPreferenceLikelihood',
    'TieLikelihood',
]
