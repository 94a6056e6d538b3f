r"""``PreferenceGP``: a BoTorch model of a latent utility learned from ratings and comparisons."""

from __future__ import annotations

import copy
import numbers
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from itertools import chain
from typing import TYPE_CHECKING, Any, cast

import torch
from botorch.acquisition.objective import PosteriorTransform
from botorch.exceptions import warnings as botorch_warnings
from botorch.exceptions.errors import UnsupportedError
from botorch.exceptions.warnings import InputDataWarning
from botorch.models.model import Model
from botorch.models.transforms.input import InputTransform
from botorch.posteriors.gpytorch import GPyTorchPosterior
from botorch.sampling.base import MCSampler
from botorch.utils.containers import SliceContainer
from botorch.utils.datasets import RankingDataset, SupervisedDataset
from gpytorch.distributions import MultivariateNormal
from gpytorch.kernels import Kernel
from gpytorch.likelihoods import Likelihood
from gpytorch.means import Mean
from gpytorch.mlls import MarginalLogLikelihood
from gpytorch.models import GP
from gpytorch.module import Module as GModule
from linear_operator.operators import DenseLinearOperator, LinearOperator
from torch import Tensor

from torchpref.data.preference_data import DEFAULT_RATING_EPS, PreferenceData
from torchpref.inference.laplace import ModeResult, Observations, PredictiveCache, laplace_evidence
from torchpref.inference.numerics import LaplaceNumericalError, pin_coincident
from torchpref.inference.padding import PaddedData, create_data
from torchpref.inference.precision import call_in_dtype, check_dtype, check_laplace_dtype, solve_dtype
from torchpref.inference.solver import PosteriorState, SolveKey, carries_gradients
from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood, TieLikelihood
from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.likelihoods.scalar_params import weak_load_hook
from torchpref.models.arguments import check_model_arguments
from torchpref.models.defaults import (  # noqa: F401  (MIN_LENGTHSCALE, PAPER_FIG4_SETTINGS: re-exported)
    MIN_LENGTHSCALE,
    PAPER_FIG4_SETTINGS,
    LikelihoodKeywords,
    LikelihoodSettings,
    PreferenceLikelihood,
    default_covar_module,
)
from torchpref.models.fantasy import condition_batch, fantasize
from torchpref.models.fast_fit import Closure, FitReport, fit_laplace
from torchpref.models.pairwise_interface import (
    TrainDataMismatchError,
    _check_strict,
    _comparisons_from_Y,
    _condition_prior_only,
    check_jitter,
    pairwise_alias,
    prior_only_data,
    ranking_comparisons,
)
from torchpref.models.posterior_state import cache_key, submodules

if TYPE_CHECKING:
    from torch.nn.modules.module import _IncompatibleKeys
    from typing_extensions import Unpack


def _initial_data(
    train_X, comparisons, ratings, rating_index, rating_eps: float, ties, rating_levels: int | None
) -> PreferenceData | PaddedData:
    """The constructor's validated data; for ``train_X = None`` BoTorch's prior-only model."""
    if train_X is not None:
        return create_data(train_X, comparisons, ratings, rating_index, rating_eps, ties, rating_levels)
    if ratings is not None or (comparisons is not None and len(comparisons)):
        raise ValueError("a prior-only model (train_X=None) takes no comparisons or ratings.")
    return prior_only_data()


def _warn_dtype(dtype: torch.dtype) -> None:
    """BoTorch's single-precision ``InputDataWarning`` (its text first, so that filters written for
    ``PairwiseGP``'s warning catch this one), and what it means here."""
    if dtype != torch.float64:
        botorch_text = getattr(botorch_warnings, "_get_single_precision_warning", None)
        head = botorch_text(str(dtype)).rstrip(". ") + ". " if botorch_text is not None else ""
        warnings.warn(
            f"{head}train_X is {dtype}; float64 is recommended (as in BoTorch). The Laplace problem is "
            "solved in float64 unless laplace_dtype says otherwise (docs/precision.md).",
            InputDataWarning,
            stacklevel=3,
        )


def _follows(module: torch.nn.Module, device: torch.device, dtype: torch.dtype) -> bool:
    """Whether ``module.to(device=device, dtype=dtype)`` would change nothing: every parameter and
    buffer on ``device``, the floating ones in ``dtype``."""
    return all(
        t.device == device and (t.dtype == dtype or not (t.is_floating_point() or t.is_complex()))
        for t in chain(module.parameters(), module.buffers())
    )


def _check_evidence(value: Tensor) -> None:
    """A non-finite Laplace evidence raised by name rather than handed to an optimiser."""
    finite = torch.isfinite(value.detach())
    if not bool(finite.all()):
        bad = torch.nonzero(~finite).flatten()[:5].tolist()
        raise LaplaceNumericalError(
            f"the Laplace evidence is not finite ({value.detach()[~finite][:3].tolist()}, problems {bad}) at "
            "these hyperparameters; they are outside what the model can evaluate."
        )


