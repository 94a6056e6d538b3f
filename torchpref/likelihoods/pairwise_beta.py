r"""The likelihoods of the model, as GPyTorch likelihoods.

Each is a function of one latent scalar per observation, its *predictor* ``eta``:

* :class:`PairwiseProbitLikelihood` (eq. 3): ``eta = f_i - f_j`` for a comparison ``[i, j]``
  (``i`` preferred), ``p(i > j | f) = Phi(eta / (sqrt 2 sigma_R))``.
* :class:`BetaRatingLikelihood` (eqs. 4-7): ``eta = f_i`` for a rating of item ``i``,
  ``u ~ Beta(nu mu, nu (1 - mu))`` with ``mu = Phi(eta / (sqrt 2 sigma_B))``.

and, in :mod:`torchpref.likelihoods.ordinal` (not in the paper), the ordered-probit ones:

* :class:`~torchpref.likelihoods.ordinal.TieLikelihood`: ``eta = f_i - f_j`` for a "no preference" answer,
  ``p(i ~ j | f) = Phi((tau - eta) / s) - Phi((-tau - eta) / s)`` (Thurstone with a threshold).
* :class:`~torchpref.likelihoods.ordinal.OrdinalRatingLikelihood`: ``eta = f_i`` for a level ``k`` in
  ``1..K``, ``p(k | f) = Phi((c_k - eta) / sigma) - Phi((c_{k-1} - eta) / sigma)`` (ordered probit).

:meth:`derivatives` returns the log-likelihood and its first and second derivatives with
respect to ``eta``, in closed form (tested against autograd); :mod:`torchpref.inference.laplace` chains
them to the latent vector. The analytic predictives of eq. 11 sit beside them.
"""

from __future__ import annotations

import math

import torch
from gpytorch.constraints import Interval
from gpytorch.distributions import MultivariateNormal
from gpytorch.likelihoods import Likelihood
from gpytorch.priors import Prior
from torch import Tensor
from torch.distributions import Bernoulli, Beta

from torchpref.inference.numerics import gauss_hermite, inv_mills, log_ndtr, normal_pdf
from torchpref.likelihoods.scalar_params import _ScalarParamsMixin, scalar_parameter

SQRT2 = math.sqrt(2.0)


def rating_link(f: Tensor, rating_scale: float | Tensor) -> Tensor:
    r"""Eq. 7's probit mean link ``mu = Phi(f / (sqrt 2 sigma_B))``: the mean rating of an item
    of latent utility ``f`` (any shape; ``rating_scale`` ``sigma_B`` broadcastable with it)."""
    return torch.special.ndtr(f / (SQRT2 * rating_scale))


def thurstone_choice_probabilities(f: Tensor, comparison_noise: float | Tensor, num_quadrature: int = 6) -> Tensor:
    r"""``... x q`` utilities -> ``... x q``: the probability that each item is chosen as the best
    when each utility is seen with ``N(0, sigma_R^2)`` noise (Thurstone; eq. 3 for ``q = 2``),
    ``P(j | f) = E_eps prod_{k != j} Phi((f_j + eps - f_k) / sigma_R)``, ``eps ~ N(0, sigma_R^2)``
    by Gauss-Hermite (``q = 2`` in closed form: ``Phi((f_1 - f_2) / (sqrt 2 sigma_R))``).
    ``comparison_noise`` broadcasts against ``f``'s leading dims."""
    noise = torch.as_tensor(comparison_noise, dtype=f.dtype, device=f.device)
    noise = noise.reshape(*noise.shape, *(1,) * (f.dim() - noise.dim()))  # leading dims, then 1s
    if f.shape[-1] == 2:
        p = torch.special.ndtr((f[..., :1] - f[..., 1:]) / (SQRT2 * noise))
        return torch.cat([p, 1 - p], -1)
    x, w = gauss_hermite(num_quadrature, f)
    diff = (f.unsqueeze(-1) - f.unsqueeze(-2)) / noise.unsqueeze(-1)  # ... x j x k
    lp = log_ndtr(diff.unsqueeze(-1) + SQRT2 * x)  # ... x j x k x H
    eye = torch.eye(f.shape[-1], dtype=torch.bool, device=f.device).unsqueeze(-1)
    p = (torch.exp(lp.masked_fill(eye, 0.0).sum(-2)) * w).sum(-1)
    return p / p.sum(-1, keepdim=True)


