r"""``PreferenceGP`` inside Ax: registration at import, and an explicit, reversible opt-in.

Ax (``pip install 'torchpref[ax]'``, tested with ax-platform 1.3.1) builds a model per metric
from a ``ModelConfig``; for its preference metric (a ``RankingDataset``) it knows only BoTorch's
``PairwiseGP``. ``import torchpref.integrations.ax`` registers ``PreferenceGP`` with Ax's two
dispatchers, its extension points for a model class, and changes nothing else (no Ax class or
function is replaced; ``ModelConfig`` stays Ax's class):

* ``fit_botorch_model``: a :class:`~torchpref.models.preference_gp.PreferenceGP` is fitted with
  :class:`~torchpref.models.preference_gp.LaplaceMarginalLogLikelihood`; Ax's default MLL for a
  model it does not know (``ExactMarginalLogLikelihood``) and ``PairwiseLaplaceMarginalLogLikelihood``
  are read as it;
* ``submodel_input_constructor``: Ax's own inputs, with no outcome transform (the utility has no
  observed scale, as for ``PairwiseGP``), ``PairwiseGP``'s kernel priors unless the config names a
  kernel (:func:`pairwise_gp_kernel`; ``model_options["kernel_priors"]``), plus the ratings of the
  metrics ``model_options["rating_metrics"]`` names, as ``ratings=`` / ``rating_index=``, or, for a
  rating metric modelled by ``PreferenceGP`` itself, its own values as ratings (docs/ax.md).

With that, ``ModelConfig(botorch_model_class=PreferenceGP, ...)`` in ``metric_to_model_configs``
works. Ax's *defaults* still build ``PairwiseGP`` until :func:`use_preference_gp` is called: it
makes the modular default for a ``RankingDataset`` (``choose_model_class``) and
``get_preference_adapter`` (so BOPE's utility trace and best point in ``best_point``) build a
``PreferenceGP``, and its handle's ``undo()`` (or the end of a ``with`` block) restores Ax's own.

Nothing here is imported by ``import torchpref``; importing it twice changes nothing.
"""

from __future__ import annotations

import dataclasses
import threading
from typing import TYPE_CHECKING, Any

try:
    from ax.generators.torch.botorch_modular import surrogate as _ax_surrogate
    from ax.generators.torch.botorch_modular import utils as _ax_utils
except ImportError as err:  # pragma: no cover - exercised where Ax is absent
    raise ImportError("torchpref.integrations.ax needs Ax (ax-platform): pip install 'torchpref[ax]'") from err

import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models.pairwise_gp import PairwiseGP, PairwiseLaplaceMarginalLogLikelihood
from botorch.models.transforms.input import Normalize
from botorch.utils.datasets import RankingDataset, SupervisedDataset
from gpytorch.constraints import GreaterThan, Interval
from gpytorch.kernels import RBFKernel, ScaleKernel
from gpytorch.mlls import ExactMarginalLogLikelihood
from gpytorch.priors import GammaPrior, SmoothedBoxPrior

from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP

if TYPE_CHECKING:
    from ax.generators.torch.botorch_modular.surrogate import ModelConfig

__all__ = [
    "KERNEL_PRIORS_OPTION",
    "RATING_METRICS_OPTION",
    "Y_TRANSFORMS",
    "PreferenceGPOptIn",
    "is_preference_model_class",
    "laplace_mll_class",
    "pairwise_gp_kernel",
    "preference_model_config",
    "rating_inputs",
    "rating_metric_names",
    "use_preference_gp",
]


#: The ``ModelConfig.model_options`` key naming the rating metrics whose data a
#: ``PreferenceGP`` takes as ratings (a list of metric names).
RATING_METRICS_OPTION = "rating_metrics"

#: The ``ModelConfig.model_options`` key choosing the kernel priors of a ``PreferenceGP`` built by
#: Ax when its ``ModelConfig`` names no ``covar_module_class``: ``"pairwise_gp"`` (the default
#: inside Ax: :func:`pairwise_gp_kernel`, ``PairwiseGP``'s priors; docs/decisions.md) or
#: ``"preference_gp"`` (torchpref's own default kernel, as outside Ax).
KERNEL_PRIORS_OPTION = "kernel_priors"
_KERNEL_PRIORS = ("pairwise_gp", "preference_gp")

#: Ax's default Y transforms (``ax.adapter.registry.Y_trans``), which rescale ratings.
Y_TRANSFORMS = "Derelativize, Winsorize, BilogY, StandardizeY"

# MLL classes Ax puts in a ModelConfig by default or for PairwiseGP: all mean "the model's evidence"
_READ_AS_LAPLACE = (ExactMarginalLogLikelihood, PairwiseLaplaceMarginalLogLikelihood)


def is_preference_model_class(cls: object) -> bool:
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
                f"rating metric {name!r}: ratings must be in [0, 1], got {Y[bad][:3].tolist()}. If the ratings "
                f"you attached are in [0, 1], one of Ax's Y transforms rescaled them (its default {Y_TRANSFORMS}): "
                "give the adapter no Y transform, e.g. transforms=[] (TorchAdapter) or generator_kwargs="
                "{'transforms': []} (GenerationStep), as torchpref.integrations.ax_recipes' strategies do."
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


