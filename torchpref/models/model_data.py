r"""The data side of :class:`~torchpref.models.preference_gp.PreferenceGP`: its observations, the input
transform applied to its items, and in-place updates that leave nothing half-done."""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import torch
from botorch.exceptions.warnings import InputDataWarning
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.inference.laplace import Observations
from torchpref.inference.padding import PaddedData

if TYPE_CHECKING:
    from torchpref.models.preference_gp import PreferenceGP


def create_data(
    train_X, comparisons, ratings, rating_index, rating_eps: float, ties=None, rating_levels: int | None = None
) -> PreferenceData | PaddedData:
    """Validated data: one problem for ``n x d`` items, one per batch element for ``b x n x d``."""
    if isinstance(train_X, Tensor) and train_X.dim() == 3:
        return PaddedData.create(
            train_X, comparisons, ratings, rating_index, rating_eps=rating_eps, ties=ties, rating_levels=rating_levels
        )
    return PreferenceData.create(
        train_X, comparisons, ratings, rating_index, rating_eps=rating_eps, ties=ties, rating_levels=rating_levels
    )


class ModelData:
    """The observations of a :class:`~torchpref.models.preference_gp.PreferenceGP` and their updates.

    Mixed into the model; relies on its ``_data``, ``_cache``, ``_warm_f``, ``_state``,
    ``posterior``, ``likelihood``, ``ties_offered``, ``rating_eps`` and ``_rating_levels``.
    """

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
                    extra = self.posterior(new.train_X[self._data.n :].unsqueeze(-2)).mean.reshape(-1)
                warm = torch.cat([f_old, extra])
            else:
                warm = f_old
        self._set_data(new, warm)
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
