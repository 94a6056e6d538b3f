r"""Observations as likelihood terms on linear predictors of the latent utilities, batch-first.

Every kind of observation the model knows scores one scalar *predictor* per observation,
``eta_k = sum_c coef_c f[index_{k, c}]``: a comparison ``[i, j]`` has ``eta = f_i - f_j``
(``coef = (1, -1)``, eq. 3), a rating of item ``i`` has ``eta = f_i`` (``coef = (1,)``,
eqs. 4-7). A :class:`Term` holds one kind (its likelihood, indices, targets and padding mask)
for a batch of ``b`` independent problems; :class:`Observations` is a tuple of terms. Adding a
likelihood kind (ties, ordinal ratings) is adding a :class:`Term` with its likelihood; the
solver (:mod:`torchpref.inference.laplace`) only ever sees the terms.

With ``d_k`` the row vector of observation ``k`` (``coef`` at its indices), the log-likelihood's
gradient is ``sum_k l'(eta_k) d_k`` and its negative Hessian is ``W = sum_k w_k d_k^T d_k``
(eq. 8) with ``w_k = -l''(eta_k)``; ``W`` is never formed densely on the solver's path.

Padding is exact: a padded observation (``mask`` false) contributes nothing (zero log-likelihood,
gradient and weight). Its index and target must still be values the likelihood can evaluate
(e.g. index 0, rating 0.5), so that no NaN reaches a gradient through ``torch.where``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from torchpref.inference.numerics import lower_t_matmul
from torchpref.inference.shapes import Latent, PerProblem, TermIndex, TermValues

#: Up to this many items ``W`` is multiplied as a dense matrix (formed by one scatter, no sparse
#: pattern to build); above it as a sparse one.
DENSE_W_MAX_ITEMS = 256


class PairLikelihood(Protocol):
    """What a :class:`Term` without targets (comparisons, ties: :func:`pairwise_term`) asks of its
    likelihood: closed-form derivatives in the predictor alone."""

    def derivatives(self, eta: Tensor, /) -> tuple[Tensor, Tensor, Tensor]:
        """``(log p, d log p / d eta, d^2 log p / d eta^2)``, elementwise."""

    def third_derivative(self, eta: Tensor, /) -> Tensor:
        """``d^3 log p / d eta^3``, elementwise."""

    def fisher(self, eta: Tensor, /) -> Tensor:
        """The expected negative second derivative (never negative); needed unless log-concave."""


class ItemLikelihood(Protocol):
    """What a :class:`Term` with targets (ratings: :func:`item_term`) asks of its likelihood:
    closed-form derivatives in the predictor, given each observation's target."""

    def derivatives(self, eta: Tensor, target: Tensor, /) -> tuple[Tensor, Tensor, Tensor]:
        """``(log p, d log p / d eta, d^2 log p / d eta^2)``, elementwise."""

    def third_derivative(self, eta: Tensor, target: Tensor, /) -> Tensor:
        """``d^3 log p / d eta^3``, elementwise."""

    def fisher(self, eta: Tensor, /) -> Tensor:
        """The expected negative second derivative (never negative); needed unless log-concave."""


#: What a :class:`Term` asks of its likelihood: closed-form derivatives in the predictor (and the
#: target, where the term has one).
TermLikelihood = PairLikelihood | ItemLikelihood


