r"""Acquisition functions over queries, in BoTorch's convention (``b x q x d`` -> ``b``).

A batch of ``q = 1`` point is a rating query; ``q = m >= 2`` points are a best-of-``m``
ranking query. So one acquisition function values both query types and a selector
(:mod:`torchpref.strategies`) compares them.

* :func:`latent_ucb`: eq. 12's UCB on the latent utility, BoTorch's own
  ``UpperConfidenceBound`` with ``beta = gamma^2`` (the paper's ``gamma = 3`` is ``beta = 9``).
* :func:`item_ucb`: eq. 12 at each point (with the posterior mean and std), what the UCB
  selectors rank by; :class:`QueryUCB`: the largest UCB among a query's items.
* :class:`QueryInformation`: the mutual information between a query's answer and the latent
  utility, ``I(y; f) = H[y] - E_f H[y | f]``, under the model's own noise: a Beta rating
  (eqs. 4-7) or a best-of-``q`` choice where each item's utility is seen with
  ``N(0, sigma_R^2)`` noise (eq. 3; for ``q = 2`` exactly the probit).
* :func:`sample_information`: the same quantity, or the information about a discrete target
  such as the location of the maximum (entropy search), from joint posterior samples and the
  answer's probabilities under each (:func:`choice_probabilities`,
  :func:`rating_bin_probabilities`); what :class:`~torchpref.strategies.InformationPerEffort`
  uses.
* :func:`membership_information`: the summed information about each item's membership of a set
  such as the top set of each sample (:func:`top_set_membership`), with a finite-sample bias
  correction; :func:`greedy_choice_set` builds a best-of-``m`` query that maximises any such
  value. Both also take a leading dim of ``T`` independent trials (each its own samples), one
  call for ``T`` active-learning runs at once.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from botorch.acquisition import AcquisitionFunction, UpperConfidenceBound
from botorch.models.model import Model
from botorch.utils.transforms import t_batch_mode_transform
from torch import Tensor
from torch.distributions import Beta

from torchpref.numerics import gauss_hermite, log_ndtr


def latent_ucb(model: Model, gamma: float = 3.0) -> UpperConfidenceBound:
    r"""Eq. 12, ``mean + gamma * std`` of the latent utility, as BoTorch's UCB (``beta = gamma^2``)."""
    return UpperConfidenceBound(model, beta=gamma**2)


def item_ucb(model, X: Tensor, gamma: float = 3.0) -> tuple[Tensor, Tensor, Tensor]:
    r"""Eq. 12's ``mean + gamma * std`` of the latent utility at each point of ``X`` (``... x d``),
    with the posterior mean and std (each ``...``). Uses ``model.marginals`` where the model has
    it (:class:`~torchpref.PreferenceGP`, :class:`~torchpref.BatchedPreferenceGP` with ``T x N x d``
    points), else any BoTorch model's posterior."""
    if hasattr(model, "marginals"):
        mean, var = model.marginals(X)
    else:
        post = model.posterior(X.unsqueeze(-2))
        mean, var = post.mean[..., 0, 0], post.variance[..., 0, 0]
    std = var.clamp_min(0).sqrt()
    return mean + gamma * std, mean, std


class QueryUCB(AcquisitionFunction):
    r"""``max_i mean(x_i) + gamma * std(x_i)`` over a query's ``q`` items (eq. 12 for ``q = 1``;
    :func:`item_ucb`)."""

    def __init__(self, model: Model, gamma: float = 3.0):
        super().__init__(model)
        self.gamma = gamma

    @t_batch_mode_transform()
    def forward(self, X: Tensor) -> Tensor:
        return item_ucb(self.model, X, self.gamma)[0].max(dim=-1).values


