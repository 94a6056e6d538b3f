r"""``PreferenceGP`` inside Ax: ``import torchpref.integrations.ax`` registers what Ax needs.

Ax (``pip install 'torchpref[ax]'``, tested with ax-platform 1.3.1) builds a model per metric
from a ``ModelConfig``; for its preference metric (a ``RankingDataset``) it knows only BoTorch's
``PairwiseGP``. Importing this module, once, before Ax fits anything:

* registers :class:`~torchpref.models.preference_gp.PreferenceGP` with Ax's model-fitting
  dispatcher (``fit_botorch_model``): the model is fitted with
  :class:`~torchpref.models.preference_gp.LaplaceMarginalLogLikelihood` (built as Ax builds MLLs,
  ``mll_class(likelihood=..., model=...)``); Ax's defaults for a model it does not know
  (``ExactMarginalLogLikelihood``) and ``PairwiseLaplaceMarginalLogLikelihood`` are read as it;
* fills a ``PreferenceGP`` ``ModelConfig`` as Ax fills a ``PairwiseGP`` one: the Laplace MLL by
  default, no outcome transform (the utility has no observed scale);
* makes ``SurrogateSpec(model_configs=[ModelConfig(PreferenceGP, ...)])`` take effect for the
  preference metric: Ax itself sends a ``RankingDataset`` that ``metric_to_model_configs`` does not
  name to a default ``ModelConfig()``, i.e. to ``PairwiseGP``, silently; here a ``PreferenceGP``
  config among ``model_configs`` is used for it instead;
* registers an input constructor (``submodel_input_constructor``) through which a rating metric's
  data reaches the model: ``ModelConfig(PreferenceGP, model_options={"rating_metrics": ["rating"]})``
  adds the rated arms to the items and their values, in ``[0, 1]``, as ``ratings=`` /
  ``rating_index=`` beside the preference metric's comparisons (docs/ax.md).

Nothing here is imported by ``import torchpref``; importing it twice changes nothing.
"""

from __future__ import annotations

import dataclasses
import threading
from typing import Any

try:
    from ax.generators.torch.botorch_modular import surrogate as _ax_surrogate
    from ax.generators.torch.botorch_modular import utils as _ax_utils
except ImportError as err:  # pragma: no cover - exercised where Ax is absent
    raise ImportError("torchpref.integrations.ax needs Ax (ax-platform): pip install 'torchpref[ax]'") from err

import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models.pairwise_gp import PairwiseLaplaceMarginalLogLikelihood
from botorch.utils.datasets import RankingDataset, SupervisedDataset
from gpytorch.mlls import ExactMarginalLogLikelihood

from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP

__all__ = ["RATING_METRICS_OPTION", "is_preference_model_class", "laplace_mll_class", "rating_inputs"]


#: The ``ModelConfig.model_options`` key naming the rating metrics whose data a
#: ``PreferenceGP`` takes as ratings (a list of metric names).
RATING_METRICS_OPTION = "rating_metrics"

# MLL classes Ax puts in a ModelConfig by default or for PairwiseGP: all mean "the model's evidence"
_READ_AS_LAPLACE = (ExactMarginalLogLikelihood, PairwiseLaplaceMarginalLogLikelihood)


def is_preference_model_class(cls: Any) -> bool:
    """Whether ``cls`` is :class:`PreferenceGP` or a subclass of it."""
    return isinstance(cls, type) and issubclass(cls, PreferenceGP)


