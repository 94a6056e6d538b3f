"""Ax's preferential-BO (PBO) and BOPE loops with PreferenceGP and with PairwiseGP (issues 21, 32).

Both loops are built as Ax's own tests build them (ax/adapter/tests/test_torch_adapter.py:
``test_pairwise_preference_generator`` for PBO, ``test_fitting_auxiliary_experiment_dataset``
for BOPE): a ``TorchAdapter`` over an ``Experiment`` whose preference data are two-arm batch
trials of the ``pairwise_pref_query`` metric, the model named in
``SurrogateSpec(metric_to_model_configs={pairwise_pref_query: [ModelConfig(...)]})`` (with
``Normalize``); the only line that differs between the arms is that ``ModelConfig``: docs/ax.md's
``tax.preference_model_config(d)`` ("PreferenceGP_pairwise_box": ``PairwiseGP``'s kernel priors,
outputscale at most 100, the default inside Ax since issue 32's prior decision), ``PreferenceGP``
with torchpref's own priors ("PreferenceGP"), with ``PairwiseGP``'s kernel exactly
("PreferenceGP_pairwise_priors"), and Ax's ``PairwiseGP`` config ("PairwiseGP"). A run that raises
(a failed fit) is recorded with its error and left out of the summary, which counts it.

* PBO: ``d = 3`` parameters in Ax's test bounds ``[10, 30]``; a hidden utility
  ``-||(x - 10) / 20 - c||^2`` (``c`` drawn per seed); 4 random pairs, then ``--iters`` pairs
  chosen by ``qExpectedUtilityOfBestOption`` (Ax's ``adapter.gen(n=2)``); the recommendation is
  the compared arm of highest posterior mean, scored by its true utility (0 is best).
* BOPE: 4 parameters, 2 outcomes ``f(x)``, a decision maker's utility ``g(y)``; the BO
  experiment carries the PE experiment as Ax's ``PE_EXPERIMENT`` auxiliary experiment and a
  ``PreferenceOptimizationConfig``, so Ax builds ``LearnedObjective(preference model)`` and
  generates with ``qLogNoisyExpectedImprovement`` under it. Each iteration adds one preference
  query and one BO candidate; the outcome is ``g(f(x))`` of the best arm found. The query is two
  observed outcome vectors drawn at random (``--pe random``) or BOPE's EUBO-zeta pair
  (``--pe eubo``); ``--pe-initial`` comparisons come before the loop.

CPU time is process time (``time.process_time``), one thread, of the fits (the adapters'
construction) and of the generation (``gen``, and the EUBO-zeta step); each process runs every
arm once first, unrecorded (lazy imports), then, per seed, the arms in an order rotating with the
seed. Each finished run is appended to ``<loop>_rows.jsonl`` at once; the summary (paired tests,
CPU ratios) is written stamped to ``benchmarks/results/ax/<loop>.json``, ``.csv`` and ``.png``.
One seed per process (as the committed results were run):

    python benchmarks/parity/ax_loops.py --loop pbo --seeds 3 --arms PreferenceGP PairwiseGP
    python benchmarks/parity/ax_loops.py --loop pbo --summarize
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import os
import time
import warnings
from pathlib import Path

import numpy as np
import torch

RESULTS = Path(__file__).resolve().parents[1] / "results" / "ax"
PREF = "pairwise_pref_query"


ARMS = ("PreferenceGP", "PairwiseGP", "PreferenceGP_pairwise_priors", "PreferenceGP_pairwise_box")


def _exact_pairwise_kernel_options(d: int) -> dict:
    """``covar_module_options`` of a ``ScaleKernel`` that is exactly ``PairwiseGP``'s default kernel
    (outputscale constraint up to 200)."""
    from gpytorch.constraints import Interval

    import torchpref.integrations.ax as tax

    kernel = tax.pairwise_gp_kernel(d)
    return {
        "base_kernel": kernel.base_kernel,
        "outputscale_prior": kernel.outputscale_prior,
        "outputscale_constraint": Interval(0.005, 200.0, initial_value=1.0),
    }


def _model_config(arm: str, d: int):
    """The arm's ``ModelConfig``: ``PreferenceGP`` with torchpref's kernel priors ("PreferenceGP"),
    with ``PairwiseGP``'s kernel exactly ("PreferenceGP_pairwise_priors"), with
    ``tax.pairwise_gp_kernel`` (``PairwiseGP``'s priors, outputscale held at most 100;
    "PreferenceGP_pairwise_box"), and ``PairwiseGP`` as Ax's tests name it."""
    from ax.generators.torch.botorch_modular.surrogate import ModelConfig
    from botorch.models.transforms.input import Normalize

    if arm.startswith("PreferenceGP"):
        import torchpref.integrations.ax as tax

        if arm == "PreferenceGP_pairwise_priors":
            from gpytorch.kernels import ScaleKernel

            options = _exact_pairwise_kernel_options(d)
            return tax.preference_model_config(d, covar_module_class=ScaleKernel, covar_module_options=options)
        priors = "pairwise_gp" if arm == "PreferenceGP_pairwise_box" else "preference_gp"
        return tax.preference_model_config(d, model_options={tax.KERNEL_PRIORS_OPTION: priors})
    from botorch.models.pairwise_gp import PairwiseGP, PairwiseLaplaceMarginalLogLikelihood

    return ModelConfig(
        botorch_model_class=PairwiseGP,
        mll_class=PairwiseLaplaceMarginalLogLikelihood,
        input_transform_classes=[Normalize],
        input_transform_options={"Normalize": {"d": d, "bounds": None, "indices": None}},
    )


