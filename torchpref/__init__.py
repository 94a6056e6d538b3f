r"""torchpref: learn what a person wants from ratings and rankings.

A Gaussian-process utility over the options' objective space, fitted by Laplace inference from
comparisons (eq. 3) and bounded ratings (eqs. 4-7) at once, as a BoTorch ``Model``.
"""

from torchpref.acquisition import QueryInformation, QueryUCB, latent_ucb
from torchpref.active import History, QueryRecord, fit_model, run_active_learning, run_active_learning_batch
from torchpref.batch import BatchedPreferenceGP
from torchpref.data import (
    PreferenceData,
    RatingBoundaryWarning,
    best_of_m,
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
from torchpref.queries import BoxCandidates, FinitePool, RankingQuery, RatingQuery
from torchpref.session import PreferenceSession
from torchpref.strategies import UCBC, InformationPerEffort, RandomMixed, RandomRankings, RandomRatings, UCBRatings
from torchpref.utility_functions import WaveFunction, evaluation_grid
from torchpref.users import SimulatedUser, User
from torchpref.version import __version__

__all__ = [
    "PAPER_FIG4_SETTINGS",
    "BatchedPreferenceGP",
    "BetaRatingLikelihood",
    "BoxCandidates",
    "FinitePool",
    "History",
    "InformationPerEffort",
    "JitterWarning",
    "LaplaceConvergenceWarning",
    "LaplaceMarginalLogLikelihood",
    "NotPSDError",
    "PairwiseProbitLikelihood",
    "PreferenceData",
    "PreferenceGP",
    "PreferenceSession",
    "QueryInformation",
    "QueryRecord",
    "QueryUCB",
    "RandomMixed",
    "RandomRankings",
    "RandomRatings",
    "RankingQuery",
    "RatingBoundaryWarning",
    "RatingQuery",
    "SimulatedUser",
    "TrainDataMismatchError",
    "UCBC",
    "UCBRatings",
    "User",
    "WaveFunction",
    "__version__",
    "best_of_m",
    "default_covar_module",
    "error_on_best",
    "evaluation_grid",
    "expected_rating",
    "fit_model",
    "latent_ucb",
    "likert_to_unit",
    "prepare_ratings",
    "rating_from_latent",
    "run_active_learning",
    "run_active_learning_batch",
    "true_positives",
    "unit_to_likert",
    "wrms",
    "wrms_authors",
]
