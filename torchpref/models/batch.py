r"""Many independent preference models at once: ``T`` trials solved as one batched model.

A simulation study (the wave experiment: 100 trials x 20 queries x 5 strategies) asks the
same kind of question of many independent models, each small (tens of items). Solved one by
one, such models cost mostly Python overhead; :class:`BatchedPreferenceGP` holds ``T`` of
them, with shared fixed hyperparameters (one kernel, one pair of likelihoods), as one
:class:`~torchpref.PreferenceGP` of batch shape ``(T,)`` over their data padded to common sizes
(:class:`~torchpref.inference.padding.PaddedData`): the batch-first Laplace solver
(:func:`~torchpref.inference.laplace.find_mode`) solves all the modes (eq. 2) together. Each trial keeps
its own validated :class:`~torchpref.data.preference_data.PreferenceData`, so adding answers works (and fails)
exactly as on a :class:`~torchpref.PreferenceGP`.

The per-trial results equal those of ``T`` separate :class:`~torchpref.PreferenceGP` models
(same Newton iterates, same predictions); ``tests/models/test_batch.py`` checks this.
Hyperparameters are fixed (no fitting): use a :class:`~torchpref.PreferenceGP` to fit them.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import cast

import torch
from torch import Tensor

from torchpref.data.preference_data import PreferenceData
from torchpref.inference.padding import PaddedData
from torchpref.models.preference_gp import PreferenceGP


class BatchedPreferenceGP:
    r"""``T`` independent mixed ratings + comparisons models with shared fixed hyperparameters.

    Build it from ``T`` :class:`~torchpref.PreferenceGP` models (:meth:`from_models`) that share
    their kernel's and likelihoods' values; each trial starts with its model's data, and the
    hyperparameters are copied (changing the models afterwards changes no trial). Answers go
    in per trial (:meth:`add_observations`); modes are re-solved, all at once and warm-started,
    when a prediction is next asked for.

    Shapes: ``T`` trials, ``X`` of shape ``T x N x d`` (``N`` points per trial).
    """

    def __init__(self, template: PreferenceGP, data: Sequence[PreferenceData]):
        if getattr(template, "input_transform", None) is not None:
            raise ValueError("BatchedPreferenceGP does not support input transforms; transform the items first.")
        if len(data) < 1:
            raise ValueError("need at least one trial.")
        self.model = copy.deepcopy(template)  # the hyperparameters as they are now
        self.model.replace_data(PaddedData.stack(list(data)))
        self.template = self.model
        self.covar_module, self.likelihood = self.model.covar_module, self.model.likelihood
        self.rating_eps = template.rating_eps
        self._data = list(data)
        self._changed = False  # data added since the model's data was last set

    @classmethod
    def from_models(cls, models: Sequence[PreferenceGP]) -> BatchedPreferenceGP:
        """One trial per model; all must hold the same hyperparameter values (a ``ValueError``
        names the first that does not). The first model's kernel and likelihoods are used."""
        if len(models) < 1:
            raise ValueError("need at least one model.")
        ref = models[0].state_dict()
        for b, m in enumerate(models[1:], start=1):
            sd = m.state_dict()
            if sd.keys() != ref.keys() or not all(torch.equal(sd[k], ref[k]) for k in ref):
                raise ValueError(f"model {b} has hyperparameters different from model 0's.")
        return cls(models[0], [cast(PreferenceData, m.data) for m in models])

    # ------------------------------------------------------------------ data
    @property
    def num_trials(self) -> int:
        """The number ``T`` of independent trials."""
        return len(self._data)

    def data(self, trial: int) -> PreferenceData:
        """The observations of one trial."""
        return self._data[trial]

    def add_observations(
        self,
        trial: int,
        X: Tensor | None = None,
        comparisons: Tensor | None = None,
        ratings: Tensor | None = None,
        rating_index: Tensor | None = None,
        ties: Tensor | None = None,
    ) -> None:
        r"""Add items and observations to one trial, as :meth:`PreferenceGP.add_observations`
        (``ties``: "no preference" pairs; validated first: on error nothing changes)."""
        if not 0 <= trial < self.num_trials:
            raise ValueError(f"trial must be in 0..{self.num_trials - 1}, got {trial}.")
        self._data[trial] = self._data[trial].add(
            X, comparisons, ratings, rating_index, rating_eps=self.rating_eps, ties=ties
        )
        self._changed = True

    def trial_model(self, trial: int) -> PreferenceGP:
        """A stand-alone :class:`~torchpref.PreferenceGP` of one trial: the trials' kernel,
        likelihoods (rating, comparison and tie), prior mean and solver settings, copied (fitting
        it changes no trial), with that trial's data."""
        if not 0 <= trial < self.num_trials:
            raise ValueError(f"trial must be in 0..{self.num_trials - 1}, got {trial}.")
        model = copy.copy(self.model)  # not the batch's solved state: only its modules, copied below
        model._data, model._cache = self._data[trial], None
        model = copy.deepcopy(model)
        return model.replace_data(self._data[trial])

    # ------------------------------------------------------------------ inference
    def _current(self) -> PreferenceGP:
        """The batched model of the current data, warm-started from the last solved modes: the old
        mode for the old items (only ever appended), the old posterior mean for the new ones."""
        if self._changed:
            new = PaddedData.stack(self._data)
            with torch.no_grad():
                f0, _ = self.model._predict(new.X, diag=True)  # under the old data
                f_old, old = self.model._state().mode.f, self.model.data
                n_old = f_old.shape[-1]
                old = cast(PaddedData, old)
                keep = old.item_mask if old.item_mask is not None else torch.ones_like(f_old, dtype=torch.bool)
                f0[:, :n_old] = torch.where(keep, f_old, f0[:, :n_old])
                if new.item_mask is not None:
                    f0 = torch.where(new.item_mask, f0, 0.0)
            self.model.replace_data(new, f0, lazy=True)
            self._changed = False
        return self.model

    def _check_X(self, X: Tensor) -> Tensor:
        d = self._data[0].dim
        if X.dim() != 3 or X.shape[0] != self.num_trials or X.shape[-1] != d:
            raise ValueError(f"X must be T x N x d = {self.num_trials} x N x {d}, got shape {tuple(X.shape)}.")
        return X.to(self._data[0].train_X)

    def marginals(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""Posterior mean and variance of each trial's latent utility at its points (``X``:
        ``T x N x d``; returns two ``T x N``), eqs. 9-10."""
        X = self._check_X(X)
        with torch.no_grad():
            return self._current()._predict(X, diag=True)

    def joint(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""Posterior mean ``T x N`` and covariance ``T x N x N`` of each trial's utility at its points."""
        X = self._check_X(X)
        with torch.no_grad():
            return self._current()._predict(X)

    def expected_rating(self, X: Tensor) -> Tensor:
        r"""Expected rating ``Phi(m / sqrt(2 sigma_B^2 + v))`` per trial and point (``T x N``)."""
        mean, var = self.marginals(X)
        return self.likelihood.rating.expected_rating(mean, var)

    def mode(self) -> list[Tensor]:
        """Each trial's posterior mode over its own items."""
        f = self._current()._state().mode.f
        return [f[b, : self._data[b].n] for b in range(self.num_trials)]

    @property
    def converged(self) -> Tensor:
        """``T`` bool: whether each trial's Newton iteration converged."""
        return self._current()._state().mode.converged
