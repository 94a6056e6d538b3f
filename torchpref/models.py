r"""``PreferenceGP``: a BoTorch model of a latent utility learned from ratings and comparisons."""

from __future__ import annotations

import math
import numbers
import warnings
from typing import Any

import torch
from botorch.acquisition.objective import PosteriorTransform
from botorch.exceptions.warnings import InputDataWarning
from botorch.models.model import Model
from botorch.models.transforms.input import InputTransform
from botorch.sampling.base import MCSampler
from botorch.posteriors.gpytorch import GPyTorchPosterior
from gpytorch.distributions import MultivariateNormal
from gpytorch.kernels import Kernel, RBFKernel, ScaleKernel
from gpytorch.mlls import MarginalLogLikelihood
from gpytorch.models import GP
from gpytorch.module import Module
from gpytorch.constraints import GreaterThan
from gpytorch.priors import GammaPrior, LogNormalPrior
from linear_operator.operators import DenseLinearOperator, LinearOperator
from torch import Tensor

from torchpref.botorch_api import PairwiseGPInterface, prior_only_data
from torchpref.data import DEFAULT_RATING_EPS, PreferenceData
from torchpref.fantasy import fantasize
from torchpref.laplace import ModeResult, Observations, laplace_evidence
from torchpref.likelihoods import BetaRatingLikelihood, PairwiseProbitLikelihood
from torchpref.numerics import pin_coincident
from torchpref.ordinal import OrdinalRatingLikelihood, StrictPreferenceLikelihood, TieLikelihood, default_cut_points
from torchpref.padding import PaddedData
from torchpref.posterior_state import PosteriorState, carries_gradients, fingerprint
from torchpref.precision import call_in_dtype, check_laplace_dtype, solve_dtype


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

    def __init__(self, comparison: PairwiseProbitLikelihood, rating: BetaRatingLikelihood | OrdinalRatingLikelihood,
                 tie: TieLikelihood | None = None):
        super().__init__()
        self.comparison = comparison
        self.rating = rating
        self.tie = tie if tie is not None else TieLikelihood(comparison=comparison)
        self.strict = StrictPreferenceLikelihood(self.tie)


def _create_data(train_X, comparisons, ratings, rating_index, rating_eps: float, ties=None,
                 rating_levels: int | None = None) -> PreferenceData | PaddedData:
    """Validated data: one problem for ``n x d`` items, one per batch element for ``b x n x d``."""
    if isinstance(train_X, Tensor) and train_X.dim() == 3:
        return PaddedData.create(train_X, comparisons, ratings, rating_index, rating_eps=rating_eps, ties=ties,
                                 rating_levels=rating_levels)
    return PreferenceData.create(train_X, comparisons, ratings, rating_index, rating_eps=rating_eps, ties=ties,
                                 rating_levels=rating_levels)


