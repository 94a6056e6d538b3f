r"""Simulated people as measured: rating offset, scale, noise and drift, partial use of the scale,
comparison lapses, and the seconds each answer takes.

:class:`~torchpref.simulation.users.SimulatedUser` answers with exactly the model's noise. Real
raters do not (docs/suite.md, "Realistic raters", has the figures and their sources). A
:class:`RealisticUser` answers from a hidden utility ``f`` through a :class:`RaterProfile`:

* **ratings**: the person's latent impression ``z_t = g f(x) + b + d_t`` (a personal gain ``g``,
  offset ``b`` and a drift ``d_t``, a random walk over the session's answers, ``d_0 = 0``), a mean
  rating ``mu = Phi(z_t / (sqrt 2 sigma_B))`` (eq. 7's link), a Beta draw
  ``u ~ Beta(nu mu, nu (1 - mu))`` (eqs. 4-6), then the part of the scale the person uses,
  ``lo + (hi - lo) u``, and, for a Likert rater, the box ticked (its bin centre ``(k - 1/2) / K``);
* **choices**: with probability ``eps`` (a lapse) a uniformly random option; otherwise the option
  of largest ``f(x_i) + e_i``, ``e_i ~ N(0, sigma_R^2)`` (eq. 3);
* **seconds**: each answer takes the :class:`EffortModel`'s seconds for its kind and number of
  options shown, times a log-normal factor (a person is not a clock); :attr:`RealisticUser.seconds`
  records them, as the browser front end records a real person's response times.

With ``g = 1``, ``b = 0``, no drift, the whole scale, no lapses, this is the paper's user.
:meth:`RaterProfile.typical` draws a person from the published ranges.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import torch
from torch import Tensor

from torchpref.data.effort import (  # the effort model's owner; importable from here too
    CHOICE_SECONDS,  # noqa: F401
    PER_EXTRA_OPTION_SECONDS,  # noqa: F401
    RATING_SECONDS,  # noqa: F401
    TRAJECTORY_VIEW_SECONDS,  # noqa: F401
    EffortModel,
    _check,
)
from torchpref.data.preference_data import likert_to_unit, unit_to_likert
from torchpref.likelihoods.pairwise_beta import rating_link
from torchpref.simulation.users import RATING_CLAMP, SimulatedUser, sample_beta

__all__ = ["EffortModel", "RaterProfile", "RealisticUser", "precision_for_noise"]


def precision_for_noise(latent_sd: float, rating_scale: float) -> float:
    r"""The Beta precision ``nu`` whose rating noise at mid-scale, read back in latent units, has
    standard deviation ``latent_sd``: ``sd(u) = 1 / (2 sqrt(nu + 1))`` at ``mu = 1/2``, divided by the
    link's slope ``d mu / d f = phi(0) / (sqrt 2 sigma_B)`` there."""
    _check("latent_sd", latent_sd, 0.0, closed=False)
    slope = 1.0 / (math.sqrt(2 * math.pi) * math.sqrt(2) * rating_scale)
    return max((0.5 / (slope * latent_sd)) ** 2 - 1.0, 0.5)