class QueryInformation(AcquisitionFunction):
    r"""Expected information (nats) that a query's answer carries about the latent utility.

    ``q = 1``: a rating ``u ~ Beta(nu mu(f), nu (1 - mu(f)))`` with ``f ~ N(m, v)``; computed by
    Gauss-Hermite quadrature over ``f`` (closed-form Beta entropies) and a midpoint grid over
    ``u`` for the predictive entropy.

    ``q >= 2``: the index of the best item when each utility is seen with ``N(0, sigma_R^2)``
    noise; ``P(j | f) = E_eps prod_{k != j} Phi((f_j + eps - f_k) / sigma_R)`` by Gauss-Hermite,
    and ``I = H[mean_s P(. | f_s)] - mean_s H[P(. | f_s)]`` over ``num_samples`` joint posterior
    samples (common random numbers from ``generator``, so values are comparable across queries).

    Args:
        model: a :class:`~torchpref.PreferenceGP`.
        num_samples: posterior samples for ranking queries.
        generator: seeds those samples.
    """

    def __init__(self, model: Model, num_samples: int = 128, generator: torch.Generator | None = None,
                 num_quadrature: int = 24, num_grid: int = 400):
        super().__init__(model)
        self.num_samples = num_samples
        self.num_quadrature = num_quadrature
        self.num_grid = num_grid
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        self._seed = int(torch.randint(0, 2**31 - 1, (1,), generator=g))

    @t_batch_mode_transform()
    def forward(self, X: Tensor) -> Tensor:
        post = self.model.posterior(X)
        if X.shape[-2] == 1:
            return self._rating_information(post.mean[..., 0, 0], post.variance[..., 0, 0])
        mvn = post.distribution
        return self._ranking_information(mvn.mean, mvn.covariance_matrix)

    def _rating_information(self, mean: Tensor, var: Tensor) -> Tensor:
        lik = self.model.likelihood.rating
        x, w = gauss_hermite(self.num_quadrature, mean)
        f = mean.unsqueeze(-1) + torch.sqrt(2 * var.clamp_min(0)).unsqueeze(-1) * x  # b x H
        _, _, nu, a, b = lik._shape(f)
        # far-out quadrature nodes can underflow a Beta shape to 0; its entropy term has weight ~0
        tiny = torch.finfo(f.dtype).tiny
        beta = Beta(a.clamp_min(tiny), b.clamp_min(tiny), validate_args=False)
        cond_entropy = (w * beta.entropy()).sum(-1)
        u = (torch.arange(self.num_grid, dtype=mean.dtype, device=mean.device) + 0.5) / self.num_grid
        logp = lik.log_prob(f.unsqueeze(-1), u)  # b x H x G
        log_mix = torch.logsumexp(logp + torch.log(w).unsqueeze(-1), dim=-2)  # b x G
        entropy = -(torch.exp(log_mix) * log_mix).sum(-1) / self.num_grid
        return (entropy - cond_entropy).clamp_min(0)

    def _ranking_information(self, mean: Tensor, cov: Tensor) -> Tensor:
        q = mean.shape[-1]
        g = torch.Generator(device=mean.device).manual_seed(self._seed)
        z = torch.randn(self.num_samples, q, generator=g, dtype=mean.dtype, device=mean.device)
        jitter = 1e-9 * torch.eye(q, dtype=mean.dtype, device=mean.device)
        L = torch.linalg.cholesky_ex(cov + jitter)[0]
        f = mean.unsqueeze(-2) + z @ L.mT  # b x S x q
        p = choice_probabilities(f, self.model.likelihood.comparison.comparison_noise, self.num_quadrature)
        ent = lambda P: -(P * torch.log(P.clamp_min(1e-300))).sum(-1)  # noqa: E731
        return (ent(p.mean(-2)) - ent(p).mean(-1)).clamp_min(0)


def _entropy(P: Tensor, dim: int = -1) -> Tensor:
    return -torch.special.xlogy(P, P).sum(dim)


def choice_probabilities(f: Tensor, comparison_noise: float | Tensor, num_quadrature: int = 6) -> Tensor:
    r"""``... x q`` utilities -> ``... x q`` probabilities that each item is chosen as the best when
    each utility is seen with ``N(0, sigma_R^2)`` noise (eq. 3):
    ``P(j | f) = E_eps prod_{k != j} Phi((f_j + eps - f_k) / sigma_R)``, Gauss-Hermite over eps."""
    x, w = gauss_hermite(num_quadrature, f)
    diff = (f.unsqueeze(-1) - f.unsqueeze(-2)) / comparison_noise  # ... x j x k
    lp = log_ndtr(diff.unsqueeze(-1) + math.sqrt(2) * x)  # ... x j x k x H
    q = f.shape[-1]
    eye = torch.eye(q, dtype=torch.bool, device=f.device).unsqueeze(-1)
    p = (torch.exp(lp.masked_fill(eye, 0.0).sum(-2)) * w).sum(-1)
    return p / p.sum(-1, keepdim=True)