class PreferenceGP(PairwiseGPInterface, Model, GP):
    r"""A GP over the items' objective space, learned from comparisons and ratings together.

    The latent utility ``f ~ GP(0, k)`` (eq. 1) is observed through comparisons (eq. 3) and
    ratings on ``[0, 1]`` (eqs. 4-7); the posterior is the Laplace approximation (eqs. 2, 8-10).
    The mode is re-solved, warm-started, whenever the hyperparameters or the data change.

    BoTorch's ``PairwiseGP`` interface is there too (``datapoints``, ``dim``, ``utility``,
    ``construct_inputs``, prior-only ``PreferenceGP(None, None)``, comparisons as
    ``condition_on_observations(X, Y)``): see :class:`~torchpref.botorch_api.PairwiseGPInterface`
    and docs/botorch.md.

    Args:
        train_X: ``n x d`` items (float64 recommended; dtype and device are followed), or
            ``None`` for a prior-only model (then no observations; ``d`` is set by the first
            data).
        comparisons: ``p x 2`` long, rows ``[preferred, other]`` (BoTorch's convention).
        ratings: ``q`` values in ``[0, 1]``; exact 0 and 1 are moved in to ``rating_eps``.
        rating_index: ``q`` long indices into ``train_X``: the item each rating rates.
        covar_module: the kernel; default :func:`default_covar_module`.
        comparison_noise: ``sigma_R`` of eq. 3 (default 1.0: BoTorch's ``PairwiseGP`` probit
            ``Phi((f_i - f_j) / sqrt 2)``, which keeps EUBO-style loops from re-asking compared
            pairs; the paper's Fig. 4 used 0.1, see :data:`PAPER_FIG4_SETTINGS`).
        rating_scale: ``sigma_B`` of eq. 7 (default 1.0, as Fig. 4).
        rating_precision: ``nu`` of eqs. 5-6 (default 80, as Fig. 4).
        learn_likelihood: make the three likelihood parameters trainable (default: fixed, as in
            the paper; with comparisons only, ``comparison_noise`` and the outputscale are not
            separately identifiable).
        input_transform: a BoTorch input transform (e.g. ``Normalize``), applied to ``train_X``
            and to every input of :meth:`posterior`.
        rating_eps: where exact 0 / 1 ratings are moved to.
        max_newton_iter: iteration budget of the mode finder (at least 1).
        ties: ``t x 2`` long, rows ``[i, j]``: "no preference" between items ``i`` and ``j``
            (:class:`~torchpref.ordinal.TieLikelihood`).
        rating_levels: ``K``: the ratings are levels ``1..K``, scored by the ordinal likelihood
            (:class:`~torchpref.ordinal.OrdinalRatingLikelihood`) instead of the Beta one.
        tie_threshold: ``tau`` of the tie likelihood (default 0.1).
        cut_points: the ordinal likelihood's ``K - 1`` cut points (default
            :func:`~torchpref.ordinal.default_cut_points`, the Beta link's bin edges).
        ties_offered: "no preference" was an allowed answer to the comparisons, which are then
            scored ``Phi((f_i - f_j - tau) / (sqrt 2 sigma_R))`` (the tie's ordered probit) instead
            of eq. 3 (a forced choice); needed to learn ``tau``. Default ``False``.
        level_noise: the ordinal likelihood's ``sigma``; default ``sqrt(pi) sigma_B / sqrt(nu + 1)``,
            the Beta likelihood's rating noise at mid-scale in latent units (0.197 at the defaults).
        laplace_dtype: the dtype the kernel matrices and the Laplace problem are computed in
            (:attr:`laplace_dtype`); default float64 whatever the model's dtype, so a float32 model
            solves in mixed precision and returns float32 posteriors. ``torch.float32`` solves a
            float32 model natively (docs/precision.md).

    Warns:
        InputDataWarning: (BoTorch's) for inputs in a dtype other than float64, and for training
            items (after ``input_transform``) outside the unit cube, whose scale the default
            kernel's lengthscale prior assumes (docs/decisions.md).

    Example:
        >>> model = PreferenceGP(X, comparisons=C, ratings=u, rating_index=idx)
        >>> fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
        >>> model.posterior(X_test).mean
    """

    _num_outputs = 1

    def __init__(
        self,
        train_X: Tensor | None,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        covar_module: Kernel | None = None,
        *,
        comparison_noise: float = 1.0,
        rating_scale: float = 1.0,
        rating_precision: float = 80.0,
        learn_likelihood: bool = False,
        input_transform: InputTransform | None = None,
        rating_eps: float = DEFAULT_RATING_EPS,
        max_newton_iter: int = 100,
        ties: Tensor | None = None,
        rating_levels: int | None = None,
        tie_threshold: float = 0.1,
        cut_points: Tensor | None = None,
        level_noise: float | None = None,
        ties_offered: bool = False,
        laplace_dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        if train_X is None:  # BoTorch's prior-only model, PairwiseGP(None, None)
            if ratings is not None or (comparisons is not None and len(comparisons)):
                raise ValueError("a prior-only model (train_X=None) takes no comparisons or ratings.")
            data = prior_only_data()
        else:
            data = _create_data(train_X, comparisons, ratings, rating_index, rating_eps, ties, rating_levels)
        X = data.train_X if isinstance(data, PreferenceData) else data.X
        if X.dtype != torch.float64:
            warnings.warn(
                f"train_X is {X.dtype}; float64 is recommended (as in BoTorch). The Laplace problem is "
                "solved in float64 unless laplace_dtype says otherwise (docs/precision.md).",
                InputDataWarning,
                stacklevel=2,
            )
        self.covar_module = covar_module if covar_module is not None else default_covar_module(X.shape[-1])
        comparison = PairwiseProbitLikelihood(comparison_noise, learn=learn_likelihood)
        if rating_levels is None:
            rating = BetaRatingLikelihood(rating_scale, rating_precision, learn=learn_likelihood)
        else:
            if cut_points is None:
                cut_points = default_cut_points(int(rating_levels), rating_scale)
            if level_noise is None:  # sd of Beta(nu/2, nu/2) over d mu / d f at f = 0
                level_noise = math.sqrt(math.pi) * rating_scale / math.sqrt(rating_precision + 1)
            rating = OrdinalRatingLikelihood(int(rating_levels), cut_points, level_noise, learn=learn_likelihood)
        self._rating_levels = None if rating_levels is None else int(rating_levels)
        self.likelihood = PreferenceLikelihood(
            comparison, rating, TieLikelihood(tie_threshold, comparison, learn=learn_likelihood))
        self.ties_offered = bool(ties_offered)
        if input_transform is not None:
            self.input_transform = input_transform
        self.rating_eps = rating_eps
        self.max_newton_iter = max_newton_iter
        self._laplace_dtype = check_laplace_dtype(laplace_dtype)
        self._scaling_warned = False
        self.to(device=X.device, dtype=X.dtype)
        self._data: PreferenceData | PaddedData = data
        self._cache: PosteriorState | None = None
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

    # ------------------------------------------------------------------ data
    @property
    def data(self) -> PreferenceData | PaddedData:
        """The observations (immutable): a :class:`~torchpref.data.PreferenceData`, or for a
        batched model (``batch_shape`` not empty) a :class:`~torchpref.padding.PaddedData`."""
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
        return self._padded().ties

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
        return 1

    @property
    def batch_shape(self) -> torch.Size:
        """``torch.Size([])`` for one problem; ``[b]`` for batched training data (BoTorch's meaning)."""
        return self._padded().batch_shape

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
        if tf is None:
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

    def _set_data(self, data: PreferenceData | PaddedData, warm_f: Tensor | None) -> None:
        """Swap in new data; re-solve the mode first and keep the old state if that fails or is
        interrupted (``BaseException``: a ``KeyboardInterrupt`` leaves nothing half-updated)."""
        old = (self._data, self._cache, self._warm_f)
        self._data, self._cache, self._warm_f = data, None, warm_f
        try:
            self._fit_input_transform()
            self._state()
        except BaseException:
            self._data, self._cache, self._warm_f = old
            self._fit_input_transform()
            raise
        self._check_scaling()

    def add_observations(
        self,
        X: Tensor | None = None,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        ties: Tensor | None = None,
    ) -> "PreferenceGP":
        r"""Add items and observations in place, warm-starting the mode (no refit from scratch).

        Indices in ``comparisons``, ``ties`` and ``rating_index`` refer to the rows of ``X`` when
        ``X`` is given (rows equal to an existing item reuse its index), otherwise to ``train_X``.
        Ratings are levels ``1..K`` for a model with ``rating_levels``. The input is validated and
        the new mode solved before anything changes: on error the model is left exactly as it was.

        Returns:
            ``self``.
        """
        if not isinstance(self._data, PreferenceData):
            raise NotImplementedError("add_observations needs a model of one problem; a batched model is "
                                      "conditioned with condition_on_observations.")
        new = self._data.add(X, comparisons, ratings, rating_index, rating_eps=self.rating_eps, ties=ties)
        warm = None
        if self._cache is not None or self._data.num_observations:
            f_old = self._state().mode.f[0]
            if new.n > self._data.n:
                with torch.no_grad():
                    extra = self.posterior(new.train_X[self._data.n:].unsqueeze(-2)).mean.reshape(-1)
                warm = torch.cat([f_old, extra])
            else:
                warm = f_old
        self._set_data(new, warm)
        return self

    def fantasize(self, X: Tensor, sampler: MCSampler, observation_noise: Tensor | None = None,
                  kind: str | None = None, **kwargs: Any) -> "PreferenceGP":
        r"""A batched fantasy model (see :func:`~torchpref.fantasy.fantasize`): comparisons among
        the ``q`` points of ``X`` (``batch x q x d``) with a ``PairwiseMCSampler``, ratings of them
        with any other sampler (or as ``kind`` says). ``observation_noise`` is not used: the
        answers' noise is the likelihoods'."""
        return fantasize(self, X, sampler, kind)

    # ------------------------------------------------------------- inference
    def _kernel(self, X1: Tensor, X2: Tensor | None = None, diag: bool = False) -> Tensor:
        """Dense ``k(X1, X2)`` (or its diagonal): the kernel's ``forward`` directly (the values
        ``__call__`` would give, without building a lazy kernel tensor) unless a kernel selects
        ``active_dims``; in :attr:`laplace_dtype`; below float64, exact at coincident points
        (:func:`~torchpref.numerics.pin_coincident`)."""
        k = self.covar_module
        X2 = X1 if X2 is None else X2
        if any(getattr(m, "active_dims", None) is not None for m in k.modules()):
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

    def _state(self, prior: tuple[PaddedData, Tensor] | None = None) -> PosteriorState:
        """The mode and prediction cache for the current hyperparameters and data (cached);
        ``prior``: :meth:`_prior`'s result if already computed (then the kernel is not evaluated again)."""
        fp = fingerprint(self)
        if self._cache is None or not self._cache.is_current(self._data, fp):
            self._cache = PosteriorState.build(self, fp, self._cache, prior)
        return self._cache

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
        dependence on the hyperparameters. Hyperparameter priors are not included (the MLL adds them)."""
        padded, K = self._prior()
        state = self._state((padded, K))
        N = padded.num_items
        value = laplace_evidence(K.reshape(-1, N, N), state.obs, state.mode, L=state.pred.L, jitter=state.jitter)
        return value.reshape(self.batch_shape).to(padded.X.dtype)

    def _predict(self, X: Tensor, diag: bool = False) -> tuple[Tensor, Tensor]:
        """Posterior moments at transformed ``X`` (:meth:`PosteriorState.moments`), in ``X``'s dtype;
        with autograd on and training items or ratings that carry gradients (a fantasy model inside
        a look-ahead acquisition), differentiable in them through the mode (:meth:`PosteriorState.traced`)."""
        state = self._state()
        if torch.is_grad_enabled() and carries_gradients(self._padded()):
            state = state.traced(*self._prior(), self._observations())
        mean, cov = state.moments(self._kernel, X, diag)
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
        **kwargs: Any,
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
        """``X`` checked (``... x d``, finite; a lower floating precision is converted to the
        model's, as BoTorch's models do), the model in eval mode, the input transform applied."""
        if self._data.dim and X.shape[-1] != self._data.dim:  # dim 0: a prior-only model takes any d
            raise ValueError(f"X must have {self._data.dim} columns (last dim), got shape {tuple(X.shape)}.")
        dtype = self.train_X.dtype
        if X.dtype != dtype and X.is_floating_point():
            if torch.finfo(X.dtype).eps < torch.finfo(dtype).eps:  # would lose precision: say so
                raise ValueError(f"X is {X.dtype} but the model is {dtype}: convert one of them "
                                 f"(X.to({dtype}) or model.to(...)).")
            X = X.to(dtype)  # BoTorch's optimisers and objectives hand over float32 candidates
        finite = torch.isfinite(X.detach())
        if not bool(finite.all()):
            bad = X.detach()[~finite][:3].tolist()
            raise ValueError(f"X must be finite, got {int((~finite).sum())} non-finite value(s) such as {bad}.")
        if self.training:
            self.eval()
        return self.transform_inputs(X)

    def __call__(self, X: Tensor) -> MultivariateNormal:  # skip gpytorch's GP.__call__ machinery
        return self.forward(X)

    # ------------------------------------------------------- predictives (eq. 11)
    def marginals(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""Posterior mean and variance of the latent utility at each row of ``X`` (``... x d``),
        each of ``X``'s shape without its last dimension: what ``posterior(X.unsqueeze(-2))``
        gives, without building a batch of ``1 x 1`` covariances and distribution objects. For a
        batched model, ``X`` is ``... x batch_shape x m x d``."""
        Xt = self._prediction_inputs(X)
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

    def _apply(self, fn, *args, **kwargs):
        super()._apply(fn, *args, **kwargs)
        data = getattr(self, "_data", None)
        if isinstance(data, PreferenceData):
            self._data = PreferenceData(*(fn(t) for t in (data.train_X, data.comparisons, data.ratings, data.rating_index,
                                                          data.ties)), data.rating_levels)
        elif data is not None:
            self._data = data.map(fn)
        if data is not None:
            self._cache, self._warm_f = None, None
        return self


class LaplaceMarginalLogLikelihood(MarginalLogLikelihood):
    r"""Laplace evidence of a :class:`PreferenceGP` plus the log densities of its hyperparameter
    priors; works with ``botorch.fit.fit_gpytorch_mll``."""

    def __init__(self, model: PreferenceGP):
        super().__init__(model.likelihood, model)

    def forward(self, *args: Any, **kwargs: Any) -> Tensor:
        res = self.model.log_marginal_likelihood()
        for _, module, prior, closure, _ in self.named_priors():
            res = res + prior.log_prob(closure(module)).sum()
        return res

    def compute_custom_loss(self, **kwargs: Any) -> Tensor:
        """The loss BoTorch's fitting routines minimise: ``-self()``."""
        return -self.forward()