class _Clock:
    """Process time of the fits (adapter construction) and of the generation (``gen``)."""

    def __init__(self) -> None:
        self.fit = self.gen = 0.0

    def adapter(self, make):
        start = time.process_time()
        out = make()
        self.fit += time.process_time() - start
        return out

    def generate(self, adapter, n: int):
        start = time.process_time()
        out = adapter.gen(n=n)
        self.gen += time.process_time() - start
        return out


def _add_pair(experiment, params_a: dict, params_b: dict, utility) -> None:
    from ax.core import Arm, GeneratorRun

    trial = experiment.new_batch_trial(generator_run=GeneratorRun([Arm(parameters=params_a), Arm(parameters=params_b)]))
    a, b = trial.arms
    better = int(utility(a.parameters) > utility(b.parameters))
    trial.attach_batch_trial_data(raw_data={a.name: {PREF: better}, b.name: {PREF: 1 - better}})
    trial.mark_running(no_runner_required=True)
    trial.mark_completed()


def _recommended(surrogate) -> torch.Tensor:
    """The training item of highest posterior mean under the preference model."""
    from botorch.utils.datasets import RankingDataset

    names = [ds.outcome_names[0] for ds in surrogate.training_data]
    data = surrogate.training_data[names.index(PREF)]
    assert isinstance(data, RankingDataset)
    model = surrogate._submodels[(PREF,)]
    X = data._X.values
    with torch.no_grad():
        mean = model.posterior(X).mean.reshape(-1)
    return X[int(mean.argmax())], model


