"""A small version of the user-family suite: files, paired verdicts, learned hyperparameters."""

import json
import math

import pytest
import torch

from torchpref.cli import main
from torchpref.experiments import suite
from torchpref.experiments.families import FAMILIES, setup


def test_families_span_dimensions_and_styles():
    dims = {f.dim for f in FAMILIES.values()}
    assert len(FAMILIES) >= 8 and dims == set(range(1, 7))
    assert any(f.likert for f in FAMILIES.values()) and any(f.pool for f in FAMILIES.values())
    for f in FAMILIES.values():
        s = setup(f, 3)
        assert s.eval_X.shape[-1] == f.dim and torch.isfinite(s.f_true).all()
        assert ((s.u_true >= 0) & (s.u_true <= 1)).all()
        r = s.user.rate(s.x0[0])
        assert 0 < r < 1
        if f.likert:
            assert round(5 * r - 0.5, 9) == round(5 * r - 0.5)  # a level's bin centre


def test_learned_kernel_is_the_grid_map():
    """learn_kernel's choice maximises evidence + prior, checked against one model per grid value."""
    from torchpref.experiments.runner import make_model

    fam = FAMILIES["narrow-peak"]
    model = suite._start_model(fam, "learned", [setup(fam, s).x0 for s in (1, 2)], [0, 1])
    g = torch.Generator().manual_seed(0)
    for b in range(2):
        X = torch.rand(6, 2, generator=g, dtype=torch.float64)
        model.add_observations(
            b,
            X,
            comparisons=torch.tensor([[0, 1], [2, 3], [4, 5]]),
            ratings=torch.tensor([0.8, 0.3]),
            rating_index=torch.tensor([0, 3]),
        )
    best = suite.learn_kernel(model, fam.dim)
    ls, os_, prior = suite._grid(fam.dim)
    for b in range(2):
        d = model.data(b)
        scores = []
        for i in range(ls.numel()):
            settings = {
                "lengthscale": float(ls[i]),
                "outputscale": float(os_[i]),
                "comparison_noise": 0.1,
                "rating_scale": 0.8,
                "rating_precision": 20.0,
            }
            m = make_model(d.train_X, d.comparisons, settings)
            m.add_observations(ratings=d.ratings, rating_index=d.rating_index)
            m.covar_module.lengthscale, m.covar_module.outputscale = ls[i], os_[i]  # exactly the grid's values
            with torch.no_grad():
                scores.append(float(m.log_marginal_likelihood()) + float(prior[i]))
        assert int(best[b]) == max(range(len(scores)), key=scores.__getitem__)
        assert float(model.covar_module.lengthscale.reshape(-1)[b]) == pytest.approx(float(ls[best[b]]))


def test_small_suite_run(tmp_path):
    argv = [
        "reproduce",
        "suite",
        "--families",
        "waves",
        "hartmann3",
        "--trials",
        "3",
        "--queries",
        "4",
        "--seed",
        "1",
        "--out",
        str(tmp_path),
        "--workers",
        "1",
    ]
    assert main(argv) == 0
    curves = json.loads((tmp_path / "suite.json").read_text())
    assert set(curves) == {"waves/fixed", "waves/learned", "hartmann3/fixed", "hartmann3/learned"}
    for cv in curves.values():
        for s in suite.STRATEGIES:
            assert len(cv["queries"][s]["regret_mean"]) == 5
            assert all(0 <= v <= 15 for v in cv["queries"][s]["tp_mean"])
    summary = json.loads((tmp_path / "suite_summary.json").read_text())
    v = summary["verdicts"]["waves/fixed"]["queries 4"]
    for m in ("wrms", "tp", "regret"):
        assert v[m]["status"][v[m]["best"]] == "best"
        assert set(v[m]["status"].values()) <= {"best", "tied", "worse"}
    rows = (tmp_path / "suite.csv").read_text().splitlines()
    assert rows[0].startswith("family,condition,axis,x,strategy,wrms_mean")
    for c in ("fixed", "learned"):
        assert (tmp_path / f"suite_{c}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not math.isnan(summary["wall_time_s"])


def test_suite_on_a_dask_cluster():
    """The suite on a ``dask.distributed`` local cluster gives what the local run gives."""
    distributed = pytest.importorskip("distributed")
    kw = dict(
        families=["waves", "hartmann3"],
        trials=2,
        queries=3,
        seed=5,
        out=None,
        progress=False,
        conditions=("fixed",),
        strategies=["UCBC", "info per effort"],
    )
    local = suite.run_suite(**kw, workers=1)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        with distributed.Client(cluster) as client:
            remote = suite.run_suite(**kw, executor=client.get_executor())
    for key, cv in local["summary"]["curves"].items():
        for s in kw["strategies"]:
            for m in ("wrms_mean", "tp_mean", "regret_mean"):
                assert remote["summary"]["curves"][key]["queries"][s][m] == pytest.approx(cv["queries"][s][m], abs=1e-9)


def test_suite_strategies_option(tmp_path):
    """``--strategies`` runs exactly the strategies named, any of the registry's (one outside the
    default set among them); an unknown name is refused before anything runs."""
    assert "top & level info" not in suite.STRATEGIES
    argv = [
        "reproduce",
        "suite",
        "--families",
        "waves",
        "--strategies",
        "top & level info",
        "UCBC",
        "--trials",
        "2",
        "--queries",
        "2",
        "--seed",
        "3",
        "--out",
        str(tmp_path),
        "--workers",
        "1",
    ]
    assert main(argv) == 0
    curves = json.loads((tmp_path / "suite.json").read_text())
    assert set(curves["waves/fixed"]["queries"]) == {"top & level info", "UCBC"}
    bad = tmp_path / "bad"
    assert main(argv[:4] + ["--strategies", "nope"] + argv[7:-3] + [str(bad), "--workers", "1"]) != 0
    assert not (bad / "suite.json").exists()
