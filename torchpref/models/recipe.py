r"""The person model's recipe: :class:`ModelSettings`, the one owner of a person model's settings
(the kernel's lengthscale and outputscale, the comparison noise, the rating likelihood's scale,
precision and ``rating_eps``, the tie threshold, whether ties are offered, ordinal levels).

A session's default model (:func:`~torchpref.sessions.settings.default_session_model`), a
population's fit (:func:`~torchpref.fit_population`) and the person model a population builds
(:meth:`~torchpref.Population.person_model`) all take their settings from it, so they agree on
every likelihood setting; changing a default (the rating likelihood's, say) is a change here, in
:data:`DEFAULT_MODEL`'s fields' defaults, and nowhere else.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import TYPE_CHECKING, Any

from gpytorch.kernels import ScaleKernel
from torch import Tensor

if TYPE_CHECKING:
    from torchpref.models.preference_gp import PreferenceGP

from torchpref.data.preference_data import DEFAULT_RATING_EPS
from torchpref.models.defaults import (
    PERSON_RATING_PRECISION,
    LikelihoodSettings,
    PreferenceLikelihood,
    default_covar_module,
)

__all__ = ["DEFAULT_MODEL", "NO_TIES_OFFERED", "ModelSettings"]


@dataclass(frozen=True)
class ModelSettings:
    r"""A person model's settings (module docstring), validated.

    Attributes:
        lengthscale: the RBF kernel's lengthscale on the unit cube (a session's default model; a
            population fits its own kernels).
        outputscale: the kernel's ``sigma_f^2``.
        comparison_noise: ``sigma_R`` of the probit comparison likelihood (eq. 3).
        rating_scale: ``sigma_B`` of the Beta rating likelihood (eq. 7).
        rating_precision: ``nu`` of the Beta rating likelihood (eqs. 5-6); a person's
            (:data:`~torchpref.models.defaults.PERSON_RATING_PRECISION`, calibrated on real raters).
        rating_eps: ratings are clamped to ``[eps, 1 - eps]`` for the Beta likelihood.
        tie_threshold: ``tau`` of the tie ("no preference") likelihood.
        ties_offered: "no preference" is an answer a person may give, so a strict choice is the tie
            likelihood's upper category (docs/likelihoods.md).
        rating_levels: ratings as ordinal levels ``1..K`` (``None``: ratings in ``[0, 1]``, the
            Beta likelihood; a Likert level is then mapped to ``[0, 1]``).

    Raises:
        ValueError: a setting out of range, naming it and its value.
    """

    lengthscale: float = 0.2
    outputscale: float = 1.0
    comparison_noise: float = 1.0
    rating_scale: float = 1.0
    rating_precision: float = PERSON_RATING_PRECISION
    rating_eps: float = DEFAULT_RATING_EPS
    tie_threshold: float = 0.1
    ties_offered: bool = True
    rating_levels: int | None = None

    def __post_init__(self) -> None:
        for name in (
            "lengthscale",
            "outputscale",
            "comparison_noise",
            "rating_scale",
            "rating_precision",
            "tie_threshold",
        ):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (math.isfinite(value) and value > 0)
            ):
                raise ValueError(f"{name} must be a finite positive number, got {value!r}.")
            object.__setattr__(self, name, float(value))
        eps = self.rating_eps
        if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not 0 < eps < 0.5:
            raise ValueError(f"rating_eps must be a number in (0, 0.5), got {eps!r}.")
        if not isinstance(self.ties_offered, bool):
            raise ValueError(f"ties_offered must be True or False, got {self.ties_offered!r}.")
        levels = self.rating_levels
        if levels is not None and (isinstance(levels, bool) or not isinstance(levels, int) or levels < 2):
            raise ValueError(f"rating_levels must be None or a whole number >= 2, got {levels!r}.")

    # -------------------------------------------------------------- building
    def likelihood_settings(self) -> LikelihoodSettings:
        """The likelihood's settings (comparison noise, rating scale and precision, tie threshold), fixed."""
        return LikelihoodSettings(
            comparison_noise=self.comparison_noise,
            rating_scale=self.rating_scale,
            rating_precision=self.rating_precision,
            tie_threshold=self.tie_threshold,
        )

    def likelihood(self) -> PreferenceLikelihood:
        """The likelihood module (float64) of a person of these settings."""
        return self.likelihood_settings().create(self.rating_levels).double()

    def kernel(self, dim: int) -> ScaleKernel:
        """The default kernel (:func:`~torchpref.models.defaults.default_covar_module`, with its
        priors) at this lengthscale and outputscale."""
        kernel = default_covar_module(dim).double()
        kernel.base_kernel.lengthscale = self.lengthscale
        kernel.outputscale = self.outputscale
        return kernel

    def model_kwargs(self) -> dict[str, Any]:
        """:class:`~torchpref.PreferenceGP`'s keywords for these settings (the kernel and mean apart)."""
        return dict(
            likelihood=self.likelihood_settings(),
            ties_offered=self.ties_offered,
            rating_eps=self.rating_eps,
            rating_levels=self.rating_levels,
        )

    def session_model(self, train_X: Tensor) -> PreferenceGP:
        """A session's model on ``train_X`` (the anchor item): :class:`~torchpref.PreferenceGP` with
        :meth:`kernel` and these settings, all fixed."""
        from torchpref.models.preference_gp import PreferenceGP

        return PreferenceGP(train_X, covar_module=self.kernel(train_X.shape[-1]).to(train_X), **self.model_kwargs())

    # ----------------------------------------------------------- recording
    def to_json(self) -> dict[str, Any]:
        """The settings as a JSON object (a population file's ``settings``)."""
        return asdict(self)

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> ModelSettings:
        """The settings of a JSON object written by :meth:`to_json`. A population file written
        before the recipe recorded everything lacks ``tie_threshold``, ``ties_offered``,
        ``rating_eps``, ``lengthscale`` and ``outputscale``: such a file was fitted with ``tau = 0.1``,
        ties not offered and ``eps = 1e-3``, and is read so.

        Raises:
            ValueError: an unknown setting, or one out of range.
        """
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(obj) - names)
        if unknown:
            raise ValueError(
                f"unknown model setting(s) {', '.join(unknown)}; the settings are {', '.join(sorted(names))}."
            )
        legacy = {"tie_threshold": 0.1, "ties_offered": False, "rating_eps": DEFAULT_RATING_EPS}
        return cls(**{**{k: v for k, v in legacy.items() if k not in obj}, **obj})

    def with_(self, **changes: Any) -> ModelSettings:
        """These settings with ``changes`` (validated)."""
        return replace(self, **changes)


DEFAULT_MODEL = ModelSettings()
"""The person model of a session and of a population, unless told otherwise."""
NO_TIES_OFFERED = DEFAULT_MODEL.with_(ties_offered=False)
"""The default person model for answers given without a "no preference" option (recorded data
sets of choices): a strict choice is then the probit comparison, not the tie model's upper category."""
