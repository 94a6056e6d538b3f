"""Ax's preferential-BO (PBO) and BOPE loops with PreferenceGP and with PairwiseGP (issue 21).

Both loops are built as Ax's own tests build them (ax/adapter/tests/test_torch_adapter.py:
``test_pairwise_preference_generator`` for PBO, ``test_fitting_auxiliary_experiment_dataset``
for BOPE): a ``TorchAdapter`` over an ``Experiment`` whose preference data are two-arm batch
trials of the ``pairwise_pref_query`` metric, the model named in
``SurrogateSpec(metric_to_model_configs={pairwise_pref_query: [ModelConfig(...)]})`` (with
``Normalize``), and the only line that differs between the two arms of the comparison is the
``ModelConfig``'s model and MLL class.

* PBO: ``d = 3`` parameters in Ax's test bounds ``[10, 30]``; a hidden utility
  ``-||(x - 10) / 20 - c||^2`` (``c`` drawn per seed); 4 random pairs, then ``--iters`` pairs
  chosen by ``qExpectedUtilityOfBestOption`` (Ax's ``adapter.gen(n=2)``); the recommendation is
  the compared arm of highest posterior mean, scored by its true utility (0 is best).
* BOPE: 4 parameters, 2 outcomes ``f(x)``, a decision maker's utility ``g(y)``; the BO
  experiment carries the PE experiment as Ax's ``PE_EXPERIMENT`` auxiliary experiment and a
  ``PreferenceOptimizationConfig``, so Ax builds ``LearnedObjective(preference model)`` and
  generates with ``qLogNoisyExpectedImprovement`` under it. Each iteration adds one preference
  query (two observed outcome vectors drawn at random, compared by ``g``: not Ax's EUBO-zeta
  PE step) and one BO candidate; the outcome is ``g(f(x))`` of the best arm found.

CPU time is process time (``time.process_time``) of each whole loop, Ax included, one thread;
the two models run interleaved per seed (the order alternating), so machine load affects both
alike. Results: ``benchmarks/results/ax/{pbo,bope}.json``, ``.csv`` and ``.png``.

    python benchmarks/parity/ax_loops.py --loop pbo --seeds 10
    python benchmarks/parity/ax_loops.py --loop bope --seeds 10
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
import warnings
from pathlib import Path

import numpy as np
import torch

RESULTS = Path(__file__).resolve().parents[1] / "results" / "ax"
PREF = "pairwise_pref_query"


def _model_config(model: str, d: int):
    from ax.generators.torch.botorch_modular.surrogate import ModelConfig
    from botorch.models.transforms.input import Normalize

    if model == "PreferenceGP":
        import torchpref.integrations.ax  # noqa: F401  (registers PreferenceGP with Ax)
        from torchpref import LaplaceMarginalLogLikelihood as mll
        from torchpref import PreferenceGP as cls
    else:
        from botorch.models.pairwise_gp import PairwiseGP as cls
        from botorch.models.pairwise_gp import PairwiseLaplaceMarginalLogLikelihood as mll
    return ModelConfig(
        botorch_model_class=cls,
        mll_class=mll,
        input_transform_classes=[Normalize],
        input_transform_options={"Normalize": {"d": d}},
    )


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
    start = time.process_time()
    for _ in range(iters):
        adapter = TorchAdapter(
            experiment=exp,
            generator=BoTorchGenerator(botorch_acqf_class=qExpectedUtilityOfBestOption, surrogate_spec=spec),
            optimization_config=opt,
            fit_tracking_metrics=False,
        )
        gr = adapter.gen(n=2)
        a, b = (arm.parameters for arm in gr.arms)
        _add_pair(exp, a, b, utility)
    adapter = TorchAdapter(
        experiment=exp,
        generator=BoTorchGenerator(botorch_acqf_class=qExpectedUtilityOfBestOption, surrogate_spec=spec),
        optimization_config=opt,
        fit_tracking_metrics=False,
    )
    x, fitted = _recommended(adapter.generator.surrogate)
    cpu = time.process_time() - start
    return {"utility": utility(dict(zip(names, x.tolist(), strict=True))), "cpu_s": cpu, "model": type(fitted).__name__}


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


def run_bope(model: str, seed: int, iters: int) -> dict:
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
    for _ in range(4):
        pe_query()
    spec = SurrogateSpec(metric_to_model_configs={PREF: [_model_config(model, 2)]})
    start = time.process_time()
    for _ in range(iters):
        pe_query()
        refresh_pe()
        adapter = TorchAdapter(
            experiment=bo,
            data=bo.lookup_data(),
            generator=BoTorchGenerator(botorch_acqf_class=qLogNoisyExpectedImprovement, surrogate_spec=spec),
            fit_tracking_metrics=False,
        )
        gr = adapter.gen(n=1)
        evaluate(dict(gr.arms[0].parameters))
    fitted = adapter.generator.surrogate._submodels[(PREF,)]
    cpu = time.process_time() - start
    return {"utility": max(scores), "cpu_s": cpu, "model": type(fitted).__name__}


def _paired(a: np.ndarray, b: np.ndarray) -> dict:
    from scipy import stats

    diff = a - b
    out = {"mean_diff": float(diff.mean()), "t_p": float(stats.ttest_rel(a, b).pvalue)}
    out["wilcoxon_p"] = float(stats.wilcoxon(a, b).pvalue) if np.any(diff != 0) else 1.0
    # one-sided: is PreferenceGP worse (lower utility) than PairwiseGP?
    out["worse_one_sided_p"] = float(stats.ttest_rel(a, b, alternative="less").pvalue)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loop", choices=("pbo", "bope"), required=True)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--iters", type=int, default=None, help="loop iterations (default: pbo 12, bope 8)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--summarize", action="store_true", help="only summarise the finished runs in *_rows.jsonl")
    args = parser.parse_args(argv)
    from tqdm import tqdm

    torch.set_num_threads(1)
    warnings.filterwarnings("ignore")
    iters = args.iters or (12 if args.loop == "pbo" else 8)
    run = run_pbo if args.loop == "pbo" else run_bope
    args.out.mkdir(parents=True, exist_ok=True)
    partial = args.out / f"{args.loop}_rows.jsonl"  # one line per finished run: a killed run keeps its seeds
    if not args.summarize:
        partial.write_text("")
        for seed in tqdm(range(args.seeds), desc=f"ax {args.loop}"):
            order = ("PreferenceGP", "PairwiseGP") if seed % 2 == 0 else ("PairwiseGP", "PreferenceGP")
            for model in order:
                res = run(model, seed, iters)
                if res["model"] != model:
                    raise RuntimeError(f"{model} requested but Ax fitted {res['model']}")
                with open(partial, "a") as f:
                    f.write(json.dumps({"seed": seed, "arm": model, "iters": iters, **res}) + "\n")
    rows = [json.loads(line) for line in partial.read_text().splitlines() if line.strip()]
    done = {r["seed"] for r in rows if r["arm"] == "PreferenceGP"} & {
        r["seed"] for r in rows if r["arm"] == "PairwiseGP"
    }
    rows = [r for r in rows if r["seed"] in done]  # complete pairs only
    iters = rows[0]["iters"] if rows else iters
    by = {
        m: np.array([r["utility"] for r in sorted(rows, key=lambda r: r["seed"]) if r["arm"] == m])
        for m in ("PreferenceGP", "PairwiseGP")
    }
    cpu = {m: np.array([r["cpu_s"] for r in sorted(rows, key=lambda r: r["seed"]) if r["arm"] == m]) for m in by}
    summary = {
        "loop": args.loop,
        "seeds": len(done),
        "iters": iters,
        "load_average": os.getloadavg(),
        "utility_mean": {m: float(v.mean()) for m, v in by.items()},
        "utility_se": {m: float(v.std(ddof=1) / np.sqrt(len(v))) for m, v in by.items()},
        "cpu_s_mean": {m: float(v.mean()) for m, v in cpu.items()},
        "cpu_ratio_pairwise_over_preference": float(cpu["PairwiseGP"].sum() / cpu["PreferenceGP"].sum()),
        "paired_utility": _paired(by["PreferenceGP"], by["PairwiseGP"]),
        "rows": rows,
    }
    (args.out / f"{args.loop}.json").write_text(json.dumps(summary, indent=1))
    with open(args.out / f"{args.loop}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["seed", "arm", "model", "iters", "utility", "cpu_s"])
        w.writeheader()
        w.writerows(rows)
    _plot(by, cpu, args.out / f"{args.loop}.png", args.loop)
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=1))


def _plot(by, cpu, path: Path, loop: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
    for ax, data, label in ((axes[0], by, "true utility of the recommendation"), (axes[1], cpu, "CPU s per loop")):
        for i in range(len(data["PreferenceGP"])):
            ax.plot([1, 2], [data["PreferenceGP"][i], data["PairwiseGP"][i]], color="0.7", lw=0.8)
        ax.boxplot([data["PreferenceGP"], data["PairwiseGP"]])
        ax.set_xticks([1, 2], ["PreferenceGP", "PairwiseGP"])
        ax.set_ylabel(label)
    fig.suptitle(f"Ax {loop.upper()} loop, {len(by['PreferenceGP'])} seeds (paired)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
