r"""torchpref: learn what a person wants from ratings and rankings.

A Gaussian-process utility over the options' objective space, fitted by Laplace inference from
comparisons (eq. 3) and bounded ratings (eqs. 4-7) at once, as a BoTorch ``Model``.

The names below are imported on first use (PEP 562), so ``import torchpref`` is instant and the
command line starts (``--help``, ``--version``, argument errors, Ctrl-C) before torch is loaded.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from torchpref.version import __version__


def _record_sources_for_a_measurement() -> None:
    """Only where ``TORCHPREF_STAMP_SOURCES`` is set (a benchmark recording what the processes it
    started ran, for its results' stamp: ``torchpref.experiments.stamp``); nothing otherwise."""
    import os

    if os.environ.get("TORCHPREF_STAMP_SOURCES"):
        from torchpref.experiments.stamp import record_at_exit

        record_at_exit()


_record_sources_for_a_measurement()

if TYPE_CHECKING:  # the same names, for type checkers and IDEs
    from torchpref.acquisition.functions import QueryInformation, QueryUCB, latent_ucb
    from torchpref.data.preference_data import (
        PreferenceData,
        RatingBoundaryWarning,
        best_of_m,
        best_of_m_with_ties,
        likert_to_unit,
        prepare_ratings,
        unit_to_likert,
    )
    from torchpref.data.queries import BoxCandidates, FinitePool, InvalidAnswer, RankingQuery, RatingQuery
    from torchpref.frontends.serve import serve
    from torchpref.inference.fast_path import fast_path, set_fast_path
    from torchpref.inference.laplace import LaplaceConvergenceWarning
    from torchpref.inference.numerics import JitterWarning, LaplaceNumericalError, NotPSDError
    from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood, StrictPreferenceLikelihood, TieLikelihood
    from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood, PairwiseProbitLikelihood
    from torchpref.likelihoods.person import LapseProbitLikelihood, PersonRatingLikelihood
    from torchpref.models.batch import BatchedPreferenceGP
    from torchpref.models.calibration import calibrate_person, fit_person
    from torchpref.models.checkpoint import CheckpointError, load_model, model_checkpoint, save_model
    from torchpref.models.defaults import LikelihoodSettings
    from torchpref.models.pairwise_interface import TrainDataMismatchError, UnsupportedLikelihoodError
    from torchpref.models.preference_gp import (
        PAPER_FIG4_SETTINGS,
        LaplaceMarginalLogLikelihood,
        PreferenceGP,
        default_covar_module,
    )
    from torchpref.population.fit import fit_population
    from torchpref.population.io import load_population, save_population
    from torchpref.population.model import Population
    from torchpref.selection.active import (
        History,
        QueryRecord,
        fit_model,
        run_active_learning,
        run_active_learning_batch,
    )
    from torchpref.selection.defaults import default_selector
    from torchpref.selection.strategies import (
        UCBC,
        InformationPerEffort,
        RandomMixed,
        RandomRankings,
        RandomRatings,
        UCBRatings,
    )
    from torchpref.selection.top_profile import ProfileVariancePerEffort
    from torchpref.selection.variance_reduction import VariancePerEffort
    from torchpref.sessions.session import PreferenceSession
    from torchpref.simulation.metrics import (
        error_on_best,
        expected_rating,
        rating_from_latent,
        true_positives,
        wrms,
        wrms_authors,
    )
    from torchpref.simulation.raters import EffortModel, RaterProfile, RealisticUser
    from torchpref.simulation.users import SimulatedUser, User
    from torchpref.simulation.utility_functions import WaveFunction, evaluation_grid

# public name -> the torchpref module that defines it
_EXPORTS = {
    "BatchedPreferenceGP": "models.batch",
    "CheckpointError": "models.checkpoint",
    "InvalidAnswer": "data.queries",
    "load_model": "models.checkpoint",
    "model_checkpoint": "models.checkpoint",
    "save_model": "models.checkpoint",
    "best_of_m": "data.preference_data",
    "best_of_m_with_ties": "data.preference_data",
    "BetaRatingLikelihood": "likelihoods.pairwise_beta",
    "BoxCandidates": "data.queries",
    "calibrate_person": "models.calibration",
    "EffortModel": "simulation.raters",
    "fit_person": "models.calibration",
    "LapseProbitLikelihood": "likelihoods.person",
    "PersonRatingLikelihood": "likelihoods.person",
    "RaterProfile": "simulation.raters",
    "RealisticUser": "simulation.raters",
    "default_covar_module": "models.preference_gp",
    "error_on_best": "simulation.metrics",
    "evaluation_grid": "simulation.utility_functions",
    "expected_rating": "simulation.metrics",
    "fast_path": "inference.fast_path",
    "set_fast_path": "inference.fast_path",
    "FinitePool": "data.queries",
    "fit_model": "selection.active",
    "History": "selection.active",
    "InformationPerEffort": "selection.strategies",
    "JitterWarning": "inference.numerics",
    "LaplaceConvergenceWarning": "inference.laplace",
    "LaplaceMarginalLogLikelihood": "models.preference_gp",
    "LikelihoodSettings": "models.defaults",
    "latent_ucb": "acquisition.functions",
    "likert_to_unit": "data.preference_data",
    "NotPSDError": "inference.numerics",
    "LaplaceNumericalError": "inference.numerics",
    "OrdinalRatingLikelihood": "likelihoods.ordinal",
    "PAPER_FIG4_SETTINGS": "models.preference_gp",
    "TrainDataMismatchError": "models.pairwise_interface",
    "UnsupportedLikelihoodError": "models.pairwise_interface",
    "PairwiseProbitLikelihood": "likelihoods.pairwise_beta",
    "PreferenceData": "data.preference_data",
    "PreferenceGP": "models.preference_gp",
    "PreferenceSession": "sessions.session",
    "Population": "population.model",
    "fit_population": "population.fit",
    "save_population": "population.io",
    "load_population": "population.io",
    "ProfileVariancePerEffort": "selection.top_profile",
    "prepare_ratings": "data.preference_data",
    "QueryInformation": "acquisition.functions",
    "QueryRecord": "selection.active",
    "QueryUCB": "acquisition.functions",
    "RandomMixed": "selection.strategies",
    "RandomRankings": "selection.strategies",
    "RandomRatings": "selection.strategies",
    "RankingQuery": "data.queries",
    "rating_from_latent": "simulation.metrics",
    "RatingBoundaryWarning": "data.preference_data",
    "RatingQuery": "data.queries",
    "run_active_learning": "selection.active",
    "run_active_learning_batch": "selection.active",
    "serve": "frontends.serve",
    "SimulatedUser": "simulation.users",
    "StrictPreferenceLikelihood": "likelihoods.ordinal",
    "TieLikelihood": "likelihoods.ordinal",
    "true_positives": "simulation.metrics",
    "UCBC": "selection.strategies",
    "default_selector": "selection.defaults",
    "UCBRatings": "selection.strategies",
    "unit_to_likert": "data.preference_data",
    "User": "simulation.users",
    "VariancePerEffort": "selection.variance_reduction",
    "WaveFunction": "simulation.utility_functions",
    "wrms": "simulation.metrics",
    "wrms_authors": "simulation.metrics",
}

__all__ = ["__version__"]
__all__ += sorted(_EXPORTS)  # noqa: PLE0605 (the lazy names, listed once above)


def __getattr__(name: str) -> object:
    module = _EXPORTS.get(name)
    if module is None:
        try:  # a submodule, as ``torchpref.sessions.session`` after ``import torchpref``
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
