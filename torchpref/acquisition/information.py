r"""How much a query's answer tells about a target, from joint posterior samples.

* :func:`sample_information`: the mutual information between an answer and the utility itself
  or a discrete target such as the location of the maximum (entropy search), from the answer's
  probabilities under each sample (:func:`~torchpref.acquisition.functions.choice_probabilities`,
  :func:`~torchpref.acquisition.functions.rating_bin_probabilities`).
* :func:`membership_information`: the summed information about each item's membership of a set
  such as the top set of each sample (:func:`top_set_membership`), with a finite-sample bias
  correction; it also takes a leading dim of ``T`` independent trials (each its own samples),
  one call for ``T`` active-learning runs at once.

What :class:`~torchpref.selection.strategies.InformationPerEffort` uses; the names are also importable
from :mod:`torchpref.acquisition.functions`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["entropy", "membership_information", "sample_information", "top_set_membership"]


def entropy(P: Tensor, dim: int = -1) -> Tensor:
    """The entropy (nats) of the distributions ``P`` along ``dim`` (``0 log 0 = 0``: ``P log(P +
    tiny)``, which equals ``xlogy(P, P)`` to rounding and takes half its time)."""
    return -(P * P.add(torch.finfo(P.dtype).tiny).log_()).sum(dim)


def sample_information(P: Tensor, labels: Tensor | None = None, num_labels: int | None = None) -> Tensor:
    r"""Mutual information (nats) between a query's answer and a target, from posterior samples.

    ``I(y; T) = H[E_s P(y | f_s)] - E_T H[P(y | T)]`` with ``P(y | T = t)`` the mean of
    ``P(y | f_s)`` over the samples whose target is ``t``.

    Args:
        P: ``batch x S x Y`` answer probabilities under each of ``S`` joint posterior samples.
        labels: ``S`` long, the discrete target of each sample (e.g. the index of its
            maximiser: information about where the maximum is). ``None``: the target is the
            utility itself, ``I(y; f) = H[E_s P] - E_s H[P_s]``.
        num_labels: number of possible labels (default ``labels.max() + 1``).

    Returns:
        ``batch`` informations, clamped at 0.
    """
    h_marginal = entropy(P.mean(-2))
    if labels is None:
        return (h_marginal - entropy(P).mean(-1)).clamp_min(0)
    S = P.shape[-2]
    k = int(labels.max()) + 1 if num_labels is None else num_labels
    onehot = torch.nn.functional.one_hot(labels, k).to(P)  # S x k
    counts = onehot.sum(0)  # k
    used = counts > 0
    onehot, counts = onehot[:, used], counts[used]
    P_t = (onehot.mT @ P) / counts.unsqueeze(-1)  # batch x k x Y
    return (h_marginal - (counts / S * entropy(P_t)).sum(-1)).clamp_min(0)


def top_set_membership(F: Tensor, k: int) -> Tensor:
    r"""``... x S x N`` joint samples -> ``... x S x N`` boolean: is item ``i`` among the ``k``
    largest of sample ``s`` (ties at the ``k``-th value count as members). Leading dims, such as
    ``T`` independent trials, are kept."""
    if not 1 <= k <= F.shape[-1]:
        raise ValueError(f"k must be in 1..{F.shape[-1]}, got {k}.")
    return F >= F.topk(k, dim=-1).values[..., -1:]


def _membership_terms(sums: Tensor, totals: Tensor, n1: Tensor, S: Tensor, Y: int, delta: bool) -> Tensor:
    """Per-item ``I(y; z_i)``, ``... x batch x N``, from the label-1 sums over the samples of
    ``P`` (and, with ``delta``, of ``P^2`` after it), answer-major: ``... x batch x Y x N`` (or
    ``2Y``), their totals over all samples (``... x batch x Y`` or ``2Y``), the label-1 counts
    (``... x 1 x N``) and the numbers of samples (``... x 1 x 1``); ``delta`` subtracts the
    second-order entropy bias. (With the answers before the items, the sums over answers run
    over contiguous rows of items: much faster than reducing a short last dimension.)"""
    n1y = n1.unsqueeze(-2)  # ... x 1 x 1 x N
    n0y = S.unsqueeze(-1) - n1y
    m_in = sums / n1y.clamp_min(1)
    m_out = ((totals.unsqueeze(-1) - sums) / n0y.clamp_min(1)).clamp_min(0)
    m_all = totals / S
    w = n1 / S
    info = (
        entropy(m_all[..., :Y]).unsqueeze(-1)
        - w * entropy(m_in[..., :Y, :], dim=-2)
        - (1 - w) * entropy(m_out[..., :Y, :], dim=-2)
    )
    if delta:

        def spread(P: Tensor, Q: Tensor, n: Tensor, dim: int) -> Tensor:
            # sum_y Var_y / P_y (ddof 1), each term in [0, 1]; + 1e-12: a mean at rounding level
            # (the out-label means are differences) adds nothing
            ratio = ((Q - P * P).clamp_min(0) / (P + 1e-12)).clamp_max(1)
            return ratio.sum(dim) * (n / (n - 1).clamp_min(1))

        s_all = spread(m_all[..., :Y], m_all[..., Y:], S.squeeze(-1), -1).unsqueeze(-1)
        info = info - (
            spread(m_in[..., :Y, :], m_in[..., Y:, :], n1, -2)
            + spread(m_out[..., :Y, :], m_out[..., Y:, :], S - n1, -2)
            - s_all
        ) / (2 * S)
    return info


# On a CPU, trials are processed in chunks whose temporaries stay in a core's cache (about this
# many float64 elements each): one T = 100 batch is slower than 100 single calls otherwise.
_MEMBERSHIP_CHUNK = 2**17


def membership_information(P: Tensor, Z: Tensor, min_count: int = 4, bias_correction: bool = True) -> Tensor:
    r"""Summed information (nats) a query's answer carries about each item's membership of a set.

    ``sum_i I(y; z_i)`` with ``z_i`` the binary label "item ``i`` is in the set" (e.g. the top
    set of :func:`top_set_membership`): the expected reduction of the summed binary entropies
    of the memberships. Each term is ``H[P] - sum_t w_t H[P_t]`` with ``P`` the mean of the
    samples' answer probabilities and ``P_t`` the mean over the samples of label ``t`` (as in
    :func:`sample_information`).

    **Bias.** The entropy of a mean of ``n`` samples is biased low, and the label means have
    few samples, so this plug-in information is biased high: summed over many items the bias
    can exceed the information itself, and it is larger for answers with many outcomes (a
    binned rating) than for a best-of-``m`` choice, so it would tilt a comparison between the
    two. ``bias_correction`` (i) subtracts each entropy's second-order bias
    ``(1 / 2n) sum_y Var(P_y) / P_y`` (sample variances) and (ii) removes what remains of the
    ``1 / S`` term by the split-half extrapolation ``2 I_S - (I_{S/2}' + I_{S/2}'') / 2``
    (items with fewer than two samples of a label in a half keep ``I_S``).

    **Trials.** With a ``T x S x N`` ``Z``, ``T`` independent trials (each its own samples and
    memberships) are valued at once: trial ``t``'s result is that of ``P[t]`` and ``Z[t]``
    alone (to rounding). The items that count differ between trials: each trial's are gathered
    and padded to the largest number, the padding masked out. On a CPU, trials are processed in
    chunks whose temporaries fit a core's cache.

    Args:
        P: ``batch x S x Y`` answer probabilities under each of ``S`` joint posterior samples
            (``batch``: any leading dims, or none); with a 3-D ``Z``, ``T x batch x S x Y``.
        Z: ``S x N`` boolean memberships in the same samples, or ``T x S x N``: one set per
            trial.
        min_count: the fewest samples each label of an item needs for the item to count: a
            (nearly) known membership carries no information to speak of, only bias.
        bias_correction: apply (i) and (ii).

    Returns:
        ``batch`` (with a 3-D ``Z``: ``T x batch``) informations, the sum clamped at 0 (without
        correction: each item's term); 0 where no item counts.
    """
    if Z.dim() == 2:
        if P.dim() < 2:
            raise ValueError(f"P must be batch x S x Y, got shape {tuple(P.shape)}.")
        return _membership_information(P.unsqueeze(0), Z.unsqueeze(0), min_count, bias_correction)[0]
    if Z.dim() != 3:
        raise ValueError(f"Z must be S x N or T x S x N, got shape {tuple(Z.shape)}.")
    if P.dim() < 3 or P.shape[0] != Z.shape[0]:
        raise ValueError(
            f"with a T x S x N Z (T={Z.shape[0]}), P must be T x batch x S x Y, got shape {tuple(P.shape)}."
        )
    return _membership_information(P, Z, min_count, bias_correction)


def _membership_information(P: Tensor, Z: Tensor, min_count: int, bias_correction: bool) -> Tensor:
    """:func:`membership_information` for ``T x batch x S x Y`` ``P`` and ``T x S x N`` ``Z``."""
    T, S = Z.shape[0], Z.shape[1]
    if P.shape[-2] != S:
        raise ValueError(f"P has {P.shape[-2]} samples, Z has {S}.")
    batch, Y = P.shape[1:-2], P.shape[-1]
    n1 = Z.sum(1)  # T x N
    lo = max(min_count, 1)
    keep = (n1 >= lo) & (n1 <= S - lo)
    if bias_correction:
        keep &= (n1 >= 2) & (n1 <= S - 2)
    n = keep.sum(-1)  # T: items that count
    if int(n.max()) == 0:
        return P.new_zeros((T, *batch))
    P = P.reshape(T, math.prod(batch), S, Y)  # T x B x S x Y
    per_trial = 3 * P.shape[1] * int(n.max()) * 2 * Y  # elements of the largest temporary
    step = max(1, _MEMBERSHIP_CHUNK // per_trial) if P.device.type == "cpu" else T
    out = [
        _membership_chunk(
            P[i : i + step], Z[i : i + step], keep[i : i + step], int(n[i : i + step].max()), bias_correction
        )
        for i in range(0, T, step)
    ]
    return (out[0] if len(out) == 1 else torch.cat(out)).reshape(T, *batch)


def _membership_chunk(P: Tensor, Z: Tensor, keep: Tensor, n: int, bias_correction: bool) -> Tensor:
    """``T x B`` informations from ``T x B x S x Y`` ``P``, ``T x S x N`` ``Z`` and the ``T x N``
    items that count, at most ``n`` per trial."""
    T, B, S, Y = P.shape
    if n == 0:
        return P.new_zeros(T, B)
    # each trial's items that count, first (in order) and padded to n: the padding is masked
    # out (with T = 1 there is none: exactly the items that count)
    cols = torch.argsort((~keep).to(torch.int8), dim=-1, stable=True)[:, :n]  # T x n
    Z = Z.gather(2, cols.unsqueeze(1).expand(T, S, n)).to(P)  # T x S x n
    keep = keep.gather(1, cols).unsqueeze(1)  # T x 1 x n
    # (einsum folds B into the product's columns; a matmul would copy Z for each of B)
    if not bias_correction:
        info = _membership_terms(
            torch.einsum("tsn,tbsy->tbyn", Z, P),
            P.sum(-2),
            Z.sum(1, keepdim=True),
            P.new_tensor(float(S)).reshape(1, 1, 1),
            Y,
            False,
        )
        return torch.where(keep, info.clamp_min(0), 0.0).sum(-1)
    PQ = torch.cat([P, P * P], dim=-1)  # T x B x S x 2Y
    if S < 8:
        info = _membership_terms(
            torch.einsum("tsn,tbsy->tbyn", Z, PQ),
            PQ.sum(-2),
            Z.sum(1, keepdim=True),
            P.new_tensor(float(S)).reshape(1, 1, 1),
            Y,
            True,
        )
        return torch.where(keep, info, 0.0).sum(-1).clamp_min(0)
    # the full sample and its two halves at once (the full sums are the halves' sums)
    h = S // 2
    Zh = Z[:, : 2 * h].reshape(T, 2, h, n)  # T x 2 x h x n
    PQh = PQ[..., : 2 * h, :].reshape(T, B, 2, h, 2 * Y)  # T x B x 2 x h x 2Y
    sums = torch.einsum("tksn,tbksy->tkbyn", Zh, PQh)  # T x 2 x B x 2Y x n
    totals, counts = PQh.sum(-2).transpose(1, 2), Zh.sum(-2).unsqueeze(-2)  # T x 2 x B x 2Y, T x 2 x 1 x n
    if S > 2 * h:  # odd S: the last sample counts in the full estimate only
        last, z_last = PQ[..., -1, :], Z[:, -1].unsqueeze(1)  # T x B x 2Y, T x 1 x n
        sums_full = sums.sum(1) + last.unsqueeze(-1) * z_last.unsqueeze(-2)
        totals_full, counts_full = totals.sum(1) + last, counts.sum(1) + z_last
    else:
        sums_full, totals_full, counts_full = sums.sum(1), totals.sum(1), counts.sum(1)
    ns = P.new_tensor([float(S), float(h), float(h)]).reshape(1, 3, 1, 1)
    terms = _membership_terms(
        torch.cat([sums_full.unsqueeze(1), sums], 1),
        torch.cat([totals_full.unsqueeze(1), totals], 1),
        torch.cat([counts_full.unsqueeze(1), counts], 1),
        ns,
        Y,
        True,
    )  # T x 3 x B x n
    info, a, b = terms.unbind(1)
    both = ((counts >= 2) & (counts <= h - 2)).all(1)  # T x 1 x n
    info = torch.where(both, 2 * info - 0.5 * (a + b), info)
    # unbiased terms may be negative: clamp only the sum
    return torch.where(keep, info, 0.0).sum(-1).clamp_min(0)
