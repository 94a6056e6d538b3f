r"""The paper's Figs. 4-5: a 1-D utility, five ratings and five comparisons, and the posterior.

    python -m torchpref.demo [--out DIR] [--seed S]

writes ``DIR/demo_fig5.png`` (left: latent utility, posterior mean +- 1 sd and the data;
centre: the predictive density of a rating over x (eq. 11); right: the predictive probability
that x_0 is preferred to x_1 for all pairs) and ``DIR/demo_fig5.json`` (the fitted numbers;
rounded to 6 decimals and without timings, so that a rerun writes the same file; the timings
are printed only). ``DIR`` is ``torchpref-results/demo`` by default (git-ignored, as the
experiments' runs are); ``--out benchmarks/results`` rewrites the copy the README shows.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref.cli import seconds_since_start
from torchpref.models.preference_gp import PreferenceGP
from torchpref.simulation.users import SimulatedUser


def true_utility(X: torch.Tensor) -> torch.Tensor:
    """The 1-D utility of the demo (``n x 1`` -> ``n``): two bumps of different heights."""
    x = X[..., 0]
    return 1.2 * torch.exp(-((x - 0.25) ** 2) / 0.01) + 1.8 * torch.exp(-((x - 0.7) ** 2) / 0.02) - 0.6


def fit_demo(seed: int = 0, num_ratings: int = 5, num_comparisons: int = 5) -> tuple[PreferenceGP, dict]:
    """Draw the paper's Fig. 4 data (sigma_B = 1, nu = 80, sigma_R = 0.1) and build the model."""
    g = torch.Generator().manual_seed(seed)
    user = SimulatedUser(true_utility, comparison_noise=0.1, rating_scale=1.0, rating_precision=80.0, generator=g)
    X_rate = torch.rand(num_ratings, 1, generator=g, dtype=torch.float64)
    ratings = torch.tensor([user.rate(x) for x in X_rate], dtype=torch.float64)
    pairs = torch.rand(num_comparisons, 2, 1, generator=g, dtype=torch.float64)
    X = torch.cat([X_rate, pairs.reshape(-1, 1)])
    comps = []
    for k in range(num_comparisons):
        i, j = num_ratings + 2 * k, num_ratings + 2 * k + 1
        c = user.choose(X[[i, j]])
        comps.append([i, j] if c == 0 else [j, i])
    kernel = ScaleKernel(RBFKernel())
    kernel.base_kernel.lengthscale = 0.1
    kernel.outputscale = 1.0
    model = PreferenceGP(
        X,
        comparisons=torch.tensor(comps),
        ratings=ratings,
        rating_index=torch.arange(num_ratings),
        covar_module=kernel,
        comparison_noise=0.1,
        rating_scale=1.0,
        rating_precision=80.0,
    )
    return model, {"X": X.squeeze(-1).tolist(), "ratings": ratings.tolist(), "comparisons": comps}


def plot_demo(model: PreferenceGP, path: Path) -> None:
    """Figs. 4-5 of the fitted ``model`` (posterior, rating density, preference probability), written to ``path``."""
    from torchpref.extras import require

    matplotlib = require("matplotlib", "the demo's figure")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = torch.linspace(0, 1, 201, dtype=torch.float64).unsqueeze(-1)
    with torch.no_grad():
        post = model.posterior(xs.unsqueeze(-2))
        mean, sd = post.mean.reshape(-1), post.variance.reshape(-1).sqrt()
        u = torch.linspace(0.005, 0.995, 100, dtype=torch.float64)
        dens = model.rating_likelihood.predictive_log_density(u.unsqueeze(-1), mean, sd**2).exp()
        pa = model.preference_probability(
            xs.unsqueeze(1).expand(-1, 201, -1).reshape(-1, 1), xs.unsqueeze(0).expand(201, -1, -1).reshape(-1, 1)
        ).reshape(201, 201)
    X, C = model.train_X.squeeze(-1), model.comparisons
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.8))
    ax[0].plot(xs, true_utility(xs), "k--", label="true f")
    ax[0].plot(xs, mean, "C0", label="posterior mean")
    ax[0].fill_between(xs.squeeze(-1), mean - sd, mean + sd, color="C0", alpha=0.25, label=r"$\pm 1\sigma$")
    f_hat = model.mode.f
    ri = model.rating_index
    ax[0].plot(X[ri], f_hat[ri], "x", color="C3", ms=9, mew=2, label="rated items (mode)")
    for i, j in C.tolist():
        ax[0].plot([X[i], X[j]], [f_hat[i], f_hat[j]], "-", color="C1", lw=1.5)
        ax[0].plot(X[i], f_hat[i], "o", color="C1", ms=6)
    ax[0].plot([], [], "-o", color="C1", label="comparison (dot: preferred)")
    ax[0].set(xlabel="x", ylabel="latent utility f", title="Posterior of f (Fig. 5, left)")
    # the legend below the axes: inside it covered rated points
    ax[0].legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3, frameon=False)
    im = ax[1].imshow(dens.T if dens.shape[0] == 201 else dens, origin="lower", aspect="auto", extent=[0, 1, 0, 1])
    ax[1].plot(X[ri], model.ratings, "wx", ms=8, mew=2)
    ax[1].set(xlabel="x", ylabel="rating u", title="Predictive density of a rating (eq. 11)")
    fig.colorbar(im, ax=ax[1], label="predictive density of u")
    im2 = ax[2].imshow(pa.T, origin="lower", extent=[0, 1, 0, 1], vmin=0, vmax=1, cmap="RdBu_r")
    ax[2].set(xlabel=r"$x_0$", ylabel=r"$x_1$", title=r"$P(x_0 \succ x_1)$ (eq. 11)")
    fig.colorbar(im2, ax=ax[2], label=r"$P(x_0 \succ x_1)$")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Fit the demo model and write its figure and summary to ``--out``; return the exit status."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="torchpref-results/demo")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    from torchpref.extras import missing

    if (line := missing(["matplotlib"], "python -m torchpref.demo")) is not None:
        print(line, file=sys.stderr)
        return 3
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print("Fitting 5 ratings + 5 comparisons of a 1-D utility (Fig. 4) ...", flush=True)
    t0 = time.perf_counter()
    model, data = fit_demo(args.seed)
    mode = model.mode
    elapsed = time.perf_counter() - t0
    with torch.no_grad():
        evidence = float(model.log_marginal_likelihood())
    print(f"  fitted in {elapsed:.2f} s ({mode.iterations} Newton steps), log evidence {evidence:.3f}", flush=True)
    print(
        "Drawing Fig. 5: the posterior, the predictive density of a rating (eq. 11) on a 201 x 100 grid, "
        "and P(x0 preferred to x1) ...",
        flush=True,
    )
    t1 = time.perf_counter()
    plot_demo(model, out / "demo_fig5.png")
    plotted = time.perf_counter() - t1
    summary = {
        **data,
        "mode": [round(v, 6) for v in mode.f.tolist()],
        "newton_iterations": mode.iterations,
        "log_evidence": round(evidence, 6),
    }
    (out / "demo_fig5.json").write_text(json.dumps(summary, indent=1))
    print(f"  drawn in {plotted:.1f} s; wrote {out / 'demo_fig5.png'} and {out / 'demo_fig5.json'}")
    print(f"Total wall time {seconds_since_start():.1f} s, start-up (Python, torch) included.")
    assert math.isfinite(evidence)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
