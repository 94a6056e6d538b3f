"""The Laplace approximation: likelihood terms, Newton's mode, padding, numerics and precision."""

from __future__ import annotations

from torchpref.inference.laplace import LaplaceConvergenceWarning
from torchpref.inference.numerics import JitterWarning, LaplaceNumericalError, NotPSDError

__all__ = ['JitterWarning', 'LaplaceConvergenceWarning', 'LaplaceNumericalError', 'NotPSDError']
