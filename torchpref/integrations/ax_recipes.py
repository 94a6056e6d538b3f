r"""Ready Ax objects for ``PreferenceGP`` (issue 32, item 2; docs/ax.md, "Recipes").

What an Ax user copies: the surrogate spec for a preference metric, generation strategies for
preferential BO (PBO) and for BOPE's BO step, and BOPE's utility trace and best point computed
with a ``PreferenceGP``. Each is Ax's own object (``SurrogateSpec``, ``GenerationStrategy``,
``best_point.get_trace``), built through Ax's public constructors; nothing of Ax's is changed.

Both loops need ``transforms=[]`` on the BoTorch step: Ax's default transforms standardise Y
(the 0/1 preference labels and any ratings lose their meaning) and, for BOPE, would move the
outcomes the learned objective reads away from the scale the preference model was fitted on.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

try:
    from ax.adapter.registry import Generators
    from ax.core.experiment import Experiment
    from ax.generation_strategy.generation_node import GenerationStep
    from ax.generation_strategy.generation_strategy import GenerationStrategy
    from ax.generators.torch.botorch_modular.surrogate import SurrogateSpec
    from ax.utils.common.constants import Keys
except ImportError as err:  # pragma: no cover - exercised where Ax is absent
    raise ImportError("torchpref.integrations.ax_recipes needs Ax (ax-platform): pip install 'torchpref[ax]'") from err
from botorch.acquisition.logei import qLogNoisyExpectedImprovement
from botorch.acquisition.preference import qExpectedUtilityOfBestOption

from torchpref.integrations.ax import RATING_METRICS_OPTION, preference_model_config, use_preference_gp

if TYPE_CHECKING:
    from ax.core.batch_trial import BatchTrial
    from ax.core.optimization_config import PreferenceOptimizationConfig
    from ax.core.search_space import SearchSpace

__all__ = [
    "PREFERENCE_METRIC",
    "add_comparison",
    "add_rating",
    "bope_experiments",
    "next_pair",
    "pbo_best_point",
    "pbo_experiment",
    "rating_generation_strategy",
    "record_preference",
    "refresh_preference_profile",
    "bope_best_point",
    "bope_generation_strategy",
    "bope_utility_trace",
    "pbo_generation_strategy",
    "preference_surrogate_spec",
]

#: Ax's preference metric (``Keys.PAIRWISE_PREFERENCE_QUERY``): two-arm batch trials, 1 for the
#: preferred arm and 0 for the other.
PREFERENCE_METRIC = Keys.PAIRWISE_PREFERENCE_QUERY.value


def _search_space(bounds: dict[str, tuple[float, float]]) -> SearchSpace:
    from ax.core.parameter import ParameterType, RangeParameter
    from ax.core.search_space import SearchSpace

    if not bounds:
        raise ValueError("bounds must name at least one parameter, got none.")
    params = []
    for name, (lo, hi) in bounds.items():
        if not float(lo) < float(hi):
            raise ValueError(f"parameter {name!r}: lower bound {lo} must be below upper bound {hi}.")
        params.append(RangeParameter(name=name, parameter_type=ParameterType.FLOAT, lower=float(lo), upper=float(hi)))
    return SearchSpace(parameters=params)


def pbo_experiment(bounds: dict[str, tuple[float, float]], name: str = "pbo") -> Experiment:
    """An Ax ``Experiment`` for preferential BO: the ``bounds`` (``{name: (lower, upper)}``) as
    float parameters and the ``pairwise_pref_query`` metric as the objective. Record each answer
    with :func:`add_comparison`."""
    from ax.core.metric import Metric
    from ax.core.objective import Objective
    from ax.core.optimization_config import OptimizationConfig

    config = OptimizationConfig(Objective(metric=Metric(PREFERENCE_METRIC), minimize=False))
    return Experiment(search_space=_search_space(bounds), optimization_config=config, name=name)


def bope_experiments(
    bounds: dict[str, tuple[float, float]], outcome_bounds: dict[str, tuple[float, float]], name: str = "bope"
) -> tuple[Experiment, Experiment]:
    """BOPE's two experiments: ``(bo, pe)``. ``bo`` has the ``bounds`` as parameters, the
    outcomes (``outcome_bounds``' keys) as metrics under a ``PreferenceOptimizationConfig``, and
    ``pe`` as its ``PE_EXPERIMENT``; ``pe`` (``pbo_experiment(outcome_bounds)``) holds the
    comparisons of outcome vectors. After adding comparisons to ``pe``, call
    :func:`refresh_preference_profile` (Ax's ``AuxiliaryExperiment`` keeps the data it was made with)."""
    from ax.core.metric import Metric
    from ax.core.objective import MultiObjective, Objective
    from ax.core.optimization_config import PreferenceOptimizationConfig

    pe = pbo_experiment(outcome_bounds, name=f"{name}_pe")
    objectives = [Objective(metric=Metric(name=m), minimize=False) for m in outcome_bounds]
    config = PreferenceOptimizationConfig(
        objective=MultiObjective(objectives=objectives), preference_profile_name=pe.name
    )
    bo = Experiment(search_space=_search_space(bounds), optimization_config=config, name=name)
    refresh_preference_profile(bo, pe)
    return bo, pe


def refresh_preference_profile(bo: Experiment, pe: Experiment) -> None:
    """Make ``pe`` (with the comparisons it holds now) ``bo``'s ``PE_EXPERIMENT``."""
    from ax.core.auxiliary import AuxiliaryExperiment, AuxiliaryExperimentPurpose

    bo.auxiliary_experiments_by_purpose[AuxiliaryExperimentPurpose.PE_EXPERIMENT] = [
        AuxiliaryExperiment(experiment=pe, data=pe.lookup_data())
    ]


def add_comparison(experiment: Experiment, a: dict, b: dict, a_preferred: bool) -> BatchTrial:
    """Record one answer as Ax's preference data: a completed two-arm batch trial of ``a`` and
    ``b`` (parameter dictionaries) with ``pairwise_pref_query`` 1 for the preferred arm, 0 for
    the other. Returns the trial."""
    from ax.core import Arm, GeneratorRun

    if not isinstance(a_preferred, bool):
        raise ValueError(f"a_preferred must be True or False, got {a_preferred!r}.")
    trial = experiment.new_batch_trial(generator_run=GeneratorRun([Arm(parameters=dict(a)), Arm(parameters=dict(b))]))
    arm_a, arm_b = trial.arms
    win = int(a_preferred)
    trial.attach_batch_trial_data(
        raw_data={arm_a.name: {PREFERENCE_METRIC: win}, arm_b.name: {PREFERENCE_METRIC: 1 - win}}
    )
    trial.mark_running(no_runner_required=True)
    trial.mark_completed()
    return trial


def add_rating(experiment: Experiment, parameters: dict, rating: float, metric: str = "rating") -> BatchTrial:
    """Record one rating in ``[0, 1]`` of the arm ``parameters`` as a completed one-arm trial of
    ``metric`` (added to the experiment as a tracking metric if it is not one of its metrics).
    Returns the trial.

    Raises:
        ValueError: a rating outside ``[0, 1]`` or not finite, named with its metric.
    """
    from ax.core import Arm, GeneratorRun
    from ax.core.metric import Metric

    value = float(rating)
    if not 0.0 <= value <= 1.0:  # NaN fails too
        raise ValueError(f"rating metric {metric!r}: a rating must be in [0, 1], got {rating!r}.")
    if metric not in experiment.metrics:
        experiment.add_metric(Metric(name=metric))
    trial = experiment.new_batch_trial(generator_run=GeneratorRun([Arm(parameters=dict(parameters))]))
    trial.attach_batch_trial_data(raw_data={trial.arms[0].name: {metric: (value, 0.0)}})
    trial.mark_running(no_runner_required=True)
    trial.mark_completed()
    return trial


def next_pair(experiment: Experiment, generation_strategy: GenerationStrategy) -> BatchTrial:
    """The next PBO query: a two-arm batch trial from ``generation_strategy`` (``gen(n=2)``), marked
    running. Answer it with :func:`record_preference`. (Ax's ``Client.get_next_trials`` makes
    one-arm trials, which hold no comparison: docs/ax.md.)"""
    (runs,) = generation_strategy.gen(experiment=experiment, n=2)
    trial = experiment.new_batch_trial(generator_runs=runs)
    if len(trial.arms) != 2:
        raise ValueError(
            f"the generation strategy gave {len(trial.arms)} distinct arms for a pair; a PBO query needs 2 "
            "(two identical candidates are collapsed by Ax)."
        )
    trial.mark_running(no_runner_required=True)
    return trial


def record_preference(trial: BatchTrial, preferred: int) -> None:
    """Answer a PBO query from :func:`next_pair`: ``preferred`` is the index (0 or 1) of the
    preferred arm in ``trial.arms``; the trial is completed."""
    if preferred not in (0, 1) or isinstance(preferred, bool):
        raise ValueError(f"preferred must be 0 or 1 (an index into trial.arms), got {preferred!r}.")
    arms = trial.arms
    trial.attach_batch_trial_data(
        raw_data={arm.name: {PREFERENCE_METRIC: int(k == preferred)} for k, arm in enumerate(arms)}
    )
    trial.mark_completed()


def preference_surrogate_spec(
    d: int | None = None, rating_metrics: list[str] | None = None, metric: str = PREFERENCE_METRIC, **config: Any
) -> SurrogateSpec:
    """``SurrogateSpec`` whose preference metric is modelled by a ``PreferenceGP``.

    Args:
        d: the number of parameters of the experiment (``Normalize`` to the data's bounds, as Ax's
            ``get_preference_adapter``); ``None``: Ax's default input transforms.
        rating_metrics: metrics whose values in ``[0, 1]`` are ratings of the arms, added to the
            model's data (docs/ax.md, "Ratings").
        metric: the metric the ``PreferenceGP`` models: the preference metric (comparisons), or a
            rating metric whose own values are the ratings (ratings alone).
        config: further ``ModelConfig`` fields (``covar_module_class=...``, ...).
    """
    if rating_metrics is not None:
        options = dict(config.pop("model_options", None) or {})
        options[RATING_METRICS_OPTION] = rating_metrics
        config["model_options"] = options
    return SurrogateSpec(metric_to_model_configs={metric: [preference_model_config(d, **config)]})


def _strategy(name: str, initial_trials: int, seed: int | None, generator_kwargs: dict) -> GenerationStrategy:
    if initial_trials < 1:
        raise ValueError(f"initial_trials must be at least 1 (the model needs data), got {initial_trials}.")
    sobol = GenerationStep(
        generator=Generators.SOBOL,
        num_trials=initial_trials,
        min_trials_observed=initial_trials,
        generator_kwargs={"seed": seed},
    )
    botorch = GenerationStep(generator=Generators.BOTORCH_MODULAR, num_trials=-1, generator_kwargs=generator_kwargs)
    return GenerationStrategy(name=name, nodes=[sobol, botorch])


def _botorch_kwargs(acqf: type, spec: SurrogateSpec, fit_tracking_metrics: bool) -> dict:
    # transforms=[]: Ax's default Y transforms would rescale the preference labels and ratings
    return {
        "surrogate_spec": spec,
        "botorch_acqf_class": acqf,
        "transforms": [],
        "fit_tracking_metrics": fit_tracking_metrics,
    }


def pbo_generation_strategy(
    d: int | None = None,
    initial_pairs: int = 4,
    seed: int | None = None,
    rating_metrics: list[str] | None = None,
    **config: Any,
) -> GenerationStrategy:
    """Preferential BO: ``initial_pairs`` Sobol pairs, then pairs chosen by
    ``qExpectedUtilityOfBestOption`` on a ``PreferenceGP`` of the ``pairwise_pref_query``
    objective (with the ratings of ``rating_metrics``, tracking metrics of the experiment, when
    given). Ask for pairs with :func:`next_pair` (``gen(n=2)``)."""
    spec = preference_surrogate_spec(d, rating_metrics, **config)
    kwargs = _botorch_kwargs(qExpectedUtilityOfBestOption, spec, fit_tracking_metrics=bool(rating_metrics))
    return _strategy("PBO+PreferenceGP", initial_pairs, seed, kwargs)


def rating_generation_strategy(
    metric: str, d: int | None = None, initial_trials: int = 4, seed: int | None = None, **config: Any
) -> GenerationStrategy:
    """BO of ratings alone: the objective ``metric`` holds ratings in ``[0, 1]`` (one arm per
    trial); ``initial_trials`` Sobol trials, then ``qLogNoisyExpectedImprovement`` on a
    ``PreferenceGP`` of the ratings (its output is the latent utility, which the expected rating
    increases with, not the rating itself)."""
    spec = preference_surrogate_spec(d, metric=metric, **config)
    kwargs = _botorch_kwargs(qLogNoisyExpectedImprovement, spec, fit_tracking_metrics=False)
    return _strategy("Ratings+PreferenceGP", initial_trials, seed, kwargs)


def bope_generation_strategy(
    pe_d: int | None = None, initial_trials: int = 6, seed: int | None = None, **config: Any
) -> GenerationStrategy:
    """BOPE's BO step: ``initial_trials`` Sobol trials, then ``qLogNoisyExpectedImprovement``
    under Ax's ``LearnedObjective`` of a ``PreferenceGP`` fitted to the ``PE_EXPERIMENT``'s
    comparisons (``pe_d``: its number of outcome parameters). The experiment carries a
    ``PreferenceOptimizationConfig`` (:func:`bope_experiments`); the outcome metrics get Ax's
    default models."""
    kwargs = _botorch_kwargs(qLogNoisyExpectedImprovement, preference_surrogate_spec(pe_d, **config), False)
    return _strategy("BOPE+PreferenceGP", initial_trials, seed, kwargs)


def bope_utility_trace(experiment: Experiment, **kwargs: Any) -> dict[int, float]:
    """Ax's BOPE utility trace (``ax.service.utils.best_point.get_trace``: the best utility so far
    by trial, utilities from a preference model of the ``PE_EXPERIMENT``'s comparisons), with that
    model a ``PreferenceGP``; Ax's defaults are restored afterwards."""
    from ax.service.utils.best_point import get_trace

    with use_preference_gp():
        return get_trace(experiment, **kwargs)


def pbo_best_point(experiment: Experiment) -> tuple[str, dict, float]:
    """PBO's recommendation: the compared arm of highest posterior mean utility under a
    ``PreferenceGP`` of the experiment's comparisons (Ax's ``get_preference_adapter`` under
    :func:`use_preference_gp`): ``(arm_name, parameters, utility)``. (Ax's
    ``Client.get_best_parameterization`` raises on PBO's batch trials: docs/ax.md.)

    Raises:
        ValueError: the experiment has no comparisons.
    """
    from ax.core.observation import ObservationFeatures
    from ax.utils.preference.preference_utils import get_preference_adapter

    data = experiment.lookup_data()
    if data.df.empty:
        raise ValueError(f"experiment {experiment.name!r} has no comparisons yet (record some with add_comparison).")
    names = sorted(set(data.df["arm_name"]))
    with use_preference_gp():
        adapter = get_preference_adapter(experiment=experiment, data=data)
    features = [ObservationFeatures(parameters=dict(experiment.arms_by_name[n].parameters)) for n in names]
    mean, _ = adapter.predict(observation_features=features, use_posterior_predictive=False)
    utility = mean[PREFERENCE_METRIC]
    best = max(range(len(names)), key=utility.__getitem__)
    return names[best], dict(experiment.arms_by_name[names[best]].parameters), float(utility[best])


def _pe_experiment(experiment: Experiment, config: PreferenceOptimizationConfig) -> Experiment:
    from ax.core.auxiliary import AuxiliaryExperimentPurpose

    aux = experiment.find_auxiliary_experiment_by_name(
        purpose=AuxiliaryExperimentPurpose.PE_EXPERIMENT,
        auxiliary_experiment_name=config.preference_profile_name,
        raise_if_not_found=False,
    )
    if aux is None:
        raise ValueError(
            f"experiment {experiment.name!r} has no PE_EXPERIMENT named {config.preference_profile_name!r} "
            "(its PreferenceOptimizationConfig's preference_profile_name)."
        )
    return aux.experiment


def bope_best_point(experiment: Experiment) -> tuple[int, str, dict, float]:
    """The observed arm of highest utility under a ``PreferenceGP`` of the ``PE_EXPERIMENT``'s
    comparisons (Ax's ``get_preference_adapter`` under :func:`use_preference_gp`; outcome
    constraints are not checked): ``(trial_index, arm_name, parameters, utility)``.

    Raises:
        ValueError: no ``PreferenceOptimizationConfig``, no ``PE_EXPERIMENT``, or no arm with
            data for every outcome.
    """
    from ax.core.observation import ObservationFeatures
    from ax.core.optimization_config import PreferenceOptimizationConfig
    from ax.utils.preference.preference_utils import get_preference_adapter

    config = experiment.optimization_config
    if not isinstance(config, PreferenceOptimizationConfig):
        raise ValueError(
            f"bope_best_point needs a BOPE experiment (a PreferenceOptimizationConfig); experiment "
            f"{experiment.name!r} has {type(config).__name__}."
        )
    pe = _pe_experiment(experiment, config)
    df = experiment.lookup_data().df
    names = list(config.objective.metric_names)
    wide = df[df["metric_name"].isin(names)].pivot_table(
        index=["trial_index", "arm_name"], columns="metric_name", values="mean"
    )
    wide = wide.dropna().reset_index()
    if wide.empty:
        raise ValueError(f"experiment {experiment.name!r} has no arm with data for all of {names}.")
    with use_preference_gp():
        adapter = get_preference_adapter(experiment=pe, data=pe.lookup_data())
    features = [ObservationFeatures(parameters={m: float(row[m]) for m in names}) for _, row in wide.iterrows()]
    mean, _ = adapter.predict(observation_features=features, use_posterior_predictive=False)
    utility = mean[PREFERENCE_METRIC]
    best = max(range(len(utility)), key=utility.__getitem__)
    trial, arm = int(wide["trial_index"].iloc[best]), str(wide["arm_name"].iloc[best])
    return trial, arm, dict(experiment.arms_by_name[arm].parameters), float(utility[best])
