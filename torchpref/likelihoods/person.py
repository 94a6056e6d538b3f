r"""Likelihoods that calibrate the person: a rating link with a personal offset and gain, and
comparisons with lapses (not in the paper; after Pérez-Ortiz et al. 2019, who fit the rating
link's offset and scale and the ratings' noise relative to the comparisons').

* :class:`PersonRatingLikelihood`: ``u ~ Beta(nu mu, nu (1 - mu))`` with
  ``mu = Phi((g eta + b) / (sqrt 2 sigma_B))``: a person's gain ``g`` (``rating_gain``) and offset
  ``b`` (``rating_offset``) on eq. 7's link; ``sigma_B`` stays the reference unit of the rating
  scale, so ``g = 1, b = 0`` is :class:`~torchpref.likelihoods.pairwise_beta.BetaRatingLikelihood`.
* :class:`LapseProbitLikelihood`: ``p(i > j) = eps / 2 + (1 - eps) Phi((f_i - f_j) / (sqrt 2 sigma_R))``:
  with probability ``eps`` (``lapse_rate``) the answer is a coin flip.

**What is identifiable.** Comparisons fix the utility's differences in units of ``sigma_R``;
ratings then tell ``g`` and ``b`` (the link's slope and level against those units) and ``nu``.
With **ratings only**, ``g`` is confounded with the kernel's outputscale and ``b`` with the
utility's level (the GP prior's zero mean): only their priors separate them, so the fit returns
close to the prior for ``g`` and ``b``. With **comparisons only**, nothing of the rating link is
learned (``g``, ``b``, ``nu`` stay at their priors' modes), and ``eps`` is told only by how many
answers contradict the rest, weakly. Both kinds of answer together identify all of them.

Default priors, from the published ranges (docs/likelihoods.md): ``b ~ N(0, 0.24^2)`` (an offset SD
of 0.24 of the utility's spread, the prior's ``sqrt(outputscale) = 1``), ``log g ~ N(0, 0.325^2)``,
``eps ~ LogNormal(log 0.1, 0.75^2)``, ``log nu ~ N(log 40, 1)`` (the NFLX noise of 0.33 of the
spread is ``nu`` of about 40-50 at the suite's spreads; without a prior, ratings that happen to lie
on the link send ``nu`` to infinity).

Both derive their closed-form derivatives in the predictor from their parents' (the gain scales
the link, ``d t / d eta = g / (sqrt 2 sigma_B)``); their parameters enter every derivative through
torch operations, so the Laplace evidence's gradient in them is exact (tests against autograd and
finite differences of the re-solved evidence).
"""

from __future__ import annotations

import math

import torch
from gpytorch.constraints import Interval
from gpytorch.priors import LogNormalPrior, NormalPrior, Prior
from torch import Tensor
from torch.distributions import Bernoulli

from torchpref.inference.numerics import log_ndtr
from torchpref.likelihoods.pairwise_beta import SQRT2, BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.likelihoods.scalar_params import scalar_parameter

__all__ = ["PersonRatingLikelihood", "LapseProbitLikelihood", "OFFSET_PRIOR_SD", "GAIN_PRIOR_SD", "LAPSE_PRIOR"]

#: the offset prior's standard deviation: 0.24 of the utility's spread (SUREAL on Netflix's NFLX data)
OFFSET_PRIOR_SD = 0.24
#: the log gain prior's standard deviation: quartiles of people's rating spreads 1.55 apart (FIRE)
GAIN_PRIOR_SD = 0.325
#: the rating precision prior's (log mean, log sd): rating noise of 0.33 of the spread is ``nu`` of about 40-50
PRECISION_PRIOR = (math.log(40.0), 1.0)
#: the lapse-rate prior's (log mean, log sd)
LAPSE_PRIOR = (math.log(0.1), 0.75)
_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