def rating_bin_probabilities(f: Tensor, rating_likelihood, num_bins: int = 32) -> Tensor:
    r"""``...`` utilities -> ``... x num_bins``: the probability of a rating in each of
    ``num_bins`` equal bins of ``[0, 1]`` (Beta density of eqs. 4-7 at the bins' midpoints,
    normalised). A binned rating carries at most the information of the rating itself."""
    u = (torch.arange(num_bins, dtype=f.dtype, device=f.device) + 0.5) / num_bins
    # bins first: the softmax then runs over contiguous rows (a short last dimension is slow)
    logp = rating_likelihood.log_prob(f.unsqueeze(0), u.reshape(num_bins, *([1] * f.dim())))
    return torch.softmax(logp, dim=0).movedim(0, -1)


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
    h_marginal = _entropy(P.mean(-2))
    if labels is None:
        return (h_marginal - _entropy(P).mean(-1)).clamp_min(0)
    S = P.shape[-2]
    k = int(labels.max()) + 1 if num_labels is None else num_labels
    onehot = torch.nn.functional.one_hot(labels, k).to(P)  # S x k
    counts = onehot.sum(0)  # k
    used = counts > 0
    onehot, counts = onehot[:, used], counts[used]
    P_t = (onehot.mT @ P) / counts.unsqueeze(-1)  # batch x k x Y
    return (h_marginal - (counts / S * _entropy(P_t)).sum(-1)).clamp_min(0)


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
    info = (_entropy(m_all[..., :Y]).unsqueeze(-1) - w * _entropy(m_in[..., :Y, :], dim=-2)
            - (1 - w) * _entropy(m_out[..., :Y, :], dim=-2))
    if delta:
        def spread(P: Tensor, Q: Tensor, n: Tensor, dim: int) -> Tensor:
            # sum_y Var_y / P_y (ddof 1), each term in [0, 1]; + 1e-12: a mean at rounding level
            # (the out-label means are differences) adds nothing
            ratio = ((Q - P * P).clamp_min(0) / (P + 1e-12)).clamp_max(1)
            return ratio.sum(dim) * (n / (n - 1).clamp_min(1))

        s_all = spread(m_all[..., :Y], m_all[..., Y:], S.squeeze(-1), -1).unsqueeze(-1)
        info = info - (spread(m_in[..., :Y, :], m_in[..., Y:, :], n1, -2)
                       + spread(m_out[..., :Y, :], m_out[..., Y:, :], S - n1, -2) - s_all) / (2 * S)
    return info


