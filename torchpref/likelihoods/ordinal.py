r"""Ordered-probit likelihoods (not in the paper): "no preference" ties and ratings given as levels.

Both score an interval of a Gaussian: a tie of ``[i, j]`` says the perceived difference
``f_i - f_j + noise`` fell within ``(-tau, tau)``; a level ``k`` says the perceived utility
``f_i + noise`` fell between the cut points ``c_{k-1}`` and ``c_k``. Their log-likelihoods and
three derivatives come from one function, :func:`torchpref.inference.numerics.normal_interval`, and both
are log-concave, so their part of ``W`` (eq. 8) is never negative. They follow the interface of
:mod:`torchpref.likelihoods.pairwise_beta` (``derivatives``, ``third_derivative``, ``fisher``, predictives).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from gpytorch.constraints import Interval
from gpytorch.distributions import MultivariateNormal
from gpytorch.likelihoods import Likelihood
from gpytorch.priors import Prior
from torch import Tensor
from torch.distributions import Bernoulli, Categorical

from torchpref.inference.numerics import normal_interval
from torchpref.likelihoods.pairwise_beta import SQRT2, PairwiseProbitLikelihood
from torchpref.likelihoods.scalar_params import _ScalarParamsMixin, scalar_parameter, weak_load_hook


class TieLikelihood(_ScalarParamsMixin, Likelihood):
    r"""Likelihood of a "no preference" answer between two items (a Thurstone tie).

    The person perceives each item's utility with the noise of eq. 3 and finds no preference
    when the perceived difference is within a threshold ``tau``:

    .. math::
        p(x_i \sim x_j \mid f) = \Phi\!\left(\frac{\tau - \eta}{s}\right)
            - \Phi\!\left(\frac{-\tau - \eta}{s}\right), \qquad \eta = f_i - f_j,\ s = \sqrt2\,\sigma_R,

    the middle category of an ordered probit on ``eta``. It is symmetric in ``eta`` (the order of
    a tie's two items does not matter) and log-concave. Strict comparisons keep eq. 3 (a forced
    choice); see docs/likelihoods.md.

    Args:
        tie_threshold: ``tau``, in latent-utility units (default 0.1: about one ``s`` at the
            default ``sigma_R``).
        comparison: the :class:`PairwiseProbitLikelihood` whose ``sigma_R`` this one shares
            (a new one with the default ``sigma_R`` if ``None``).
        learn: whether ``tie_threshold`` is a trainable parameter.
    """

    log_concave = True  # its weights in W are never negative

    #: the compiled path (:mod:`torchpref.inference._compiled`) knows this likelihood; a subclass
    #: (which may change its derivatives) is solved by the torch solver unless it says so too
    compiled_kind = "tie"

    def __init__(
        self,
        tie_threshold: float = 0.1,
        comparison: PairwiseProbitLikelihood | None = None,
        *,
        learn: bool = False,
        tie_threshold_prior: Prior | None = None,
        tie_threshold_constraint: Interval | None = None,
    ):
        super().__init__()
        self.comparison = comparison if comparison is not None else PairwiseProbitLikelihood()
        self._register("tie_threshold", tie_threshold, tie_threshold_constraint, tie_threshold_prior, learn)

    tie_threshold = scalar_parameter(
        "tie_threshold", '``tau``, the largest perceived difference answered with "no preference".'
    )

    def forward(self, function_samples: Tensor, ties: Tensor) -> Bernoulli:
        """Distribution of "no preference" for each row ``[i, j]`` of ``ties`` (``t x 2`` long)
        given latent values ``function_samples`` (``... x n``): a Bernoulli of batch ``... x t``."""
        eta = function_samples[..., ties[:, 0]] - function_samples[..., ties[:, 1]]
        return Bernoulli(probs=self.log_prob(eta).exp())

    def log_prob(self, eta: Tensor) -> Tensor:
        """``log p`` of a tie given its predictor ``eta = f_i - f_j``."""
        return self.derivatives(eta)[0]

    def derivatives(self, eta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        r"""``(log p, d log p / d eta, d^2 log p / d eta^2)``, elementwise: those of a Gaussian
        interval probability (:func:`torchpref.inference.numerics.normal_interval` with bounds
        ``+-tau - eta`` and scale ``s``); the second derivative is never positive."""
        tau = self.tie_threshold
        lp, d1, d2 = normal_interval(tau - eta, -tau - eta, self.comparison.scale)
        return lp, d1, d2

    def third_derivative(self, eta: Tensor) -> Tensor:
        """``d^3 log p / d eta^3``, elementwise (for the evidence's gradient)."""
        tau = self.tie_threshold
        return normal_interval(tau - eta, -tau - eta, self.comparison.scale, third=True)[3]

    def fisher(self, eta: Tensor) -> Tensor:
        """Negative second derivative; already non-negative (log-concave)."""
        return -self.derivatives(eta)[2]

    def tie_probability(self, mean_diff: Tensor, var_diff: Tensor) -> Tensor:
        r"""Predictive ``P(a ~ b) = Phi((tau - m) / r) - Phi((-tau - m) / r)`` with
        ``r = sqrt(2 sigma_R^2 + v)``, ``m = m_a - m_b`` and ``v`` the posterior variance of
        ``f_a - f_b``."""
        tau = self.tie_threshold
        r = torch.sqrt(2 * self.comparison.comparison_noise**2 + var_diff.clamp_min(0))
        return normal_interval(tau - mean_diff, -tau - mean_diff, r)[0].exp()

    def marginal(self, function_dist: MultivariateNormal, ties: Tensor) -> Bernoulli:
        """Analytic predictive of "no preference" for each row of ``ties`` under a joint Gaussian."""
        m, S = function_dist.mean, function_dist.covariance_matrix
        i, j = ties[:, 0], ties[:, 1]
        return Bernoulli(
            probs=self.tie_probability(m[..., i] - m[..., j], S[..., i, i] + S[..., j, j] - 2 * S[..., i, j])
        )


class StrictPreferenceLikelihood(Likelihood):
    r"""A strict comparison where "no preference" was an allowed answer: the upper category of the
    tie's ordered probit,

    .. math::
        p(x_i \succ x_j \mid f) = \Phi\!\left(\frac{\eta - \tau}{s}\right), \qquad \eta = f_i - f_j,

    so that strict answers, ties and reversed answers sum to one. Without it (eq. 3, a forced
    choice) the likelihood of the data only grows with ``tau`` and ``tau`` cannot be learned.
    With ``tau = 0`` it is eq. 3. Log-concave.

    Args:
        tie: the :class:`TieLikelihood` whose ``tau`` and ``sigma_R`` it uses.
    """

    log_concave = True  # its weights in W are never negative
    #: the compiled path (:mod:`torchpref.inference._compiled`) knows this likelihood; a subclass
    #: (which may change its derivatives or link) is solved by the torch solver unless it says so too
    compiled_kind = "strict"

    def __init__(self, tie: TieLikelihood):
        super().__init__()
        weak_load_hook(self)
        self.tie = tie

    def _bounds(self, eta: Tensor) -> tuple[Tensor, Tensor]:
        return torch.full_like(eta, math.inf), self.tie.tie_threshold - eta

    def forward(self, function_samples: Tensor, comparisons: Tensor) -> Bernoulli:
        """Distribution of "the first item of each row is strictly preferred" (``... x p``)."""
        eta = function_samples[..., comparisons[:, 0]] - function_samples[..., comparisons[:, 1]]
        return Bernoulli(probs=self.log_prob(eta).exp())

    def log_prob(self, eta: Tensor) -> Tensor:
        """``log p`` of a strict answer given its predictor ``eta = f_preferred - f_other``."""
        return self.derivatives(eta)[0]

    def derivatives(self, eta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(log p, d log p / d eta, d^2 log p / d eta^2)``, elementwise."""
        lp, d1, d2 = normal_interval(*self._bounds(eta), self.tie.comparison.scale)
        return lp, d1, d2

    def third_derivative(self, eta: Tensor) -> Tensor:
        """``d^3 log p / d eta^3``, elementwise (for the evidence's gradient)."""
        return normal_interval(*self._bounds(eta), self.tie.comparison.scale, third=True)[3]

    def fisher(self, eta: Tensor) -> Tensor:
        """Negative second derivative; already non-negative (log-concave)."""
        return -self.derivatives(eta)[2]

    def preference_probability(self, mean_diff: Tensor, var_diff: Tensor) -> Tensor:
        r"""Predictive ``P(a > b) = Phi((m - tau) / sqrt(2 sigma_R^2 + v))``."""
        r = torch.sqrt(2 * self.tie.comparison.comparison_noise**2 + var_diff.clamp_min(0))
        return torch.special.ndtr((mean_diff - self.tie.tie_threshold) / r)


def default_cut_points(num_levels: int, rating_scale: float = 1.0) -> Tensor:
    r"""``c_k = sqrt 2 sigma_B Phi^{-1}(k / K)``, ``k = 1..K-1``: where the Beta likelihood's mean
    rating (eq. 7) crosses the edges of the ``K`` equal bins of ``likert_to_unit``, so that the
    latent scale means the same under both rating likelihoods (5 levels: ``-1.19, -0.36, 0.36, 1.19``)."""
    k = torch.arange(1, num_levels, dtype=torch.float64)
    return SQRT2 * rating_scale * torch.special.ndtri(k / num_levels)


class OrdinalRatingLikelihood(_ScalarParamsMixin, Likelihood):
    r"""Ordered-probit likelihood of a rating given as a level ``k`` in ``1..K``.

    .. math::
        p(k \mid f) = \Phi\!\left(\frac{c_k - f}{\sigma}\right) - \Phi\!\left(\frac{c_{k-1} - f}{\sigma}\right),
        \qquad c_0 = -\infty < c_1 < \dots < c_{K-1} < c_K = \infty.

    The cut points are ``c_1 = r_1``, ``c_k = c_{k-1} + softplus(r_k)`` for the raw parameters
    ``r``, so they stay ordered whatever the optimiser does. Log-concave in ``f``.

    Args:
        num_levels: ``K >= 2``.
        cut_points: ``K - 1`` increasing values; default :func:`default_cut_points`.
        level_noise: ``sigma``, the noise on the latent utility when a person picks a level
            (default 0.2: the Beta likelihood's default noise at mid-scale, in latent units).
        learn: whether the cut points are trainable (by default with a ``Normal(initial, 0.5)``
            prior on each, which keeps unused levels' cut points from drifting away).
        cut_points_prior: a prior on the ``K - 1`` cut points (replaces the default one).
        learn_noise: whether ``level_noise`` is trainable (it is not identifiable separately from
            the kernel's outputscale and the cut points without comparisons).
    """

    log_concave = True  # its weights in W are never negative

    #: the compiled path (:mod:`torchpref.inference._compiled`) knows this likelihood; a subclass
    #: (which may change its derivatives) is solved by the torch solver unless it says so too
    compiled_kind = "ordinal"

    def __init__(
        self,
        num_levels: int = 5,
        cut_points: Tensor | Sequence[float] | None = None,
        level_noise: float = 0.2,
        *,
        learn: bool = False,
        cut_points_prior: Prior | None = None,
        learn_noise: bool = False,
        level_noise_prior: Prior | None = None,
    ):
        super().__init__()
        if int(num_levels) != num_levels or num_levels < 2:
            raise ValueError(f"num_levels must be an integer of at least 2, got {num_levels}.")
        self.num_levels = int(num_levels)
        self._register("level_noise", level_noise, None, level_noise_prior, learn_noise)
        self.register_parameter(
            "raw_cut_points",
            torch.nn.Parameter(torch.zeros(self.num_levels - 1, dtype=torch.float64), requires_grad=learn),
        )
        self.cut_points = default_cut_points(self.num_levels) if cut_points is None else cut_points
        if learn and cut_points_prior is None:
            from gpytorch.priors import NormalPrior

            cut_points_prior = NormalPrior(torch.as_tensor(self.cut_points).detach().clone(), 0.5)
        if cut_points_prior is not None:
            self.register_prior(
                "cut_points_prior", cut_points_prior, lambda m: m.cut_points, lambda m, v: setattr(m, "cut_points", v)
            )

    level_noise = scalar_parameter("level_noise", "``sigma``, the noise on the latent utility when a level is picked.")

    @property
    def cut_points(self) -> Tensor:
        """The ``K - 1`` increasing cut points ``c_1..c_{K-1}``."""
        r = self.raw_cut_points
        return torch.cat([r[:1], r[:1] + torch.cumsum(torch.nn.functional.softplus(r[1:]), 0)])

    @cut_points.setter
    def cut_points(self, value: Tensor | Sequence[float]) -> None:
        raw = self.raw_cut_points
        c = torch.as_tensor(value, dtype=raw.dtype, device=raw.device).reshape(-1)
        if c.numel() != self.num_levels - 1 or not torch.isfinite(c).all() or (c.diff() <= 0).any():
            raise ValueError(
                f"cut_points must be {self.num_levels - 1} finite, strictly increasing values, got {c.tolist()}."
            )
        gaps = c.diff()
        with torch.no_grad():  # softplus^-1(g) = g + log(-expm1(-g))
            raw.copy_(torch.cat([c[:1], gaps + torch.log(-torch.expm1(-gaps))]))

    def check_levels(self, levels: Tensor | Sequence[float]) -> Tensor:
        """``levels`` as a long tensor, or a ``ValueError`` naming any value not an integer in ``1..K``."""
        y = torch.as_tensor(levels)
        bad = (
            (y != y.round()) | (y < 1) | (y > self.num_levels)
            if y.is_floating_point()
            else ((y < 1) | (y > self.num_levels))
        )
        if bad.any():
            raise ValueError(f"rating levels must be integers in 1..{self.num_levels}, got {y[bad][:5].tolist()}.")
        return y.long()

    def _bounds(self, eta: Tensor, levels: Tensor) -> tuple[Tensor, Tensor]:
        """``(c_k - eta, c_{k-1} - eta)`` for each level ``k``."""
        y = self.check_levels(levels).to(eta.device)
        inf = eta.new_full((1,), math.inf)
        c = torch.cat([-inf, self.cut_points.to(eta), inf])
        return c[y] - eta, c[y - 1] - eta

    def forward(self, function_samples: Tensor) -> Categorical:
        """The distribution of the level (category ``k - 1`` is level ``k``) given latent values
        (any shape ``...``): a Categorical of batch shape ``...`` over ``K`` categories."""
        levels = torch.arange(1, self.num_levels + 1, device=function_samples.device)
        return Categorical(logits=self.log_prob(function_samples.unsqueeze(-1), levels))

    def log_prob(self, eta: Tensor, levels: Tensor) -> Tensor:
        """``log p(k | eta)`` of each level ``k`` (``levels`` broadcast with ``eta``)."""
        return normal_interval(*self._bounds(eta, levels), self.level_noise)[0]

    def derivatives(self, eta: Tensor, levels: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        r"""``(log p, d log p / d eta, d^2 log p / d eta^2)``, elementwise: those of a Gaussian
        interval probability (:func:`torchpref.inference.numerics.normal_interval` with bounds
        ``c_k - eta``, ``c_{k-1} - eta`` and scale ``sigma``)."""
        lp, d1, d2 = normal_interval(*self._bounds(eta, levels), self.level_noise)
        return lp, d1, d2

    def third_derivative(self, eta: Tensor, levels: Tensor) -> Tensor:
        """``d^3 log p / d eta^3``, elementwise (for the evidence's gradient)."""
        return normal_interval(*self._bounds(eta, levels), self.level_noise, third=True)[3]

    def fisher(self, eta: Tensor) -> Tensor:
        r"""Expected negative second derivative ``sum_k p(k | eta) (-d^2 log p(k | eta))`` (non-negative)."""
        levels = torch.arange(1, self.num_levels + 1, device=eta.device)
        lp, _, d2 = normal_interval(*self._bounds(eta.unsqueeze(-1), levels), self.level_noise)
        return -(lp.exp() * d2).sum(-1)

    def level_probabilities(self, mean: Tensor, var: Tensor) -> Tensor:
        r"""Predictive ``P(k) = Phi((c_k - m) / r) - Phi((c_{k-1} - m) / r)``, ``r = sqrt(sigma^2 + v)``:
        ``mean``, ``var`` (broadcast, shape ``...``) give ``... x K``."""
        mean, var = torch.broadcast_tensors(mean, var)
        levels = torch.arange(1, self.num_levels + 1, device=mean.device)
        r = torch.sqrt(self.level_noise**2 + var.clamp_min(0)).unsqueeze(-1)
        return normal_interval(*self._bounds(mean.unsqueeze(-1), levels), r)[0].exp()

    def expected_level(self, mean: Tensor, var: Tensor) -> Tensor:
        r"""Predictive mean level ``E[k] = 1 + sum_k Phi((m - c_k) / sqrt(sigma^2 + v))``, in ``[1, K]``."""
        r = torch.sqrt(self.level_noise**2 + var.clamp_min(0)).unsqueeze(-1)
        return 1 + torch.special.ndtr((mean.unsqueeze(-1) - self.cut_points.to(mean)) / r).sum(-1)

    def expected_rating(self, mean: Tensor, var: Tensor) -> Tensor:
        r"""The expected level on ``[0, 1]`` as ``likert_to_unit`` maps levels: ``(E[k] - 1/2) / K``
        (so that code written for the Beta likelihood's ``expected_rating`` reads the same scale)."""
        return (self.expected_level(mean, var) - 0.5) / self.num_levels

    def marginal(self, function_dist: MultivariateNormal) -> Categorical:
        """Predictive distribution of the level at each point (category ``k - 1`` is level ``k``)."""
        return Categorical(probs=self.level_probabilities(function_dist.mean, function_dist.variance))