class PersonRatingLikelihood(BetaRatingLikelihood):
    r"""Beta rating likelihood with a personal gain and offset on the probit link (module notes).

    .. math::
        u \sim \mathrm{Beta}(\nu \mu, \nu (1 - \mu)), \qquad
        \mu = \Phi\!\left(\frac{g\,f + b}{\sqrt{2}\,\sigma_B}\right)

    Args:
        rating_scale: ``sigma_B``, the reference unit of the rating link (fixed).
        rating_precision: ``nu``, the ratings' noise (learned with ``learn_precision``).
        rating_offset: ``b``, the person's offset (latent units).
        rating_gain: ``g``, the person's gain.
        learn: ``b`` and ``g`` are trainable (default).
        learn_precision: ``nu`` is trainable (default).
        rating_offset_prior, rating_gain_prior, rating_precision_prior: priors (``None``: the
            module's defaults); pass ``False`` for none.
    """

    def __init__(
        self,
        rating_scale: float = 0.8,
        rating_precision: float = 20.0,
        rating_offset: float = 0.0,
        rating_gain: float = 1.0,
        *,
        learn: bool = True,
        learn_precision: bool = True,
        rating_offset_prior: Prior | None | bool = None,
        rating_gain_prior: Prior | None | bool = None,
        rating_precision_prior: Prior | None | bool = None,
        rating_gain_constraint: Interval | None = None,
    ):
        if rating_precision_prior is None:
            rating_precision_prior = LogNormalPrior(*PRECISION_PRIOR)
        super().__init__(
            rating_scale, rating_precision, learn=False, rating_precision_prior=rating_precision_prior or None
        )
        self.raw_rating_precision.requires_grad_(bool(learn_precision))
        self._register("rating_gain", rating_gain, rating_gain_constraint, None, learn)
        offset = float(rating_offset)
        if not math.isfinite(offset):
            raise ValueError(f"rating_offset must be finite, got {rating_offset!r}.")
        self.register_parameter(
            "raw_rating_offset", torch.nn.Parameter(torch.tensor(offset, dtype=torch.float64), requires_grad=learn)
        )
        if rating_offset_prior is None:
            rating_offset_prior = NormalPrior(0.0, OFFSET_PRIOR_SD)
        if rating_gain_prior is None:
            rating_gain_prior = LogNormalPrior(0.0, GAIN_PRIOR_SD)
        if rating_offset_prior is not False:
            self.register_prior(
                "rating_offset_prior", rating_offset_prior, lambda m: m.rating_offset, lambda m, v: m._set_offset(v)
            )
        if rating_gain_prior is not False:
            self.register_prior(
                "rating_gain_prior", rating_gain_prior, lambda m: m.rating_gain, lambda m, v: m._set("rating_gain", v)
            )

    rating_gain = scalar_parameter("rating_gain", "``g``: the person's gain on the rating link.")

    #: the compiled path (:mod:`torchpref.inference._compiled`) knows this likelihood (a Beta rating
    #: with the link scale divided by ``g`` and ``b / g`` added to the predictor); a subclass is
    #: solved by the torch solver unless it says so too
    compiled_kind = "person_rating"

    @property
    def rating_offset(self) -> Tensor:
        """``b``: the person's offset on the rating link (latent units)."""
        return self.raw_rating_offset

    @rating_offset.setter
    def rating_offset(self, value: float | Tensor) -> None:
        self._set_offset(value)

    def _set_offset(self, value) -> None:
        v = torch.as_tensor(value, dtype=self.raw_rating_offset.dtype)
        if not bool(torch.isfinite(v).all()):
            raise ValueError(f"rating_offset must be finite, got {v.tolist()}.")
        with torch.no_grad():
            self.raw_rating_offset.copy_(v.expand_as(self.raw_rating_offset))

    def _link(self, eta: Tensor) -> tuple[Tensor, Tensor]:
        # t = (g eta + b) / (sqrt 2 sigma_B); d eta / d t = sqrt 2 sigma_B / g
        c0 = SQRT2 * self.rating_scale
        g = self.rating_gain
        return c0 / g, (g * eta + self.rating_offset) / c0

    def _latent_at(self, u: Tensor) -> Tensor:
        c0 = SQRT2 * self.rating_scale.detach()
        return (c0 * torch.special.ndtri(u) - self.rating_offset.detach()) / self.rating_gain.detach()

    def expected_rating(self, mean: Tensor, var: Tensor) -> Tensor:
        r"""This person's predictive mean rating, ``Phi((g m + b) / sqrt(2 sigma_B^2 + g^2 v))``
        (eq. 11 with the person's link). :meth:`unbiased_rating` is the rating without ``b``."""
        g, b = self.rating_gain.to(mean), self.rating_offset.to(mean)
        s2 = 2 * self.rating_scale.to(mean) ** 2
        return torch.special.ndtr((g * mean + b) / torch.sqrt(s2 + g * g * var.clamp_min(0)))

    def unbiased_rating(self, mean: Tensor, var: Tensor) -> Tensor:
        r"""This person's predictive mean rating without their offset,
        ``Phi(g m / sqrt(2 sigma_B^2 + g^2 v))``: the utility on the rating scale with the person's
        bias ``b`` removed. The gain stays: where comparisons are near-exact it is not separable
        from the utility's amplitude (module notes), so ``g f`` is what the answers determine."""
        g = self.rating_gain.to(mean)
        s2 = 2 * self.rating_scale.to(mean) ** 2
        return torch.special.ndtr(g * mean / torch.sqrt(s2 + g * g * var.clamp_min(0)))