# On a CPU, trials are processed in chunks whose temporaries stay in a core's cache (about this
# many float64 elements each): one T = 100 batch is slower than 100 single calls otherwise.
_MEMBERSHIP_CHUNK = 2**17
_GREEDY_CHUNK = 2**19


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
        raise ValueError(f"with a T x S x N Z (T={Z.shape[0]}), P must be T x batch x S x Y, got shape "
                         f"{tuple(P.shape)}.")
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
    out = [_membership_chunk(P[i:i + step], Z[i:i + step], keep[i:i + step], int(n[i:i + step].max()), bias_correction)
           for i in range(0, T, step)]
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
        info = _membership_terms(torch.einsum("tsn,tbsy->tbyn", Z, P), P.sum(-2), Z.sum(1, keepdim=True),
                                 P.new_tensor(float(S)).reshape(1, 1, 1), Y, False)
        return torch.where(keep, info.clamp_min(0), 0.0).sum(-1)
    PQ = torch.cat([P, P * P], dim=-1)  # T x B x S x 2Y
    if S < 8:
        info = _membership_terms(torch.einsum("tsn,tbsy->tbyn", Z, PQ), PQ.sum(-2), Z.sum(1, keepdim=True),
                                 P.new_tensor(float(S)).reshape(1, 1, 1), Y, True)
        return torch.where(keep, info, 0.0).sum(-1).clamp_min(0)
    # the full sample and its two halves at once (the full sums are the halves' sums)
    h = S // 2
    Zh = Z[:, :2 * h].reshape(T, 2, h, n)  # T x 2 x h x n
    PQh = PQ[..., :2 * h, :].reshape(T, B, 2, h, 2 * Y)  # T x B x 2 x h x 2Y
    sums = torch.einsum("tksn,tbksy->tkbyn", Zh, PQh)  # T x 2 x B x 2Y x n
    totals, counts = PQh.sum(-2).transpose(1, 2), Zh.sum(-2).unsqueeze(-2)  # T x 2 x B x 2Y, T x 2 x 1 x n
    if S > 2 * h:  # odd S: the last sample counts in the full estimate only
        last, z_last = PQ[..., -1, :], Z[:, -1].unsqueeze(1)  # T x B x 2Y, T x 1 x n
        sums_full = sums.sum(1) + last.unsqueeze(-1) * z_last.unsqueeze(-2)
        totals_full, counts_full = totals.sum(1) + last, counts.sum(1) + z_last
    else:
        sums_full, totals_full, counts_full = sums.sum(1), totals.sum(1), counts.sum(1)
    ns = P.new_tensor([float(S), float(h), float(h)]).reshape(1, 3, 1, 1)
    terms = _membership_terms(torch.cat([sums_full.unsqueeze(1), sums], 1),
                              torch.cat([totals_full.unsqueeze(1), totals], 1),
                              torch.cat([counts_full.unsqueeze(1), counts], 1), ns, Y, True)  # T x 3 x B x n
    info, a, b = terms.unbind(1)
    both = ((counts >= 2) & (counts <= h - 2)).all(1)  # T x 1 x n
    info = torch.where(both, 2 * info - 0.5 * (a + b), info)
    # unbiased terms may be negative: clamp only the sum
    return torch.where(keep, info, 0.0).sum(-1).clamp_min(0)


