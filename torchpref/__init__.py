r"""torchpref: learn what a person wants from ratings and rankings.

A Gaussian-process utility over the options' objective space, fitted by Laplace inference from
comparisons (eq. 3) and bounded ratings (eqs. 4-7) at once, as a BoTorch ``Model``.

The names below are imported on first use (PEP 562), so ``import torchpref`` is instant and the
command line starts (``--help``, ``--version``, argument errors, Ctrl-C) before torch is loaded.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from torchpref.version import __version__

if TYPE_CHECKING:  # the same names, for type checkers and IDEs
    from torchpref.acquisition import QueryInformation, QueryUCB, latent_ucb
    from torchpref.active import History, QueryRecord, fit_model, run_active_learning, run_active_learning_batch
    from torchpref.batch import BatchedPreferenceGP
    from torchpref.checkpoint import CheckpointError, load_model, model_checkpoint, save_model
    from torchpref.data import (
        PreferenceData,
        RatingBoundaryWarning,
        best_of_m,
        best_of_m_with_ties,
        likert_to_unit,
        prepare_ratings,
        unit_to_likert,
    )
    from torchpref.botorch_api import TrainDataMismatchError
    from torchpref.laplace import LaplaceConvergenceWarning
    from torchpref.likelihoods import BetaRatingLikelihood, PairwiseProbitLikelihood
    from torchpref.metrics import error_on_best, expected_rating, rating_from_latent, true_positives, wrms, wrms_authors
    from torchpref.models import PAPER_FIG4_SETTINGS, LaplaceMarginalLogLikelihood, PreferenceGP, default_covar_module
    from torchpref.numerics import JitterWarning, NotPSDError
    from torchpref.ordinal import OrdinalRatingLikelihood, StrictPreferenceLikelihood, TieLikelihood
    from torchpref.queries import BoxCandidates, FinitePool, RankingQuery, RatingQuery
    from torchpref.session import PreferenceSession
    from torchpref.strategies import UCBC, InformationPerEffort, RandomMixed, RandomRankings, RandomRatings, UCBRatings
    from torchpref.top_profile import ProfileVariancePerEffort
    from torchpref.utility_functions import WaveFunction, evaluation_grid
    from torchpref.variance_reduction import VariancePerEffort
    from torchpref.users import SimulatedUser, User

# public name -> the torchpref module that defines it
_EXPORTS = {
    "BatchedPreferenceGP": "batch",
    "CheckpointError": "checkpoint",
    "load_model": "checkpoint",
    "model_checkpoint": "checkpoint",
    "save_model": "checkpoint",
    "best_of_m": "data",
    "best_of_m_with_ties": "data",
    "BetaRatingLikelihood": "likelihoods",
    "BoxCandidates": "queries",
    "default_covar_module": "models",
    "error_on_best": "metrics",
    "evaluation_grid": "utility_functions",
    "expected_rating": "metrics",
    "FinitePool": "queries",
    "fit_model": "active",
    "History": "active",
    "InformationPerEffort": "strategies",
    "JitterWarning": "numerics",
    "LaplaceConvergenceWarning": "laplace",
    "LaplaceMarginalLogLikelihood": "models",
    "latent_ucb": "acquisition",
    "likert_to_unit": "data",
    "NotPSDError": "numerics",
    "OrdinalRatingLikelihood": "ordinal",
    "PAPER_FIG4_SETTINGS": "models",
    "TrainDataMismatchError": "botorch_api",
    "PairwiseProbitLikelihood": "likelihoods",
    "PreferenceData": "data",
    "PreferenceGP": "models",
    "PreferenceSession": "session",
    "ProfileVariancePerEffort": "top_profile",
    "prepare_ratings": "data",
    "QueryInformation": "acquisition",
    "QueryRecord": "active",
    "QueryUCB": "acquisition",
    "RandomMixed": "strategies",
    "RandomRankings": "strategies",
    "RandomRatings": "strategies",
    "RankingQuery": "queries",
    "rating_from_latent": "metrics",
    "RatingBoundaryWarning": "data",
    "RatingQuery": "queries",
    "run_active_learning": "active",
    "run_active_learning_batch": "active",
    "SimulatedUser": "users",
    "StrictPreferenceLikelihood": "ordinal",
    "TieLikelihood": "ordinal",
    "true_positives": "metrics",
    "UCBC": "strategies",
    "UCBRatings": "strategies",
    "unit_to_likert": "data",
    "User": "users",
    "VariancePerEffort": "variance_reduction",
    "WaveFunction": "utility_functions",
    "wrms": "metrics",
    "wrms_authors": "metrics",
}

__all__ = sorted([*_EXPORTS, "__version__"])


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        try:  # a submodule, as ``torchpref.session`` after ``import torchpref``
            return importlib.import_module(f"torchpref.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"torchpref.{name}":
                raise
            raise AttributeError(f"module 'torchpref' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(f"torchpref.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
