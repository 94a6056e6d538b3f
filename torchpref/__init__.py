r"""torchpref: learn what a person wants from ratings and rankings.

A Gaussian-process utility over the options' objective space, fitted by Laplace inference from
comparisons (eq. 3) and bounded ratings (eqs. 4-7) at once, as a BoTorch ``Model``.
"""

from torchpref.data import PreferenceData, best_of_m, likert_to_unit, prepare_ratings, unit_to_likert
from torchpref.laplace import LaplaceConvergenceWarning
from torchpref.likelihoods import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.models import LaplaceMarginalLogLikelihood, PreferenceGP, default_covar_module
from torchpref.numerics import NotPSDError
from torchpref.version import __version__

__all__ = [
    "BetaRatingLikelihood",
    "LaplaceConvergenceWarning",
    "LaplaceMarginalLogLikelihood",
    "NotPSDError",
    "PairwiseProbitLikelihood",
    "PreferenceData",
    "PreferenceGP",
    "__version__",
    "best_of_m",
    "default_covar_module",
    "likert_to_unit",
    "prepare_ratings",
    "unit_to_likert",
]
