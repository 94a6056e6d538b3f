r"""Best-of-``m`` queries built greedily to maximise a value of their answer's probabilities.

:func:`greedy_choice_set` adds, one at a time, the item that most increases a value (such as
:func:`~torchpref.acquisition.information.membership_information`) of the choice probabilities of
:func:`~torchpref.acquisition.functions.choice_probabilities` under joint posterior samples, for one trial
or ``T`` independent trials at once. Also importable from :mod:`torchpref.acquisition.functions`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from torchpref.inference.numerics import gauss_hermite

__all__ = ["greedy_choice_set", "greedy_choice_sets", "greedy_choice_steps"]

# On a CPU, trials are processed in chunks whose temporaries stay in a core's cache (about this
# many float64 elements each): one T = 100 batch is slower than 100 single calls otherwise.
_GREEDY_CHUNK = 2**19


def greedy_choice_set(
    F: Tensor,
    comparison_noise: float | Tensor | Any,
    m: int,
    value: Callable[[Tensor], Tensor],
    start: int | Tensor | None = None,
    num_quadrature: int = 6,
) -> tuple[list[int], float] | tuple[Tensor, Tensor]:
    r"""Build a best-of-``m`` query greedily among ``K`` items to maximise ``value``.

    Starting from item ``start`` (or, if ``None``, the best pair), add the item that most
    increases ``value(P)``, ``P`` the choice probabilities of :func:`choice_probabilities`
    under the samples ``F`` of the candidate sets. Each item's product of pairwise ``Phi``
    terms with the chosen items is kept and multiplied incrementally, and only the ``Phi`` terms
    a step needs are evaluated (all ``K^2`` only for the best pair). Ties go to the first
    candidate set (lowest item indices).

    **Trials.** A ``T x S x K`` ``F`` builds ``T`` independent queries at once, one per trial;
    trial ``t``'s query is that of ``F[t]`` alone (same items in the same order, values to
    rounding) when ``value`` treats the trials independently (e.g.
    :func:`membership_information` with a ``T x S x N`` ``Z``). ``value`` is called once per
    step for all trials. Memory (float64, ``H = num_quadrature``): the products,
    ``T x K x S x H`` (9 MB for ``T = 100``, ``K = 15``, ``S = 128``, ``H = 6``), and the
    probabilities handed to ``value``, ``T x R x S x q`` (``R = K (K - 1) / 2`` pairs: 22 MB);
    the ``Phi`` terms, ``K x K x S x H`` a trial, are not held for all ``T`` (140 MB) but
    evaluated as needed, on a CPU in chunks of trials that fit a core's cache.

    Args:
        F: ``S x K`` joint samples of the items' utilities, or ``T x S x K``.
        comparison_noise: ``sigma_R`` (eq. 3), a float or a 0-d tensor; with a 3-D ``F`` also a
            ``T`` tensor, one per trial. Or the model's comparison likelihood: its ``sigma_R``,
            and ``value`` sees its answer probabilities (``with_lapses``: a lapsing person's
            choices tell less), as its ``choice_probabilities`` gives them.
        m: items in the query, ``2 <= m <= K``.
        value: maps ``R x S x q`` probabilities of ``R`` candidate sets of ``q`` items to ``R``
            values; with a 3-D ``F``, ``T x R x S x q`` to ``T x R``.
        start: the first item, or ``None`` to start from the best pair; with a 3-D ``F`` an int
            (every trial) or a ``T`` long tensor.
        num_quadrature: Gauss-Hermite nodes ``H`` over the choice noise.

    Returns:
        2-D ``F``: the chosen columns of ``F`` (a list, in the order added) and the value of the
        final set (a float). 3-D ``F``: a ``T x m`` long tensor of the chosen columns and the
        ``T`` values of the final sets.
    """
    if F.dim() == 2:
        start = int(start) if isinstance(start, Tensor) else start
        one: Callable[[Tensor], Tensor] = lambda P: value(P[0]).unsqueeze(0)  # noqa: E731
        chosen, best = greedy_choice_sets(F.unsqueeze(0), comparison_noise, m, one, start, num_quadrature)
        return chosen[0].tolist(), float(best[0])
    return greedy_choice_sets(F, comparison_noise, m, value, start, num_quadrature)


def greedy_choice_sets(
    F: Tensor,
    comparison_noise: float | Tensor | Any,
    m: int,
    value: Callable[[Tensor], Tensor],
    start: int | Tensor | None = None,
    num_quadrature: int = 6,
) -> tuple[Tensor, Tensor]:
    r""":func:`greedy_choice_set` for ``T`` trials at once (``F``: ``T x S x K``): a ``T x m`` long
    tensor of the chosen columns and the ``T`` values of the final sets."""
    chosen, steps = greedy_choice_steps(F, comparison_noise, m, value, start, num_quadrature)
    return chosen, steps[:, -1]


def greedy_choice_steps(
    F: Tensor,
    comparison_noise: float | Tensor | Any,
    m: int,
    value: Callable[[Tensor], Tensor],
    start: int | Tensor | None = None,
    num_quadrature: int = 6,
) -> tuple[Tensor, Tensor]:
    r""":func:`greedy_choice_sets` with the value of every prefix of each set: a ``T x m`` long
    tensor of the chosen columns and ``T x (m - 1)`` values, column ``q - 2`` the value of the
    first ``q`` items (the set the greedy search held once it had ``q``). The values are the
    search's own: Gauss-Hermite choice probabilities for every ``q``, the pair's included."""
    if F.dim() != 3:
        raise ValueError(f"F must be S x K or T x S x K, got shape {tuple(F.shape)}.")
    if not isinstance(comparison_noise, (float, int, Tensor)):  # a comparison likelihood: its own probabilities
        likelihood: Any = comparison_noise
        comparison_noise = likelihood.comparison_noise.detach().to(F)
        value = _through(likelihood, value)
    return _greedy_choice_set(F, comparison_noise, m, value, start, num_quadrature)


def _through(likelihood: Any, value: Callable[[Tensor], Tensor]) -> Callable[[Tensor], Tensor]:
    """``value`` of the likelihood's answer probabilities (its ``with_lapses`` of the Thurstone ones)."""

    def lapsing(P: Tensor) -> Tensor:
        return value(likelihood.with_lapses(P))

    return lapsing


