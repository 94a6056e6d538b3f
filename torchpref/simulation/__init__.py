"""Simulated people, the hidden utilities they answer from, and the metrics that score a model."""

from __future__ import annotations

from torchpref.simulation.metrics import (
    error_on_best,
    expected_rating,
    rating_from_latent,
    true_positives,
    wrms,
    wrms_authors,
)
from torchpref.simulation.raters import EffortModel, RaterProfile, RealisticUser
from torchpref.simulation.users import RATING_CLAMP, LikertUser, SimulatedUser, User, sample_beta, sample_log_gamma
from torchpref.simulation.utility_functions import (
    GaussianBumps,
    Plateau,
    RescaledUtility,
    WaveFunction,
    evaluation_grid,
)

__all__ = [
    'EffortModel',
    'GaussianBumps',
    'LikertUser',
    'Plateau',
    'RATING_CLAMP',
    'RaterProfile',
    'RealisticUser',
    'RescaledUtility',
    'SimulatedUser',
    'User',
    'WaveFunction',
    'error_on_best',
    'evaluation_grid',
    'expected_rating',
    'rating_from_latent',
    'sample_beta',
    'sample_log_gamma',
    'true_positives',
    'wrms',
    'wrms_authors',
]
