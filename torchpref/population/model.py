r""":class:`Population`: a fitted population prior, and a new person's model from it."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from gpytorch.kernels import Kernel
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.models.preference_gp import PreferenceGP
from torchpref.models.recipe import ModelSettings
from torchpref.population.prior import PopulationCovariance, PopulationMean


class Population:
    r"""What a population's answers say about a new person: the posterior of the mean utility
    ``m`` at the population's distinct items ``U`` and the fitted kernels ``k_m`` (the mean's)
    and ``k_g`` (a person's deviation; its outputscale is the between-person spread ``s^2``).

    Built by :func:`torchpref.fit_population`; saved and loaded with
    :func:`torchpref.save_population` / :func:`torchpref.load_population`.

    Attributes:
        U: ``M x d``, the items the mean is represented at: all people's distinct items for the
            exact fit, the inducing items otherwise (``stats["mean"]`` says which).
        alpha: ``M``: ``E[m(x) | D] = k_m(x, U) alpha``.
        L_U: ``M x M``, ``chol(k_m(U, U) + jitter I)``.
        S_chol: ``M x M``, Cholesky factor of the Schur complement: ``Cov[a | D] = S^{-1}``.
        A: ``M x M``, ``I - S^{-1}``: what a new person's prior covariance needs of the
            population, computed once (and saved) so that a person model costs ``O(M^2)`` per item.
        settings: the person model's settings (:class:`~torchpref.models.recipe.ModelSettings`'
            JSON; :attr:`model_settings`) its fit used and a person model is built with.
        stats: people, distinct items, answers, evidence, which mean (``"exact"`` or
            ``"inducing"``) and how many items it is represented at, and the fit's costs.
        names: the features' names (the objective space), if given to the fit.
    """

    def __init__(
        self,
        k_m: Kernel,
        k_g: Kernel,
        U: Tensor,
        alpha: Tensor,
        L_U: Tensor,
        S_chol: Tensor,
        settings: dict[str, Any],
        stats: dict[str, Any] | None = None,
        names: Sequence[str] | None = None,
        A: Tensor | None = None,
    ):
        self.k_m, self.k_g = k_m, k_g
        self.U, self.alpha, self.L_U, self.S_chol = U, alpha, L_U, S_chol
        self.A = self.covariance_update(S_chol) if A is None else A
        self.settings = dict(settings)
        self.stats = dict(stats or {})
        self.names = None if names is None else tuple(str(n) for n in names)
        if self.names is not None and len(self.names) != self.dim:
            raise ValueError(f"names must name the {self.dim} features, got {len(self.names)}: {list(self.names)}.")

    @classmethod
    def from_mode(
        cls,
        k_m: Kernel,
        k_g: Kernel,
        U: Tensor,
        L_U: Tensor,
        a: Tensor,
        S_chol: Tensor,
        settings: dict,
        stats: dict,
        names: Sequence[str] | None = None,
    ) -> Population:
        """The population of a solved joint mode (whitened ``a`` of ``m(U) = L_U a``, and the
        Schur complement's factor ``S_chol``: :func:`~torchpref.population.joint.newton`)."""
        with torch.no_grad():
            alpha = torch.linalg.solve_triangular(L_U.mT, a.detach().unsqueeze(-1), upper=True).squeeze(-1)
        return cls(k_m, k_g, U, alpha, L_U.detach(), S_chol.detach(), settings, stats, names)

    @property
    def model_settings(self) -> ModelSettings:
        """The person model's settings the population was fitted with (and its person models get)."""
        return ModelSettings.from_json(self.settings)

    @property
    def dim(self) -> int:
        """``d``, the number of features."""
        return int(self.U.shape[-1])

    @property
    def mean_kind(self) -> str:
        """``"exact"`` (the mean at every distinct item) or ``"inducing"`` (at ``M`` of them)."""
        return str(self.stats.get("mean", "exact"))

    @property
    def spread(self) -> float:
        """``s^2``: ``k_g``'s outputscale, the between-person variance of the utility."""
        return float(getattr(self.k_g, "outputscale", torch.tensor(float("nan"))).detach())

    def check_space(self, names: tuple[str, ...] | list[str] | None = None, dim: int | None = None) -> None:
        """Raise a ``ValueError`` naming both when the items' objective space (``dim`` features
        named ``names``) is not this population's."""
        if dim is not None and int(dim) != self.dim:
            raise ValueError(f"this population's objective space has d = {self.dim} features, the items {dim}.")
        if names is not None and self.names is not None and tuple(names) != self.names:
            raise ValueError(
                f"this population was fitted on the objective space {list(self.names)}, not {list(names)}."
            )

    @staticmethod
    def covariance_update(S_chol: Tensor) -> Tensor:
        """``A = I - S^{-1}`` (symmetrised), from the Schur complement's factor: ``O(M^3)``, once."""
        with torch.no_grad():
            A = torch.eye(S_chol.shape[-1], dtype=S_chol.dtype) - torch.cholesky_inverse(S_chol)
            return 0.5 * (A + A.mT)

    def mean(self) -> PopulationMean:
        """The population's posterior mean utility as a GPyTorch ``Mean``."""
        return PopulationMean(self.k_m, self.U, self.alpha)

    def covariance(self) -> PopulationCovariance:
        """A new person's prior covariance as a GPyTorch ``Kernel``."""
        return PopulationCovariance(self.k_m, self.k_g, self.U, self.L_U, self.A)

    def person_model(self, data: PreferenceData | Tensor | None = None, **kwargs: Any) -> PreferenceGP:
        r"""A new person's :class:`~torchpref.PreferenceGP` with the population's prior: mean
        ``E[m | D]``, covariance ``k_g + Cov[m | D]``.

        Args:
            data: the person's items and answers (a ``PreferenceData``, answers optional), or
                ``n x d`` items alone, or ``None`` (a prior-only model; ``d`` is the population's).
            kwargs: further :class:`~torchpref.PreferenceGP` settings (e.g. ``max_newton_iter``).

        Raises:
            ValueError: items with a number of features other than the population's.
        """
        if isinstance(data, Tensor):
            data = PreferenceData.create(data)
        if data is not None and not isinstance(data, PreferenceData):
            raise ValueError(f"data must be a PreferenceData, an n x d tensor or None, got {type(data).__name__}.")
        if data is not None and data.train_X.shape[-1] != self.dim:
            raise ValueError(
                f"the person's items have {data.train_X.shape[-1]} features; this population's objective "
                f"space has d = {self.dim}."
            )
        recipe = self.model_settings
        levels = recipe.rating_levels
        if data is not None and data.num_observations and data.ratings.numel() and data.rating_levels != levels:
            raise ValueError(f"the person's rating_levels={data.rating_levels}; the population's is {levels}.")
        common = dict(covar_module=self.covariance(), mean_module=self.mean(), **recipe.model_kwargs())
        common.update(kwargs)
        if data is None:
            model = PreferenceGP(None, None, **common)
            return model.to(self.U.dtype)
        return PreferenceGP(data.train_X, data.comparisons, data.ratings, data.rating_index, ties=data.ties, **common)