def laplace_mll_class(mll_class: type | None) -> type:
    """The MLL class a ``PreferenceGP`` is fitted with in Ax: ``LaplaceMarginalLogLikelihood`` (or
    a subclass given) for ``None``, ``ExactMarginalLogLikelihood`` (Ax's default for a model class
    it does not know) and ``PairwiseLaplaceMarginalLogLikelihood`` (``PairwiseGP``'s).

    Raises:
        ValueError: any other MLL class, named.
    """
    if mll_class is None or mll_class in _READ_AS_LAPLACE:  # exactly these (LOO-PL subclasses the exact MLL)
        return LaplaceMarginalLogLikelihood
    if isinstance(mll_class, type) and issubclass(mll_class, LaplaceMarginalLogLikelihood):
        return mll_class
    raise ValueError(
        f"mll_class={getattr(mll_class, '__name__', mll_class)!r} cannot fit a PreferenceGP: use "
        "torchpref.LaplaceMarginalLogLikelihood (the Laplace evidence of its comparisons and ratings)."
    )


def _fit_preference_gp(model: PreferenceGP, mll_class: type | None, mll_options: dict | None = None) -> None:
    """Ax's ``fit_botorch_model`` for a ``PreferenceGP``: BoTorch's ``fit_gpytorch_mll`` of its
    Laplace evidence (a failed fit raises BoTorch's ``ModelFittingError``, as for GPyTorch models)."""
    mll = laplace_mll_class(mll_class)(likelihood=model.likelihood, model=model, **(mll_options or {}))
    fit_gpytorch_mll(mll)


_ORIGINAL_DEFAULTS = _ax_utils.copy_model_config_with_default_values


def _copy_model_config_with_default_values(model_config, dataset, search_space_digest):
    """Ax's defaults, then a ``PreferenceGP``'s: the Laplace MLL, no outcome transform."""
    config = _ORIGINAL_DEFAULTS(model_config=model_config, dataset=dataset, search_space_digest=search_space_digest)
    if is_preference_model_class(config.botorch_model_class):
        config.mll_class = laplace_mll_class(config.mll_class)
        config.outcome_transform_classes = None
        options = dict(config.model_options or {})
        if RATING_METRICS_OPTION in options and not isinstance(dataset, RankingDataset):
            raise ValueError(
                f"model_options[{RATING_METRICS_OPTION!r}] is for the preference metric's PreferenceGP; "
                f"metric {dataset.outcome_names[0]!r} is not a preference metric (its data are not rankings)."
            )
    return config


_ModelConfig = _ax_surrogate.ModelConfig
_routed = threading.local()  # the PreferenceGP configs of the Surrogate.fit in progress, if any


def _model_config(*args, **kwargs):
    """Ax's ``ModelConfig`` as ``Surrogate.fit`` calls it; inside a fit that routes rankings, the bare
    ``ModelConfig()`` Ax falls back to for a preference metric is the spec's ``PreferenceGP`` config."""
    configs = getattr(_routed, "configs", None)
    if configs and not args and not kwargs:
        return dataclasses.replace(configs[0])
    return _ModelConfig(*args, **kwargs)


def _ranking_configs(surrogate, datasets) -> list:
    """The spec's ``PreferenceGP`` configs where ``model_configs`` name one and some preference metric
    is not named by ``metric_to_model_configs`` (Ax would fall back to ``PairwiseGP`` for it)."""
    spec = surrogate.surrogate_spec
    explicit = spec.metric_to_model_configs or {}
    if not any(isinstance(d, RankingDataset) and d.outcome_names[0] not in explicit for d in datasets):
        return []
    return [c for c in spec.model_configs or [] if is_preference_model_class(c.botorch_model_class)]


_ORIGINAL_FIT = _ax_surrogate.Surrogate.fit


def _fit(self, datasets, search_space_digest, *args, **kwargs):
    configs = _ranking_configs(self, datasets)
    if not configs:
        return _ORIGINAL_FIT(self, datasets, search_space_digest, *args, **kwargs)
    _routed.configs = configs
    try:
        return _ORIGINAL_FIT(self, datasets, search_space_digest, *args, **kwargs)
    finally:
        _routed.configs = None


_fit.__doc__ = _ORIGINAL_FIT.__doc__
_fit.__wrapped__ = _ORIGINAL_FIT


