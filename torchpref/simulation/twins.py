r"""Twins of a population's people: simulated people whose hidden utility is a new person of a
fitted population, but who are *not* the learner's own model.

A population (:func:`torchpref.fit_population`) says what a new person's utility looks like:
``f = m + g`` with the population's mean ``m`` (its posterior given everyone's answers,
``E[m | D]`` and ``Cov[m | D]``) and a deviation ``g ~ GP(0, k_g)``. A learner that starts a
person from ``pop.person_model(...)`` assumes exactly that. A twin departs from it where real
people would:

* **the deviation is drawn with another kernel** (:func:`twin_deviation_covariance`): a Matérn
  kernel of smoothness ``nu`` 1/2 or 3/2 (rougher than the learner's RBF), each lengthscale the
  population's times a factor ``c_j ~ logU(1/2, 2)`` and the between-person spread ``s^2``
  times ``a ~ logU(1/2, 2)``; the mean part is a draw of ``m`` from the population's posterior
  (not its posterior mean);
* **answers are a realistic person's** (:class:`~torchpref.simulation.raters.RealisticUser`,
  :meth:`~torchpref.simulation.raters.RaterProfile.typical`): lapses, a rating offset, gain, drift
  and partial use of the scale from the ranges docs/suite.md cites, ratings on a Likert scale.

:func:`draw_twin` returns the twin's utility at a finite pool of items (the design space the
selectors choose from) as a :class:`PoolUtility` (a callable over rows of the pool) and the
settings drawn, so a results file can record each twin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchpref.population.model import Population

__all__ = [
    "PoolUtility",
    "TwinDraw",
    "draw_twin",
    "matern_covariance",
    "population_mean_posterior",
    "twin_deviation_covariance",
]

#: the Matérn smoothness of a twin's deviation: one of these, uniformly (the learner's RBF is nu = inf)
TWIN_NUS = (0.5, 1.5)
#: a twin's lengthscales and spread are the population's times ``exp(U(-log 2, log 2))`` each
TWIN_FACTOR = 2.0


def matern_covariance(X: Tensor, lengthscale: Tensor, outputscale: float, nu: float) -> Tensor:
    r"""The ``N x N`` Matérn covariance ``s^2 k_nu(r)`` of the rows of ``X`` (``N x d``), ``r`` the
    distance scaled by ``lengthscale`` (``d`` values): ``nu = 1/2``: ``e^{-r}``; ``3/2``:
    ``(1 + sqrt 3 r) e^{-sqrt 3 r}``; ``5/2``: ``(1 + sqrt 5 r + 5 r^2 / 3) e^{-sqrt 5 r}``.

    Raises:
        ValueError: another ``nu``, a lengthscale that is not positive, or shapes that do not match.
    """
    if nu not in (0.5, 1.5, 2.5):
        raise ValueError(f"nu must be 0.5, 1.5 or 2.5, got {nu!r}.")
    ls = torch.as_tensor(lengthscale, dtype=X.dtype).reshape(-1)
    if X.dim() != 2 or ls.numel() not in (1, X.shape[-1]) or not bool((ls > 0).all()):
        raise ValueError(f"need X of N x d and d positive lengthscales, got {tuple(X.shape)} and {ls.tolist()}.")
    Z = X / ls
    r = torch.cdist(Z, Z).clamp_min(0)
    if nu == 0.5:
        k = torch.exp(-r)
    elif nu == 1.5:
        k = (1 + math.sqrt(3) * r) * torch.exp(-math.sqrt(3) * r)
    else:
        k = (1 + math.sqrt(5) * r + 5 * r.square() / 3) * torch.exp(-math.sqrt(5) * r)
    return float(outputscale) * k


@dataclass(frozen=True)
class TwinDraw:
    """What was drawn for one twin: its deviation kernel (``nu``, lengthscale and spread factors)."""

    nu: float
    lengthscale_factors: tuple[float, ...]
    spread_factor: float


def _log_uniform(n: int, generator: torch.Generator) -> Tensor:
    u = torch.rand(n, generator=generator, dtype=torch.float64)
    return torch.exp((2 * u - 1) * math.log(TWIN_FACTOR))


def twin_deviation_covariance(pop: Population, X: Tensor, generator: torch.Generator) -> tuple[Tensor, TwinDraw]:
    r"""A twin's deviation covariance at ``X`` (``N x d``) and what was drawn (module notes): a
    Matérn of ``nu`` in :data:`TWIN_NUS`, the population's deviation lengthscales times
    ``logU(1/2, 2)`` factors (one per feature), its spread ``s^2`` times a ``logU(1/2, 2)`` factor."""
    base = getattr(pop.k_g, "base_kernel", pop.k_g)
    ls = getattr(base, "lengthscale", None)
    if ls is None:
        raise ValueError(f"the population's deviation kernel has no lengthscale to vary: {type(base).__name__}.")
    ls = ls.detach().to(X).reshape(-1)
    if ls.numel() == 1:
        ls = ls.expand(X.shape[-1])
    nu = TWIN_NUS[int(torch.randint(len(TWIN_NUS), (1,), generator=generator))]
    factors = _log_uniform(X.shape[-1], generator)
    spread = _log_uniform(1, generator)
    K = matern_covariance(X, ls * factors.to(X), pop.spread * float(spread), nu)
    return K, TwinDraw(nu, tuple(factors.tolist()), float(spread))


def _sample(mean: Tensor, cov: Tensor, generator: torch.Generator) -> Tensor:
    """One draw of ``N(mean, cov)``, with a relative jitter as large as the Cholesky needs."""
    cov = 0.5 * (cov + cov.mT)
    scale = cov.diagonal().mean().clamp_min(1e-12)
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype)
    for k in range(-10, -1):
        L, info = torch.linalg.cholesky_ex(cov + (10.0**k) * scale * eye)
        if int(info) == 0:
            return mean + L @ torch.randn(cov.shape[-1], generator=generator, dtype=cov.dtype)
    raise ValueError("a twin's covariance is not positive definite even with a jitter of 1 % of its scale.")


def population_mean_posterior(pop: Population, X: Tensor) -> tuple[Tensor, Tensor]:
    r"""``E[m(X) | D]`` and ``Cov[m(X) | D]`` (``N``, ``N x N``): a new person's prior at ``X``
    (:meth:`~torchpref.Population.person_model`, mean and covariance ``k_g + Cov[m | D]``) less the
    deviation's ``k_g(X, X)``."""
    with torch.no_grad():
        prior = pop.person_model(X).posterior(X).distribution
        mean = prior.mean.reshape(-1)
        cov = prior.covariance_matrix.reshape(X.shape[0], X.shape[0]) - pop.k_g(X).to_dense()
    return mean, 0.5 * (cov + cov.mT)


