"""``python -m torchpref.demo`` (``make demo``): its figure, its progress lines, and the
predictive density of a rating (eq. 11) on its grid, which must not depend on the batch."""

import json

import torch

from torchpref.demo import fit_demo, main


def test_demo_writes_its_files_and_reports_progress(tmp_path, capsys):
    assert main(["--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "Fitting" in out and "Drawing Fig. 5" in out and "start-up (Python, torch) included" in out
    assert (tmp_path / "demo_fig5.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "demo_fig5.json").read_text())["newton_iterations"] >= 1


def test_demo_json_is_the_same_on_a_rerun(tmp_path):
    """A rerun writes the same ``demo_fig5.json`` (no timings in it), so the committed copy in
    benchmarks/results changes only when the fitted numbers do."""
    first = main(["--out", str(tmp_path / "a")]), (tmp_path / "a" / "demo_fig5.json").read_bytes()
    second = main(["--out", str(tmp_path / "b")]), (tmp_path / "b" / "demo_fig5.json").read_bytes()
    assert first == second


def test_predictive_density_on_the_demo_grid_is_elementwise():
    """Each element's adaptive quadrature stops on its own (the work shrinks with the unfinished
    elements): the whole 100 x 201 grid at once equals each element computed alone."""
    model, _ = fit_demo(0)
    xs = torch.linspace(0, 1, 201, dtype=torch.float64).unsqueeze(-1)
    with torch.no_grad():
        post = model.posterior(xs.unsqueeze(-2))
        mean, var = post.mean.reshape(-1), post.variance.reshape(-1)
        u = torch.linspace(0.005, 0.995, 100, dtype=torch.float64)
        lik = model.rating_likelihood
        grid = lik.predictive_log_density(u.unsqueeze(-1), mean, var)
        assert grid.shape == (100, 201) and torch.isfinite(grid).all()
        g = torch.Generator().manual_seed(0)
        for i, j in zip(
            torch.randint(100, (25,), generator=g).tolist() + [0, 99],
            torch.randint(201, (25,), generator=g).tolist() + [0, 200],
        ):
            alone = lik.predictive_log_density(u[i], mean[j], var[j])
            torch.testing.assert_close(grid[i, j], alone, rtol=0, atol=1e-12)
