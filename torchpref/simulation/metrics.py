r"""Performance measures of the paper's experiments (Sec. IV) and the rating links they use.

All functions reduce over the last dimension and broadcast over any leading batch
dimensions, so ``trials x points`` tensors give one value per trial.

* :func:`wrms`: the weighted RMS error of eq. 14 (weights ``max(u_est, u_true)``).
* :func:`wrms_authors`: the variant in the authors' public code (weights ``u_true`` inside
  the square).
* :func:`true_positives`: how many of the true top-``k`` points are in the estimated
  top-``k`` (Fig. 6b, ``k = 15``).
* :func:`error_on_best`: mean absolute rating error on the best items (Fig. 9a: the lake
  paths the user rates 5).
* :func:`rating_from_latent` / :func:`expected_rating`: latent values to the rating scale,
  through eq. 7's probit link, without and with posterior uncertainty (eq. 11): the
  likelihood's own link (:func:`torchpref.likelihoods.pairwise_beta.rating_link`,
  :func:`~torchpref.likelihoods.pairwise_beta.predictive_rating`) with the inputs checked.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchpref.likelihoods.pairwise_beta import predictive_rating, rating_link

__all__ = [
    "wrms",
    "wrms_authors",
    "true_positives",
    "error_on_best",
    "rating_from_latent",
    "expected_rating",
]


def _pair(name_a: str, a: Tensor, name_b: str, b: Tensor) -> tuple[Tensor, Tensor]:
    a, b = torch.as_tensor(a), torch.as_tensor(b)
    if not a.is_floating_point():
        a = a.to(torch.float64)
    if not b.is_floating_point():
        b = b.to(torch.float64)
    if a.dim() == 0 or b.dim() == 0:
        raise ValueError(
            f"{name_a} and {name_b} need a last (points) dimension, got shapes {tuple(a.shape)} and {tuple(b.shape)}."
        )
    if a.shape[-1] != b.shape[-1] or a.shape[-1] == 0:
        raise ValueError(
            f"{name_a} and {name_b} must have the same non-zero number of points, got "
            f"shapes {tuple(a.shape)} and {tuple(b.shape)}."
        )
    if a.shape != b.shape:
        try:
            torch.broadcast_shapes(a.shape, b.shape)
        except RuntimeError as e:
            raise ValueError(f"{name_a} {tuple(a.shape)} and {name_b} {tuple(b.shape)} do not broadcast.") from e
    return a, b


def wrms(u_est: Tensor, u_true: Tensor) -> Tensor:
    r"""Weighted RMS error of ratings, eq. 14 of the paper.

    .. math::

        \mathrm{WRMS} = \sqrt{\frac{1}{n} \sum_i (u^{est}_i - u^{true}_i)^2
        \max(u^{est}_i, u^{true}_i)}

    Weighting by the larger of the two ratings penalises both a high estimate where the truth
    is low and a low estimate where the truth is high. Ratings are expected in ``[0, 1]``
    (the weights must be non-negative for the root to be real).

    Args:
        u_est: estimated ratings, ``batch_shape x n``.
        u_true: true ratings, ``batch_shape x n`` (broadcastable with ``u_est``).

    Returns:
        A ``batch_shape`` tensor (a scalar for 1-D inputs).

    Raises:
        ValueError: if the last dimensions differ or are empty, or the shapes do not
            broadcast.
    """
    u_est, u_true = _pair("u_est", u_est, "u_true", u_true)
    return ((u_est - u_true).square() * torch.maximum(u_est, u_true)).mean(dim=-1).sqrt()


def wrms_authors(u_est: Tensor, u_true: Tensor) -> Tensor:
    r"""Weighted RMS error as computed in the authors' public code (not eq. 14).

    The code weights the error by the *true* rating inside the square:

    .. math::

        \sqrt{\frac{1}{n} \sum_i \left(u^{true}_i (u^{est}_i - u^{true}_i)\right)^2}

    Unlike :func:`wrms`, an over-estimate where the truth is near 0 costs almost nothing.
    Provided to compare with numbers produced by that code.

    Args:
        u_est: estimated ratings, ``batch_shape x n``.
        u_true: true ratings, ``batch_shape x n`` (broadcastable with ``u_est``).

    Returns:
        A ``batch_shape`` tensor.

    Raises:
        ValueError: as :func:`wrms`.
    """
    u_est, u_true = _pair("u_est", u_est, "u_true", u_true)
    return (u_true * (u_est - u_true)).square().mean(dim=-1).sqrt()


def true_positives(est: Tensor, true: Tensor, k: int = 15) -> Tensor:
    r"""Number of the true top-``k`` points that are also in the estimated top-``k``.

    The measure of the paper's Fig. 6b (``k = 15`` out of the test grid). Only the order of
    the values matters, so latent values or ratings can be passed. Ties are broken by
    :func:`torch.topk`'s (unspecified but deterministic) order.

    Args:
        est: estimated values, ``batch_shape x n``.
        true: true values, ``batch_shape x n`` (broadcastable with ``est``).
        k: the size of the top set, ``1 <= k <= n``.

    Returns:
        A ``batch_shape`` long tensor with values in ``0..k``.

    Raises:
        ValueError: if ``k`` is not in ``1..n`` or the shapes do not match.
    """
    est, true = _pair("est", est, "true", true)
    n = est.shape[-1]
    if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= n:
        raise ValueError(f"k must be an integer in 1..{n} (the number of points), got {k!r}.")
    if est.shape != true.shape:
        shape = torch.broadcast_shapes(est.shape, true.shape)
        est, true = est.expand(shape), true.expand(shape)
    shape = est.shape
    in_est = torch.zeros(shape, dtype=torch.bool, device=est.device)
    in_est.scatter_(-1, est.topk(k, dim=-1).indices, True)
    return in_est.gather(-1, true.topk(k, dim=-1).indices).sum(dim=-1)


def error_on_best(
    u_est: Tensor,
    u_true: Tensor,
    mask: Tensor | None = None,
    *,
    threshold: float | None = None,
) -> Tensor:
    r"""Mean absolute rating error on the best items (paper Fig. 9a).

    In the lake experiment, the error of the predicted rating on the test paths that the
    simulated user rates 5. The items are chosen by, in order of precedence:

    * ``mask``: a boolean ``batch_shape x n`` tensor (broadcastable), ``True`` for the items
      to score;
    * ``threshold``: the items with ``u_true >= threshold``;
    * neither: the items whose true rating equals its maximum (per batch element).

    Args:
        u_est: estimated ratings, ``batch_shape x n``.
        u_true: true ratings, ``batch_shape x n``.
        mask: optional boolean selection, ``batch_shape x n``.
        threshold: optional rating threshold (used only when ``mask`` is ``None``).

    Returns:
        A ``batch_shape`` tensor: ``mean(|u_est - u_true|)`` over the selected items.

    Raises:
        ValueError: if the shapes do not match, ``mask`` is not boolean, both ``mask`` and
            ``threshold`` are given, or some batch element selects no item.
    """
    u_est, u_true = _pair("u_est", u_est, "u_true", u_true)
    if mask is not None and threshold is not None:
        raise ValueError(f"Give mask or threshold, not both (got threshold={threshold}).")
    if mask is None:
        if threshold is None:
            mask = u_true == u_true.amax(dim=-1, keepdim=True)
        else:
            mask = u_true >= threshold
    else:
        mask = torch.as_tensor(mask, device=u_est.device)
        if mask.dtype != torch.bool:
            raise ValueError(f"mask must be a boolean tensor, got dtype {mask.dtype}.")
        if mask.dim() == 0 or mask.shape[-1] != u_est.shape[-1]:
            raise ValueError(
                f"mask must have {u_est.shape[-1]} points in its last dimension, got shape {tuple(mask.shape)}."
            )
    err = (u_est - u_true).abs()
    shape = torch.broadcast_shapes(err.shape, mask.shape)
    err, mask = err.expand(shape), mask.expand(shape)
    count = mask.sum(dim=-1)
    if (count == 0).any():
        raise ValueError(
            f"error_on_best: {int((count == 0).sum())} batch element(s) select no item (threshold={threshold})."
        )
    return torch.where(mask, err, torch.zeros_like(err)).sum(dim=-1) / count


def _check_scale(rating_scale: float | Tensor) -> Tensor | float:
    s = torch.as_tensor(rating_scale)
    if not (torch.isfinite(s).all() and (s > 0).all()):
        raise ValueError(f"rating_scale (sigma_B) must be positive and finite, got {rating_scale}.")
    return rating_scale


def rating_from_latent(f: Tensor, rating_scale: float | Tensor) -> Tensor:
    r"""Map latent values to the rating scale with eq. 7's probit mean link.

    .. math::

        u = \mu_B(x) = \Phi\left(\frac{f(x)}{\sigma_B \sqrt{2}}\right)

    This is the mean of the Beta rating likelihood (eqs. 4-7) at a known latent value, used
    as the "true rating" of a test point.

    Args:
        f: latent values, any shape.
        rating_scale: ``sigma_B`` (positive; a float or a tensor broadcastable with ``f``).

    Returns:
        Ratings in ``(0, 1)``, the shape of ``f``.

    Raises:
        ValueError: if ``rating_scale`` is not positive and finite.
    """
    _check_scale(rating_scale)
    f = torch.as_tensor(f)
    if not f.is_floating_point():
        f = f.to(torch.float64)
    return rating_link(f, rating_scale)


def expected_rating(mean: Tensor, var: Tensor, rating_scale: float | Tensor) -> Tensor:
    r"""Expected rating under a Gaussian latent posterior (eq. 11 for the Beta mean).

    With ``f ~ N(mean, var)`` and eq. 7's link,

    .. math::

        \mathbb{E}[\mu_B] = \int \Phi\left(\frac{f}{\sigma_B\sqrt{2}}\right)
        \mathcal{N}(f; m, v)\, df = \Phi\left(\frac{m}{\sqrt{2\sigma_B^2 + v}}\right),

    which is also the predictive mean of the rating, since the Beta mean is ``mu_B``.

    Args:
        mean: posterior latent means, ``batch_shape x n`` (any shape).
        var: posterior latent variances (non-negative), broadcastable with ``mean``.
        rating_scale: ``sigma_B`` (positive).

    Returns:
        Expected ratings in ``(0, 1)``, the broadcast shape of ``mean`` and ``var``.

    Raises:
        ValueError: if ``rating_scale`` is not positive or ``var`` has negative entries.
    """
    _check_scale(rating_scale)
    mean, var = torch.as_tensor(mean), torch.as_tensor(var)
    if not mean.is_floating_point():
        mean = mean.to(torch.float64)
    if (var < 0).any():
        raise ValueError(f"var must be non-negative, got a minimum of {var.min().item()}.")
    return predictive_rating(mean, var, rating_scale)