def predictive_rating(mean: Tensor, var: Tensor, rating_scale: float | Tensor) -> Tensor:
    r"""Predictive mean rating under ``f ~ N(mean, var)`` (eq. 11 for the Beta mean):
    ``E[Phi(f / (sqrt 2 sigma_B))] = Phi(m / sqrt(2 sigma_B^2 + v))`` (negative ``var`` counts as 0)."""
    scale = torch.as_tensor(rating_scale, dtype=mean.dtype, device=mean.device)
    return torch.special.ndtr(mean / torch.sqrt(2 * scale.square() + var.clamp_min(0)))


class PairwiseProbitLikelihood(_ScalarParamsMixin, Likelihood):
    r"""Probit likelihood of a comparison, eq. 3.

    .. math::
        p(x_i \succ x_j \mid f) = \Phi\!\left(\frac{f_i - f_j}{\sqrt{2}\,\sigma_R}\right)

    Args:
        comparison_noise: ``sigma_R``, the standard deviation of the noise on each item's utility
            when the person compares. BoTorch's ``PairwiseGP`` uses ``Phi((f_i - f_j) / sqrt 2)``,
            which is ``comparison_noise = 1``.
        learn: whether ``comparison_noise`` is a trainable parameter (off by default: with
            comparisons only it is not identifiable separately from the kernel's outputscale).
    """

    def __init__(
        self,
        comparison_noise: float = 0.1,
        *,
        learn: bool = False,
        comparison_noise_prior: Prior | None = None,
        comparison_noise_constraint: Interval | None = None,
    ):
        super().__init__()
        self._register("comparison_noise", comparison_noise, comparison_noise_constraint, comparison_noise_prior, learn)

    comparison_noise = scalar_parameter("comparison_noise", "``sigma_R`` (eq. 3): the noise of a comparison.")

    #: the compiled path (:mod:`torchpref.inference._compiled`) knows this likelihood; a subclass
    #: (which may change its derivatives) is solved by the torch solver unless it says so too
    compiled_kind = "probit"

    @property
    def scale(self) -> Tensor:
        """The probit's scale ``sqrt(2) sigma_R``: ``P(i > j) = Phi((f_i - f_j) / scale)`` (eq. 3)."""
        return SQRT2 * self.comparison_noise

    def forward(self, function_samples: Tensor, comparisons: Tensor) -> Bernoulli:
        r"""Distribution of "the first item of each comparison row is preferred".

        Args:
            function_samples: ``... x n`` latent values.
            comparisons: ``p x 2`` long.

        Returns:
            A Bernoulli of batch shape ``... x p``.
        """
        eta = function_samples[..., comparisons[:, 0]] - function_samples[..., comparisons[:, 1]]
        return Bernoulli(probs=torch.special.ndtr(eta / self.scale))

    def log_prob(self, eta: Tensor) -> Tensor:
        """``log p`` of each comparison given its predictor ``eta = f_preferred - f_other``."""
        return log_ndtr(eta / self.scale)

    def derivatives(self, eta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        r"""``(log p, d log p / d eta, d^2 log p / d eta^2)``, elementwise.

        With ``s = sqrt 2 sigma_R``, ``z = eta / s`` and ``r = phi(z) / Phi(z)``:
        ``d/d eta = r / s`` and ``d^2/d eta^2 = -r (z + r) / s^2`` (always negative: the
        probit is log-concave).
        """
        s = self.scale
        z = eta / s
        log_cdf = log_ndtr(z)
        r = inv_mills(z, log_cdf)
        return log_cdf, r / s, -r * (z + r) / (s * s)

    def third_derivative(self, eta: Tensor) -> Tensor:
        r"""``d^3 log p / d eta^3 = -r (1 - (z + r)(z + 2 r)) / s^3``, elementwise (how fast the
        curvature changes; the evidence's gradient needs it)."""
        s = self.scale
        z = eta / s
        r = inv_mills(z)
        return -r * (1 - (z + r) * (z + 2 * r)) / s**3

    def fisher(self, eta: Tensor) -> Tensor:
        """Negative second derivative; already non-negative for the probit."""
        return -self.derivatives(eta)[2]

    def with_lapses(self, P: Tensor) -> Tensor:
        r"""The answer probabilities of a best-of-``q`` choice (``... x q``) as this person gives
        them: unchanged here; :class:`~torchpref.likelihoods.person.LapseProbitLikelihood` mixes in
        its lapses."""
        return P

    def choice_probabilities(self, f: Tensor, num_quadrature: int = 6) -> Tensor:
        r"""The probability of each answer to a best-of-``q`` query given latent values ``f``
        (``... x q`` -> ``... x q``; ``q = 2`` is a comparison, eq. 3): the one home of an
        answer's probability, which acquisition and selection call. Thurstone's choice with this
        likelihood's ``sigma_R`` (:func:`thurstone_choice_probabilities`), then
        :meth:`with_lapses`."""
        return self.with_lapses(thurstone_choice_probabilities(f, self.comparison_noise, num_quadrature))

    def preference_probability(self, mean_diff: Tensor, var_diff: Tensor) -> Tensor:
        r"""Predictive ``P(a > b)`` (eq. 11): ``Phi((m_a - m_b) / sqrt(2 sigma_R^2 + v_a + v_b - 2 c_ab))``.

        Args:
            mean_diff: ``m_a - m_b``.
            var_diff: ``v_a + v_b - 2 c_ab``, the posterior variance of ``f_a - f_b``.
        """
        return torch.special.ndtr(mean_diff / torch.sqrt(2 * self.comparison_noise**2 + var_diff.clamp_min(0)))

    def marginal(self, function_dist: MultivariateNormal, comparisons: Tensor) -> Bernoulli:
        """Analytic predictive of each comparison row under a joint Gaussian over the items."""
        m = function_dist.mean
        S = function_dist.covariance_matrix
        i, j = comparisons[:, 0], comparisons[:, 1]
        var = S[..., i, i] + S[..., j, j] - 2 * S[..., i, j]
        return Bernoulli(probs=self.preference_probability(m[..., i] - m[..., j], var))


class BetaRatingLikelihood(_ScalarParamsMixin, Likelihood):
    r"""Beta likelihood of a rating ``u`` in ``(0, 1)`` with a probit mean link, eqs. 4-7.

    .. math::
        u \sim \mathrm{Beta}(\nu \mu, \nu (1 - \mu)), \qquad
        \mu = \Phi\!\left(\frac{f}{\sqrt{2}\,\sigma_B}\right)

    (the paper prints ``beta = (1 - nu) mu``, a typo: see docs/decisions.md).

    Args:
        rating_scale: ``sigma_B``, how the latent utility maps onto the rating scale (eq. 7).
        rating_precision: ``nu``, the Beta precision: larger means less noisy ratings.
        learn: whether both are trainable parameters (off by default).
    """

    def __init__(
        self,
        rating_scale: float = 1.0,
        rating_precision: float = 80.0,
        *,
        learn: bool = False,
        rating_scale_prior: Prior | None = None,
        rating_precision_prior: Prior | None = None,
        rating_scale_constraint: Interval | None = None,
        rating_precision_constraint: Interval | None = None,
    ):
        super().__init__()
        self._register("rating_scale", rating_scale, rating_scale_constraint, rating_scale_prior, learn)
        self._register(
            "rating_precision",
            rating_precision,
            rating_precision_constraint,
            rating_precision_prior,
            learn,
            default="precision",
        )

    rating_scale = scalar_parameter(
        "rating_scale", "``sigma_B`` (eq. 7): how the latent utility maps onto the rating scale."
    )

    rating_precision = scalar_parameter(
        "rating_precision",
        "``nu`` (eqs. 4-7): the precision of a rating's Beta distribution (larger: less noisy ratings).",
    )

    #: the compiled path (:mod:`torchpref.inference._compiled`) knows this likelihood; a subclass
    #: (which may change its derivatives or link) is solved by the torch solver unless it says so too
    compiled_kind = "beta"

    def mean_link(self, f: Tensor) -> Tensor:
        r"""``mu = Phi(f / (sqrt 2 sigma_B))``, eq. 7 (:func:`rating_link`)."""
        return torch.special.ndtr(self._link(f)[1])

    def forward(self, function_samples: Tensor) -> Beta:
        """The distribution of a rating given latent values ``function_samples`` (any shape)."""
        _, t = self._link(function_samples)
        nu = self.rating_precision
        return Beta(nu * torch.special.ndtr(t), nu * torch.special.ndtr(-t))

    def _link(self, eta: Tensor) -> tuple[Tensor, Tensor]:
        """The link's scale ``c = d eta / d t`` (here ``sqrt 2 sigma_B``) and the standardised
        predictor ``t`` (here ``eta / c``) with ``mu = Phi(t)``; a subclass may shift and scale it."""
        c = SQRT2 * self.rating_scale
        return c, eta / c

    def _latent_at(self, u: Tensor) -> Tensor:
        """The latent value whose mean rating is ``u`` (``Phi(t) = u``)."""
        return SQRT2 * self.rating_scale.detach() * torch.special.ndtri(u)

    def _log_shape(self, eta: Tensor):
        """``c = sqrt 2 sigma_B``, ``t = eta / c``, ``nu``, ``log mu`` and ``log(1 - mu)``."""
        c, t = self._link(eta)
        return c, t, self.rating_precision, log_ndtr(t), log_ndtr(-t)

    def beta_parameters(self, eta: Tensor) -> tuple[Tensor, Tensor]:
        r"""The Beta's ``(alpha, beta) = (nu mu, nu (1 - mu))`` of a rating at latent ``eta``
        (eqs. 5-7), computed through ``log mu`` so that neither underflows to a NaN."""
        _, _, nu, log_mu, log_1mmu = self._log_shape(eta)
        return nu * torch.exp(log_mu), nu * torch.exp(log_1mmu)

    def _parts(self, eta: Tensor, u: Tensor):
        r"""``log p`` (with ``lgamma(a) = lgamma(a + 1) - log a``, ``log a = log nu + log mu``), the
        first derivative ``g``, the :meth:`fisher` weight ``F``, and ``c, t, nu, a, b`` and the
        ratios ``mu' / mu``, ``mu' / (1 - mu)``: all finite where ``mu`` rounds to 0 or 1."""
        c, t, nu, log_mu, log_1mmu = self._log_shape(eta)
        a, b = nu * torch.exp(log_mu), nu * torch.exp(log_1mmu)
        r_a, r_b = inv_mills(t) / c, inv_mills(-t) / c  # mu' / mu, mu' / (1 - mu)
        dmu = normal_pdf(t) / c
        logp = (
            (a - 1) * torch.log(u)
            + (b - 1) * torch.log1p(-u)
            + torch.lgamma(nu)
            - torch.lgamma(a + 1)
            - torch.lgamma(b + 1)
            + 2 * torch.log(nu)
            + log_mu
            + log_1mmu
        )
        g = nu * (torch.log(u) - torch.log1p(-u) - torch.digamma(a + 1) + torch.digamma(b + 1)) * dmu + r_a - r_b
        F = r_a**2 + r_b**2 + nu**2 * (torch.polygamma(1, a + 1) + torch.polygamma(1, b + 1)) * dmu**2
        return logp, g, F, (c, t, nu, a, b, r_a, r_b, dmu)

    def log_prob(self, eta: Tensor, u: Tensor) -> Tensor:
        """``log Beta(u; a, b)`` of each rating ``u`` given its item's latent value ``eta``."""
        return self._parts(eta, u)[0]

    def derivatives(self, eta: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        r"""``(log p, d log p / d eta, d^2 log p / d eta^2)``, elementwise.

        With ``a = nu mu``, ``b = nu (1 - mu)``, ``mu' = phi(t) / c``, ``mu'' = -t phi(t) / c^2``
        (``c = sqrt 2 sigma_B``, ``t = eta / c``):
        ``d log p / d mu = nu (log u - log(1-u) - psi(a) + psi(b))`` and
        ``d^2 log p / d mu^2 = -nu^2 (psi'(a) + psi'(b))``. The second derivative in ``eta``
        can be positive far from the data (the Beta log-likelihood is not log-concave in f).

        Computed with ``psi(x) = psi(x + 1) - 1 / x``, so that ``nu psi(a) mu' = nu psi(a + 1) mu'
        - mu' / mu`` (an inverse Mills ratio over ``c``): the first derivative is ``g = nu (log u -
        log(1-u) - psi(a + 1) + psi(b + 1)) mu' + mu' / mu - mu' / (1 - mu)`` and the second
        ``-F - t g / c`` with ``F`` the :meth:`fisher` weight. Finite where ``mu`` rounds to 0 or 1
        (``Phi(t)`` underflows below ``t`` of about -13 in float32 and -37 in float64, where the
        direct form's ``psi(a)`` is infinite).
        """
        logp, g, F, (c, t, *_) = self._parts(eta, u)
        return logp, g, -F - t * g / c

    def third_derivative(self, eta: Tensor, u: Tensor) -> Tensor:
        r"""``d^3 log p / d eta^3``, elementwise: ``l3 mu'^3 + 3 l2 mu' mu'' + l1 mu'''`` with
        ``l1, l2`` the ``mu``-derivatives of :meth:`derivatives`,
        ``l3 = -nu^3 (psi''(a) - psi''(b))`` and ``mu''' = (t^2 - 1) phi(t) / c^3``. With
        ``psi''(x) = psi''(x + 1) - 2 / x^3``: ``l3 mu'^3 = -nu^3 (psi''(a + 1) - psi''(b + 1)) mu'^3
        + 2 (mu' / mu)^3 - 2 (mu' / (1 - mu))^3``, ``3 l2 mu' mu'' = 3 F t / c`` and
        ``l1 mu''' = g (t^2 - 1) / c^2`` (``g``, ``F`` as in :meth:`derivatives`)."""
        _, g, F, (c, t, nu, a, b, r_a, r_b, dmu) = self._parts(eta, u)
        l3 = -(nu**3) * (torch.polygamma(2, a + 1) - torch.polygamma(2, b + 1)) * dmu**3 + 2 * r_a**3 - 2 * r_b**3
        return l3 + 3 * F * t / c + g * (t * t - 1) / (c * c)

    def fisher(self, eta: Tensor) -> Tensor:
        r"""Expected negative second derivative ``nu^2 (psi'(a) + psi'(b)) mu'^2 >= 0`` (Fisher
        scoring weight, used for Newton steps where the exact Hessian is not negative definite).

        Written with ``psi'(x) = 1 / x^2 + psi'(x + 1)`` as
        ``(mu' / mu)^2 + (mu' / (1 - mu))^2 + nu^2 (psi'(a + 1) + psi'(b + 1)) mu'^2``, where
        ``mu' / mu = phi(t) / (c Phi(t))`` is an inverse Mills ratio: finite where ``mu`` rounds
        to 0 or 1 (the direct form is ``inf * 0 = NaN`` there)."""
        c, t, nu, log_mu, log_1mmu = self._log_shape(eta)
        a, b = nu * torch.exp(log_mu), nu * torch.exp(log_1mmu)
        dmu = normal_pdf(t) / c
        return (
            (inv_mills(t) / c) ** 2
            + (inv_mills(-t) / c) ** 2
            + nu**2 * (torch.polygamma(1, a + 1) + torch.polygamma(1, b + 1)) * dmu**2
        )

    def expected_rating(self, mean: Tensor, var: Tensor) -> Tensor:
        r"""Predictive mean rating (eq. 11 for the Beta mean): ``Phi(m / sqrt(2 sigma_B^2 + v))``
        (:func:`predictive_rating`)."""
        return predictive_rating(mean, var, self.rating_scale)

    def predictive_log_density(self, u: Tensor, mean: Tensor, var: Tensor, num_points: int = 40) -> Tensor:
        r"""``log p(u | data) = log \int Beta(u; f) N(f; m, v) df`` (eq. 11) by adaptive Gauss-Hermite.

        The Beta factor is much narrower in ``f`` than the posterior once ``v`` is of the order of
        the prior variance (width ``~ c / sqrt(nu)``), so nodes spread over ``N(m, v)`` miss its
        peak. The nodes are instead centred at the mode of the integrand (a few safeguarded
        Newton steps in ``delta = f - m``) and scaled by its curvature, which is exact for a
        Gaussian integrand. ``u``, ``mean`` and ``var`` broadcast together; ``num_points`` nodes;
        ``var == 0`` gives ``log Beta(u; mean)``.
        """
        x, w = gauss_hermite(num_points, mean, expectation=False)
        u, mean, var = torch.broadcast_tensors(u, mean, var)
        v = var.clamp_min(1e-200)
        with torch.no_grad():
            d, s = self._integrand_peak(u.detach(), mean.detach(), v.detach())
        # nodes d_k = d + sqrt(2) s x_k; int g = sqrt(2) s sum_k w_k e^{x_k^2} g(d_k)
        dk = d.unsqueeze(-1) + (SQRT2 * s).unsqueeze(-1) * x
        lp = self.log_prob(mean.unsqueeze(-1) + dk, u.unsqueeze(-1)) - 0.5 * dk * dk / v.unsqueeze(-1)
        out = (
            torch.logsumexp(lp + x * x + torch.log(w), dim=-1) + torch.log(SQRT2 * s) - 0.5 * torch.log(2 * math.pi * v)
        )
        return torch.where(var > 0, out, self.log_prob(mean, u))

    def _integrand_peak(
        self, u: Tensor, m: Tensor, v: Tensor, max_iter: int = 50, max_halvings: int = 30
    ) -> tuple[Tensor, Tensor]:
        r"""The mode ``d`` (in ``delta = f - m``) and scale ``s = (-h)^{-1/2}`` of eq. 11's integrand
        ``log g(d) = log Beta(u; m + d) - d^2 / (2 v)``, by Newton steps with elementwise
        backtracking (never decreasing ``log g``; Fisher scoring where ``h`` is not negative).

        Each element stops when its step is below ``1e-10`` of its scale, or cannot be taken, or no
        longer increases ``log g`` in floating point (then ``d`` is at the peak to rounding); only
        the unfinished elements are evaluated, so the work shrinks with them.
        """

        def log_g(d_, u_, m_, v_):
            return self.log_prob(m_ + d_, u_) - 0.5 * d_ * d_ / v_

        def slope_curvature(d_, u_, m_, v_):
            _, g1, g2 = self.derivatives(m_ + d_, u_)
            h_ = g2 - 1 / v_
            return g1 - d_ / v_, torch.where(h_ < 0, h_, -self.fisher(m_ + d_) - 1 / v_)

        shape = u.shape
        u, m, v = (t.reshape(-1) for t in (u, m, v))
        f_u = self._latent_at(u)  # where the Beta mean equals u
        P = self.fisher(f_u)
        d = v * P * (f_u - m) / (1 + v * P)
        cur = log_g(d, u, m, v)
        active = torch.arange(d.numel(), device=d.device)
        for _ in range(max_iter):
            ua, ma, va, da, ca = u[active], m[active], v[active], d[active], cur[active]
            g, h = slope_curvature(da, ua, ma, va)
            step = -g / h
            t, new = torch.ones_like(step), torch.empty_like(ca)
            ok = torch.zeros_like(step, dtype=torch.bool)
            todo = torch.arange(step.numel(), device=d.device)
            for k in range(max_halvings + 1):  # halve each element's step until log g does not decrease
                cand = log_g(da[todo] + t[todo] * step[todo], ua[todo], ma[todo], va[todo])
                good = torch.isfinite(cand) & (cand >= ca[todo])
                new[todo], ok[todo] = cand, good
                todo = todo[~good]
                if todo.numel() == 0 or k == max_halvings:
                    break
                t[todo] = 0.5 * t[todo]
            d[active] = torch.where(ok, da + t * step, da)
            cur[active] = torch.where(ok, new, ca)
            # done: converged, no step possible, or no measurable gain in log g (at its peak to rounding)
            done = ~ok | (new <= ca) | (step.abs() <= 1e-10 * (d[active].abs() + va.sqrt()))
            active = active[~done]
            if active.numel() == 0:
                break
        _, h = slope_curvature(d, u, m, v)
        return d.reshape(shape), torch.rsqrt(-h).reshape(shape)  # s: the integrand's scale at its mode

    def marginal(self, function_dist: MultivariateNormal) -> Beta:
        """Moment-matched Beta with the exact predictive mean (eq. 11) and the precision ``nu``.

        The exact predictive density is :meth:`predictive_log_density`.
        """
        mu = self.expected_rating(function_dist.mean, function_dist.variance)
        nu = self.rating_precision
        return Beta(nu * mu, nu * (1 - mu))