class _ChoiceTerms:
    """The ``Phi`` terms of the choice model (eq. 3) for ``T x S x K`` samples ``F``, evaluated as
    needed, a chunk of trials at a time (``chunks``: each chunk's ``t x K x S`` samples and its
    slice of trials)."""

    def __init__(self, F: Tensor, comparison_noise: float | Tensor, num_quadrature: int):
        T, S, K = F.shape
        self.x, self.w = gauss_hermite(num_quadrature, F)
        # the nodes are symmetric (x_{H-1-h} = -x_h): Phi(k, j) at node h is 1 - Phi(j, k) at
        # node H-1-h, read from k's column instead of evaluated again
        self.symmetric = bool(torch.allclose(self.x, -self.x.flip(0), rtol=0.0, atol=1e-12))
        noise = comparison_noise
        self.per_trial = isinstance(noise, Tensor) and noise.dim() > 0
        if isinstance(noise, Tensor) and noise.dim() > 0:
            if noise.shape != (T,):
                raise ValueError(
                    f"comparison_noise must be a scalar or a T={T} tensor, got shape {tuple(noise.shape)}."
                )
            noise = noise.to(F)
        self.noise, self.device = noise, F.device
        step = max(1, _GREEDY_CHUNK // (K * K * S * num_quadrature)) if F.device.type == "cpu" else T
        parts = [slice(i, min(i + step, T)) for i in range(0, T, step)]
        self.chunks = [(F[sl].mT, sl) for sl in parts]  # t x K x S per chunk

    def phi(self, diff: Tensor, sl: slice) -> Tensor:
        """``f_j - f_k``, ``t x ... x S`` -> ``Phi((f_j + eps - f_k) / s) = erfc(-z / sqrt 2) / 2`` at
        the ``H`` nodes, ``t x ... x S x H``, in place: products instead of sums of logs (an
        underflow to 0 only drops a negligible probability)."""
        noise = self.noise
        s = noise[sl].reshape(-1, *(1,) * (diff.dim() - 1)) if isinstance(noise, Tensor) and self.per_trial else noise
        z = (diff / s).unsqueeze(-1) + math.sqrt(2) * self.x
        return z.mul_(-1 / math.sqrt(2)).erfc_().mul_(0.5)

    def pair(self, Ft: Tensor, j: Tensor, c: Tensor, sl: slice) -> Tensor:
        """``t x R x S x 2``: the choice probabilities of the pairs ``(j, c)`` in closed form,
        ``Phi((f_j - f_c) / (sqrt 2 s))`` and its complement (the Gauss-Hermite rule's limit; as
        :func:`~torchpref.likelihoods.pairwise_beta.thurstone_choice_probabilities` gives a pair)."""
        noise = self.noise
        s = noise[sl].reshape(-1, 1, 1) if isinstance(noise, Tensor) and self.per_trial else noise
        p = torch.special.ndtr((Ft[:, j] - Ft[:, c]) / (math.sqrt(2) * s))  # t x R x S
        return torch.stack([p, 1 - p], -1)

    def column(self, Ft: Tensor, k: Tensor, sl: slice) -> Tensor:
        """``t x K x S x H``: ``Phi`` of ``(j, k_t)`` for every ``j``; 1 at ``j = k_t``."""
        t = torch.arange(Ft.shape[0], device=Ft.device)
        ph = self.phi(Ft - Ft[t, k].unsqueeze(1), sl)
        ph[t, k] = 1.0
        return ph

    def probs(self, *prods: Tensor) -> Tensor:
        """``t x R x q_i x S x H`` products, ... -> ``t x R x S x q`` choice probabilities (``q = sum q_i``)."""
        p = torch.cat([prod @ self.w for prod in prods], dim=2)  # t x R x q x S
        return (p / p.sum(-2, keepdim=True)).transpose(-1, -2)


def _values(value: Callable[[Tensor], Tensor], Ps: list[Tensor], T: int, R: int) -> Tensor:
    """``value`` of the chunks' probabilities ``Ps`` of ``R`` candidate sets: ``T x R``."""
    P = Ps[0] if len(Ps) == 1 else torch.cat(Ps)
    vals = value(P)
    if vals.shape != (T, R):
        raise ValueError(f"value must map {tuple(P.shape)} probabilities to {(T, R)}, got {tuple(vals.shape)}.")
    return vals


def _best_pair(terms: _ChoiceTerms, value: Callable[[Tensor], Tensor], T: int, K: int) -> tuple[Tensor, Tensor]:
    """The best pair ``(j, c)``, ``j < c``, of each trial, every pair's choice in closed form, a
    chunk at a time: ``T x 2`` items, ``T`` values."""
    j, c = torch.triu_indices(K, K, 1, device=terms.device)
    Ps = [terms.pair(Ft, j, c, sl) for Ft, sl in terms.chunks]
    vals = _values(value, Ps, T, j.numel())
    b = vals.argmax(-1)
    return torch.stack([j[b], c[b]], -1), vals[torch.arange(T, device=terms.device), b]


def _first_items(start: int | Tensor, T: int, K: int, device: torch.device) -> Tensor:
    """``start`` (an int or a ``T`` tensor) as the ``T x 1`` first item of each trial."""
    first = torch.as_tensor(start, dtype=torch.long, device=device)
    if first.dim() > 1 or first.numel() not in (1, T):
        raise ValueError(f"start must be an int or a T={T} tensor, got shape {tuple(first.shape)}.")
    first = first.reshape(-1).expand(T)
    if not bool(((first >= 0) & (first < K)).all()):
        raise ValueError(f"start must be in 0..{K - 1}, got {start}.")
    return first.reshape(T, 1)


def _add_best_item(
    terms: _ChoiceTerms,
    As: list[Tensor],
    chosen: Tensor,
    value: Callable[[Tensor], Tensor],
    columns: list[list[Tensor]] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Each trial's ``chosen`` (``T x c``) items with the one of the rest that maximises ``value``
    added: ``T x (c + 1)`` items, ``T`` values and the ``T`` items added. ``As``: per chunk, the
    product over the chosen items ``k`` of ``Phi(j, k)`` for each item ``j``, ``t x K x S x H``;
    ``columns``: per chunk, each chosen item's ``Phi(j, k)`` (where the nodes are symmetric: a
    chosen item's terms against the rest are then read from them, not evaluated)."""
    (T, c), K = chosen.shape, As[0].shape[1]
    tt = torch.arange(T, device=chosen.device)
    mask = torch.ones(T, K, dtype=torch.bool, device=chosen.device)
    mask[tt.unsqueeze(-1), chosen] = False
    rest = mask.nonzero()[:, 1].reshape(T, K - c)  # ascending, per trial
    Ps = []
    for i, ((Ft, sl), A) in enumerate(zip(terms.chunks, As)):
        ch, re = chosen[sl].unsqueeze(1), rest[sl].unsqueeze(-1)  # t x 1 x c, t x r x 1
        ti = torch.arange(Ft.shape[0], device=Ft.device).reshape(-1, 1, 1)
        if columns is not None:  # Phi(k, j) = 1 - Phi(j, k) at the mirrored node
            cols = torch.stack(columns[i], dim=2)  # t x K x c x S x H
            phi = (1 - cols[ti[..., 0], re[..., 0]].flip(-1)).clamp_min_(0)  # t x r x c x S x H
        else:
            phi = terms.phi(Ft[ti, ch] - Ft[ti, re], sl)
        old = A[ti, ch] * phi  # t x r x c x S x H: the chosen items
        Ps.append(terms.probs(old, A[ti, re]))  # and the added one: sets t x r x (c + 1) x S x H
    vals = _values(value, Ps, T, K - c)
    b = vals.argmax(-1)
    new = rest[tt, b]
    return torch.cat([chosen, new.unsqueeze(-1)], -1), vals[tt, b], new


def _greedy_choice_set(
    F: Tensor,
    comparison_noise: float | Tensor,
    m: int,
    value: Callable[[Tensor], Tensor],
    start: int | Tensor | None,
    num_quadrature: int,
) -> tuple[Tensor, Tensor]:
    """:func:`greedy_choice_set` for ``T x S x K`` ``F``: ``T x m`` chosen columns, ``T x (m - 1)``
    values of the prefixes of 2..m items."""
    T, S, K = F.shape
    if not 2 <= m <= K:
        raise ValueError(f"need 2 <= m <= {K} items, got m={m}.")
    terms = _ChoiceTerms(F, comparison_noise, num_quadrature)
    if start is None:
        chosen, best = _best_pair(terms, value, T, K)
    else:
        chosen, best = _first_items(start, T, K, F.device), F.new_full((T,), math.nan)
    # A[t, j] = prod over chosen k of Phi(j, k): t x K x S x H per chunk
    # and each chosen item's column Phi(j, k), kept where the nodes are symmetric
    As, columns = [], []
    for Ft, sl in terms.chunks:
        cols = [terms.column(Ft, chosen[sl, i], sl) for i in range(chosen.shape[1])]
        A = cols[0].clone()
        for col in cols[1:]:
            A.mul_(col)
        As.append(A)
        columns.append(cols)
    kept = columns if terms.symmetric else None
    steps = [best] if chosen.shape[1] == 2 else []  # from one item the first step values a pair
    while chosen.shape[1] < m:
        chosen, best, new = _add_best_item(terms, As, chosen, value, kept)
        steps.append(best)
        if chosen.shape[1] < m:
            for (Ft, sl), A, cols in zip(terms.chunks, As, columns):
                col = terms.column(Ft, new[sl], sl)
                A.mul_(col)
                cols.append(col)
    return chosen, torch.stack(steps, -1)