def rating_inputs(
    train_X: torch.Tensor, rating_sets: list[SupervisedDataset]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""The items with the rated arms added, and the ratings with their rows.

    Args:
        train_X: ``n x d`` items of the preference metric (Ax's transformed parameters).
        rating_sets: the rating metrics' datasets (``X``: ``r x d`` in the same space, ``Y``:
            ``r x 1`` ratings in ``[0, 1]``).

    Returns:
        ``(items, ratings, rating_index)``: an arm already among the items reuses its row.

    Raises:
        ValueError: a rating outside ``[0, 1]`` or not finite (named with its metric), or a
            rating metric's inputs of another width.
    """
    items = train_X
    ratings, index = [], []
    for ds in rating_sets:
        name = ds.outcome_names[0]
        X, Y = ds.X.to(train_X), ds.Y.to(train_X).reshape(-1)
        if X.shape[-1] != train_X.shape[-1]:
            raise ValueError(
                f"rating metric {name!r} has {X.shape[-1]} input columns, the preference metric {train_X.shape[-1]}."
            )
        bad = ~(torch.isfinite(Y) & (Y >= 0) & (Y <= 1))
        if bool(bad.any()):
            raise ValueError(
                f"rating metric {name!r}: ratings must be in [0, 1], got {Y[bad][:3].tolist()}; Ax's Y "
                "transforms (Standardize, ...) must not apply to it (docs/ax.md)."
            )
        for x, y in zip(X, Y, strict=True):
            same = (items == x).all(-1).nonzero()
            if len(same):
                row = int(same[0, 0])
            else:
                row, items = items.shape[0], torch.cat([items, x.unsqueeze(0)])
            ratings.append(y)
            index.append(row)
    long = torch.long
    if not ratings:
        return items, train_X.new_zeros(0), torch.zeros(0, dtype=long, device=train_X.device)
    return items, torch.stack(ratings), torch.tensor(index, dtype=long, device=train_X.device)


def _preference_inputs(botorch_model_class, model_config, dataset, search_space_digest, surrogate) -> dict:
    """Ax's model inputs for a ``PreferenceGP``: its own base constructor's, plus the ratings of
    the metrics ``model_options["rating_metrics"]`` names (from the surrogate's training data)."""
    options = dict(model_config.model_options or {})
    wanted = options.pop(RATING_METRICS_OPTION, None) or []
    if isinstance(wanted, str):
        wanted = [wanted]
    config = dataclasses.replace(model_config, model_options=options)
    inputs = _ax_surrogate._submodel_input_constructor_base(
        botorch_model_class,
        model_config=config,
        dataset=dataset,
        search_space_digest=search_space_digest,
        surrogate=surrogate,
    )
    if not wanted:
        return inputs
    by_name = {d.outcome_names[0]: d for d in surrogate.training_data if not isinstance(d, RankingDataset)}
    missing = [name for name in wanted if name not in by_name]
    if missing:
        raise ValueError(
            f"rating metrics {missing} have no data in this fit (the surrogate holds {sorted(by_name)}): a rating "
            "metric must be modelled by the adapter (an objective, a constraint, or a tracking metric with "
            "fit_tracking_metrics=True)."
        )
    items, ratings, index = rating_inputs(inputs["train_X"], [by_name[name] for name in wanted])
    inputs.update(train_X=items, ratings=ratings, rating_index=index)
    return inputs


def _register() -> None:
    if getattr(_ax_utils, "_torchpref_registered", False):
        return
    _ax_utils.fit_botorch_model.register(PreferenceGP)(_fit_preference_gp)
    _ax_surrogate.submodel_input_constructor.register(PreferenceGP)(_preference_inputs)
    _ax_utils.copy_model_config_with_default_values = _copy_model_config_with_default_values
    _ax_surrogate.copy_model_config_with_default_values = _copy_model_config_with_default_values
    _ax_surrogate.Surrogate.fit = _fit
    _ax_surrogate.ModelConfig = _model_config  # only Surrogate.fit's fallback ModelConfig() is changed
    _ax_utils._torchpref_registered = True


_register()
