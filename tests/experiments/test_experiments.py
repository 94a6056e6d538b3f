"""A tiny run of the wave experiment writes the documented files; the runner is generic."""

import json
from concurrent.futures import ThreadPoolExecutor

import pytest

from torchpref.cli import main
from torchpref.experiments.results import mean_sem, paired_tests
from torchpref.experiments.runner import run_trials
from torchpref.experiments.wave import STRATEGIES


def _square(x):
    return x * x


def test_run_trials_any_executor():
    with ThreadPoolExecutor(2) as ex:
        assert run_trials(_square, [(i,) for i in range(5)], executor=ex, progress=False) == [0, 1, 4, 9, 16]
    assert run_trials(_square, [(3,)], progress=False, workers=1) == [9]


def test_statistics():
    m, s = mean_sem([[1.0, 2.0], [3.0, 2.0]])
    assert m == [2.0, 2.0] and s[0] == pytest.approx(1.0) and s[1] == 0.0
    nan = float("nan")  # missing values: each point uses the trials that have one
    m, s = mean_sem([[1.0, nan, nan], [3.0, 2.0, nan], [5.0, 4.0, nan]])
    assert m == pytest.approx([3.0, 3.0, 0.0]) and s == pytest.approx([2 / 3**0.5, 1.0, 0.0])
    t = paired_tests([1.0, 2.0, 3.0, 4.5], [0.5, 1.0, 2.5, 3.0])
    assert t["mean_diff"] == pytest.approx(0.875) and t["wins"] == 4 and 0 < t["p_ttest"] < 0.05
    with pytest.raises(ValueError, match="3"):
        paired_tests([1.0, 2.0, 3.0], [1.0, 2.0])


def test_tiny_wave_run(tmp_path):
    assert (
        main(
            [
                "reproduce",
                "wave",
                "--trials",
                "2",
                "--queries",
                "3",
                "--seed",
                "1",
                "--out",
                str(tmp_path),
                "--workers",
                "1",
            ]
        )
        == 0
    )
    data = json.loads((tmp_path / "wave.json").read_text())
    assert data["trials"] == 2 and data["queries"] == 3
    assert set(data["strategies"]) == set(STRATEGIES)
    for v in data["strategies"].values():
        assert set(v) == {"wrms_mean", "wrms_sem", "tp_mean", "tp_sem"}
        assert all(len(x) == 4 for x in v.values())
    rows = (tmp_path / "wave.csv").read_text().splitlines()
    assert rows[0].startswith("strategy,queries") and len(rows) == 1 + 4 * len(STRATEGIES)
    for name in ("wave.png", "wave_effort.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((tmp_path / "wave_summary.json").read_text())
    assert "info per effort vs UCBC" in summary["paired_tests"]["queries"]


def test_wave_batched_run_equals_trial_by_trial():
    from concurrent.futures import ThreadPoolExecutor

    from torchpref.experiments.wave import run_wave_experiment

    kw = dict(trials=3, queries=4, seed=2, out=None, progress=False)
    one = run_wave_experiment(**kw, workers=1, batch_size=None)
    with ThreadPoolExecutor(2) as ex:  # chunks of 2 and 1 trials, any executor
        two = run_wave_experiment(**kw, executor=ex, batch_size=2)
    for s in STRATEGIES:
        for k in ("wrms_mean", "tp_mean"):
            assert one["strategies"][s][k] == pytest.approx(two["strategies"][s][k], abs=1e-9)
    assert one["summary"]["fraction_ratings"] == two["summary"]["fraction_ratings"]
    with pytest.raises(ValueError, match="batch_size"):
        run_wave_experiment(**kw, batch_size=0)


def test_registry_and_fixed_kernel():
    import torch
    from gpytorch.kernels import RBFKernel, ScaleKernel

    from torchpref.experiments.runner import STRATEGIES as ALL
    from torchpref.experiments.runner import make_model, make_selector
    from torchpref.models.kernels import fixed_rbf_kernel

    for name in ALL:
        assert callable(make_selector(name, m=3).select_batch)
    with pytest.raises(ValueError, match="no such"):
        make_selector("no such")
    X = torch.rand(7, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = ScaleKernel(RBFKernel())
    ref.base_kernel.lengthscale, ref.outputscale = 0.3, 0.5
    ref = ref.to(X)
    k = fixed_rbf_kernel(0.3, 0.5, X)
    assert torch.equal(k(X, X[:3]).to_dense(), ref(X, X[:3]).to_dense())  # the same to the bit
    assert torch.equal(k.forward(X, X, diag=True), ref.forward(X, X, diag=True))
    settings = {
        "lengthscale": 0.3,
        "outputscale": 0.5,
        "comparison_noise": 0.2,
        "rating_scale": 0.8,
        "rating_precision": 60.0,
    }
    model = make_model(X[:2], torch.tensor([[0, 1]]), settings)
    assert float(model.likelihood.rating.rating_precision) == pytest.approx(60.0)


def test_fixed_kernel_batch_of_values():
    import torch

    from torchpref.models.kernels import FixedRBFKernel

    X = torch.rand(3, 6, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ls, os_ = torch.tensor([0.1, 0.3, 1.0], dtype=torch.float64), torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)
    k = FixedRBFKernel(ls, os_)
    K, d = k.forward(X, X), k.forward(X, X.flip(1), diag=True)
    for b in range(3):
        one = FixedRBFKernel(ls[b], os_[b])
        torch.testing.assert_close(K[b], one.forward(X[b], X[b]), rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(d[b], one.forward(X[b], X[b].flip(0), diag=True), rtol=1e-12, atol=1e-14)
    assert k.forward(X[0], X[0]).shape == (3, 6, 6)  # one set of points, three kernels