@dataclass(frozen=True, eq=False)
class Term:
    r"""One kind of observation for ``b`` problems: ``m`` predictors each, scored by ``likelihood``.

    Args:
        likelihood: a :class:`TermLikelihood`.
        index: ``b x m x c`` long, the items each predictor combines.
        coef: the ``c`` coefficients, ``(1.0, -1.0)`` for ``f_i - f_j``, ``(1.0,)`` for ``f_i``.
        target: ``b x m`` observed values passed to the likelihood after ``eta``, or ``None``.
        mask: ``b x m`` bool, false for padding; ``None``: all observations are real.
        log_concave: the exact weights ``-l''`` are never negative, so Fisher scoring keeps them.
        offset: ``b x m`` values added to each predictor before the likelihood sees it, or
            ``None``: ``d_k m`` for a prior mean ``m`` of the items (:meth:`Observations.shifted`),
            so that the likelihood scores ``d_k (m + g)`` while the solver works on ``g``.
    """

    likelihood: TermLikelihood
    index: TermIndex
    coef: tuple[float, ...]
    target: TermValues | None = None
    mask: TermValues | None = None
    log_concave: bool = False
    offset: TermValues | None = None
    _patterns: dict = field(default_factory=dict, repr=False)

    @property
    def size(self) -> int:
        """The number ``m`` of observations in this term."""
        return self.index.shape[-2]

    def _args(self) -> tuple[Tensor, ...]:
        return () if self.target is None else (self.target,)

    def _masked(self, x: Tensor) -> Tensor:
        return x if self.mask is None else torch.where(self.mask, x, 0.0)

    def predictor(self, f: Tensor) -> Tensor:
        """``eta`` (``b x m``) at ``f`` (``b x n``)."""
        b, n = f.shape
        flat, eta = f.reshape(-1), None
        for c, coef in enumerate(self.coef):
            x = flat.index_select(0, self._flat_index(c, b, n)).view(b, -1)
            eta = (x if coef == 1.0 else coef * x) if eta is None else (eta - x if coef == -1.0 else eta + coef * x)
        assert eta is not None  # a term has at least one coefficient
        return eta

    def adjoint(self, x: Tensor, n: int) -> Tensor:
        """``sum_k x_k d_k`` (``b x n``) for per-observation values ``x`` (``b x m``)."""
        b = x.shape[0]
        out = x.new_zeros(b * n)
        for c, coef in enumerate(self.coef):
            out.index_add_(0, self._flat_index(c, b, n), x.reshape(-1), alpha=coef)
        return out.view(b, n)

    def _flat_index(self, c: int, b: int, n: int) -> Tensor:
        """The items of coefficient ``c`` as positions among the ``b n`` items (or rows of ``b``
        stacked ``n x k`` matrices) of all problems."""
        key = ("flat_rows", c, b, n)
        if key not in self._patterns:
            with torch.inference_mode(False):  # kept for later autograd passes even if first asked for in a solve
                offset = (torch.arange(b, device=self.index.device) * n).reshape(-1, 1) if b > 1 else 0
                self._patterns[key] = (self.index[..., c] + offset).reshape(-1)
        return self._patterns[key]

    def rows(self, L: Tensor) -> Tensor:
        """``D L`` (``b x m x k``): each observation's row ``d_k`` times ``L`` (``b x n x k``)."""
        b, n, k = L.shape
        flat = L.reshape(b * n, k)  # the rows of all problems: one index_select per coefficient
        out = None
        for c, coef in enumerate(self.coef):
            picked = flat.index_select(0, self._flat_index(c, b, n)).reshape(b, -1, k)
            out = (picked if coef == 1.0 else coef * picked) if out is None else out.add_(picked, alpha=coef)
        assert out is not None  # a term has at least one coefficient
        return out

    def adjoint_rows(self, X: Tensor, n: int) -> Tensor:
        """``D^T X`` (``b x n x k``) for one row per observation, ``X`` (``b x m x k``): the transpose of :meth:`rows`."""
        b, k = X.shape[0], X.shape[-1]
        out = X.new_zeros(b * n, k)
        for c, coef in enumerate(self.coef):
            out.index_add_(0, self._flat_index(c, b, n), X.reshape(-1, k), alpha=coef)
        return out.reshape(b, n, k)

    def evaluate(
        self, f: Tensor, fisher: Tensor | None = None, eta: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``(log p summed per problem (b), d log p / d eta (b x m), weights w (b x m))``;
        ``fisher`` (``b`` bool) swaps in the Fisher weights for those problems; ``eta``: the
        predictors at ``f`` if already computed."""
        eta = self.predictor(f) if eta is None else eta
        if self.offset is not None:
            eta = eta + self.offset
        lp, d1, d2 = self.likelihood.derivatives(eta, *self._args())
        w = -d2
        if fisher is not None and not self.log_concave and bool(fisher.any()):
            w = torch.where(fisher.unsqueeze(-1), self.likelihood.fisher(eta), w)
        return self._masked(lp).sum(-1), self._masked(d1), self._masked(w)

    def curvature_slope(self, f: Tensor) -> Tensor:
        """``d w / d eta = -l'''(eta)`` (``b x m``), for the evidence's gradient."""
        eta = self.predictor(f) if self.offset is None else self.predictor(f) + self.offset
        return self._masked(-self.likelihood.third_derivative(eta, *self._args()))

    def W_entries(self, n: int) -> tuple[Tensor, Tensor]:
        """``W``'s nonzero pattern over the block-diagonal ``Bn x Bn`` matrix: ``(rows, cols)``
        of each of the ``c^2`` entries per observation (flattened in :meth:`W_values`' order)."""
        if n not in self._patterns:
            offset = (torch.arange(self.index.shape[0], device=self.index.device) * n).reshape(-1, 1)
            rows, cols = [], []
            for c in range(len(self.coef)):
                for e in range(len(self.coef)):
                    rows.append((self.index[..., c] + offset).reshape(-1))
                    cols.append((self.index[..., e] + offset).reshape(-1))
            self._patterns[n] = (torch.cat(rows), torch.cat(cols))
        return self._patterns[n]

    def W_flat_index(self, n: int) -> Tensor:
        """:meth:`W_entries` as positions in the flattened ``b x n x n`` batch of ``W`` matrices."""
        key = ("flat", n)
        if key not in self._patterns:
            rows, cols = self.W_entries(n)
            self._patterns[key] = rows * n + cols % n
        return self._patterns[key]

    def W_values(self, w: Tensor) -> Tensor:
        """The values matching :meth:`W_entries`: ``coef_c coef_e w_k``."""
        key = ("coef", w.dtype, w.device)
        if key not in self._patterns:  # the c^2 products coef_c coef_e, one per row
            self._patterns[key] = torch.tensor(
                [ci * ce for ci in self.coef for ce in self.coef], dtype=w.dtype, device=w.device
            ).unsqueeze(-1)
        return (self._patterns[key] * w.reshape(1, -1)).reshape(-1)


def pairwise_term(likelihood: PairLikelihood, comparisons: Tensor, mask: Tensor | None = None, **kw) -> Term:
    """A term on ``f_i - f_j`` for comparisons ``b x p x 2`` (rows ``[i, j]``)."""
    return Term(likelihood, comparisons, (1.0, -1.0), mask=mask, **kw)


def item_term(
    likelihood: ItemLikelihood, index: Tensor, target: Tensor | None = None, mask: Tensor | None = None, **kw
) -> Term:
    """A term on ``f_i`` for items ``index`` (``b x q``) with observed values ``target``."""
    return Term(likelihood, index.unsqueeze(-1), (1.0,), target=target, mask=mask, **kw)


class LikelihoodTerms(NamedTuple):
    """The log-likelihood and its derivatives at one ``f``, per problem."""

    log_lik: PerProblem
    grad: Latent  # d log p / d f
    weights: tuple[TermValues, ...]  # per term: W = sum_k w_k d_k^T d_k


@dataclass(frozen=True, eq=False)
class Observations:
    """The observations of ``batch`` independent problems, as a tuple of :class:`Term`."""

    terms: tuple[Term, ...]
    batch: int
    _sparse: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_data(
        cls,
        comparisons: Tensor,
        ratings: Tensor,
        rating_index: Tensor,
        comparison_likelihood: PairLikelihood,
        rating_likelihood: ItemLikelihood,
        comparison_mask: Tensor | None = None,
        rating_mask: Tensor | None = None,
        *,
        ties: Tensor | None = None,
        tie_likelihood: PairLikelihood | None = None,
        tie_mask: Tensor | None = None,
    ) -> Observations:
        """Comparisons (``p x 2`` or ``b x p x 2``), ratings (``q`` or ``b x q``, of items
        ``rating_index``) and ties (``t x 2`` or ``b x t x 2``, scored by ``tie_likelihood``) as
        terms; empty kinds are left out. A likelihood with ``log_concave = True`` (the ordinal
        ones, :mod:`torchpref.likelihoods.ordinal`) keeps its exact weights under Fisher scoring."""
        batched = comparisons.dim() == 3
        if not batched:
            comparisons, ratings, rating_index = comparisons[None], ratings[None], rating_index[None]
            comparison_mask = None if comparison_mask is None else comparison_mask[None]
            rating_mask = None if rating_mask is None else rating_mask[None]
            ties = None if ties is None else ties[None]
            tie_mask = None if tie_mask is None else tie_mask[None]
        terms = []
        if comparisons.shape[-2]:
            log_concave = getattr(comparison_likelihood, "log_concave", True)  # lapses are not
            terms.append(pairwise_term(comparison_likelihood, comparisons, comparison_mask, log_concave=log_concave))
        if ratings.shape[-1]:
            terms.append(
                item_term(
                    rating_likelihood,
                    rating_index,
                    ratings,
                    rating_mask,
                    log_concave=getattr(rating_likelihood, "log_concave", False),
                )
            )
        if ties is not None and ties.shape[-2]:
            if tie_likelihood is None:
                raise ValueError("ties need a tie_likelihood.")
            terms.append(pairwise_term(tie_likelihood, ties, tie_mask, log_concave=True))
        return cls(tuple(terms), comparisons.shape[0])

    def shifted(self, mean: Tensor | None) -> Observations:
        r"""These observations under a prior mean ``mean`` of the items (``b x n``): each term's
        :attr:`Term.offset` set to ``D mean`` (replacing any earlier one), so that the likelihood
        scores ``D (mean + g)`` for the solver's ``g ~ GP(0, K)``. ``None`` removes the offsets
        (``self`` when there are none). The terms' index patterns are shared, not rebuilt; the
        offsets carry ``mean``'s gradients (the evidence's gradient in a mean's parameters)."""
        if mean is None and all(t.offset is None for t in self.terms):
            return self
        terms = tuple(replace(t, offset=None if mean is None else t.predictor(mean)) for t in self.terms)
        return replace(self, terms=terms)

    @property
    def num_observations(self) -> int:
        """The number of observations over all terms."""
        return sum(t.size for t in self.terms)

    def evaluate(self, f: Tensor, fisher: Tensor | None = None) -> LikelihoodTerms:
        """Log-likelihood, gradient and weights at ``f`` (``b x n``); ``fisher`` as :meth:`Term.evaluate`."""
        ll, grad, weights = f.new_zeros(f.shape[0]), torch.zeros_like(f), []
        for t in self.terms:
            lp, d1, w = t.evaluate(f, fisher)
            ll, grad = ll + lp, grad + t.adjoint(d1, f.shape[-1])
            weights.append(w)
        return LikelihoodTerms(ll, grad, tuple(weights))

    def evaluate_whitened(self, a: Tensor, rows: Sequence[Tensor]) -> LikelihoodTerms:
        """:meth:`evaluate` at ``f = L a`` given each term's rows ``D L`` (:meth:`whitened_rows`),
        with the gradient in ``a``: ``L^T d log p / d f`` (``b x n``)."""
        ll: Tensor | None = None
        grad = torch.zeros_like(a)
        weights = []
        for t, R in zip(self.terms, rows):
            lp, d1, w = t.evaluate(a, eta=(R @ a.unsqueeze(-1)).squeeze(-1))
            g = (R.mT @ d1.unsqueeze(-1)).squeeze(-1)
            ll, grad = (lp, g) if ll is None else (ll + lp, grad + g)
            weights.append(w)
        if ll is None:
            ll = a.new_zeros(a.shape[0])
        return LikelihoodTerms(ll, grad, tuple(weights))

    def whitened_rows(self, L: Tensor) -> tuple[Tensor, ...] | None:
        """Each term's rows ``D L`` (``b x m x n``) for ``L`` (``b x n x n``), where forming them
        once pays: when :meth:`whitened_hessian` takes the rows' path (``m n^2`` against the
        ``n^3`` of ``L^T (W L)``: up to ``2 n`` observations for a small ``n``, fewer than
        ``n / 2`` for a large one); else ``None``."""
        n, m = L.shape[-1], self.num_observations
        if not self.terms or m > (2 * n if n <= DENSE_W_MAX_ITEMS else n // 2):
            return None
        return tuple(t.rows(L) for t in self.terms)

    def adjoint(self, values: Sequence[Tensor], n: int, like: Tensor) -> Tensor:
        """``sum over terms and k of x_k d_k`` (``b x n``, dtype and device of ``like``) for
        per-term values."""
        out = like.new_zeros(self.batch, n)
        for t, x in zip(self.terms, values):
            out = out + t.adjoint(x, n)
        return out

    def curvature_slopes(self, f: Tensor) -> tuple[Tensor, ...]:
        """Each term's :meth:`Term.curvature_slope` at ``f``."""
        return tuple(t.curvature_slope(f) for t in self.terms)

    def rows(self, X: Tensor) -> tuple[Tensor, ...]:
        """Each term's rows ``D X`` (``b x m x k``) for ``X`` (``b x n x k``)."""
        return tuple(t.rows(X) for t in self.terms)

    def adjoint_rows(self, values: Sequence[Tensor], n: int, like: Tensor) -> Tensor:
        """``sum over terms of D^T X`` (``b x n x k``, dtype and device of ``like``) for per-term
        rows ``X`` (``b x m x k``)."""
        out = like.new_zeros(self.batch, n, like.shape[-1])
        for t, X in zip(self.terms, values):
            out = out + t.adjoint_rows(X, n)
        return out

    def W_vector(self, weights: Sequence[Tensor], x: Tensor) -> Tensor:
        """``W x = sum_k w_k d_k (d_k^T x)`` (``b x n``) for ``x`` (``b x n``), from the terms."""
        return self.adjoint([w * t.predictor(x) for t, w in zip(self.terms, weights)], x.shape[-1], like=x)

    def W_blocks(self, n: int, weights: Sequence[Tensor]) -> Tensor:
        """``W`` of all problems as one block-diagonal sparse ``Bn x Bn`` COO matrix (coalesced)."""
        if n not in self._sparse:
            rows = torch.cat([t.W_entries(n)[0] for t in self.terms])
            cols = torch.cat([t.W_entries(n)[1] for t in self.terms])
            N = self.batch * n
            keys, slot = torch.unique(rows * N + cols, return_inverse=True)  # sorted: coalesced order
            self._sparse[n] = (torch.stack([keys // N, keys % N]), slot, N)
        index, slot, N = self._sparse[n]
        vals = torch.cat([t.W_values(w) for t, w in zip(self.terms, weights)])
        vals = vals.new_zeros(index.shape[-1]).index_add(0, slot, vals)
        return torch.sparse_coo_tensor(index, vals, (N, N), is_coalesced=True, check_invariants=False)

    def W_operator(self, n: int, weights: Sequence[Tensor], dense: Tensor | None = None) -> Callable[[Tensor], Tensor]:
        """``X -> W X`` (``b x n x k`` to ``b x n x k``) with ``W`` formed once for repeated
        products: dense for small ``n`` (``dense``, if given, is that matrix), else block-sparse."""
        if not self.terms:
            return torch.zeros_like
        if n <= DENSE_W_MAX_ITEMS:
            W = self.W_dense(n, weights) if dense is None else dense
            return W.__matmul__
        W_sparse = self.W_blocks(n, weights)
        return lambda X: torch.sparse.mm(W_sparse, X.reshape(-1, X.shape[-1])).reshape(X.shape)

    def W_times(self, weights: Sequence[Tensor], X: Tensor) -> Tensor:
        """``W X`` (``b x n x k``) for ``b x n x k`` ``X``: dense for small ``n``, else block-sparse."""
        return self.W_operator(X.shape[-2], weights)(X)

    def W_dense(self, n: int, weights: Sequence[Tensor], like: Tensor | None = None) -> Tensor:
        """``W`` (``b x n x n``, eq. 8) densely, for the evidence's gradient, inspection and tests
        (dtype and device of the weights, or of ``like`` when there are no terms)."""
        ref = weights[0] if weights else like
        W = torch.zeros(
            self.batch,
            n,
            n,
            dtype=ref.dtype if ref is not None else torch.float64,
            device=ref.device if ref is not None else None,
        )
        for t, w in zip(self.terms, weights):
            W.view(-1).index_put_((t.W_flat_index(n),), t.W_values(w), accumulate=True)
        return W

    def whitened_hessian(self, L: Tensor, weights: Sequence[Tensor], rows: Sequence[Tensor] | None = None) -> Tensor:
        r"""``B = I + L^T W L`` (``b x n x n``) for ``L`` (``b x n x n``).

        Given each term's rows ``D L`` (``rows``, :meth:`whitened_rows`), or with a gradient to
        track, or with few observations per item: ``sum_terms (D L)^T diag(w) (D L)`` (``m n^2``
        per term, differentiable). Otherwise ``L^T (W L)`` (one ``n^3`` product).
        """
        n = L.shape[-1]
        tracked = torch.is_grad_enabled() and (L.requires_grad or any(w.requires_grad for w in weights))
        if rows is None and not tracked and 2 * self.num_observations > n:
            WL = self.W_times(weights, L)
            H = lower_t_matmul(L[0], WL[0]).unsqueeze(0) if L.shape[0] == 1 else L.mT @ WL
        else:
            H = torch.zeros_like(L)
            for k, (t, w) in enumerate(zip(self.terms, weights)):
                DL = t.rows(L) if rows is None else rows[k]
                H = DL.mT @ (w.unsqueeze(-1) * DL) if k == 0 else torch.baddbmm(H, DL.mT, w.unsqueeze(-1) * DL)
        H.diagonal(dim1=-2, dim2=-1).add_(1.0)
        return H