def run_pbo(model: str, seed: int, iters: int, d: int = 3) -> dict:
    from ax.adapter.torch import TorchAdapter
    from ax.core.metric import Metric
    from ax.core.objective import Objective
    from ax.core.optimization_config import OptimizationConfig
    from ax.generators.torch.botorch_modular.generator import BoTorchGenerator
    from ax.generators.torch.botorch_modular.surrogate import SurrogateSpec
    from ax.utils.testing.preference_stubs import get_pbo_experiment
    from botorch.acquisition.preference import qExpectedUtilityOfBestOption

    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    centre = rng.uniform(0.2, 0.8, d)
    names = [f"x{i}" for i in range(1, d + 1)]

    def utility(p: dict) -> float:
        z = (np.array([p[n] for n in names]) - 10.0) / 20.0
        return -float(((z - centre) ** 2).sum())

    opt = OptimizationConfig(Objective(metric=Metric(PREF), minimize=False))
    exp = get_pbo_experiment(
        num_parameters=d,
        num_experimental_metrics=0,
        num_experimental_trials=0,
        num_preference_trials=0,
        num_preference_trials_w_repeated_arm=0,
        include_sq=False,
        optimization_config=opt,
    )
    for _ in range(4):
        a, b = (dict(zip(names, 10 + 20 * rng.random(d), strict=True)) for _ in range(2))
        _add_pair(exp, a, b, utility)
    spec = SurrogateSpec(metric_to_model_configs={PREF: [_model_config(model, d)]})
    clock = _Clock()

    def make():
        return TorchAdapter(
            experiment=exp,
            generator=BoTorchGenerator(botorch_acqf_class=qExpectedUtilityOfBestOption, surrogate_spec=spec),
            optimization_config=opt,
            fit_tracking_metrics=False,
        )

    for _ in range(iters):
        gr = clock.generate(clock.adapter(make), 2)
        a, b = (arm.parameters for arm in gr.arms)
        _add_pair(exp, a, b, utility)
    x, fitted = _recommended(clock.adapter(make).generator.surrogate)
    return {
        "utility": utility(dict(zip(names, x.tolist(), strict=True))),
        **_times(clock),
        "model": type(fitted).__name__,
        "outputscale": _outputscale(fitted),
    }


def _times(clock: _Clock) -> dict:
    return {"cpu_s": clock.fit + clock.gen, "fit_cpu_s": clock.fit, "gen_cpu_s": clock.gen}


def _outputscale(model) -> float:
    return float(model.covar_module.outputscale.detach().reshape(-1)[0])


def _bope_problem(rng):
    shift = rng.uniform(0.3, 0.7, 4)
    target = rng.uniform(0.6, 0.9, 2)

    def outcomes(p: dict) -> np.ndarray:
        z = (np.array([p[f"x{i}"] for i in range(1, 5)]) - 10.0) / 20.0
        y1 = 1 - ((z[:2] - shift[:2]) ** 2).sum() - 0.3 * z[2]
        y2 = 1 - ((z[2:] - shift[2:]) ** 2).sum() - 0.3 * z[0]
        return np.array([y1, y2])

    def g(y) -> float:
        y = np.asarray(y, dtype=float)
        return -float(((y - target) ** 2).sum())

    return outcomes, g


