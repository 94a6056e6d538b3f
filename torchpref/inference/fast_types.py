r"""What crosses the boundary of the compiled path (:mod:`torchpref.inference._compiled`,
:mod:`torchpref.inference._compiled_fit`): named structures of NumPy arrays and numbers, and the
codes the compiled calls return, without numba (so that deciding whether the path applies imports
nothing heavy).

Every structure is built by its function here (:func:`answers`, :func:`prior`, :func:`fit_spec`,
:func:`fit_state`), which fixes each field's type (int64 and float64 C-contiguous writable arrays,
Python ints and floats): numba compiles one version per combination of argument types, and the
build (:mod:`torchpref.inference.fast_cache`) compiles exactly the combination these give, so no call
ever meets the compiler.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

#: status codes of the compiled calls (:mod:`torchpref.inference._compiled`; 6 is internal there);
#: a fit's :data:`STALLED`: stopped at its last good point where no line search finds a step (SciPy's
#: ``ABNORMAL_TERMINATION_IN_LNSRCH``); :data:`WEAK_STEP`: a line search's step with sufficient
#: decrease but not the curvature condition (internal to the fit)
OK, NOT_PD, NOT_FINITE, NOT_CONVERGED, LINE_SEARCH_FAILED, FISHER = 0, 1, 2, 3, 4, 5
STALLED, WEAK_STEP = 7, 8
#: the statuses of a result the caller uses
SUCCESS = (OK, STALLED)
#: the statuses' names, for messages and reports
STATUS_NAMES = {
    OK: "ok",
    NOT_PD: "not positive definite",
    NOT_FINITE: "not finite",
    NOT_CONVERGED: "not converged",
    LINE_SEARCH_FAILED: "line search failed",
    FISHER: "Fisher weights at the mode",
    STALLED: "stalled: no line search step from the last good point",
    WEAK_STEP: "weak step",
}
#: the likelihood of an :class:`Answers` row
PROBIT, BETA, INTERVAL, LAPSE = 0, 1, 2, 3
#: kernel kinds: GPyTorch's RBF, and Matern with nu = 1/2, 3/2, 5/2
RBF, MATERN12, MATERN32, MATERN52 = 0, 1, 2, 3
#: prior kinds on a positive hyperparameter
NO_PRIOR, LOG_NORMAL, GAMMA = 0, 1, 2
#: constraint transforms of a raw parameter: GPyTorch's ``GreaterThan`` (softplus) and ``Interval`` (sigmoid)
SOFTPLUS, SIGMOID = 0, 1


class Answers(NamedTuple):
    """One problem's observations, one row each: the predictor of row ``k`` is
    ``eta_k = f[first_k] - f[second_k] + offset_k`` (``second_k = -1``: an item's own, ``f[first_k] +
    offset_k``), scored by its kind ``kind_k``:

    * :data:`PROBIT`: ``Phi(eta / scale_k)`` (eq. 3, ``scale = sqrt 2 sigma_R``; a strict choice
      where ties were offered is ``Phi((eta - tau) / scale)``: its offset carries ``-tau``);
    * :data:`BETA`: the rating ``target_k ~ Beta(nu mu, nu (1 - mu))``, ``mu = Phi(eta / c)`` with
      ``c = rating_scale`` (``sqrt 2 sigma_B``; a person's gain ``g`` and offset ``b`` divide it by
      ``g`` and add ``b / g`` to the offset) and ``nu = rating_precision``;
    * :data:`INTERVAL`: ``Phi((upper_k - eta) / scale_k) - Phi((lower_k - eta) / scale_k)`` (a tie,
      ``(-tau, tau)``; an ordinal level ``k``, ``(c_{k-1}, c_k)``; either bound may be infinite);
    * :data:`LAPSE`: ``lapse_k / 2 + (1 - lapse_k) Phi(eta / scale_k)`` (a comparison with lapses).

    Unused columns of a row hold ``0`` (``scale``, ``lapse``, ``target``) or ``-inf`` / ``inf``
    (``lower`` / ``upper``)."""

    first: np.ndarray
    second: np.ndarray
    kind: np.ndarray
    offset: np.ndarray
    target: np.ndarray
    scale: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    lapse: np.ndarray
    rating_scale: float
    rating_precision: float


class Prior(NamedTuple):
    """A LogNormal(``p1``, ``p2``) or Gamma(concentration ``p1``, rate ``p2``) prior on a positive
    hyperparameter (``kind``: :data:`NO_PRIOR`, :data:`LOG_NORMAL`, :data:`GAMMA`), whose constant
    part is ``const`` (computed by the prior itself, in its own dtype)."""

    kind: int
    p1: float
    p2: float
    const: float


class FitSpec(NamedTuple):
    """What the raw parameters ``x`` of a fit are: the lengthscales are ``softplus(x[ls_start :
    ls_start + ls_count]) + ls_lower`` (one shared value when ``ls_count = 1``), the outputscale
    ``softplus(x[os_index]) + os_lower`` (``fixed_outputscale`` where ``os_index < 0``), of a
    kernel of kind ``kernel`` (:data:`RBF`, ...), each with its prior; and, where ``nu_index >= 0``,
    the Beta ratings' precision ``nu`` (:data:`SOFTPLUS`: ``softplus(x[nu_index]) + nu_lower``;
    :data:`SIGMOID`: GPyTorch's ``Interval``, ``nu_lower + (nu_upper - nu_lower) sigmoid(x[nu_index])``)
    with its prior (where ``nu_index < 0`` the answers' own precision, fixed)."""

    kernel: int
    ls_start: int
    ls_count: int
    ls_lower: float
    ls_prior: Prior
    os_index: int
    os_lower: float
    os_prior: Prior
    fixed_outputscale: float
    nu_index: int
    nu_transform: int
    nu_lower: float
    nu_upper: float
    nu_prior: Prior


class FitState(NamedTuple):
    """Buffers each successful fit evaluation overwrites: the mode ``f`` (``n``; also the next
    evaluation's warm start), whitened ``a``, ``L`` with ``L L^T = K + jitter I``, ``B``'s factor
    ``M``, the weights ``w`` of the answers, ``jitter`` and Newton's ``iterations`` (one value each)."""

    f: np.ndarray
    a: np.ndarray
    L: np.ndarray
    M: np.ndarray
    w: np.ndarray
    jitter: np.ndarray
    iterations: np.ndarray


class NewtonResult(NamedTuple):
    """What :func:`~torchpref.inference._compiled.newton` returns: the whitened mode ``a``, ``B``'s
    Cholesky factor ``M`` there, the answers' weights, Newton's iterations, the status and the last
    Newton decrement."""

    a: np.ndarray
    M: np.ndarray
    weights: np.ndarray
    iterations: int
    status: int
    decrement: float


class LossResult(NamedTuple):
    """What :func:`~torchpref.inference._compiled_fit.fit_loss` returns: BoTorch's loss, its
    gradient in the raw parameters and the status."""

    loss: float
    grad: np.ndarray
    status: int


class FitResult(NamedTuple):
    """What :func:`~torchpref.inference._compiled_fit.fit_lbfgs` returns: the raw parameters, the
    loss there, the status (:data:`OK` or :data:`STALLED` on success), L-BFGS's iterations and the
    loss evaluations."""

    x: np.ndarray
    loss: float
    status: int
    iterations: int
    evaluations: int


#: each entry point's result, by name (:func:`torchpref.inference.fast_path.call` wraps the tuples)
RESULTS: dict[str, type] = {"newton": NewtonResult, "fit_loss": LossResult, "fit_lbfgs": FitResult}


def floats(x: npt.ArrayLike, ndim: int = 1) -> np.ndarray:
    """``x`` as a float64 C-contiguous writable array of ``ndim`` dimensions (a copy only if need be)."""
    out = np.require(x, dtype=np.float64, requirements=("C", "W", "A"))
    if out.ndim != ndim:
        raise ValueError(f"expected a {ndim}-d array, got shape {out.shape}")
    return out


def ints(x: npt.ArrayLike) -> np.ndarray:
    """``x`` as an int64 C-contiguous writable vector."""
    out = np.require(x, dtype=np.int64, requirements=("C", "W", "A"))
    if out.ndim != 1:
        raise ValueError(f"expected a vector, got shape {out.shape}")
    return out


def answers(
    first: npt.ArrayLike,
    second: npt.ArrayLike,
    kind: npt.ArrayLike,
    offset: npt.ArrayLike,
    target: npt.ArrayLike,
    scale: npt.ArrayLike,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    lapse: npt.ArrayLike,
    rating_scale: float,
    rating_precision: float,
) -> Answers:
    """An :class:`Answers` with its fields' types fixed."""
    return Answers(
        ints(first),
        ints(second),
        ints(kind),
        floats(offset),
        floats(target),
        floats(scale),
        floats(lower),
        floats(upper),
        floats(lapse),
        float(rating_scale),
        float(rating_precision),
    )


def prior(kind: int, p1: float, p2: float, const: float) -> Prior:
    """A :class:`Prior` with its fields' types fixed."""
    return Prior(int(kind), float(p1), float(p2), float(const))


def fit_spec(
    kernel: int,
    ls_start: int,
    ls_count: int,
    ls_lower: float,
    ls_prior: tuple,
    os_index: int,
    os_lower: float,
    os_prior: tuple,
    fixed_outputscale: float,
    nu_index: int = -1,
    nu_transform: int = SOFTPLUS,
    nu_lower: float = 0.0,
    nu_upper: float = 0.0,
    nu_prior: tuple = (NO_PRIOR, 0.0, 0.0, 0.0),
) -> FitSpec:
    """A :class:`FitSpec` with its fields' types fixed (by default the ratings' precision fixed)."""
    return FitSpec(
        int(kernel),
        int(ls_start),
        int(ls_count),
        float(ls_lower),
        prior(*ls_prior),
        int(os_index),
        float(os_lower),
        prior(*os_prior),
        float(fixed_outputscale),
        int(nu_index),
        int(nu_transform),
        float(nu_lower),
        float(nu_upper),
        prior(*nu_prior),
    )


def fit_state(f0: np.ndarray, m: int) -> FitState:
    """Fresh buffers for a fit of ``n = len(f0)`` items and ``m`` answers, warm-starting from ``f0``."""
    n = f0.shape[0]
    zeros = np.zeros
    return FitState(floats(f0.copy()), zeros(n), zeros((n, n)), zeros((n, n)), zeros(m), zeros(1), ints(zeros(1)))
