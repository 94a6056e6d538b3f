r"""pytest-benchmark: ``PreferenceGP`` against BoTorch's ``PairwiseGP`` on the same data.

Timings are recorded, not asserted (shared machines); the ratios with targets come from
``speed_pairwise.py``, which runs both libraries in one process. Run with::

    .venv/bin/python -m pytest benchmarks/ --benchmark-only

Each test is parametrised over the sizes in ``bench_common.SIZES`` and the two libraries; the
benchmark group is the task and size, so pytest-benchmark prints the two libraries side by side.
"""

from __future__ import annotations

import bench_common as bc
import pytest

LIBS = ["torchpref", "pairwisegp"]


def _size(data) -> str:
    X, C = data
    return f"n={X.shape[0]},p={C.shape[0]}"


@pytest.mark.parametrize("lib", LIBS)
def test_mode(benchmark, comparisons_data, lib):
    """Construction + Laplace mode at the initial hyperparameters."""
    X, C = comparisons_data
    benchmark.group = f"mode {_size(comparisons_data)}"
    fn = (lambda: bc.mode_torchpref(X, C)) if lib == "torchpref" else (lambda: bc.build_pairwisegp(X, C))
    model = benchmark.pedantic(fn, rounds=5, iterations=1, warmup_rounds=1)
    f = model.mode.f if lib == "torchpref" else model.utility
    assert f.shape == (X.shape[0],)


@pytest.mark.parametrize("lib", LIBS)
def test_fit(benchmark, comparisons_data, lib):
    """``fit_gpytorch_mll`` with the model's Laplace MLL, each round from the same initial values
    (the model is built, and its mode solved, outside the timing)."""
    X, C = comparisons_data
    benchmark.group = f"fit {_size(comparisons_data)}"
    if lib == "torchpref":
        setup = lambda: ((bc.mode_torchpref(X, C),), {})  # noqa: E731
        fit = bc.fit_torchpref
    else:
        setup = lambda: ((bc.build_pairwisegp(X, C),), {})  # noqa: E731
        fit = bc.fit_pairwisegp
    benchmark.pedantic(fit, setup=setup, rounds=3, iterations=1)
    model = setup()[0][0]
    fit(model)
    benchmark.extra_info.update(bc.hyperparameters(model))
    ev = bc.evidence_torchpref(model) if lib == "torchpref" else bc.evidence_pairwisegp(model)
    benchmark.extra_info["evidence"] = ev


@pytest.mark.parametrize("lib", LIBS)
def test_posterior(benchmark, comparisons_data, fitted_models, lib):
    r"""``posterior(X).mean`` and ``.variance`` on a ``1000 x 1 x d`` batch, model fitted and cached."""
    benchmark.group = f"posterior 1000x1x2 {_size(comparisons_data)}"
    Xq = bc.query_points()
    mean, var = benchmark.pedantic(bc.posterior_moments, args=(fitted_models[lib], Xq), rounds=3, iterations=1)
    assert mean.shape == (1000, 1, 1) and var.shape == (1000, 1, 1)


def test_mixed_mode(benchmark):
    """2,000 items, 2,000 comparisons and 1,000 ratings: construct + mode (target under 5 s)."""
    X, C, u, ri = bc.make_mixed()
    benchmark.group = f"mixed mode n={bc.MIXED_N}"

    def run():
        return bc.PreferenceGP(
            X, comparisons=C, ratings=u, rating_index=ri, covar_module=bc.make_kernel(), comparison_noise=0.1
        ).mode

    mode = benchmark.pedantic(run, rounds=3, iterations=1, warmup_rounds=1)
    benchmark.extra_info["newton_iterations"] = mode.iterations
    benchmark.extra_info["target_s"] = 5.0
    assert mode.converged