def pairwise_gp_kernel(d: int) -> ScaleKernel:
    """``PairwiseGP``'s default kernel for ``d`` inputs (float64): an ARD RBF kernel with a
    Gamma(2.4, 2.7) lengthscale prior (lengthscales above 1e-4, started at the prior's mode) in a
    ``ScaleKernel`` with a SmoothedBox(0.01, 100) outputscale prior, started at 1, with one change:
    the outputscale is held in [0.005, 100] (``PairwiseGP``'s constraint reaches 200, but its prior
    is a wall 0.01 wide at 100 on which L-BFGS-B's line search fails when the evidence climbs to
    it: docs/decisions.md). Inside Ax, ``PreferenceGP`` is built with it by default."""
    if not isinstance(d, int) or isinstance(d, bool) or d < 1:
        raise ValueError(f"d must be a positive int (the number of inputs), got {d!r}.")
    ls_prior = GammaPrior(2.4, 2.7)
    mode = float((ls_prior.concentration - 1) / ls_prior.rate)
    base = RBFKernel(
        ard_num_dims=d,
        lengthscale_prior=ls_prior,
        lengthscale_constraint=GreaterThan(1e-4, transform=None, initial_value=mode),
    )
    kernel = ScaleKernel(
        base,
        outputscale_prior=SmoothedBoxPrior(0.01, 100.0),
        outputscale_constraint=Interval(0.005, 100.0, initial_value=1.0),
    )
    return kernel.to(torch.float64)


def _kernel_priors(options: dict) -> str:
    priors = options.pop(KERNEL_PRIORS_OPTION, "pairwise_gp")
    if priors not in _KERNEL_PRIORS:
        raise ValueError(f"model_options[{KERNEL_PRIORS_OPTION!r}] must be one of {_KERNEL_PRIORS}, got {priors!r}.")
    return priors


def rating_metric_names(options: dict) -> list[str]:
    """The metric names ``options[RATING_METRICS_OPTION]`` gives (removed from ``options``).

    Raises:
        ValueError: not a list (or tuple) of strings, a bare string included, or a name given twice.
    """
    wanted = options.pop(RATING_METRICS_OPTION, None)
    if wanted is None:
        return []
    if isinstance(wanted, str) or not isinstance(wanted, list | tuple) or not all(isinstance(n, str) for n in wanted):
        hint = f": write [{wanted!r}]" if isinstance(wanted, str) else ""
        raise ValueError(
            f"model_options[{RATING_METRICS_OPTION!r}] must be a list of metric names, got {wanted!r}{hint}."
        )
    twice = sorted({n for n in wanted if list(wanted).count(n) > 1})
    if twice:
        raise ValueError(
            f"model_options[{RATING_METRICS_OPTION!r}] names {twice} more than once: each of their ratings would "
            "be counted once per name; name each rating metric once."
        )
    return list(wanted)


class _RatingsOnly(PreferenceGP):
    """Ax's base input constructor's view of a ``PreferenceGP`` fitted to a rating metric's own data:
    its inputs start with no items; :func:`rating_inputs` adds the rated arms."""

    @classmethod
    def construct_inputs(cls, training_data: SupervisedDataset, **kwargs: object) -> dict[str, Any]:
        return {"train_X": training_data.X[:0], **kwargs}


def _preference_inputs(botorch_model_class, model_config, dataset, search_space_digest, surrogate) -> dict:
    """Ax's model inputs for a ``PreferenceGP``: its own base constructor's with no outcome
    transform, plus ratings. The metric modelled is the preference metric (a ``RankingDataset``:
    comparisons) or a rating metric (any other dataset: its values are ratings in ``[0, 1]``); the
    metrics ``model_options["rating_metrics"]`` names add their ratings (from the surrogate's
    training data)."""
    options = dict(model_config.model_options or {})
    wanted = rating_metric_names(options)
    priors = _kernel_priors(options)
    name = dataset.outcome_names[0]
    own = [] if isinstance(dataset, RankingDataset) else [dataset]  # a rating metric modelled by itself
    if name in wanted:
        raise ValueError(
            f"metric {name!r} is named in model_options[{RATING_METRICS_OPTION!r}] of its own model: "
            + (
                "its values are the model's ratings already (they would count twice); leave it out."
                if own
                else "it is the preference metric (comparisons), not a rating metric."
            )
        )
    # no outcome transform: the utility has no observed scale (Ax drops it for PairwiseGP alike)
    config = dataclasses.replace(model_config, model_options=options, outcome_transform_classes=None)
    inputs = _ax_surrogate._submodel_input_constructor_base(
        _RatingsOnly if own else botorch_model_class,
        model_config=config,
        dataset=dataset,
        search_space_digest=search_space_digest,
        surrogate=surrogate,
    )
    if model_config.covar_module_class is None and priors == "pairwise_gp":
        inputs["covar_module"] = pairwise_gp_kernel(int(inputs["train_X"].shape[-1]))
    if not wanted and not own:
        return inputs
    by_name = {d.outcome_names[0]: d for d in surrogate.training_data if not isinstance(d, RankingDataset)}
    missing = [n for n in wanted if n not in by_name]
    if missing:
        raise ValueError(
            f"rating metrics {missing} have no data in this fit (the surrogate holds {sorted(by_name)}): a rating "
            "metric must be modelled by the adapter (an objective, a constraint, or a tracking metric with "
            "fit_tracking_metrics=True)."
        )
    items, ratings, index = rating_inputs(inputs["train_X"], own + [by_name[n] for n in wanted])
    inputs.update(train_X=items, ratings=ratings, rating_index=index)
    return inputs