class PreferenceGP(Model, GP):
    r"""A GP over the items' objective space, learned from comparisons and ratings together.

    The latent utility ``f ~ GP(0, k)`` (eq. 1) is observed through comparisons (eq. 3) and
    ratings on ``[0, 1]`` (eqs. 4-7); the posterior is the Laplace approximation (eqs. 2, 8-10).
    The mode is re-solved, warm-started, whenever the hyperparameters or the data change.

    BoTorch's ``PairwiseGP`` interface is there too (``datapoints``, ``dim``, ``utility``,
    ``construct_inputs``, prior-only ``PreferenceGP(None, None)``, comparisons as
    ``condition_on_observations(X, Y)``): see the class's last section (its aliases and errors in
    :mod:`torchpref.models.pairwise_interface`) and docs/botorch.md.

    Args:
        train_X: ``n x d`` items (float64 recommended; dtype and device are followed), or
            ``None`` for a prior-only model (then no observations; ``d`` is set by the first
            data).
        comparisons: ``p x 2`` long, rows ``[preferred, other]`` (BoTorch's convention).
        ratings: ``q`` values in ``[0, 1]``; exact 0 and 1 are moved in to ``rating_eps``.
        rating_index: ``q`` long indices into ``train_X``: the item each rating rates.
        covar_module: the kernel; default :func:`default_covar_module`.
        input_transform: a BoTorch input transform (e.g. ``Normalize``), applied to ``train_X``
            and to every input of :meth:`posterior` (positional here as in ``PairwiseGP``). A
            prior-only model takes one too; its bounds are learned from the first data.
        likelihood: the answer likelihoods' settings, a
            :class:`~torchpref.models.defaults.LikelihoodSettings` (``sigma_R``, ``sigma_B``, ``nu``,
            whether they are learned, the tie threshold, the ordinal cut points and noise); or
            ``PairwiseGP``'s argument: BoTorch's ``PairwiseProbitLikelihood`` (eq. 3 with
            ``sigma_R = 1``, the default) or torchpref's
            :class:`~torchpref.likelihoods.pairwise_beta.PairwiseProbitLikelihood` (its ``sigma_R``);
            any other (``PairwiseLogitLikelihood``) raises
            :class:`~torchpref.models.pairwise_interface.UnsupportedLikelihoodError`.
        **likelihood_settings: the fields of :class:`~torchpref.models.defaults.LikelihoodSettings`
            as keywords (``comparison_noise=0.1``, ``rating_scale``, ``rating_precision``,
            ``learn_likelihood``, ``tie_threshold``, ``cut_points``, ``level_noise``), overriding
            ``likelihood``'s; any other keyword is a ``TypeError`` naming it.
        datapoints: ``PairwiseGP``'s name for ``train_X`` (give one of them).
        jitter: ``PairwiseGP``'s argument, accepted and not used: a kernel matrix is jittered only
            when its Cholesky factorisation fails, relative to its diagonal and dtype.
        rating_eps: where exact 0 / 1 ratings are moved to.
        max_newton_iter: iteration budget of the mode finder (at least 1).
        ties: ``t x 2`` long, rows ``[i, j]``: "no preference" between items ``i`` and ``j``
            (:class:`~torchpref.likelihoods.ordinal.TieLikelihood`).
        rating_levels: ``K``: the ratings are levels ``1..K``, scored by the ordinal likelihood
            (:class:`~torchpref.likelihoods.ordinal.OrdinalRatingLikelihood`) instead of the Beta one.
        ties_offered: "no preference" was an allowed answer to the comparisons, which are then
            scored ``Phi((f_i - f_j - tau) / (sqrt 2 sigma_R))`` (the tie's ordered probit) instead
            of eq. 3 (a forced choice); needed to learn ``tau``. Default ``False``.
        laplace_dtype: the dtype the kernel matrices and the Laplace problem are computed in
            (:attr:`laplace_dtype`); default float64 whatever the model's dtype, so a float32 model
            solves in mixed precision and returns float32 posteriors. ``torch.float32`` solves a
            float32 model natively (docs/precision.md).
        mean_module: the prior mean of the utility, a GPyTorch ``Mean`` (default ``None``: zero,
            eq. 1). The utility is ``f = m + g`` with ``g ~ GP(0, k)``: the likelihoods score
            ``m(X) + g`` and Newton solves for ``g`` (the mean enters the solve only as an offset,
            :meth:`~torchpref.inference.observations.Observations.shifted`); :meth:`posterior` adds
            ``m`` back. Its parameters are fitted with the kernel's. A population's person model
            (:meth:`torchpref.population.Population.person_model`) has one.

    Warns:
        InputDataWarning: (BoTorch's) for inputs in a dtype other than float64, and for training
            items (after ``input_transform``) outside the unit cube, whose scale the default
            kernel's lengthscale prior assumes (docs/decisions.md).

    Example:
        >>> model = PreferenceGP(X, comparisons=C, ratings=u, rating_index=idx)
        >>> fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
        >>> model.posterior(X_test).mean
    """

    _max_newton_iter: int

    _num_outputs = 1

    def __init__(
        self,
        train_X: Tensor | None = None,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        covar_module: Kernel | None = None,
        input_transform: InputTransform | None = None,
        *,
        likelihood: LikelihoodSettings | Likelihood | None = None,
        mean_module: Mean | None = None,
        ties: Tensor | None = None,
        rating_levels: int | None = None,
        ties_offered: bool = False,
        rating_eps: float = DEFAULT_RATING_EPS,
        max_newton_iter: int = 100,
        laplace_dtype: torch.dtype | None = None,
        datapoints: Tensor | None = None,
        jitter: float | None = None,
        **likelihood_settings: Unpack[LikelihoodKeywords],
    ) -> None:
        super().__init__()
        weak_load_hook(self)
        train_X = pairwise_alias(train_X, datapoints)
        settings = LikelihoodSettings.of(likelihood, likelihood_settings)
        check_jitter(jitter)
        check_model_arguments(
            covar_module,
            input_transform,
            flags={"ties_offered": ties_offered},
            rating_eps=rating_eps,
            mean_module=mean_module,
        )
        data = _initial_data(train_X, comparisons, ratings, rating_index, rating_eps, ties, rating_levels)
        X = data.train_X if isinstance(data, PreferenceData) else data.X
        check_dtype(X.dtype)
        _warn_dtype(X.dtype)
        self.covar_module = covar_module if covar_module is not None else default_covar_module(X.shape[-1])
        self.mean_module = mean_module
        self.likelihood = settings.create(rating_levels)
        self._rating_levels = None if rating_levels is None else int(rating_levels)
        self.ties_offered = bool(ties_offered)
        if input_transform is not None:
            self.input_transform = input_transform
        self.rating_eps = rating_eps
        self.max_newton_iter = max_newton_iter
        self._laplace_dtype = check_laplace_dtype(laplace_dtype)
        self._scaling_warned = False
        if not _follows(self, X.device, X.dtype):
            self.to(device=X.device, dtype=X.dtype)
        self._data: PreferenceData | PaddedData = data
        self._cache: PosteriorState | None = None
        #: how the last ``fit_gpytorch_mll`` went: which solver fitted, how it stopped (``None``: not fitted)
        self.last_fit: FitReport | None = None
        self._transitions = 0  # train / eval switches: part of the cache's key
        self._warm_f: Tensor | None = None
        self._fit_input_transform()
        self._check_scaling()
        self.eval()

    @property
    def max_newton_iter(self) -> int:
        """Iteration budget of the mode finder (an integer, at least 1)."""
        return self._max_newton_iter

    @max_newton_iter.setter
    def max_newton_iter(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
            raise ValueError(f"max_newton_iter must be an integer of at least 1, got {value!r}.")
        self._max_newton_iter = int(value)

    @property
    def laplace_dtype(self) -> torch.dtype:
        """The dtype of the kernel matrices and the Laplace solve: the ``laplace_dtype`` asked
        for (default float64), or the model's dtype where that is more precise. Outputs
        (posteriors, the evidence) come back in the model's dtype; :attr:`mode` stays in this one."""
        return solve_dtype(self._padded().X.dtype, self._laplace_dtype)

    @laplace_dtype.setter
    def laplace_dtype(self, value: torch.dtype | None) -> None:
        self._laplace_dtype, self._cache = check_laplace_dtype(value), None

    # ------------------------------------------------------------ likelihoods
    @property
    def comparison_likelihood(self) -> PairwiseProbitLikelihood:
        """The comparisons' likelihood (eq. 3), a :class:`~torchpref.PairwiseProbitLikelihood`."""
        return self.likelihood.comparison

    @property
    def rating_likelihood(self) -> BetaRatingLikelihood | OrdinalRatingLikelihood:
        """The ratings' likelihood: a :class:`~torchpref.BetaRatingLikelihood` (eqs. 4-7), or an
        :class:`~torchpref.OrdinalRatingLikelihood` for a model with ``rating_levels``."""
        return self.likelihood.rating

    @property
    def tie_likelihood(self) -> TieLikelihood:
        """The "no preference" likelihood (:class:`~torchpref.TieLikelihood`)."""
        return self.likelihood.tie

    def fantasize(
        self,
        X: Tensor,
        sampler: MCSampler,
        observation_noise: Tensor | None = None,
        kind: str | None = None,
        **kwargs: object,
    ) -> PreferenceGP:
        r"""A batched fantasy model (see :func:`~torchpref.models.fantasy.fantasize`): comparisons among
        the ``q`` points of ``X`` (``batch x q x d``) with a ``PairwiseMCSampler``, ratings of them
        with any other sampler (or as ``kind`` says). ``observation_noise`` is not used: the
        answers' noise is the likelihoods'."""
        return fantasize(self, X, sampler, kind)

    def custom_fit(
        self,
        mll: MarginalLogLikelihood,
        closure: Closure | None = None,
        closure_kwargs: dict[str, Any] | None = None,
        optimizer_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> MarginalLogLikelihood:
        """BoTorch's hook for a model's own fitting routine: ``fit_gpytorch_mll(mll)`` comes here.
        A :class:`LaplaceMarginalLogLikelihood` is fitted on the compiled path where it applies
        (:func:`~torchpref.models.fast_fit.fit_laplace`: the same L-BFGS-B from the same start,
        each evaluation one compiled call), else, as any other MLL, by BoTorch's own routine."""
        if isinstance(mll, LaplaceMarginalLogLikelihood):
            return fit_laplace(mll, closure, closure_kwargs, optimizer_kwargs, **kwargs)
        from botorch.fit import _fit_fallback, _fit_fallback_approximate
        from gpytorch.mlls._approximate_mll import _ApproximateMarginalLogLikelihood

        fallback = _fit_fallback_approximate if isinstance(mll, _ApproximateMarginalLogLikelihood) else _fit_fallback
        return fallback(
            mll, closure=closure, closure_kwargs=closure_kwargs, optimizer_kwargs=optimizer_kwargs, **kwargs
        )

    # ------------------------------------------------------------- inference
    def _kernel(self, X1: Tensor, X2: Tensor | None = None, diag: bool = False) -> Tensor:
        """Dense ``k(X1, X2)`` (or its diagonal): the kernel's ``forward`` directly (the values
        ``__call__`` would give, without building a lazy kernel tensor) unless a kernel selects
        ``active_dims``; in :attr:`laplace_dtype`; below float64, exact at coincident points
        (:func:`~torchpref.inference.numerics.pin_coincident`)."""
        k = self.covar_module
        X2 = X1 if X2 is None else X2
        if any(getattr(m, "active_dims", None) is not None for m in submodules(k)):

            def evaluate(A, B, diag):
                out = k(A, B, diag=diag)
                return out if diag else out.to_dense()
        else:
            evaluate = k.forward
        dtype = solve_dtype(X1.dtype, self._laplace_dtype)
        out = call_in_dtype(k, dtype, lambda A, B: evaluate(A, B, diag=diag), X1, X2)
        # kernels such as LinearKernel return a LinearOperator from forward: evaluate it densely
        out = out.to_dense() if isinstance(out, LinearOperator) else out
        if diag or out.dtype == torch.float64:  # float64's round-off there is ~1e-16: not worth a pass
            return out
        return pin_coincident(out, X1, X2, evaluate(X1, X1, diag=True))

    def _prior(self) -> tuple[PaddedData, Tensor]:
        """The problems with their items transformed, and their prior covariance ``K``
        (``batch x N x N``, padded items independent; differentiable in the hyperparameters)."""
        padded = self._padded().with_items(self._transformed_train_X())
        return padded, padded.prior_covariance(self._kernel(padded.X))

    def _item_mean(self, padded: PaddedData) -> Tensor | None:
        """The prior mean ``m`` of the problems' (transformed) items, ``B x N`` in
        :attr:`laplace_dtype` (``None`` for a zero mean): the Laplace solve's offset."""
        if self.mean_module is None:
            return None
        m = self._mean(padded.X)
        return m.reshape(-1, padded.num_items)

    def _mean(self, X: Tensor) -> Tensor:
        """``m(X)`` at transformed ``X`` (``... x q x d``): ``... x q`` in :attr:`laplace_dtype`."""
        mean = cast(Mean, self.mean_module)
        dtype = solve_dtype(X.dtype, self._laplace_dtype)
        out = call_in_dtype(mean, dtype, mean.forward, X)
        return out.expand(X.shape[:-1])

    def _state(self, prior: tuple[PaddedData, Tensor] | None = None) -> PosteriorState:
        """The mode and prediction cache for the current hyperparameters and data (cached);
        ``prior``: :meth:`_prior`'s result if already computed (then the kernel is not evaluated again)."""
        fp, structure = cache_key(self)
        key = SolveKey(self._data, fp, structure, self.likelihood)
        if self._cache is None or not self._cache.key.matches(key):
            with torch.no_grad():
                if prior is None:
                    prior = self._prior()
                mean = self._item_mean(prior[0])
            self._cache = PosteriorState.solve(
                key,
                *prior,
                self._observations,
                previous=self._cache,
                warm_f=self._warm_f,
                max_iter=self.max_newton_iter,
                mean=mean,
            )
        return self._cache

    def _adopt_mode(self, L: Tensor, jitter: float, mode: ModeResult) -> None:
        """Keep ``mode`` (one problem's, solved elsewhere for the current hyperparameters and data,
        ``L L^T = K + jitter I``: the compiled fit's last, :func:`~torchpref.models.fast_fit.hand_back`)
        as the posterior cache, so that the next prediction does not solve it again."""
        fp, structure = cache_key(self)
        with torch.no_grad():
            padded = self._padded().with_items(self._transformed_train_X().detach())
            mean = self._item_mean(padded)
        obs = self._observations().shifted(None if mean is None else mean.reshape(L.shape[:-1]))
        key = SolveKey(self._data, fp, structure, self.likelihood)
        self._cache = PosteriorState(key, padded, jitter, obs, mode, PredictiveCache.from_mode(L, mode))

    def train(self, mode: bool = True) -> PreferenceGP:
        """Train or eval mode, as for any module; a switch between them makes the posterior cache
        stale (as GPyTorch resets an exact GP's ``prediction_strategy``): the next prediction
        re-solves the mode, warm-started from the cached one."""
        if mode != self.training:
            self._transitions = getattr(self, "_transitions", 0) + 1
        return super().train(mode)

    @property
    def mode(self) -> ModeResult:
        """The Laplace mode (``.f``), ``W``'s factors and solver diagnostics, for the current state
        (with a leading dimension over the flattened batch for a batched model)."""
        mode = self._state().mode
        return mode.select(0) if not self.batch_shape else mode

    def W(self) -> Tensor:
        r"""``batch_shape x n x n`` negative Hessian of the log-likelihood at the mode (eq. 8): the
        exact one, or the Fisher one if the exact ``B`` was not positive definite there
        (``mode.fisher_fallback``)."""
        state = self._state()
        n = state.padded.num_items
        return state.obs.W_dense(n, state.mode.weights, like=state.pred.L).reshape(*self.batch_shape, n, n)

    def log_marginal_likelihood(self) -> Tensor:
        r"""Laplace evidence ``log q(Y) = log p(Y|f) - f^T K^-1 f / 2 - log|I + W K| / 2`` at the
        mode (``batch_shape``), differentiable, with a gradient that includes the mode's implicit
        dependence on the hyperparameters. Hyperparameter priors are not included (the MLL adds them).

        Raises:
            ValueError: the model has no items (prior-only or empty): there is nothing to fit.
            NotPSDError: a matrix of the solve is not positive definite at these hyperparameters.
            LaplaceNumericalError: (a ``NotPSDError``) the mode or the evidence is not finite at
                these hyperparameters. ``fit_gpytorch_mll`` retries both from resampled ones.
        """
        if self.train_X.shape[-2] == 0:
            raise ValueError(
                "the evidence needs data: this model has no items (a prior-only or empty model); "
                "add observations before fitting its hyperparameters."
            )
        padded, K = self._prior()
        state = self._state((padded, K))
        N = padded.num_items
        obs = state.obs if self.mean_module is None else state.obs.shifted(self._item_mean(padded))
        value = laplace_evidence(K.reshape(-1, N, N), obs, state.mode, L=state.pred.L, jitter=state.jitter)
        _check_evidence(value)
        return value.reshape(self.batch_shape).to(padded.X.dtype)

    def _predict(self, X: Tensor, diag: bool = False) -> tuple[Tensor, Tensor]:
        """Posterior moments at transformed ``X`` (:meth:`PosteriorState.moments`), in ``X``'s dtype;
        with autograd on and training items or ratings that carry gradients (a fantasy model inside
        a look-ahead acquisition), differentiable in them through the mode (:meth:`PosteriorState.traced`)."""
        state = self._state()
        if torch.is_grad_enabled() and carries_gradients(self._padded()):
            padded, K = self._prior()
            state = state.traced(padded, K, self._observations().shifted(self._item_mean(padded)))
        mean, cov = state.moments(self._kernel, X, diag)
        if self.mean_module is not None:
            mean = mean + self._mean(X)
        return mean.to(X.dtype), cov.to(X.dtype)

    def forward(self, X: Tensor) -> MultivariateNormal:
        """The Laplace posterior of the latent utility at ``X`` (``batch x q x d``, transformed)."""
        mean, cov = self._predict(X)
        # a lazy covariance: no Cholesky at construction (pairs of equal points are singular)
        return MultivariateNormal(mean, DenseLinearOperator(cov))

    def posterior(
        self,
        X: Tensor,
        output_indices: list[int] | None = None,
        observation_noise: bool | Tensor = False,
        posterior_transform: PosteriorTransform | None = None,
        **kwargs: object,
    ) -> GPyTorchPosterior:
        r"""Posterior of the latent utility (eqs. 9-10) at ``X`` (``batch_shape x q x d``).

        The factorisations are cached: repeated calls with unchanged hyperparameters and data
        cost kernel evaluations and triangular solves only.

        Args:
            X: ``batch_shape x q x d`` inputs (untransformed).
            output_indices: ``None`` or ``[0]`` (the one output).
            observation_noise: ``False``: the latent utility ``f``. ``True``: the utility as
                perceived in a comparison, ``f + eps`` with independent ``eps ~ N(0, sigma_R^2)``
                per point (eq. 3; what ``qMaxValueEntropy`` asks for). A tensor
                (``batch_shape x q x 1``): those noise variances instead. BoTorch's
                ``PairwiseGP`` ignores this argument.
            posterior_transform: applied to the result.
        """
        if output_indices is not None and [int(i) for i in output_indices] not in ([0], [-1]):
            raise ValueError(f"PreferenceGP has one output; got output_indices={output_indices}.")
        X = self._prediction_inputs(X)
        if X.dim() == 1:  # a single point
            X = X.unsqueeze(0)
        mvn = self(X)
        if observation_noise is not False:
            mvn = self._add_observation_noise(mvn, observation_noise)
        post = GPyTorchPosterior(mvn)
        if posterior_transform is not None:
            return posterior_transform(post)
        return post

    def _prediction_inputs(self, X: Tensor) -> Tensor:
        """``X`` checked (``... x d``, real and finite, not boolean; a lower floating precision is
        converted to the model's, as BoTorch's models do), the model in eval mode, the input
        transform applied."""
        if self._data.dim and X.shape[-1] != self._data.dim:  # dim 0: a prior-only model takes any d
            raise ValueError(f"X must have {self._data.dim} columns (last dim), got shape {tuple(X.shape)}.")
        dtype = self.train_X.dtype
        check_dtype(dtype, "this model")
        if X.is_complex() or X.dtype == torch.bool:
            raise ValueError(f"X must hold real numbers, got {X.dtype}.")
        if X.dtype != dtype and X.is_floating_point():
            if torch.finfo(X.dtype).eps < torch.finfo(dtype).eps:  # would lose precision: say so
                raise ValueError(
                    f"X is {X.dtype} but the model is {dtype}: convert one of them (X.to({dtype}) or model.to(...))."
                )
            X = X.to(dtype)  # BoTorch's optimisers and objectives hand over float32 candidates
        elif not X.is_floating_point():  # integer items: predictions in the model's dtype, not truncated
            X = X.to(dtype)
        if self.training:
            self.eval()
        Xt = self.transform_inputs(X)
        # one check (one synchronisation) for both: finite, and small enough that the kernel's
        # squared distances (x / lengthscale)^2, lengthscales >= 1e-4, do not overflow to inf - inf
        if not bool((Xt.detach().abs() <= torch.finfo(dtype).max ** 0.5 * 1e-5).all()):
            finite = torch.isfinite(X.detach())
            if not bool(finite.all()):
                bad = X.detach()[~finite][:3].tolist()
                raise ValueError(f"X must be finite, got {int((~finite).sum())} non-finite value(s) such as {bad}.")
            raise ValueError(
                f"X is too large for the kernel: values up to {float(Xt.detach().abs().max()):.3g} "
                "(after any input transform) overflow its squared distances; the model expects "
                "items in the unit cube (scale them, or pass input_transform=Normalize(d, bounds))."
            )
        return Xt

    def __call__(self, X: Tensor) -> MultivariateNormal:  # skip gpytorch's GP.__call__ machinery
        return self.forward(X)

    # ================================================================ data
    @property
    def data(self) -> PreferenceData | PaddedData:
        """The observations (immutable): a :class:`~torchpref.data.preference_data.PreferenceData`, or for a
        batched model (``batch_shape`` not empty) a :class:`~torchpref.inference.padding.PaddedData`."""
        return self._data

    def _padded(self) -> PaddedData:
        d = self._data
        return PaddedData.single(d) if isinstance(d, PreferenceData) else d

    @property
    def train_X(self) -> Tensor:
        """``batch_shape x n x d`` items."""
        return self._padded().X

    @property
    def comparisons(self) -> Tensor:
        """``batch_shape x p x 2`` comparisons (rows ``[preferred, other]``)."""
        return self._padded().comparisons

    @property
    def ratings(self) -> Tensor:
        """``batch_shape x r`` ratings in ``(0, 1)``."""
        return self._padded().ratings

    @property
    def rating_index(self) -> Tensor:
        """``batch_shape x r`` rows of :attr:`train_X` the :attr:`ratings` are of."""
        return self._padded().rating_index

    @property
    def ties(self) -> Tensor:
        """``batch_shape x t x 2`` long: the "no preference" pairs."""
        return cast(Tensor, self._padded().ties)  # never None for a model's data

    @property
    def rating_levels(self) -> int | None:
        """``K`` when ratings are levels ``1..K`` (ordinal likelihood), else ``None``."""
        return self._rating_levels

    @property
    def train_inputs(self) -> tuple[Tensor]:
        """``(train_X,)``, as GPyTorch models hold their inputs."""
        return (self.train_X,)

    @property
    def num_outputs(self) -> int:
        """``1``: one latent utility."""
        return 1

    @property
    def batch_shape(self) -> torch.Size:
        """``torch.Size([])`` for one problem; ``[b]`` for batched training data (BoTorch's meaning)."""
        return self._padded().batch_shape

    # The model applies its input transform itself (``_transformed_train_X``): BoTorch's
    # swapping of transformed training inputs on train()/eval() must not replace the data.
    def _set_transformed_inputs(self) -> None:
        pass

    def _revert_to_original_inputs(self) -> None:
        pass

    def _fit_input_transform(self) -> None:
        tf = getattr(self, "input_transform", None)
        if tf is not None and self.train_X.shape[-2] > 0:  # no items: nothing to learn bounds from
            was_training = tf.training
            tf.train()
            with torch.no_grad():
                tf(self.train_X)
            tf.train(was_training)

    def _check_scaling(self) -> None:
        """BoTorch's ``InputDataWarning`` (once per model) when the items, after the input
        transform, leave the unit cube by more than BoTorch's tolerance of 0.01."""
        X = self._transformed_train_X()
        if self._scaling_warned or X.shape[-2] == 0:
            return
        with torch.no_grad():
            X = X.reshape(-1, X.shape[-1])
            lo, hi = X.min(0).values, X.max(0).values
        out = ((lo < -0.01) | (hi > 1.01)).nonzero().reshape(-1).tolist()
        if out:
            self._scaling_warned = True
            ranges = ", ".join(f"column {i}: [{float(lo[i]):.3g}, {float(hi[i]):.3g}]" for i in out[:5])
            warnings.warn(
                f"the items are not contained in the unit cube ({ranges}); the default kernel's "
                f"lengthscale prior assumes inputs in [0, 1]: pass input_transform=Normalize(d={X.shape[-1]}, "
                "bounds=...) with your domain's bounds (botorch.models.transforms), or scale the items yourself.",
                InputDataWarning,
                stacklevel=3,
            )

    def _transformed_train_X(self) -> Tensor:
        tf = getattr(self, "input_transform", None)
        if tf is None or self.train_X.shape[-1] == 0:  # a prior-only model's 0 x 0 items: d not known yet
            return self.train_X
        was_training = tf.training
        tf.eval()  # bounds were learned from train_X when the data was set
        X = tf(self.train_X)
        tf.train(was_training)
        return X

    def _observations(self) -> Observations:
        """The observations of the ``B`` problems (flattened batch) as likelihood terms; strict
        comparisons as the tie's upper category where ties were offered."""
        lik = self.likelihood
        comparison = lik.strict if self.ties_offered else lik.comparison
        padded, dtype = self._padded(), self.laplace_dtype
        if padded.X.dtype != dtype:
            padded = padded.map(lambda t: t.to(dtype) if t.is_floating_point() else t)
        return padded.observations(comparison, lik.rating, lik.tie)

    def replace_data(
        self, data: PreferenceData | PaddedData, warm_f: Tensor | None = None, *, lazy: bool = False
    ) -> PreferenceGP:
        """Swap in new observations: a :class:`~torchpref.data.preference_data.PreferenceData`, or for
        a batched model a :class:`~torchpref.inference.padding.PaddedData`, with Newton started from
        ``warm_f`` (the mode of ``data``'s items, flattened batch first; ``None``: from zero).

        By default the input transform learns from the new items and the mode is solved at once;
        if that fails or is interrupted (any ``BaseException``: a ``KeyboardInterrupt`` leaves
        nothing half-updated), the model is put back as it was and the error raised. With
        ``lazy=True`` nothing is solved (the next prediction does it) and the input transform is
        kept as it is: the data of a fantasy or of a batch's members, in the model's own inputs.

        The one writer of the model's observations: :meth:`add_observations`, fantasies, the
        batched model and sessions all go through it.

        Returns:
            ``self``.
        """
        if not isinstance(data, (PreferenceData, PaddedData)):
            raise TypeError(f"data must be a PreferenceData or a PaddedData, got {type(data).__name__}.")
        if lazy:
            self._data, self._cache, self._warm_f = data, None, warm_f
            return self
        with self.rollback():
            self._data, self._cache, self._warm_f = data, None, warm_f
            self._fit_input_transform()
            self._state()
        self._check_scaling()
        return self

    @contextmanager
    def rollback(self) -> Iterator[PreferenceGP]:
        """A block after which the model is exactly as before it if the block raises (any
        ``BaseException``): its observations, posterior cache and warm start are put back, with no
        computation, and the input transform relearns the old items; the error goes on. A block
        that completes keeps its changes. ::

            with model.rollback():
                model.add_observations(X, ratings=[0.7], rating_index=[0])
                journal.append(record)  # fails: the answer is not in the model either
        """
        saved = (self._data, self._cache, self._warm_f)
        try:
            yield self
        except BaseException:
            self._data, self._cache, self._warm_f = saved
            self._fit_input_transform()
            raise

    @property
    def jitter(self) -> float | Tensor:
        """The diagonal jitter added to the kernel matrix for its Cholesky factor (one per problem
        for a batched model), at the current hyperparameters."""
        return self._state().jitter

    def add_observations(
        self,
        X: Tensor | None = None,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        ties: Tensor | None = None,
    ) -> PreferenceGP:
        r"""Add items and observations in place, warm-starting the mode (no refit from scratch).

        Indices in ``comparisons``, ``ties`` and ``rating_index`` refer to the rows of ``X`` when
        ``X`` is given (rows equal to an existing item reuse its index), otherwise to ``train_X``.
        Ratings are levels ``1..K`` for a model with ``rating_levels``. The input is validated and
        the new mode solved before anything changes: on error the model is left exactly as it was.

        Returns:
            ``self``.
        """
        if not isinstance(self._data, PreferenceData):
            raise NotImplementedError(
                "add_observations needs a model of one problem; a batched model is "
                "conditioned with condition_on_observations."
            )
        new = self._data.add(X, comparisons, ratings, rating_index, rating_eps=self.rating_eps, ties=ties)
        warm = None
        if self._cache is not None or self._data.num_observations:
            f_old = self._state().mode.f[0]
            if new.n > self._data.n:
                with torch.no_grad():
                    X_new = new.train_X[self._data.n :]
                    extra = self.posterior(X_new.unsqueeze(-2)).mean.reshape(-1)
                    if self.mean_module is not None:  # the warm start is of the deviation g = f - m
                        extra = extra - self._mean(self.transform_inputs(X_new)).to(extra)
                warm = torch.cat([f_old, extra])
            else:
                warm = f_old
        self.replace_data(new, warm)
        return self

    def _apply(self, fn, *args, **kwargs):
        super()._apply(fn, *args, **kwargs)
        data = getattr(self, "_data", None)
        if isinstance(data, PreferenceData):
            self._data = PreferenceData(
                *(fn(t) for t in (data.train_X, data.comparisons, data.ratings, data.rating_index, data.ties)),
                data.rating_levels,
            )
        elif data is not None:
            self._data = data.map(fn)
        if data is not None:
            self._cache, self._warm_f = None, None
        return self

    # ================================================================ predictives (eq. 11)
    def marginals(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""Posterior mean and variance of the latent utility at each row of ``X`` (``... x d``),
        each of ``X``'s shape without its last dimension: what ``posterior(X.unsqueeze(-2))``
        gives, without building a batch of ``1 x 1`` covariances and distribution objects. For a
        batched model, ``X`` is ``... x batch_shape x m x d``."""
        Xt = self._prediction_inputs(X)
        if X.shape[:-1].numel() == 0:  # an empty batch: empty results
            empty = Xt.new_zeros(X.shape[:-1])
            return empty, empty.clone()
        if not self.batch_shape:  # one problem: all rows as one block
            Xt = Xt.reshape(-1, X.shape[-1])
        mean, var = self._predict(Xt, diag=True)
        return mean.reshape(X.shape[:-1]), var.reshape(X.shape[:-1])

    def expected_rating(self, X: Tensor) -> Tensor:
        r"""Expected rating ``Phi(m / sqrt(2 sigma_B^2 + v))`` at each row of ``X`` (``... x d``);
        returns the shape of ``X`` without its last dimension."""
        mean, var = self.marginals(X)
        return self.likelihood.rating.expected_rating(mean, var)

    def expected_level(self, X: Tensor) -> Tensor:
        r"""Expected level ``1 + sum_k Phi((m - c_k) / sqrt(sigma^2 + v))`` at each row of ``X``
        (``... x d``), for a model with ``rating_levels``."""
        return self._ordinal().expected_level(*self.marginals(X))

    def level_probabilities(self, X: Tensor) -> Tensor:
        r"""Predictive probability of each level at each row of ``X`` (``... x d``): ``... x K``."""
        return self._ordinal().level_probabilities(*self.marginals(X))

    def _ordinal(self) -> OrdinalRatingLikelihood:
        if not isinstance(self.likelihood.rating, OrdinalRatingLikelihood):
            raise ValueError("levels are predicted by a model with rating_levels=K (ordinal ratings).")
        return self.likelihood.rating

    def _pair_moments(self, Xa: Tensor, Xb: Tensor) -> tuple[Tensor, Tensor]:
        """Posterior mean and variance of ``f(a) - f(b)``, row by row."""
        if Xa.shape != Xb.shape:
            raise ValueError(f"Xa and Xb must have the same shape, got {tuple(Xa.shape)} and {tuple(Xb.shape)}.")
        mvn = self.posterior(torch.stack([Xa, Xb], dim=-2)).distribution
        m, S = mvn.mean, mvn.covariance_matrix
        return m[..., 0] - m[..., 1], S[..., 0, 0] + S[..., 1, 1] - 2 * S[..., 0, 1]

    def preference_probability(self, Xa: Tensor, Xb: Tensor) -> Tensor:
        r"""``P(a preferred to b)`` row by row (``... x d`` each): ``Phi((m_a - m_b) /
        sqrt(2 sigma_R^2 + v_a + v_b - 2 c_ab))`` (with ``ties_offered``, ``m_a - m_b - tau``)."""
        lik = self.likelihood.strict if self.ties_offered else self.likelihood.comparison
        return lik.preference_probability(*self._pair_moments(Xa, Xb))

    def tie_probability(self, Xa: Tensor, Xb: Tensor) -> Tensor:
        r"""``P(no preference between a and b)`` row by row (``... x d`` each), the tie likelihood
        integrated over the posterior of ``f(a) - f(b)``."""
        return self.likelihood.tie.tie_probability(*self._pair_moments(Xa, Xb))

    def best_item(self, X: Tensor | None = None) -> tuple[int, Tensor]:
        r"""The item of highest posterior mean utility among the rows of ``X`` (``n x d``;
        default :attr:`train_X`), in ``X``'s own coordinates (an input transform is applied as in
        :meth:`posterior`).

        Returns:
            ``(row, item)``: the row of ``X`` (the first on a tie) and that ``d`` item.

        Raises:
            ValueError: a batched model, or ``X`` not ``n x d`` with ``n >= 1``.
        """
        if self.batch_shape:
            raise ValueError(f"best_item needs a single model, this one has batch shape {tuple(self.batch_shape)}.")
        X = self.train_X if X is None else X
        d = self.train_X.shape[-1]
        if not isinstance(X, Tensor) or X.dim() != 2 or X.shape[0] < 1 or X.shape[-1] != d:
            raise ValueError(f"X must be an n x {d} tensor with n >= 1, got {getattr(X, 'shape', type(X).__name__)}.")
        with torch.no_grad():
            mean, _ = self.marginals(X)
        i = int(mean.argmax())
        return i, X[i]

    # ================================================================ BoTorch's PairwiseGP interface
    # ------------------------------------------------------------ names read by BoTorch
    @property
    def datapoints(self) -> Tensor:
        r"""``batch_shape x n x d`` items as given (before any input transform):
        ``PairwiseGP.datapoints``. For a prior-only model an empty ``0 x 0`` tensor of the
        model's dtype and device."""
        return self.train_X

    @property
    def dim(self) -> int | None:
        """Number of input columns ``d`` (``None`` for a prior-only model that has seen no
        items yet): ``PairwiseGP.dim``, read by BoTorch's EUBO input constructors."""
        return self._data.dim or None

    @property
    def utility(self) -> Tensor:
        r"""``batch_shape x n`` posterior-mode utilities of the items (``PairwiseGP.utility``), in
        the model's dtype."""
        f = self.mode.f.reshape(*self.batch_shape, -1)
        if self.mean_module is not None:  # the mode is of the deviation g = f - m
            with torch.no_grad():
                f = f + self._mean(self._transformed_train_X())
        return f.to(self.train_X.dtype)

    @property
    def has_data(self) -> bool:
        """Whether the model holds any item (a prior-only model does not)."""
        return self.train_X.shape[-2] > 0

    # ---------------------------------------------------------------- construction
    @classmethod
    def construct_inputs(cls, training_data: SupervisedDataset, **kwargs: object) -> dict[str, Any]:
        r"""Constructor keyword arguments from BoTorch's ``RankingDataset``.

        A ranking dataset holds items (``X.values``, ``n x d``), the items of each query
        (``X.indices``, ``r x m``) and the rank of each of them (``Y``, ``r x m``, 0 = best,
        ties share a rank). A query becomes comparisons ``[preferred, other]`` between the items
        of adjacent ranks: for ``m = 2`` exactly ``PairwiseGP``'s comparisons, for a strict
        ranking of ``m`` items ``m - 1`` of them (tied items are not compared).

        Returns:
            ``{"train_X": n x d, "comparisons": p x 2}`` (plus ``kwargs``), for ``cls(**inputs)``.

        Raises:
            UnsupportedError: for any other dataset (as ``PairwiseGP`` does): a
                ``SupervisedDataset``'s ``Y`` could be ratings or utilities; give ratings
                explicitly with ``ratings=`` and ``rating_index=``.
        """
        if not isinstance(training_data, RankingDataset):
            raise UnsupportedError(
                f"PreferenceGP.construct_inputs supports only a RankingDataset, got {type(training_data).__name__}; "
                "pass ratings to the constructor with ratings= and rating_index=."
            )
        X = cast(SliceContainer, training_data._X)  # a RankingDataset's items: values and indices
        comparisons = ranking_comparisons(X.indices, training_data.Y)
        return {"train_X": X.values, "comparisons": comparisons, **kwargs}

    def subset_output(self, idcs: list[int]) -> PreferenceGP:
        """A copy of this one-output model for ``idcs == [0]`` (BoTorch's output subsetting).

        Raises:
            ValueError: for any other output index.
        """
        if [int(i) for i in idcs] not in ([0], [-1]):
            raise ValueError(f"PreferenceGP has one output (index 0); got output indices {list(idcs)}.")
        return copy.deepcopy(self)

    def load_state_dict(  # type: ignore[override]
        self, state_dict: dict[str, Any], strict: bool = False, assign: bool = False
    ) -> _IncompatibleKeys:
        r"""Load hyperparameters; **non-strict by default**, as ``PairwiseGP.load_state_dict``.

        A state dict holds hyperparameters (kernel, likelihoods, input transform), never the data.
        With ``strict=False`` a key the model does not have is ignored (listed in the result's
        ``unexpected_keys``) and a parameter the dict lacks keeps its current value (listed in
        ``missing_keys``): an empty dict, as BoTorch's and Ax's cross-validation load, changes
        nothing. A value of the wrong shape raises, as in PyTorch. ``strict=True`` (which
        ``PairwiseGP`` refuses) requires exactly the model's keys. The posterior follows the new
        values at the next call (its cache is keyed on every parameter).

        Returns:
            PyTorch's ``_IncompatibleKeys`` (``missing_keys``, ``unexpected_keys``).
        """
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    # ------------------------------------------------------------------ data
    def set_train_data(
        self,
        train_X: Tensor | None = None,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        strict: bool = False,
        update_model: bool = True,
        ties: Tensor | None = None,
    ) -> None:
        r"""Replace all data; validated and the mode solved first, so the model is unchanged on
        error. ``train_X=None`` keeps no items (a prior-only model keeps its unknown ``d``).

        Args:
            train_X: ``n x d`` items, or ``None``.
            comparisons: ``p x 2`` long, rows ``[preferred, other]``.
            ratings: ``q`` values in ``[0, 1]``, with ``rating_index`` (``q`` long).
            strict: as in GPyTorch: the new items, comparisons and ratings must have the shapes,
                dtype and device of the current ones (used when only values change).
            update_model: accepted for ``PairwiseGP``'s signature; the mode is always re-solved.
            ties: ``t x 2`` "no preference" pairs; ratings are levels for a model with ``rating_levels``.

        Raises:
            TrainDataMismatchError: ``strict`` and a shape, dtype or device differs.
        """
        old_X = self.train_X
        if train_X is None:
            if comparisons is not None or ratings is not None:
                raise ValueError("comparisons and ratings need the items they index: train_X is None.")
            train_X = old_X[..., :0, :]
        if strict:
            _check_strict(self, train_X, comparisons, ratings)
        if train_X.dim() != 2:
            raise UnsupportedError(
                f"set_train_data takes n x d items, got shape {tuple(train_X.shape)}; "
                "a batched model is built by the constructor or condition_on_observations."
            )
        if self._data.dim == 0 and train_X.shape[-1] == 0:
            return
        new = PreferenceData.create(
            train_X,
            comparisons,
            ratings,
            rating_index,
            rating_eps=self.rating_eps,
            ties=ties,
            rating_levels=self.rating_levels,
        )
        self.replace_data(new.to(device=old_X.device, dtype=old_X.dtype), None)

    def condition_on_observations(
        self,
        X: Tensor,
        Y: Tensor | None = None,
        *,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        **kwargs: object,
    ) -> PreferenceGP:
        r"""A new model with the items ``X`` and observations among them added (``self`` is
        unchanged), with BoTorch's meaning of ``Y``.

        * ``Y`` of integer dtype and shape ``m x 2`` holds comparisons, rows
          ``[preferred, other]`` indexing the rows of ``X`` (``PairwiseGP``'s meaning and
          what ``PairwiseSobolQMCNormalSampler`` fantasises); so does ``comparisons=``.
        * Ratings go in by keyword only: ``ratings=`` (``q`` values in ``[0, 1]``) with
          ``rating_index=`` (rows of ``X``; by default one rating per row of ``X``).

        Batched ``X`` (``batch x m x d``), batched observations (``batch x m x 2`` comparisons,
        ``batch x q`` ratings) or a batched model give a batched model, one problem per batch
        element (:func:`~torchpref.models.fantasy.condition_batch`): fantasies.

        Args:
            X: ``m x d`` items (a row equal to an existing item reuses its index).
            Y: comparisons as above, or ``None``.

        Raises:
            ValueError: for a floating-point ``Y`` (ratings and comparisons cannot be told
                apart: use ``ratings=`` or a long ``Y``), an integer ``Y`` not of shape
                ``m x 2``, or ``Y`` together with ``comparisons=``.
        """
        if not isinstance(X, Tensor):  # nested lists of numbers, as everywhere else in the API
            X = torch.as_tensor(X, dtype=self.train_X.dtype, device=self.train_X.device)
        if Y is not None:
            if comparisons is not None:
                raise ValueError("give comparisons either as Y or as comparisons=, not both.")
            comparisons = _comparisons_from_Y(Y)
        elif comparisons is not None:
            comparisons = torch.as_tensor(comparisons)
        if ratings is not None:
            ratings = torch.as_tensor(ratings)
            if ratings.dim() > 1 and ratings.shape[-1] == 1:  # BoTorch's m x 1 outcomes
                ratings = ratings.squeeze(-1)
            if rating_index is None:
                rating_index = torch.arange(ratings.shape[-1], device=X.device).expand(ratings.shape)
        if not self.has_data and self._data.dim == 0:  # prior-only: these become the data
            return _condition_prior_only(self, X, comparisons, ratings, rating_index)
        batched = (
            self.batch_shape
            or X.dim() > 2
            or (comparisons is not None and comparisons.dim() > 2)
            or (ratings is not None and ratings.dim() > 1)
        )
        if batched:
            return condition_batch(self, X, comparisons, ratings, rating_index)
        return copy.deepcopy(self).add_observations(X, comparisons, ratings, rating_index)

    # ------------------------------------------------------------ observation noise
    def _add_observation_noise(self, mvn: MultivariateNormal, observation_noise: bool | Tensor) -> MultivariateNormal:
        r"""The posterior of the utility as a person perceives it when comparing: ``f + eps``
        with independent ``eps ~ N(0, sigma_R^2)`` per item (eq. 3), or with the given
        ``batch x q x 1`` (or ``q``) variances when ``observation_noise`` is a tensor."""
        cov = mvn.covariance_matrix
        if isinstance(observation_noise, Tensor):
            noise = observation_noise.to(cov)
            if noise.dim() > 1 and noise.shape[-1] == 1:
                noise = noise.squeeze(-1)
            try:
                noise = noise.expand(cov.shape[:-1])
            except RuntimeError:
                raise ValueError(
                    f"observation_noise must be variances of shape {(*cov.shape[:-1], 1)} (or "
                    f"broadcast to it), got shape {tuple(observation_noise.shape)}."
                ) from None
            ok = (noise.detach() >= 0) & noise.detach().isfinite()
            if not bool(ok.all()):
                raise ValueError(
                    f"observation_noise must be finite variances >= 0, got {noise.detach()[~ok][:3].tolist()}."
                )
        else:
            noise = (self.likelihood.comparison.comparison_noise**2).to(cov).expand(cov.shape[:-1])
        return MultivariateNormal(mvn.mean, DenseLinearOperator(cov + torch.diag_embed(noise)))

    # ------------------------------------------------------- predictives (eq. 11)


def _priors(root: torch.nn.Module):
    """``(module, prior, closure)`` for each prior that GPyTorch's ``root.named_priors()`` lists, in
    its order (depth first, a module's children each once per parent), without building names."""
    stack = [root]
    while stack:
        module = stack.pop()
        if isinstance(module, GModule):
            for prior, closure, _ in module._priors.values():
                if prior is not None:
                    yield module, prior, closure
        children = list(dict.fromkeys(c for c in module._modules.values() if c is not None))
        stack.extend(reversed(children))


class LaplaceMarginalLogLikelihood(MarginalLogLikelihood):
    r"""Laplace evidence of a :class:`PreferenceGP` plus the log densities of its hyperparameter
    priors; works with ``botorch.fit.fit_gpytorch_mll``.

    Built as ``LaplaceMarginalLogLikelihood(model)``, or as GPyTorch's MLLs are,
    ``LaplaceMarginalLogLikelihood(likelihood, model)`` (also by keyword, as Ax and BoFire build
    ``PairwiseLaplaceMarginalLogLikelihood``): the likelihood must then be ``model.likelihood``
    (or ``None``), since the evidence is that of the model's own likelihoods.

    Raises:
        ValueError: no model, a model that is not a :class:`PreferenceGP`, or a likelihood other
            than the model's.
    """

    def __init__(self, likelihood: object = None, model: PreferenceGP | None = None):
        if model is None and isinstance(likelihood, PreferenceGP):  # the one-argument form
            likelihood, model = None, likelihood
        if not isinstance(model, PreferenceGP):
            raise ValueError(
                f"LaplaceMarginalLogLikelihood needs a PreferenceGP, as LaplaceMarginalLogLikelihood(model) or "
                f"(likelihood, model); got model={type(model).__name__}."
            )
        if likelihood is not None and likelihood is not model.likelihood:
            raise ValueError(
                f"the likelihood must be the model's own (model.likelihood) or None, got a "
                f"{type(likelihood).__name__}: the evidence is of the likelihoods the model was built with "
                "(pass likelihood= or comparison_noise= to PreferenceGP)."
            )
        super().__init__(model.likelihood, model)
        weak_load_hook(self)

    def forward(self, *args: object, **kwargs: object) -> Tensor:
        """The evidence of the model's own data. ``mll(output, comparisons)``, as BoTorch calls
        ``PairwiseLaplaceMarginalLogLikelihood``, is accepted; comparisons other than the
        model's raise :class:`~torchpref.models.pairwise_interface.TrainDataMismatchError` (``PairwiseGP``:
        ``RuntimeError``) rather than being ignored."""
        given = args[1] if len(args) > 1 else None
        if isinstance(given, Tensor) and not (
            given.shape == self.model.comparisons.shape
            and torch.equal(given.to(self.model.comparisons), self.model.comparisons)
        ):
            raise TrainDataMismatchError(
                f"the evidence is of the model's own comparisons; got other comparisons "
                f"(shape {tuple(given.shape)}): use set_train_data to change them."
            )
        res = self.model.log_marginal_likelihood()
        # the model's priors, its likelihood's among them, each once (GPyTorch's exact MLL walks
        # ``model.named_priors()`` alike; walking ``self`` would count the likelihood's twice)
        for module, prior, closure in _priors(self.model):
            res = res + prior.log_prob(closure(module)).sum()
        return res

    def compute_custom_loss(self, **kwargs: object) -> Tensor:
        """The loss BoTorch's fitting routines minimise: ``-self()``."""
        return -self.forward()