def draw_twin(
    pop: Population, X: Tensor, generator: torch.Generator, prior: tuple[Tensor, Tensor] | None = None
) -> tuple[PoolUtility, TwinDraw]:
    r"""A twin's utility over the pool ``X`` (``N x d``, distinct rows): a draw of the population's
    mean ``m`` from its posterior plus a deviation from :func:`twin_deviation_covariance`.
    ``prior``: :func:`population_mean_posterior` at ``X``, if already computed (many twins of one pool)."""
    mean, cov_m = population_mean_posterior(pop, X) if prior is None else prior
    K, draw = twin_deviation_covariance(pop, X, generator)
    m = _sample(mean, cov_m, generator)
    g = _sample(torch.zeros_like(mean), K, generator)
    return PoolUtility(X, m + g), draw


class PoolUtility:
    r"""A utility known at a finite pool's items: ``f(x)`` for rows ``x`` of the pool ``X``.

    Args:
        X: ``N x d`` distinct items.
        f: ``N`` utilities.

    Raises:
        ValueError (on call): an item that is not a row of the pool (by more than ``1e-9``).
    """

    def __init__(self, X: Tensor, f: Tensor):
        if X.dim() != 2 or f.shape != X.shape[:1] or not bool(torch.isfinite(f).all()):
            raise ValueError(f"need N x d items and N finite utilities, got {tuple(X.shape)} and {tuple(f.shape)}.")
        self.X, self.f = X, f

    def __call__(self, Z: Tensor) -> Tensor:
        Z = torch.as_tensor(Z, dtype=self.X.dtype)
        flat = Z.reshape(-1, self.X.shape[-1])
        dist, rows = (flat.unsqueeze(-2) - self.X).abs().amax(-1).min(-1)  # exact: no matrix-product rounding
        if bool((dist > 1e-9).any()):
            bad = flat[dist > 1e-9][0].tolist()
            raise ValueError(f"item {bad} is not in the twin's pool.")
        return self.f[rows].reshape(Z.shape[:-1])