def run_bope(model: str, seed: int, iters: int, pe_step: str = "random", pe_initial: int = 4) -> dict:
    from ax.adapter.torch import TorchAdapter
    from ax.core import Arm, GeneratorRun
    from ax.core.auxiliary import AuxiliaryExperiment, AuxiliaryExperimentPurpose
    from ax.core.metric import Metric
    from ax.core.objective import MultiObjective, Objective
    from ax.core.optimization_config import OptimizationConfig, PreferenceOptimizationConfig
    from ax.generators.torch.botorch_modular.generator import BoTorchGenerator
    from ax.generators.torch.botorch_modular.surrogate import SurrogateSpec
    from ax.utils.testing.preference_stubs import get_pbo_experiment
    from botorch.acquisition.logei import qLogNoisyExpectedImprovement

    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    outcomes, g = _bope_problem(rng)
    metrics = ["m1", "m2"]
    pe = get_pbo_experiment(
        optimization_config=OptimizationConfig(Objective(metric=Metric(PREF), minimize=False)),
        num_parameters=2,
        num_experimental_metrics=0,
        parameter_names=metrics,
        num_experimental_trials=0,
        num_preference_trials=0,
        num_preference_trials_w_repeated_arm=0,
        unbounded_search_space=True,
        include_sq=False,
        experiment_name="pe_exp",
    )
    config = PreferenceOptimizationConfig(
        objective=MultiObjective(objectives=[Objective(metric=Metric(name=m), minimize=False) for m in metrics]),
        preference_profile_name=pe.name,
    )
    bo = get_pbo_experiment(
        num_parameters=4,
        num_experimental_metrics=2,
        tracking_metric_names=metrics,
        num_experimental_trials=0,
        num_preference_trials=0,
        num_preference_trials_w_repeated_arm=0,
        include_sq=False,
        experiment_name="bo_exp",
        optimization_config=config,
    )

    def refresh_pe() -> None:  # an AuxiliaryExperiment holds the PE data it was built with
        bo.auxiliary_experiments_by_purpose[AuxiliaryExperimentPurpose.PE_EXPERIMENT] = [
            AuxiliaryExperiment(experiment=pe, data=pe.lookup_data())
        ]

    seen: list[np.ndarray] = []
    scores: list[float] = []

    def evaluate(params: dict) -> None:
        trial = bo.new_batch_trial(generator_run=GeneratorRun([Arm(parameters=params)]))
        (arm,) = trial.arms
        y = outcomes(arm.parameters)
        trial.attach_batch_trial_data(
            raw_data={arm.name: {m: (float(v), 0.0) for m, v in zip(metrics, y, strict=True)}}
        )
        trial.mark_running(no_runner_required=True)
        trial.mark_completed()
        seen.append(y)
        scores.append(g(y))

    def pe_query() -> None:
        i, j = rng.choice(len(seen), 2, replace=False)
        ya, yb = (dict(zip(metrics, map(float, seen[k]), strict=True)) for k in (i, j))
        _add_pair(pe, ya, yb, lambda p: g([p[m] for m in metrics]))

    for _ in range(6):
        evaluate({f"x{i}": float(10 + 20 * rng.random()) for i in range(1, 5)})
    for _ in range(pe_initial):
        pe_query()
    spec = SurrogateSpec(metric_to_model_configs={PREF: [_model_config(model, 2)]})
    clock = _Clock()
    for _ in range(iters):
        if pe_step == "random":
            pe_query()
        refresh_pe()
        adapter = clock.adapter(
            lambda: TorchAdapter(
                experiment=bo,
                data=bo.lookup_data(),
                generator=BoTorchGenerator(botorch_acqf_class=qLogNoisyExpectedImprovement, surrogate_spec=spec),
                fit_tracking_metrics=False,
            )
        )
        gr = clock.generate(adapter, 1)
        evaluate(dict(gr.arms[0].parameters))
        if pe_step == "eubo":
            start = time.process_time()
            ya, yb = _eubo_zeta_pair(adapter, metrics)
            clock.gen += time.process_time() - start
            _add_pair(pe, ya, yb, lambda p: g([p[m] for m in metrics]))
    fitted = adapter.generator.surrogate._submodels[(PREF,)]
    return {
        "utility": max(scores),
        **_times(clock),
        "model": type(fitted).__name__,
        "outputscale": _outputscale(fitted),
    }


def _eubo_zeta_pair(adapter, metrics: list[str]) -> tuple[dict, dict]:
    """BOPE's preference-exploration step (EUBO-zeta, Lin et al. 2022): the pair of designs whose
    predicted outcomes maximise ``qExpectedUtilityOfBestOption(pref_model, outcome_model)``, the
    outcome model one fixed posterior sample of the outcome GPs (BoTorch's
    BOPE mode, as Ax's ``botorch_acqf_options={"pref_model": ...}`` builds it), optimised with Ax's
    default restarts and raw samples; returns the two outcome vectors (posterior means) shown to the
    decision maker. The models are those the adapter just fitted."""
    from botorch.acquisition.preference import qExpectedUtilityOfBestOption
    from botorch.models.deterministic import FixedSingleSampleModel
    from botorch.models.model import ModelList
    from botorch.optim import optimize_acqf

    models = adapter.generator.surrogate._submodels
    outcome_model = ModelList(*[models[(m,)] for m in metrics])
    # the BOPE tutorial's outcome model for EUBO-zeta: one fixed posterior sample (a deterministic model)
    sample = FixedSingleSampleModel(model=outcome_model)
    acqf = qExpectedUtilityOfBestOption(pref_model=models[(PREF,)], outcome_model=sample)
    bounds = torch.tensor([[10.0] * 4, [30.0] * 4], dtype=torch.float64)
    X, _ = optimize_acqf(acqf, bounds, q=2, num_restarts=20, raw_samples=1024)
    with torch.no_grad():
        Y = outcome_model.posterior(X).mean
    return tuple(dict(zip(metrics, map(float, y), strict=True)) for y in Y)  # type: ignore[return-value]


