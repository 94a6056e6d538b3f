r"""The defaults of :class:`~torchpref.models.preference_gp.PreferenceGP`: its kernel, its likelihood settings,
and the likelihood module (``model.likelihood``) it builds from them."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import TypedDict

import torch
from gpytorch.constraints import GreaterThan
from gpytorch.kernels import RBFKernel, ScaleKernel
from gpytorch.module import Module
from gpytorch.priors import GammaPrior, LogNormalPrior
from torch import Tensor

from torchpref.likelihoods.ordinal import (
    OrdinalRatingLikelihood,
    StrictPreferenceLikelihood,
    TieLikelihood,
    default_cut_points,
)
from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.likelihoods.scalar_params import shared_constraint, weak_load_hook
from torchpref.models.arguments import check_model_arguments

#: The likelihood settings of the paper's Fig. 4 (``sigma_R``, ``sigma_B``, ``nu``), for runs that
#: reproduce the paper: ``PreferenceGP(X, ..., **PAPER_FIG4_SETTINGS)`` (docs/botorch.md).
PAPER_FIG4_SETTINGS = {"comparison_noise": 0.1, "rating_scale": 1.0, "rating_precision": 80.0}

#: Lower bound of the default kernel's lengthscales (inputs in the unit cube).
MIN_LENGTHSCALE = 1e-4


def default_covar_module(dim: int) -> ScaleKernel:
    r"""``ScaleKernel(RBFKernel(ard_num_dims=d))`` (eq. 1) with BoTorch's dimension-scaled
    lengthscale prior ``LogNormal(sqrt 2 + log(d) / 2, sqrt 3)`` (inputs in the unit cube) and a
    ``Gamma(2, 1)`` prior on the outputscale ``sigma_f^2`` (utilities of order one on the
    rating link's scale). Lengthscales stay above ``1e-4`` (as ``PairwiseGP``'s): at exactly 0,
    where an optimiser's long step can send a softplus-constrained one, the kernel matrix is NaN.
    ``dim = 0`` (not known yet: a prior-only model) gives one shared lengthscale with the
    ``d = 1`` prior."""
    base = RBFKernel(
        ard_num_dims=dim or None,
        lengthscale_prior=LogNormalPrior(math.sqrt(2) + 0.5 * math.log(max(dim, 1)), math.sqrt(3)),
        lengthscale_constraint=GreaterThan(MIN_LENGTHSCALE),
    )
    return ScaleKernel(base, outputscale_prior=GammaPrior(2.0, 1.0))


class PreferenceLikelihood(Module):
    """The likelihoods of the model, held together (``model.likelihood``): ``comparison``,
    ``rating`` (Beta, or ordinal for levels), ``tie`` (which shares ``comparison``'s ``sigma_R``) and
    ``strict`` (a comparison where "no preference" was allowed, the tie's upper category)."""

    def __init__(
        self,
        comparison: PairwiseProbitLikelihood,
        rating: BetaRatingLikelihood | OrdinalRatingLikelihood,
        tie: TieLikelihood | None = None,
    ):
        super().__init__()
        weak_load_hook(self)
        self.comparison = comparison
        self.rating = rating
        self.tie = tie if tie is not None else TieLikelihood(comparison=comparison)
        self.strict = StrictPreferenceLikelihood(self.tie)

    @classmethod
    def create(
        cls,
        comparison_noise: float,
        rating_scale: float,
        rating_precision: float,
        learn: bool,
        tie_threshold: float,
        rating_levels: int | None = None,
        cut_points: Tensor | None = None,
        level_noise: float | None = None,
    ) -> PreferenceLikelihood:
        r"""The model's likelihoods from its settings (:class:`~torchpref.models.preference_gp.PreferenceGP`'s
        arguments of the same names): a Beta rating likelihood, or for ``rating_levels`` an ordinal
        one whose ``level_noise`` defaults to ``sqrt(pi) sigma_B / sqrt(nu + 1)``.

        A learned Beta precision (``learn``) has a prior, :func:`rating_precision_prior` centred on
        the given ``nu``: without one the evidence of a few ratings that the mode can fit exactly grows
        without bound in ``nu`` (docs/likelihoods.md, "Learning the rating precision")."""
        positive = shared_constraint("positive")  # the model's likelihoods share their default constraints
        comparison = PairwiseProbitLikelihood(comparison_noise, learn=learn, comparison_noise_constraint=positive)
        if rating_levels is None:
            rating = BetaRatingLikelihood(
                rating_scale,
                rating_precision,
                learn=learn,
                rating_scale_constraint=positive,
                rating_precision_constraint=shared_constraint("precision"),
                rating_precision_prior=rating_precision_prior(rating_precision) if learn else None,
            )
        else:
            if cut_points is None:
                cut_points = default_cut_points(int(rating_levels), rating_scale)
            if level_noise is None:  # sd of Beta(nu/2, nu/2) over d mu / d f at f = 0
                level_noise = math.sqrt(math.pi) * rating_scale / math.sqrt(rating_precision + 1)
            rating = OrdinalRatingLikelihood(int(rating_levels), cut_points, level_noise, learn=learn)
        return cls(
            comparison, rating, TieLikelihood(tie_threshold, comparison, learn=learn, tie_threshold_constraint=positive)
        )


#: ``nu`` of the Beta rating likelihood of a *person's* model: a session's default model, a
#: population's people and a study's participants. Real ratings on a coarse scale are much noisier
#: than the paper's simulated ``nu = 80``: chosen on real people who both rated and ranked (SUSHI,
#: ``torchpref reproduce sushi``; docs/real_raters.md), where ratings and the ranking together then
#: predict better than either alone. :class:`LikelihoodSettings` keeps the paper's 80 as
#: ``PreferenceGP``'s own default.
PERSON_RATING_PRECISION = 3.0

#: the spread, in natural-log units, of a learned rating precision's prior (:func:`rating_precision_prior`)
RATING_PRECISION_LOG_SD = 1.0


def rating_precision_prior(rating_precision: float) -> LogNormalPrior:
    r"""The prior of a learned Beta precision ``nu``: log-normal with median the setting's ``nu`` and
    log-sd :data:`RATING_PRECISION_LOG_SD` (a factor ``e`` either way is one sd). It keeps the
    learned ``nu`` finite: a few ratings the mode fits exactly otherwise drive it to the constraint's
    bound (``1e6``)."""
    return LogNormalPrior(
        torch.tensor(math.log(float(rating_precision)), dtype=torch.float64),
        torch.tensor(RATING_PRECISION_LOG_SD, dtype=torch.float64),
    )


class LikelihoodKeywords(TypedDict, total=False):
    """:class:`LikelihoodSettings`' fields as keywords of
    :class:`~torchpref.models.preference_gp.PreferenceGP` (``PreferenceGP(X, C, comparison_noise=0.1)``)."""

    comparison_noise: float
    rating_scale: float
    rating_precision: float
    learn_likelihood: bool
    tie_threshold: float
    cut_points: Tensor | None
    level_noise: float | None


@dataclass(frozen=True)
class LikelihoodSettings:
    r"""The settings of a model's answer likelihoods, in one object:
    ``PreferenceGP(X, C, likelihood=LikelihoodSettings(comparison_noise=0.1))``. The same names are
    accepted as keyword arguments of :class:`~torchpref.models.preference_gp.PreferenceGP`
    (``PreferenceGP(X, C, comparison_noise=0.1)``), which builds this object from them.

    Attributes:
        comparison_noise: ``sigma_R`` of eq. 3 (default 1.0: BoTorch's ``PairwiseGP`` probit
            ``Phi((f_i - f_j) / sqrt 2)``; the paper's Fig. 4 used 0.1, :data:`PAPER_FIG4_SETTINGS`).
        rating_scale: ``sigma_B`` of eq. 7 (default 1.0, as Fig. 4).
        rating_precision: ``nu`` of eqs. 5-6 (default 80, as Fig. 4).
        learn_likelihood: make the likelihood parameters trainable (default: fixed, as in the
            paper; with comparisons only, ``comparison_noise`` and the outputscale are not
            separately identifiable).
        tie_threshold: ``tau`` of the tie likelihood (default 0.1).
        cut_points: the ordinal likelihood's ``K - 1`` cut points (default
            :func:`~torchpref.likelihoods.ordinal.default_cut_points`, the Beta link's bin edges).
        level_noise: the ordinal likelihood's ``sigma``; default ``sqrt(pi) sigma_B / sqrt(nu + 1)``.

    Raises:
        ValueError: a setting of the wrong type or range, naming it.
    """

    comparison_noise: float = 1.0
    rating_scale: float = 1.0
    rating_precision: float = 80.0
    learn_likelihood: bool = False
    tie_threshold: float = 0.1
    cut_points: Tensor | None = None
    level_noise: float | None = None

    def __post_init__(self) -> None:
        reals = {k: v for k, v in asdict(self).items() if k not in ("learn_likelihood", "cut_points")}
        check_model_arguments(reals=reals, flags={"learn_likelihood": self.learn_likelihood})
        for name, value in reals.items():
            if value is not None and not float(value) > 0:
                raise ValueError(f"{name} must be positive, got {float(value)}.")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The settings' names (also :class:`~torchpref.models.preference_gp.PreferenceGP`'s keywords)."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def of(cls, likelihood: object, keywords: LikelihoodKeywords) -> LikelihoodSettings:
        """The settings of ``PreferenceGP(..., likelihood=likelihood, **keywords)``: ``likelihood`` a
        :class:`LikelihoodSettings` (``keywords`` then override its fields), ``None``, or
        ``PairwiseGP``'s comparison likelihood (BoTorch's or torchpref's probit: its ``sigma_R``).

        Raises:
            TypeError: a keyword that is not a setting (naming it and the settings).
            ValueError: see :func:`~torchpref.models.pairwise_interface.pairwise_likelihood_noise`.
        """
        from torchpref.models.pairwise_interface import pairwise_likelihood_noise

        unknown = sorted(set(keywords) - set(cls.names()))
        if unknown:
            raise TypeError(
                f"PreferenceGP got unexpected keyword argument(s) {', '.join(unknown)}; its likelihood "
                f"settings are {', '.join(cls.names())} (torchpref.LikelihoodSettings)."
            )
        if isinstance(likelihood, LikelihoodSettings):
            return replace(likelihood, **keywords) if keywords else likelihood
        noise = pairwise_likelihood_noise(likelihood, keywords.pop("comparison_noise", None))
        settings: LikelihoodKeywords = {**keywords, "comparison_noise": noise}
        return cls(**settings)

    def create(self, rating_levels: int | None = None) -> PreferenceLikelihood:
        """The model's likelihood module (:class:`PreferenceLikelihood`) for ratings on ``[0, 1]``
        (Beta) or, with ``rating_levels``, levels ``1..K`` (ordinal)."""
        return PreferenceLikelihood.create(
            self.comparison_noise,
            self.rating_scale,
            self.rating_precision,
            self.learn_likelihood,
            self.tie_threshold,
            rating_levels,
            self.cut_points,
            self.level_noise,
        )


def preference_likelihood(model: Module) -> PreferenceLikelihood:
    """``model.likelihood``, typed: a :class:`PreferenceLikelihood` (the model's comparison, rating,
    tie and strict likelihoods). Raises ``ValueError`` naming the type for any other model, so a
    selector or acquisition function given, say, a ``PairwiseGP`` says so instead of failing on a
    missing attribute."""
    lik = getattr(model, "likelihood", None)
    if not isinstance(lik, PreferenceLikelihood):
        raise ValueError(
            f"this needs a torchpref PreferenceGP (its likelihood holds comparison and rating likelihoods), "
            f"got a {type(model).__name__} whose likelihood is a {type(lik).__name__}."
        )
    return lik
