r"""Large pools: any selector's choice among a shortlist found in one pass linear in the pool.

A selector that values questions on joint posterior samples builds the joint covariance of its
``N`` candidates (``N x N``: 80 GB at ``N = 100,000``). :class:`Shortlisted` wraps any
:class:`~torchpref.selection.strategies.Selector` and hands it a shortlist of ``size`` candidates
instead of the pool, chosen in passes over the pool in chunks of ``chunk`` rows (never more than
``chunk x 2 x 2`` covariances, never ``N x N``):

1. **marginals**: the posterior mean ``mu_i`` and standard deviation ``s_i`` of every item; the
   *incumbent* ``b`` is the item of largest mean;
2. **against the incumbent**: the joint posterior of ``(f_i, f_b)`` for every item, and the
   probability that it beats the incumbent, ``P(f_i > f_b) = Phi((mu_i - mu_b) / sd(f_i - f_b))``
   (its correlation with the incumbent counted). An item's probability of being the maximiser
   is at most its probability of beating the incumbent, so an item left out by this ranking is
   no likelier to be the maximiser than the last one kept by it;
3. the shortlist, ``size`` distinct items taken in this order, each kind up to its share: the
   items already answered about that are in the pool (an eighth), the largest posterior means (an
   eighth), the likeliest to beat the incumbent (an eighth), the largest upper confidence bounds
   ``mu + gamma s`` (an eighth), the items nearest the edge of the pool's top share ``straddle =
   1.96 s - |mu - e|`` (``e`` the posterior mean of rank ``top_fraction * N``, the wrapped
   selector's ``top_fraction`` or 0.2; an eighth), items at evenly spaced ranks of the posterior
   mean over the whole pool (three eighths: a miniature of the pool, so that what a selector
   reads relative to its candidates, a top share, the best rating's value, stays close to the
   pool's), then the next likeliest to beat the incumbent until ``size`` are kept.

The wrapped selector then chooses among the shortlist exactly as it would among a pool of those
items. What it can miss: a question worth most about an item in none of these rankings (a
mid-ranked item away from the top share's edge whose answer would inform many others); and a
target defined relative to the candidates (a top *share*, as the clipped profile's; the best
rating's value that ``decide="sum"`` divides by) is computed on the shortlist, which the evenly
spaced ranks keep close to the pool's but not equal. docs/selection.md measures what the shortlist gives up
against the exact choice where that fits (``benchmarks/speed/large_pools.py``).

Sessions apply it themselves where the pool has more than :data:`SHORTLIST_ABOVE` distinct items
(:func:`for_pool`), around the selector they were given or the default; selectors whose cost is
already linear in the pool (random ones, UCB ratings, :class:`~torchpref.UCBC`) are left as they
are.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchpref.data.queries import Query, RankingQuery, RatingQuery
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.models.preference_gp import PreferenceGP
from torchpref.selection.samples import SelectorModel
from torchpref.selection.strategies import UCBC, RandomMixed, RandomRankings, RandomRatings, Selector, UCBRatings

__all__ = ["SHORTLIST_ABOVE", "SHORTLIST_SIZE", "Shortlisted", "for_pool", "shortlist_rows"]

SHORTLIST_SIZE = 256
"""The default shortlist's size."""
SHORTLIST_ABOVE = 1000
"""Pools of more distinct items than this get a shortlist in a session (:func:`for_pool`)."""
CHUNK = 16384
"""Rows per chunk of a pass over the pool."""

#: selectors whose cost is already linear in the pool: no shortlist (``linear_in_pool = True`` on
#: a selector of one's own says the same)
_LINEAR: tuple[type, ...] = (RandomRatings, RandomRankings, RandomMixed, UCBRatings, UCBC)