def _paired(a: np.ndarray, b: np.ndarray) -> dict:
    from scipy import stats

    diff = a - b
    out = {"mean_diff": float(diff.mean()), "t_p": float(stats.ttest_rel(a, b).pvalue)}
    out["wilcoxon_p"] = float(stats.wilcoxon(a, b).pvalue) if np.any(diff != 0) else 1.0
    # one-sided: is PreferenceGP worse (lower utility) than PairwiseGP?
    out["worse_one_sided_p"] = float(stats.ttest_rel(a, b, alternative="less").pvalue)
    return out


def _arrays(rows: list[dict], arms, key: str) -> dict:
    return {m: np.array([r[key] for r in sorted(rows, key=lambda r: r["seed"]) if r["arm"] == m]) for m in arms}


#: The paired comparisons summarised: the documented config and PreferenceGP with PairwiseGP's
#: kernel priors, each against PairwiseGP, and the two priors (item 4).
COMPARISONS = (
    ("PreferenceGP_pairwise_box", "PairwiseGP"),
    ("PreferenceGP", "PairwiseGP"),
    ("PreferenceGP_pairwise_priors", "PairwiseGP"),
    ("PreferenceGP", "PreferenceGP_pairwise_box"),
    ("PreferenceGP", "PreferenceGP_pairwise_priors"),
)


