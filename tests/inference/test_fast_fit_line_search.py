"""The compiled fit's line search (issue 52): the fit that ended in ``LINE_SEARCH_FAILED`` and was
refitted from scratch by BoTorch's routine (200 items, 400 comparisons, ``torch.set_default_dtype``
float64 as in BoTorch's tutorials) now ends on the compiled path, converged, under either default
dtype, at the evidence SciPy's L-BFGS-B reaches on the same loss; and the safeguarded cubic step
stays inside its bracket. The sweep over sizes, seeds and densities is
``benchmarks/speed/speed_line_search.py``."""

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torchpref import LaplaceMarginalLogLikelihood
from torchpref.inference import fast_path, fast_types

needs_numba = pytest.mark.skipif(not fast_path.available(), reason="numba is not installed (the fast extra)")
BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "speed"


@pytest.fixture(scope="module")
def bench_common():
    sys.path.insert(0, str(BENCH))
    try:
        import bench_common
    finally:
        sys.path.remove(str(BENCH))
    return bench_common


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_issue_s_fit_stays_compiled_and_converges(bench_common, dtype):
    """``make_comparisons(200, 400)`` through ``mode_torchpref`` / ``fit_torchpref`` under either
    default dtype: the compiled solver fits (no fallback), converged, in a few dozen evaluations at
    most, to the optimum SciPy's L-BFGS-B finds on the compiled loss (1e-6)."""
    from scipy.optimize import minimize

    from torchpref.models import fast_fit

    before = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        with fast_path.fast_path("on"):
            assert fast_path.warm_up() is not None, fast_path.status()
            X, C = bench_common.make_comparisons(200, 400)
            model = bench_common.mode_torchpref(X, C)
            problem = fast_fit.compiled_problem(LaplaceMarginalLogLikelihood(model))
            with warnings.catch_warnings():
                warnings.simplefilter("error", fast_path.FastPathWarning)
                bench_common.fit_torchpref(model)
    finally:
        torch.set_default_dtype(before)
    report = model.last_fit
    assert report.solver == "compiled" and report.status == "ok", report
    assert report.evaluations <= 40 and model.mode.solver == "compiled"
    # SciPy's L-BFGS-B on the same compiled loss, from the same start
    state = fast_types.fit_state(problem.f0, problem.answers.first.shape[0])

    def loss(x):
        out = fast_path.call(
            "fit_loss",
            fast_types.floats(x),
            problem.X,
            problem.answers,
            problem.spec,
            state,
            problem.tol,
            problem.max_iter,
        )
        assert out.status == fast_types.OK
        return out.loss, out.grad

    x0 = np.concatenate([t.detach().reshape(-1).numpy() for t in problem.params.values()])
    with fast_path.fast_path("on"):
        scipy_fit = minimize(loss, x0, jac=True, method="L-BFGS-B")
    ours = -bench_common.evidence_torchpref(model)
    assert abs(ours - scipy_fit.fun) <= 1e-6 * abs(scipy_fit.fun), (ours, scipy_fit.fun)


@needs_numba
def test_the_cubic_step_is_safeguarded_inside_its_bracket():
    """The zoom's trial step: the cubic's minimiser where it lies well inside the bracket (exact for
    a cubic), else clipped to the middle 80% of it; the midpoint where a value is not finite."""
    from torchpref.inference._compiled_fit import cubic_step

    step = cubic_step.py_func

    def phi(t):  # a cubic with its minimiser at t = 0.4 on [0, 1]
        return (t - 0.4) ** 2 * (t + 1.0), 2 * (t - 0.4) * (t + 1.0) + (t - 0.4) ** 2

    (f0, g0), (f1, g1) = phi(0.0), phi(1.0)
    assert math.isclose(step(0.0, f0, g0, 1.0, f1, g1), 0.4, rel_tol=1e-12)
    assert math.isclose(step(1.0, f1, g1, 0.0, f0, g0), 0.4, rel_tol=1e-12)  # a bracket given backwards
    (fa, ga), (fb, gb) = phi(0.38), phi(1.0)  # the minimiser at 0.4: closer than 10% to the end 0.38
    assert math.isclose(step(0.38, fa, ga, 1.0, fb, gb), 0.38 + 0.1 * 0.62, rel_tol=1e-12)
    assert step(0.0, 1.0, -1.0, 2.0, math.inf, math.inf) == 1.0
    assert step(0.0, 1.0, -1.0, 2.0, 0.5, math.nan) == 1.0