def preference_model_config(d: int | None = None, **kwargs: Any) -> ModelConfig:
    """Ax's ``ModelConfig`` for a ``PreferenceGP``, as Ax's ``get_preference_adapter`` writes one for
    ``PairwiseGP``: the Laplace MLL and, with ``d`` (the number of parameters), ``Normalize`` to the
    data's bounds (without ``d``, Ax's default input transforms: ``Normalize`` to the search space's
    bounds); ``kwargs`` are passed on (``model_options={"rating_metrics": [...]}``, ...)."""
    config: dict[str, Any] = {"botorch_model_class": PreferenceGP, "mll_class": LaplaceMarginalLogLikelihood}
    if d is not None:
        config.update(
            input_transform_classes=[Normalize],
            input_transform_options={"Normalize": {"d": d, "bounds": None, "indices": None}},
        )
    return _ax_surrogate.ModelConfig(**{**config, **kwargs})


def _choose_model_class(dataset, search_space_digest, specified_model_class=None):
    """Ax's ``choose_model_class``, with ``PreferenceGP`` where it would choose ``PairwiseGP`` by default."""
    chosen = _ORIGINAL_CHOOSE(
        dataset=dataset, search_space_digest=search_space_digest, specified_model_class=specified_model_class
    )
    if chosen is PairwiseGP and specified_model_class is None and isinstance(dataset, RankingDataset):
        return PreferenceGP
    return chosen


_ORIGINAL_CHOOSE = _ax_utils.choose_model_class
setattr(_choose_model_class, "__wrapped__", _ORIGINAL_CHOOSE)  # noqa: B010  # functools' convention
_lock = threading.Lock()
_active: list[PreferenceGPOptIn] = []


class PreferenceGPOptIn:
    """The handle :func:`use_preference_gp` returns: ``undo()`` (once; again is a no-op) or the end
    of a ``with`` block restores Ax's defaults when no other opt-in is active."""

    def __init__(self) -> None:
        with _lock:
            if not _active:
                _ax_utils.choose_model_class = _choose_model_class
            _active.append(self)

    @property
    def active(self) -> bool:
        """Whether this opt-in is still in effect (not undone)."""
        return any(h is self for h in _active)

    def undo(self) -> None:
        """End this opt-in; Ax's own ``choose_model_class`` is back once no opt-in is active."""
        with _lock:
            if not self.active:
                return
            _active.remove(self)
            if not _active:
                _ax_utils.choose_model_class = _ORIGINAL_CHOOSE

    def __enter__(self) -> PreferenceGPOptIn:
        return self

    def __exit__(self, *exc: object) -> None:
        self.undo()


def use_preference_gp() -> PreferenceGPOptIn:
    """Make Ax's defaults that build ``PairwiseGP`` for comparison data build ``PreferenceGP``.

    Ax sends a ``RankingDataset`` that ``metric_to_model_configs`` does not name to a default
    ``ModelConfig()``, whose class ``choose_model_class`` fills: ``PairwiseGP``. That is the path of
    the modular default (``Generators.BOTORCH_MODULAR``, ``SurrogateSpec()`` or
    ``SurrogateSpec(model_configs=[...])`` for the outcome metrics), of BOPE's preference model, and
    of ``get_preference_adapter`` (whose own ``PairwiseGP`` config never reaches the preference
    metric), so of BOPE's utility trace and best point (``ax.service.utils.best_point``). After
    this call the class filled is ``PreferenceGP`` (with the Laplace MLL, no outcome transform,
    ``PairwiseGP``'s kernel priors;
    ``PairwiseGP`` named explicitly in a ``ModelConfig`` is still built). It rebinds one function,
    ``ax.generators.torch.botorch_modular.utils.choose_model_class``, to a wrapper of Ax's own
    (nothing changes at import); the handle's ``undo()`` restores it::

        import torchpref.integrations.ax as tax
        tax.use_preference_gp()             # or: with tax.use_preference_gp(): ...
    """
    return PreferenceGPOptIn()


def _register() -> None:
    """Register ``PreferenceGP`` with Ax's dispatchers (its extension points); nothing else."""
    _ax_utils.fit_botorch_model.register(PreferenceGP)(_fit_preference_gp)  # registering again replaces
    _ax_surrogate.submodel_input_constructor.register(PreferenceGP)(_preference_inputs)


_register()