@dataclass(frozen=True)
class RaterProfile:
    r"""How one person answers (module notes). Latent-unit values (``rating_offset``, ``drift_sd``,
    ``comparison_noise``) are in the utility's units.

    Attributes:
        comparison_noise: ``sigma_R`` of a choice (eq. 3).
        lapse_rate: ``eps``, the probability that a choice is a uniformly random option.
        rating_offset: ``b``, added to the person's impression of every item.
        rating_gain: ``g``, the person's scale: their impression is ``g f``.
        rating_precision: ``nu`` of the Beta draw (eqs. 5-6).
        rating_scale: ``sigma_B`` of the link (eq. 7).
        drift_sd: standard deviation of the random walk's step after each answer.
        scale_range: ``(lo, hi)``, the part of ``[0, 1]`` the person's ratings use.
        levels: ``K`` boxes of a Likert scale, or ``None`` (a slider).
        effort: seconds per answer.
        time_noise: standard deviation of the log of a response time's factor.
    """

    comparison_noise: float = 0.1
    lapse_rate: float = 0.0
    rating_offset: float = 0.0
    rating_gain: float = 1.0
    rating_precision: float = 40.0
    rating_scale: float = 0.8
    drift_sd: float = 0.0
    scale_range: tuple[float, float] = (0.0, 1.0)
    levels: int | None = None
    effort: EffortModel = field(default_factory=EffortModel)
    time_noise: float = 0.3

    def __post_init__(self):
        _check("comparison_noise", self.comparison_noise, 0.0, closed=False)
        _check("lapse_rate", self.lapse_rate, 0.0, 1.0)
        _check("rating_offset", self.rating_offset, -math.inf)
        _check("rating_gain", self.rating_gain, 0.0, closed=False)
        _check("rating_precision", self.rating_precision, 0.0, closed=False)
        _check("rating_scale", self.rating_scale, 0.0, closed=False)
        _check("drift_sd", self.drift_sd)
        _check("time_noise", self.time_noise)
        lo, hi = (float(v) for v in self.scale_range)
        if not (0.0 <= lo < hi <= 1.0):
            raise ValueError(f"scale_range must be (lo, hi) with 0 <= lo < hi <= 1, got {self.scale_range!r}.")
        if self.levels is not None and (int(self.levels) != self.levels or self.levels < 2):
            raise ValueError(f"levels must be an integer >= 2 or None, got {self.levels!r}.")
        if not isinstance(self.effort, EffortModel):
            raise ValueError(f"effort must be an EffortModel, got {self.effort!r}.")

    @classmethod
    def typical(
        cls, generator: torch.Generator, spread: float = 1.0, rating_scale: float = 0.8, **overrides
    ) -> RaterProfile:
        r"""A person drawn from the published ranges (docs/suite.md), for utilities whose spread over
        items (standard deviation) is ``spread``:

        * offset ``b ~ N(0, (0.24 spread)^2)`` (SUREAL on Netflix's NFLX data: offset SD 0.29
          against a quality SD of 1.20);
        * gain ``log g ~ N(0, 0.325^2)``: a ratio of 1.55 between the quartiles of people's spreads (FIRE);
        * rating noise ``0.33 spread`` in latent units (NFLX: 0.39 against 1.20), as a Beta precision
          (:func:`precision_for_noise`);
        * lapse rate ``eps ~ U(0.05, 0.25)``: choices agree with a consensus 72-77 % of the time
          (Stiennon et al. 2020; Ouyang et al. 2022), noise included;
        * drift: a step of ``0.05 spread`` after each answer (an assumption: re-ratings differ by
          RMSE 0.56-0.82 stars on 1-5, Amatriain et al. 2009, and comparisons are ~20 % more stable
          than ratings, Jones et al. 2011; no study gives a drift rate);
        * partial use of the scale with probability 0.16: a random sub-range of width ``U(0.4, 0.67)``
          (16 % of people use less than two thirds of a 1-7 scale, FIRE).

        ``overrides`` replace any drawn field.
        """
        _check("spread", spread, 0.0, closed=False)
        z = torch.randn(3, generator=generator, dtype=torch.float64).tolist()
        u = torch.rand(4, generator=generator, dtype=torch.float64).tolist()
        width = 0.4 + 0.27 * u[2]
        lo = u[3] * (1.0 - width)
        drawn = dict(
            rating_offset=0.24 * spread * z[0],
            rating_gain=math.exp(0.325 * z[1]),
            rating_precision=precision_for_noise(0.33 * spread, rating_scale),
            rating_scale=rating_scale,
            lapse_rate=0.05 + 0.2 * u[0],
            drift_sd=0.05 * spread,
            scale_range=(lo, lo + width) if u[1] < 0.16 else (0.0, 1.0),
        )
        drawn.update(overrides)
        return cls(**drawn)

    def as_dict(self) -> dict:
        """The profile as plain values (for a results file)."""
        return asdict(self)

    def with_effort(self, effort: EffortModel) -> RaterProfile:
        """The same person under another effort model."""
        return replace(self, effort=effort)


