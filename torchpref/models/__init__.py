"""PreferenceGP (a BoTorch Model), its MLL, kernels, fantasies, checkpoints and the batched model."""

from __future__ import annotations

from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.calibration import calibrate_person, fit_person
from torchpref.models.checkpoint import CheckpointError, load_model, model_checkpoint, save_model
from torchpref.models.defaults import LikelihoodSettings
from torchpref.models.kernels import FixedRBFKernel, fixed_rbf_kernel
from torchpref.models.pairwise_interface import TrainDataMismatchError, UnsupportedLikelihoodError
from torchpref.models.preference_gp import (
    PAPER_FIG4_SETTINGS,
    LaplaceMarginalLogLikelihood,
    PreferenceGP,
    default_covar_module,
)

__all__ = [
    'BatchedPreferenceGP',
    'CheckpointError',
    'FixedRBFKernel',
    'LaplaceMarginalLogLikelihood',
    'LikelihoodSettings',
    'PAPER_FIG4_SETTINGS',
    'PreferenceGP',
    'TrainDataMismatchError',
    'UnsupportedLikelihoodError',
    'calibrate_person',
    'default_covar_module',
    'fixed_rbf_kernel',
    'fit_person',
    'load_model',
    'model_checkpoint',
    'save_model',
]
