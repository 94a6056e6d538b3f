"""Simulated people, the hidden utilities they answer from, and the metrics that score a model."""

from __future__ import annotations

from torchpref.simulation.metrics import (
    wrms,
    wrms_authors,
    true_positives,
    error_on_best,
    rating_from_latent,
    expected_rating,
)
from torchpref.simulation.users import User, SimulatedUser, LikertUser, sample_beta, sample_log_gamma, RATING_CLAMP
from torchpref.simulation.raters import EffortModel, RaterProfile, RealisticUser
from torchpref.simulation.utility_functions import (
    WaveFunction,
    evaluation_grid,
    GaussianBumps,
    Plateau,
    RescaledUtility,
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
