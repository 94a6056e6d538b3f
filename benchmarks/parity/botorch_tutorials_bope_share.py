"""How much of ``bope``'s acquisition optimisations is the preference model (Amdahl's law for the
tutorial's wall-time target), for ``PairwiseGP`` and ``PreferenceGP`` in one run.

On one mid-loop state of ``botorch_tutorials_bope.py`` (an outcome ``SingleTaskGP`` on 8 Sobol
designs, a preference model fitted to 16 comparisons of 32 sampled outcomes), each acquisition
of the loop is optimised as the tutorial does, with the preference model's ``posterior`` and the
outcome model's one-sample forward timed (CPU time, forward passes only: the backward passes are
not split between the models):

* EUBO-zeta: ``AnalyticExpectedUtilityOfBestOption`` through ``FixedSingleSampleModel``;
* the learned objective: ``qSimpleRegret`` and ``qLogNEI`` through ``LearnedObjective``.

Writes ``results/botorch_tutorials_bope_share.json``.

Usage: ``nice -n 10 python benchmarks/parity/botorch_tutorials_bope_share.py [--repeats 4]``
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import botorch_tutorials_bope as bp
import torch
from botorch.acquisition import LearnedObjective
from botorch.acquisition.preference import AnalyticExpectedUtilityOfBestOption
from botorch.models.deterministic import FixedSingleSampleModel
from botorch.optim.optimize import optimize_acqf
from botorch_tutorials_common import MODELS, RESULTS, fit_preference_model, seed_all

from torchpref.experiments.results import write_json


class Timer:
    """CPU seconds spent in the wrapped callables, per name."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    def wrap(self, name: str, fn):
        def timed(*args, **kwargs):
            t0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[name] = self.seconds.get(name, 0.0) + time.process_time() - t0

        return timed


def eubo_share(pref, outcome, repeats: int) -> dict:
    """CPU per EUBO-zeta optimisation, and the part in each model's forward passes."""
    timer, total = Timer(), 0.0
    pref.posterior = timer.wrap("preference_posterior", pref.posterior)
    for s in range(repeats):
        torch.manual_seed(s)
        one = FixedSingleSampleModel(model=outcome)
        one.forward = timer.wrap("outcome_sample", one.forward)
        acqf = AnalyticExpectedUtilityOfBestOption(pref_model=pref, outcome_model=one)
        t0 = time.process_time()
        optimize_acqf(
            acqf,
            q=2,
            bounds=bp.PROBLEM.bounds,
            num_restarts=bp.NUM_RESTARTS,
            raw_samples=bp.RAW_SAMPLES,
            options={"batch_limit": bp.BATCH_LIMIT},
        )
        total += time.process_time() - t0
    del pref.posterior  # the instance attribute: back to the class's method
    return {"cpu_s": total / repeats, **{k: v / repeats for k, v in timer.seconds.items()}}


def learned_objective_share(pref, outcome, X_baseline, repeats: int) -> dict:
    """CPU per ``qSimpleRegret`` / ``qLogNEI`` optimisation through ``LearnedObjective``, and the
    part in the preference model's forward passes."""
    timer, total = Timer(), 0.0
    pref.posterior = timer.wrap("preference_posterior", pref.posterior)
    for s in range(repeats):
        torch.manual_seed(s)
        t0 = time.process_time()
        bp.candidates(outcome, LearnedObjective(pref_model=pref), "qNEI" if s % 2 else "posterior_mean", X_baseline)
        total += time.process_time() - t0
    del pref.posterior
    return {"cpu_s": total / repeats, **{k: v / repeats for k, v in timer.seconds.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")  # BoTorch's fitting chatter; benchmark output only
    seed_all(1)
    X = bp.sobol_designs(bp.N_INIT)
    outcome = bp.outcome_model_for(X, bp.PROBLEM(X))
    Y = outcome.posterior(bp.sobol_designs(32)).sample().squeeze(0)
    comps = bp.pair_comparisons(bp.utility(Y))
    out = {}
    for name in MODELS:
        pref = fit_preference_model(name, Y, comps)
        out[name] = {
            "eubo_zeta": eubo_share(pref, outcome, args.repeats),
            "learned_objective": learned_objective_share(pref, outcome, X, args.repeats),
        }
        for part in out[name].values():
            part["preference_share"] = part["preference_posterior"] / part["cpu_s"]
        print(name, json.dumps(out[name]))
    write_json(
        (RESULTS / "botorch_tutorials_bope_share.json"), out, measured="harness: the tutorial rewritten as a script"
    )


if __name__ == "__main__":
    main()