def summarize(rows: list[dict], loop: str) -> dict:
    """Paired comparisons (:data:`COMPARISONS`) over the seeds both arms of each finished."""
    out: dict = {"loop": loop, "comparisons": {}, "failed_runs": [r for r in rows if "error" in r]}
    rows = [r for r in rows if "error" not in r]
    for a, b in COMPARISONS:
        seeds = {r["seed"] for r in rows if r["arm"] == a} & {r["seed"] for r in rows if r["arm"] == b}
        pair = [r for r in rows if r["seed"] in seeds and r["arm"] in (a, b)]
        if len(seeds) < 2:
            continue
        by = _arrays(pair, (a, b), "utility")
        cpu = {k: _arrays(pair, (a, b), k) for k in ("cpu_s", "fit_cpu_s", "gen_cpu_s")}
        out["comparisons"][f"{a} vs {b}"] = {
            "seeds": sorted(seeds),
            "n_seeds": len(seeds),
            "iters": sorted({r["iters"] for r in pair}),
            "utility_mean": {m: float(v.mean()) for m, v in by.items()},
            "utility_se": {m: float(v.std(ddof=1) / np.sqrt(len(v))) for m, v in by.items()},
            "wins_first": int((by[a] > by[b]).sum()),
            "ties": int((by[a] == by[b]).sum()),
            "paired_utility": _paired(by[a], by[b]),
            "cpu_s_mean": {k: {m: float(v.mean()) for m, v in c.items()} for k, c in cpu.items()},
            "cpu_ratio_second_over_first": {k: float(c[b].sum() / c[a].sum()) for k, c in cpu.items()},
            "outputscale_median": {m: float(np.median(v)) for m, v in _arrays(pair, (a, b), "outputscale").items()},
            "load_average_range": [
                float(min(r["load_before"][0] for r in pair)),
                float(max(r["load_before"][0] for r in pair)),
            ],
        }
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loop", choices=("pbo", "bope"), required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)), help="seeds run in this process")
    parser.add_argument("--arms", nargs="+", default=list(ARMS[:2]), choices=ARMS)
    parser.add_argument("--iters", type=int, default=None, help="loop iterations (default: pbo 12, bope 8)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--pe", choices=("random", "eubo"), default="random", help="BOPE's PE step: a random pair, or EUBO-zeta"
    )
    parser.add_argument("--pe-initial", type=int, default=4, help="BOPE: comparisons before the loop")
    parser.add_argument("--tag", default="", help="suffix of the result files (bope_eubo, ...)")
    parser.add_argument("--summarize", action="store_true", help="only summarise the finished runs in *_rows.jsonl")
    args = parser.parse_args(argv)
    from tqdm import tqdm

    torch.set_num_threads(1)
    warnings.filterwarnings("ignore")
    iters = args.iters or (12 if args.loop == "pbo" else 8)
    run = run_pbo if args.loop == "pbo" else functools.partial(run_bope, pe_step=args.pe, pe_initial=args.pe_initial)
    stem = args.loop + args.tag
    args.out.mkdir(parents=True, exist_ok=True)
    partial = args.out / f"{stem}_rows.jsonl"  # one line per finished run, appended: a killed run keeps its seeds
    if not args.summarize:
        for arm in args.arms:  # warm-up, not recorded: the first fit in a process pays for lazy imports
            run(arm, 10_000, 1)
        for seed in tqdm(args.seeds, desc=f"ax {args.loop}"):
            k = seed % len(args.arms)  # the order rotates with the seed
            for arm in args.arms[k:] + args.arms[:k]:
                load = os.getloadavg()
                try:
                    res = run(arm, seed, iters)
                except Exception as err:  # a failed fit: recorded, and the other arms still run
                    res = {"error": f"{type(err).__name__}: {err}"[:300], "model": arm.split("_")[0]}
                if res["model"] != arm.split("_")[0]:
                    raise RuntimeError(f"{arm} requested but Ax fitted {res['model']}")
                row = {
                    "seed": seed,
                    "arm": arm,
                    "iters": iters,
                    **res,
                    "load_before": load,
                    "load_after": os.getloadavg(),
                }
                with open(partial, "a") as f:
                    f.write(json.dumps(row) + "\n")
    rows = [json.loads(line) for line in partial.read_text().splitlines() if line.strip()]
    summary = summarize(rows, args.loop)
    summary.update(
        cpu_count=os.cpu_count(),
        threads=1,
        pe_step=args.pe if args.loop == "bope" else None,
        pe_initial=args.pe_initial if args.loop == "bope" else None,
        rows=rows,
    )
    from torchpref.experiments.results import write_json

    root = Path(__file__).resolve().parents[2]
    write_json(
        args.out / f"{stem}.json",
        summary,
        measured="user",
        sources=[__file__, root / "torchpref" / "integrations" / "ax.py"],
    )
    with open(args.out / f"{stem}.csv", "w", newline="") as f:
        fields = ["seed", "arm", "model", "iters", "utility", "cpu_s", "fit_cpu_s", "gen_cpu_s", "outputscale"]
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(sorted(rows, key=lambda r: (r["seed"], r["arm"])))
    arms = COMPARISONS[0]
    main_pair = summary["comparisons"].get(f"{arms[0]} vs {arms[1]}")
    if main_pair:
        pair = [r for r in rows if r["seed"] in main_pair["seeds"]]
        _plot(_arrays(pair, arms, "utility"), _arrays(pair, arms, "cpu_s"), args.out / f"{stem}.png", args.loop)
    print(json.dumps({k: v["n_seeds"] for k, v in summary["comparisons"].items()}, indent=1))


def _plot(by, cpu, path: Path, loop: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, b = by
    labels = [a, b]
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.4))
    for ax, data, label in ((axes[0], by, "true utility of the recommendation"), (axes[1], cpu, "CPU s per loop")):
        for i in range(len(data[a])):
            ax.plot([1, 2], [data[a][i], data[b][i]], color="0.7", lw=0.8)
        ax.boxplot([data[a], data[b]])
        ax.set_xticks([1, 2], labels)
        ax.set_ylabel(label)
    fig.suptitle(f"Ax {loop.upper()} loop, {len(by[a])} seeds (paired)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