def greedy_choice_set(
    F: Tensor,
    comparison_noise: float | Tensor,
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
            ``T`` tensor, one per trial.
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
        if isinstance(start, Tensor):
            start = int(start)
        chosen, best = _greedy_choice_set(F.unsqueeze(0), comparison_noise, m,
                                          lambda P: value(P[0]).unsqueeze(0), start, num_quadrature)
        return chosen[0].tolist(), float(best[0])
    if F.dim() != 3:
        raise ValueError(f"F must be S x K or T x S x K, got shape {tuple(F.shape)}.")
    return _greedy_choice_set(F, comparison_noise, m, value, start, num_quadrature)


def _greedy_choice_set(F: Tensor, comparison_noise: float | Tensor, m: int, value: Callable[[Tensor], Tensor],
                       start: int | Tensor | None, num_quadrature: int) -> tuple[Tensor, Tensor]:
    """:func:`greedy_choice_set` for ``T x S x K`` ``F``: ``T x m`` chosen columns, ``T`` values."""
    T, S, K = F.shape
    if not 2 <= m <= K:
        raise ValueError(f"need 2 <= m <= {K} items, got m={m}.")
    x, w = gauss_hermite(num_quadrature, F)
    noise = comparison_noise
    per_trial = isinstance(noise, Tensor) and noise.dim() > 0
    if per_trial:
        if noise.shape != (T,):
            raise ValueError(f"comparison_noise must be a scalar or a T={T} tensor, got shape {tuple(noise.shape)}.")
        noise = noise.to(F)
    step = max(1, _GREEDY_CHUNK // (K * K * S * num_quadrature)) if F.device.type == "cpu" else T
    parts = [slice(i, min(i + step, T)) for i in range(0, T, step)]
    Fts = [F[sl].mT for sl in parts]  # t x K x S per chunk

    def phi(diff: Tensor, sl: slice) -> Tensor:
        # f_j - f_k, t x ... x S -> Phi((f_j + eps - f_k) / s) = erfc(-z / sqrt 2) / 2 at the H
        # nodes, t x ... x S x H, in place: products instead of sums of logs (an underflow to 0
        # only drops a negligible probability)
        s = noise[sl].reshape(-1, *(1,) * (diff.dim() - 1)) if per_trial else noise
        z = (diff / s).unsqueeze(-1) + math.sqrt(2) * x
        return z.mul_(-1 / math.sqrt(2)).erfc_().mul_(0.5)

    def column(Ft: Tensor, k: Tensor, sl: slice) -> Tensor:  # t x K x S x H: Phi of (j, k_t) for every j; 1 at j = k_t
        t = torch.arange(Ft.shape[0], device=F.device)
        ph = phi(Ft - Ft[t, k].unsqueeze(1), sl)
        ph[t, k] = 1.0
        return ph

    def probs(*prods: Tensor) -> Tensor:  # t x R x q_i x S x H, ... -> t x R x S x q (q = sum q_i)
        p = torch.cat([prod @ w for prod in prods], dim=2)  # t x R x q x S
        return (p / p.sum(-2, keepdim=True)).transpose(-1, -2)

    def run_value(Ps: list[Tensor], R: int) -> Tensor:
        P = Ps[0] if len(Ps) == 1 else torch.cat(Ps)
        vals = value(P)
        if vals.shape != (T, R):
            raise ValueError(f"value must map {tuple(P.shape)} probabilities to {(T, R)}, got {tuple(vals.shape)}.")
        return vals

    tt = torch.arange(T, device=F.device)
    if start is None:  # every pair (j, c), j < c, from all the Phi terms of a chunk at a time
        j, c = torch.triu_indices(K, K, 1, device=F.device)
        Ps = []
        for Ft, sl in zip(Fts, parts):
            ph = phi(Ft.unsqueeze(2) - Ft.unsqueeze(1), sl)  # t x j x k x S x H (j != k only)
            Ps.append(probs(ph[:, j, c].unsqueeze(2), ph[:, c, j].unsqueeze(2)))
            del ph
        vals = run_value(Ps, j.numel())
        b = vals.argmax(-1)
        chosen, best = torch.stack([j[b], c[b]], -1), vals[tt, b]  # T x 2, T
    else:
        first = torch.as_tensor(start, dtype=torch.long, device=F.device)
        if first.dim() > 1 or first.numel() not in (1, T):
            raise ValueError(f"start must be an int or a T={T} tensor, got shape {tuple(first.shape)}.")
        first = first.reshape(-1).expand(T)
        if not bool(((first >= 0) & (first < K)).all()):
            raise ValueError(f"start must be in 0..{K - 1}, got {start}.")
        chosen, best = first.reshape(T, 1), F.new_full((T,), math.nan)
    # A[t, j] = prod over chosen k of Phi(j, k): t x K x S x H per chunk
    As = []
    for Ft, sl in zip(Fts, parts):
        A = column(Ft, chosen[sl, 0], sl)
        for i in range(1, chosen.shape[1]):
            A.mul_(column(Ft, chosen[sl, i], sl))
        As.append(A)
    while chosen.shape[1] < m:
        c = chosen.shape[1]
        mask = torch.ones(T, K, dtype=torch.bool, device=F.device)
        mask[tt.unsqueeze(-1), chosen] = False
        rest = mask.nonzero()[:, 1].reshape(T, K - c)  # ascending, per trial
        Ps = []
        for Ft, A, sl in zip(Fts, As, parts):
            ch, re = chosen[sl].unsqueeze(1), rest[sl].unsqueeze(-1)  # t x 1 x c, t x r x 1
            ti = torch.arange(Ft.shape[0], device=F.device).reshape(-1, 1, 1)
            old = A[ti, ch] * phi(Ft[ti, ch] - Ft[ti, re], sl)  # t x r x c x S x H: the chosen items
            Ps.append(probs(old, A[ti, re]))  # and the added one: sets t x r x (c + 1) x S x H
        vals = run_value(Ps, K - c)
        b = vals.argmax(-1)
        new = rest[tt, b]
        chosen, best = torch.cat([chosen, new.unsqueeze(-1)], -1), vals[tt, b]
        if chosen.shape[1] < m:
            for Ft, A, sl in zip(Fts, As, parts):
                A.mul_(column(Ft, new[sl], sl))
    return chosen, best