class LapseProbitLikelihood(PairwiseProbitLikelihood):
    r"""A comparison with lapses: ``p = eps / 2 + (1 - eps) Phi(eta / s)``, ``s = sqrt 2 sigma_R``.

    Not log-concave (the constant floor ``eps / 2`` flattens ``log p`` in the far tail), so
    :meth:`fisher` gives the Newton solver a non-negative weight where the exact one is negative.
    With ``q = (1 - eps) phi(z) / p`` (``z = eta / s``), the derivatives are ``l' = q / s``,
    ``l'' = -(z q + q^2) / s^2`` and ``l''' = ((z^2 - 1) q + 3 z q^2 + 2 q^3) / s^3``.

    Args:
        comparison_noise: ``sigma_R`` (eq. 3).
        lapse_rate: ``eps``, in ``(0, 0.5)``.
        learn: ``eps`` is trainable (default).
        learn_noise: ``sigma_R`` is trainable (off: it sets the utility's unit).
        lapse_rate_prior: default ``LogNormal(log 0.1, 0.75)``; ``False`` for none.
    """

    log_concave = False

    #: the compiled path (:mod:`torchpref.inference._compiled`) knows this likelihood; a subclass
    #: (which may change its derivatives) is solved by the torch solver unless it says so too
    compiled_kind = "lapse"

    def __init__(
        self,
        comparison_noise: float = 0.1,
        lapse_rate: float = 0.05,
        *,
        learn: bool = True,
        learn_noise: bool = False,
        lapse_rate_prior: Prior | None | bool = None,
        lapse_rate_constraint: Interval | None = None,
    ):
        super().__init__(comparison_noise, learn=learn_noise)
        if lapse_rate_prior is None:
            lapse_rate_prior = LogNormalPrior(*LAPSE_PRIOR)
        constraint = Interval(1e-6, 0.5) if lapse_rate_constraint is None else lapse_rate_constraint
        self._register(
            "lapse_rate", lapse_rate, constraint, None if lapse_rate_prior is False else lapse_rate_prior, learn
        )

    lapse_rate = scalar_parameter("lapse_rate", "``eps``: the probability that a comparison is a coin flip.")

    def _parts(self, eta: Tensor):
        s = self.scale
        z = eta / s
        eps = self.lapse_rate
        log_keep = torch.log1p(-eps)
        log_p = torch.logaddexp(torch.log(eps / 2), log_keep + log_ndtr(z))
        q = torch.exp(log_keep - 0.5 * z * z - _LOG_SQRT_2PI - log_p)  # (1 - eps) phi(z) / p
        return s, z, eps, log_keep, log_p, q

    def forward(self, function_samples: Tensor, comparisons: Tensor) -> Bernoulli:
        """Distribution of "the first item of each comparison row is preferred" (``... x n`` latent
        values, ``p x 2`` comparisons -> batch ``... x p``)."""
        eta = function_samples[..., comparisons[:, 0]] - function_samples[..., comparisons[:, 1]]
        eps = self.lapse_rate
        return Bernoulli(probs=eps / 2 + (1 - eps) * torch.special.ndtr(eta / self.scale))

    def log_prob(self, eta: Tensor) -> Tensor:
        """``log p`` of each comparison given ``eta = f_preferred - f_other``."""
        return self._parts(eta)[4]

    def derivatives(self, eta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(log p, l', l'')`` in ``eta``, elementwise (class notes)."""
        s, z, _, _, log_p, q = self._parts(eta)
        return log_p, q / s, -(z * q + q * q) / (s * s)

    def third_derivative(self, eta: Tensor) -> Tensor:
        """``l'''`` in ``eta``, elementwise (class notes)."""
        s, z, _, _, _, q = self._parts(eta)
        return ((z * z - 1) * q + 3 * z * q * q + 2 * q**3) / s**3

    def fisher(self, eta: Tensor) -> Tensor:
        r"""The Bernoulli's Fisher information in ``eta``, ``p'^2 / (p (1 - p)) = l'^2 p / (1 - p)``
        (non-negative)."""
        s, z, eps, log_keep, log_p, q = self._parts(eta)
        log_1mp = torch.logaddexp(torch.log(eps / 2), log_keep + log_ndtr(-z))
        return (q / s) ** 2 * torch.exp(log_p - log_1mp)

    def with_lapses(self, P: Tensor) -> Tensor:
        r"""A best-of-``q`` choice's probabilities ``P`` (``... x q``) with lapses: ``eps / q + (1 -
        eps) P`` (a lapse picks one of the ``q`` shown uniformly; ``q = 2`` is :meth:`forward`'s
        ``eps / 2 + (1 - eps) Phi``)."""
        eps = self.lapse_rate.to(P)
        return eps / P.shape[-1] + (1 - eps) * P

    def preference_probability(self, mean_diff: Tensor, var_diff: Tensor) -> Tensor:
        r"""Predictive ``P(a > b) = eps / 2 + (1 - eps) Phi((m_a - m_b) / sqrt(2 sigma_R^2 + v))``."""
        eps = self.lapse_rate
        return eps / 2 + (1 - eps) * super().preference_probability(mean_diff, var_diff)