class RealisticUser:
    r"""A simulated person who answers through a :class:`RaterProfile` (module notes).

    It follows the :class:`~torchpref.simulation.users.User` protocol (``rate``, ``choose``) and
    records the seconds each answer took (:attr:`seconds`: ``(kind, m, seconds)`` per answer).

    Args:
        utility: the person's hidden utility ``f``, ``n x d -> n``.
        profile: how they answer.
        generator: the source of all randomness.

    Attributes:
        drift: the current drift ``d_t`` of the person's impressions.
        seconds: ``(kind, options shown, seconds)`` of each answer so far.
    """

    def __init__(
        self, utility: Callable[[Tensor], Tensor], profile: RaterProfile, generator: torch.Generator | None = None
    ):
        if not isinstance(profile, RaterProfile):
            raise ValueError(f"profile must be a RaterProfile, got {profile!r}.")
        self.profile = profile
        self.generator = generator if generator is not None else torch.Generator()
        # the paper's user, for the utility's checks and the undistorted mean rating
        self._base = SimulatedUser(
            utility, profile.comparison_noise, profile.rating_scale, profile.rating_precision, self.generator
        )
        self.drift = 0.0
        self.seconds: list[tuple[str, int, float]] = []

    @property
    def utility(self) -> Callable[[Tensor], Tensor]:
        """The hidden utility ``f`` (``n x d -> n``)."""
        return self._base.utility

    def latent(self, X: Tensor) -> Tensor:
        """The true utilities ``f(X)`` (``n x d -> n``)."""
        return self._base.latent(X)

    def mean_rating(self, X: Tensor) -> Tensor:
        r"""The undistorted mean rating ``Phi(f / (sqrt 2 sigma_B))`` of each item (``n x d -> n``):
        what a rater without offset, gain, drift or compression would give on average (the metrics' truth)."""
        return self._base.mean_rating(X)

    def person_mean_rating(self, X: Tensor) -> Tensor:
        r"""This person's mean rating now, ``lo + (hi - lo) Phi((g f + b + d_t) / (sqrt 2 sigma_B))``
        (before a Likert box is ticked)."""
        p = self.profile
        mu = rating_link(p.rating_gain * self.latent(X) + p.rating_offset + self.drift, p.rating_scale)
        lo, hi = p.scale_range
        return lo + (hi - lo) * mu

    def _answered(self, kind: str, m: int) -> None:
        p = self.profile
        base = p.effort.rating() if kind == "rating" else p.effort.ranking(m)
        factor = math.exp(p.time_noise * float(torch.randn((), generator=self.generator, dtype=torch.float64)))
        self.seconds.append((kind, m, base * factor))
        if p.drift_sd > 0:
            self.drift += p.drift_sd * float(torch.randn((), generator=self.generator, dtype=torch.float64))

    def rate(self, x: Tensor) -> float:
        """Rate one item (``d``, or ``1 x d``): a rating in ``(0, 1)`` (module notes)."""
        x = torch.as_tensor(x)
        if x.dim() == 2 and x.shape[0] == 1:
            x = x[0]
        if x.dim() != 1:
            raise ValueError(f"x must be a single item (a d tensor), got shape {tuple(x.shape)}.")
        p = self.profile
        mu = rating_link(p.rating_gain * self.latent(x[None]) + p.rating_offset + self.drift, p.rating_scale)
        mu = mu.to(torch.float64).clamp(RATING_CLAMP, 1 - RATING_CLAMP)
        u = float(sample_beta(p.rating_precision * mu, p.rating_precision * (1 - mu), self.generator)[0])
        lo, hi = p.scale_range
        u = min(max(lo + (hi - lo) * u, RATING_CLAMP), 1 - RATING_CLAMP)
        if p.levels is not None:
            u = float(likert_to_unit(unit_to_likert(u, p.levels), p.levels))
        self._answered("rating", 1)
        return u

    def choose(self, X: Tensor) -> int:
        """Pick the best of ``m`` items (``m x d``, ``m >= 2``): a lapse with probability ``eps``."""
        X = torch.as_tensor(X)
        if X.dim() != 2 or X.shape[0] < 2:
            raise ValueError(f"X must be an m x d tensor with m >= 2 items, got shape {tuple(X.shape)}.")
        m = X.shape[0]
        f = self.latent(X).to(torch.float64)
        lapse = float(torch.rand((), generator=self.generator, dtype=torch.float64)) < self.profile.lapse_rate
        if lapse:
            choice = int(torch.randint(0, m, (), generator=self.generator))
        else:
            noise = torch.randn(f.shape, generator=self.generator, dtype=f.dtype)
            choice = int((f + self.profile.comparison_noise * noise).argmax())
        self._answered("ranking", m)
        return choice

    def mean_seconds(self) -> dict[str, float]:
        """The mean recorded seconds of each answer kind so far (``{}`` before any answer)."""
        out: dict[str, list[float]] = {}
        for kind, _, s in self.seconds:
            out.setdefault(kind, []).append(s)
        return {k: sum(v) / len(v) for k, v in out.items()}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.profile!r}, answers={len(self.seconds)})"
