r"""The names of the solver's shapes and factors, used in the annotations of :mod:`torchpref.inference`.

Shapes (every tensor of the solver is batch-first):

* ``b``: the number of independent problems in a batch (a single problem is ``b = 1``);
* ``n``: the items of a problem (padded to the largest problem of the batch);
* ``m``: the observations of one likelihood term, ``c`` the items each predictor combines
  (``c = 2`` for a comparison ``f_i - f_j``, ``c = 1`` for a rating of ``f_i``);
* ``t x q``: ``t`` test sets of ``q`` points each (the predictive).

Factors, one name each:

* ``K``: the kernel matrix of the items, ``b x n x n``;
* ``L``: the prior's factor, the lower Cholesky factor of ``K + jitter I``;
* ``W``: the negative Hessian of the log-likelihood in ``f`` (never formed densely on the solver's path);
* ``B = I + L^T W L``: Newton's matrix in the whitened coordinates ``a`` (``f = L a``), and ``M``
  its lower Cholesky factor (:attr:`~torchpref.inference.laplace.ModeResult.M`,
  :attr:`~torchpref.inference.newton.Factor.M`);
* ``V = M^{-1} L^T``: the posterior covariance is ``Sigma = (K^{-1} + W)^{-1} = V^T V``.

The aliases are ``Tensor`` to a type checker; the string is the shape, for the reader (the
convention of ``jaxtyping``'s ``Float[Tensor, "b n"]``, without the dependency).
"""

from __future__ import annotations

from typing import Annotated

from torch import Tensor

__all__ = ["PerProblem", "Latent", "Matrices", "TermValues", "TermIndex", "ProblemMask"]

PerProblem = Annotated[Tensor, "b"]
"""One value per problem (a log evidence, a decrement)."""

ProblemMask = Annotated[Tensor, "b"]
"""One bool per problem (converged, Fisher fallback)."""

Latent = Annotated[Tensor, "b n"]
"""A vector over the items per problem: ``f``, ``a``, a gradient."""

Matrices = Annotated[Tensor, "b n n"]
"""A square matrix or lower Cholesky factor per problem: ``K``, ``L``, ``M``."""

TermValues = Annotated[Tensor, "b m"]
"""One value per observation of a term: predictors ``eta``, targets, weights ``w``, masks."""

TermIndex = Annotated[Tensor, "b m c"]
"""The items each predictor of a term combines (long)."""