def _check_size(name: str, value: object, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ValueError(f"{name} must be a whole number >= {lo}, got {value!r}.")
    return value


def _marginals(model: SelectorModel, X: Tensor) -> tuple[Tensor, Tensor]:
    """Posterior mean and variance at ``X`` (``T x c x d``): ``T x c`` each."""
    if isinstance(model, (PreferenceGP, BatchedPreferenceGP)):
        mean, var = model.marginals(X)
    else:  # any BoTorch model (T = 1)
        post: Any = model.posterior(X.unsqueeze(-2))  # any posterior with a mean and a variance
        mean, var = post.mean[..., 0, 0], post.variance[..., 0, 0]
    return mean.reshape(X.shape[:2]), var.reshape(X.shape[:2])


def _pairs(model: SelectorModel, X: Tensor, xb: Tensor) -> tuple[Tensor, Tensor]:
    """Mean and variance of ``f(x_i) - f(x_b)`` for the rows of ``X`` (``T x c x d``) and each
    trial's incumbent ``xb`` (``T x d``): the joint posterior of each pair, ``c`` blocks of 2."""
    T, c, d = X.shape
    X2 = torch.stack([X, xb.unsqueeze(1).expand(T, c, d)], dim=-2)  # T x c x 2 x d
    if isinstance(model, BatchedPreferenceGP):
        mean, cov = model._current()._predict(X2.transpose(0, 1).to(model.model.train_X))  # c x T x 2 (x 2)
        mean, cov = mean.transpose(0, 1), cov.transpose(0, 1)
    else:
        post: Any = model.posterior(X2[0])  # c x 2 x d: c Gaussian posteriors of two points (T = 1)
        mean = post.mean[..., 0].unsqueeze(0)
        cov = post.distribution.covariance_matrix.unsqueeze(0)
    diff_mean = mean[..., 0] - mean[..., 1]
    diff_var = cov[..., 0, 0] + cov[..., 1, 1] - 2 * cov[..., 0, 1]
    return diff_mean, diff_var


def _beat_order(
    model: SelectorModel, X: Tensor, mean: Tensor, std: Tensor, best: Tensor, size: int, chunk: int
) -> Tensor:
    r"""``T x N`` scores whose ``size`` largest are the items likeliest to beat each trial's
    incumbent ``best``: ``z_i = (mu_i - mu_b) / sd(f_i - f_b)`` (``P = Phi(z)``), exact for those
    and for every item whose bound could reach them, ``-inf`` for the others, ``+inf`` for ``b``.

    Since ``sd(f_i - f_b) <= s_i + s_b`` and ``mu_i <= mu_b``, ``z_i <= (mu_i - mu_b) / (s_i +
    s_b)``: the pairs' joint posteriors are computed in the order of that bound, a block at a time
    (each twice the last, up to ``chunk``), until the bound of the next item is no larger than the
    ``size``-th largest exact score so far."""
    T, N, _ = X.shape
    tiny = torch.finfo(mean.dtype).tiny
    ar = torch.arange(T)
    xb = X[ar, best]  # T x d
    bound = (mean - mean[ar, best, None]) / (std + std[ar, best, None]).clamp_min(tiny)
    order = bound.argsort(-1, descending=True)  # T x N
    z = torch.full_like(mean, -torch.inf)
    start, block = 0, max(4 * size, 1024)
    while start < N:  # blocks doubling up to a chunk: few calls where the bound prunes little (high d)
        rows = order[:, start : start + block]  # T x B
        for s in range(0, rows.shape[1], chunk):
            r = rows[:, s : s + chunk]
            Xr = X.gather(1, r.unsqueeze(-1).expand(*r.shape, X.shape[-1]))
            dm, dv = _pairs(model, Xr, xb)
            z.scatter_(1, r, dm / dv.clamp_min(tiny).sqrt())
        z[ar, best] = torch.inf
        done = start + rows.shape[1]
        if done >= N:
            break
        kth = z.topk(min(size, done), dim=-1).values[:, -1]  # T
        if bool((bound.gather(1, order[:, done : done + 1]).squeeze(-1) <= kth).all()):
            break
        start, block = done, min(2 * block, max(chunk, block))
    return z


def _answered(model: SelectorModel, X: Tensor, chunk: int) -> list[Tensor]:
    """Per trial, the rows of ``X`` (``T x N x d``) equal to an item the model was told about."""
    T = X.shape[0]
    if isinstance(model, BatchedPreferenceGP):
        seen = [model.data(b).train_X for b in range(T)]
    elif isinstance(model, PreferenceGP) and isinstance(model.train_X, Tensor) and model.train_X.dim() == 2:
        seen = [model.train_X]
    else:
        return [X.new_zeros(0, dtype=torch.long) for _ in range(T)]
    out = []
    for b in range(T):
        S = seen[b].to(X)
        if S.shape[0] == 0:
            out.append(X.new_zeros(0, dtype=torch.long))
            continue
        near = torch.nonzero(torch.isin(X[b, :, 0], S[:, 0])).reshape(-1)  # first coordinate, then all
        same = (X[b, near, None, :] == S[None]).all(-1).any(-1) if near.numel() <= chunk else None
        if same is None:  # many rows share a first coordinate with an answered item: in chunks
            same = torch.cat(
                [(X[b, near[k : k + chunk], None] == S[None]).all(-1).any(-1) for k in range(0, near.numel(), chunk)]
            )
        out.append(near[same])
    return out


def shortlist_rows(
    model: SelectorModel,
    X: Tensor,
    size: int = SHORTLIST_SIZE,
    gamma: float = 3.0,
    chunk: int = CHUNK,
    top_fraction: float = 0.2,
) -> Tensor:
    r"""``T x size`` distinct rows of each trial's candidates ``X`` (``T x N x d``, ``N > size``)
    in the module's order (answered items, largest means, likeliest to beat the incumbent, largest
    UCBs, nearest the edge of the top ``top_fraction``, evenly spaced ranks of the mean, then the
    next likeliest to beat the incumbent). Cost linear in ``N`` besides one sort of the ``N``
    means; memory ``O(chunk)`` besides a few ``T x N`` vectors."""
    T, N, _ = X.shape
    size, chunk = _check_size("size", size, 1), _check_size("chunk", chunk, 1)
    if N <= size:
        raise ValueError(f"a shortlist of {size} needs a pool of more items, got N={N}.")
    with torch.no_grad():
        mean, var = (
            torch.cat(t, dim=1) for t in zip(*(_marginals(model, X[:, s : s + chunk]) for s in range(0, N, chunk)))
        )
        std = var.clamp_min(0).sqrt()
        best = mean.argmax(-1)  # T
        beat = _beat_order(model, X, mean, std, best, size, chunk)
        ucb = mean + gamma * std
        k = max(1, min(N, round(top_fraction * N)))
        edge = mean.topk(k, dim=-1).values[:, -1:]  # the top share's edge in the posterior means
        straddle = 1.96 * std - (mean - edge).abs()
        answered = _answered(model, X, chunk)
        rows = []
        for b in range(T):
            by_beat = beat[b].topk(size).indices
            spread = mean[b].argsort(descending=True)[torch.linspace(0, N - 1, 3 * size // 8).round().long()]
            quotas = (
                (answered[b][: size // 8], size // 8),
                (mean[b].topk(size // 8).indices, size // 8),
                (by_beat, size // 8),
                (ucb[b].topk(size // 8).indices, size // 8),
                (straddle[b].topk(size // 8).indices, size // 8),
                (spread, 3 * size // 8),
                (by_beat, size),
            )
            kept: dict[int, None] = {}
            for order, quota in quotas:
                added = 0
                for i in order.tolist():
                    if len(kept) == size or added == quota:
                        break
                    if i not in kept:
                        kept[i] = None
                        added += 1
            rows.append(torch.tensor(list(kept), dtype=torch.long))
        return torch.stack(rows)


class Shortlisted(Selector):
    r"""``selector``'s choice among a shortlist of ``size`` candidates (module notes): where there
    are more candidates than ``size``, it sees only :func:`shortlist_rows`'; otherwise all of them.

    Args:
        selector: any selector (``select``, or ``select_batch`` for ``T > 1`` trials).
        size: the shortlist's size.
        gamma: the UCB's ``gamma`` in the shortlist's order.
        chunk: rows per chunk of a pass over the pool.

    Raises:
        ValueError: ``size`` or ``chunk`` not a whole number >= 1, or a ``selector`` without ``select``.
    """

    def __init__(self, selector: Selector, size: int = SHORTLIST_SIZE, gamma: float = 3.0, chunk: int = CHUNK):
        if not callable(getattr(selector, "select", None)):
            raise ValueError(f"selector must be a Selector (with select), got {selector!r:.80}.")
        self.selector = selector
        self.size, self.chunk = _check_size("size", size, 1), _check_size("chunk", chunk, 1)
        self.gamma = float(gamma)
        self.name = f"{getattr(selector, 'name', type(selector).__name__)} (shortlist {self.size})"
        if hasattr(selector, "m"):
            self.m = selector.m

    def select_batch(
        self,
        model: SelectorModel,
        X: Tensor,
        indices: Sequence[Tensor | None],
        step: int,
        num_steps: int,
        generators: Sequence[torch.Generator],
    ) -> list[Query]:
        T, N, d = X.shape
        if N <= self.size:
            return self._inner(model, X, list(indices), step, num_steps, generators)
        share = getattr(self.selector, "top_fraction", 0.2)
        rows = shortlist_rows(model, X, self.size, self.gamma, self.chunk, share)  # T x K
        Xs = X.gather(1, rows.unsqueeze(-1).expand(*rows.shape, d))
        inner_idx = [rows[b] if idx is None else idx[rows[b]] for b, idx in enumerate(indices)]
        out = self._inner(model, Xs, inner_idx, step, num_steps, generators)
        return [_without_rows(q) if indices[b] is None else q for b, q in enumerate(out)]

    def _inner(self, model, X: Tensor, indices: list, step: int, num_steps: int, generators) -> list[Query]:
        if X.shape[0] == 1:  # a selector of one's own may implement select alone
            return [self.selector.select(model, X[0], indices[0], step, num_steps, generators[0])]
        return self.selector.select_batch(model, X, indices, step, num_steps, generators)

    def choose(
        self,
        model: SelectorModel,
        queries: Sequence[Query],
        *,
        step: int = 0,
        num_steps: int = 1,
        generator: torch.Generator,
    ) -> int:
        """The wrapped selector's choice among given queries (a list, not a pool: no shortlist)."""
        return self.selector.choose(model, queries, step=step, num_steps=num_steps, generator=generator)


def _without_rows(q: Query) -> Query:
    """The query without pool rows (the caller gave none)."""
    return RatingQuery(q.item, None) if isinstance(q, RatingQuery) else RankingQuery(q.items, None)


def for_pool(selector: Selector, num_items: int | None, above: int = SHORTLIST_ABOVE) -> Selector:
    """``selector``, wrapped in :class:`Shortlisted` where there are more than ``above``
    candidates (a pool's distinct items, or a box's points per question) and its cost is not
    already linear in them (random selectors, UCB ratings, :class:`~torchpref.UCBC`, or one with
    ``linear_in_pool = True``); ``None`` (not known) or a selector already shortlisted is left as it is."""
    if num_items is None or num_items <= above or isinstance(selector, Shortlisted):
        return selector
    if isinstance(selector, _LINEAR) or getattr(selector, "linear_in_pool", False):
        return selector
    return Shortlisted(selector)
