"""Ties and ordinal levels in PreferenceGP: the Laplace mode against SciPy on the log posterior,
the evidence gradient (kernel, tie threshold, cut points) against finite differences, fitting,
predictives and bad input."""

import math

import numpy as np
import pytest
import torch
from botorch.fit import fit_gpytorch_mll
from gpytorch.kernels import RBFKernel, ScaleKernel
from scipy import optimize, special, stats

from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP
from torchpref.testing import assert_evidence_gradient, rand, random_comparisons

SQRT2 = math.sqrt(2.0)


def kernel(ls: float, os_: float, d: int) -> ScaleKernel:
    k = ScaleKernel(RBFKernel(ard_num_dims=d)).to(torch.float64)
    k.base_kernel.lengthscale = torch.full((d,), ls, dtype=torch.float64)
    k.outputscale = torch.tensor(os_, dtype=torch.float64)
    return k


def build(kind: str, seed: int = 0, learn: bool = False, n: int = 10, d: int = 2, offered: bool = False):
    """Comparisons, ties and either Beta ratings or 5-level ratings on ``n`` random items."""
    g = torch.Generator().manual_seed(seed)
    X = rand(n, d, generator=g)
    C = random_comparisons(n, 6, g)
    ties = random_comparisons(n, 4, g)
    ri = torch.randperm(n, generator=g)[:6]
    if kind == "levels":
        r = torch.tensor([1, 2, 3, 5, 4, 2], dtype=torch.float64)
        model = PreferenceGP(
            X,
            C,
            r,
            ri,
            kernel(0.4, 1.3, d),
            ties=ties,
            rating_levels=5,
            tie_threshold=0.15,
            learn_likelihood=learn,
            comparison_noise=0.3,
            ties_offered=offered,
        )
    else:
        r = rand(6, generator=g, low=0.1, high=0.9)
        model = PreferenceGP(
            X,
            C,
            r,
            ri,
            kernel(0.4, 1.3, d),
            ties=ties,
            tie_threshold=0.15,
            learn_likelihood=learn,
            comparison_noise=0.3,
            ties_offered=offered,
        )
    return model


def scipy_log_posterior(model):
    """``log p(Y | f)`` and its gradient, with SciPy's normal CDF and density only (comparisons,
    ties and levels)."""
    C, T, u, ri = (model.comparisons.numpy(), model.ties.numpy(), model.ratings.numpy(), model.rating_index.numpy())
    s = SQRT2 * float(model.likelihood.comparison.comparison_noise)
    tau = float(model.likelihood.tie.tie_threshold)
    rating = model.likelihood.rating
    c = np.concatenate([[-np.inf], rating.cut_points.detach().numpy(), [np.inf]])
    k = u.astype(int)
    sig = float(rating.level_noise)
    N = stats.norm
    shift = tau if model.ties_offered else 0.0  # strict answers: Phi((eta - tau) / s) when ties were offered

    def interval(a, b):  # Phi(a) - Phi(b), a > b, without 1 - 1 in the upper tail
        return np.where(b > 0, N.sf(b) - N.sf(a), N.cdf(a) - N.cdf(b))

    def value(f):
        d = f[T[:, 0]] - f[T[:, 1]]
        return (
            special.log_ndtr((f[C[:, 0]] - f[C[:, 1]] - shift) / s).sum()
            + np.log(interval((tau - d) / s, (-tau - d) / s)).sum()
            + np.log(interval((c[k] - f[ri]) / sig, (c[k - 1] - f[ri]) / sig)).sum()
        )

    def grad(f):
        g = np.zeros_like(f)
        z = (f[C[:, 0]] - f[C[:, 1]] - shift) / s
        r = N.pdf(z) / N.cdf(z) / s
        np.add.at(g, C[:, 0], r)
        np.add.at(g, C[:, 1], -r)
        d = f[T[:, 0]] - f[T[:, 1]]
        a, b = (tau - d) / s, (-tau - d) / s
        r = (N.pdf(b) - N.pdf(a)) / interval(a, b) / s
        np.add.at(g, T[:, 0], r)
        np.add.at(g, T[:, 1], -r)
        a, b = (c[k] - f[ri]) / sig, (c[k - 1] - f[ri]) / sig
        np.add.at(g, ri, (N.pdf(b) - N.pdf(a)) / interval(a, b) / sig)
        return g

    return value, grad


@pytest.mark.parametrize("offered", [False, True])
def test_mode_matches_scipy(offered):
    """Comparisons, ties and ordinal levels together: our Newton mode is SciPy's maximum (strict
    comparisons as eq. 3 or, with ties offered, as the tie's upper category)."""
    model = build("levels", offered=offered)
    value, grad = scipy_log_posterior(model)
    # maximise log p(Y | L a) - a^T a / 2 over whitened a (L from NumPy): a well-conditioned problem
    Lnp = np.linalg.cholesky(model.covar_module(model.train_X).to_dense().detach().numpy())
    res = optimize.minimize(
        lambda a: -value(Lnp @ a) + 0.5 * a @ a,
        np.zeros(Lnp.shape[0]),
        jac=lambda a: -Lnp.T @ grad(Lnp @ a) + a,
        method="BFGS",
        options={"gtol": 1e-8, "maxiter": 10000},
    )
    root = optimize.root(lambda a: Lnp.T @ grad(Lnp @ a) - a, res.x, tol=1e-14)  # polish: zero gradient
    assert np.abs(root.fun).max() < 1e-10 and -value(Lnp @ root.x) + 0.5 * root.x @ root.x <= res.fun + 1e-9
    f_scipy = Lnp @ root.x
    ours = model.mode.f.numpy()
    np.testing.assert_allclose(ours, f_scipy, atol=1e-7)
    # W (eq. 8) against central differences of SciPy's gradient of log p(Y|f)
    n, h = ours.shape[0], 1e-5
    H = np.stack([(grad(ours + h * e) - grad(ours - h * e)) / (2 * h) for e in np.eye(n)], axis=1)
    np.testing.assert_allclose(model.W().numpy(), -0.5 * (H + H.T), atol=1e-6 * np.abs(H).max())


def _raw_params(model, learn: bool) -> dict:
    k = model.covar_module
    params = {"lengthscale": k.base_kernel.raw_lengthscale, "outputscale": k.raw_outputscale}
    if learn:
        params["tie_threshold"] = model.likelihood.tie.raw_tie_threshold
        params["comparison_noise"] = model.likelihood.comparison.raw_comparison_noise
        if model.rating_levels:
            params["cut_points"] = model.likelihood.rating.raw_cut_points
    return params


@pytest.mark.parametrize(
    "kind,learn,offered", [("levels", True, True), ("beta", True, False), ("levels", False, False)]
)
def test_evidence_gradient_vs_finite_differences(kind, learn, offered):
    model = build(kind, seed=3, learn=learn, offered=offered)
    params = _raw_params(model, learn)
    assert_evidence_gradient(model, params)


def test_fit_learns_tie_threshold_and_cut_points():
    """``fit_gpytorch_mll`` on answers simulated from the model itself (ties within ``tau = 0.3``,
    levels from the default cut points) moves the tie threshold and the cut points, keeps the cut
    points ordered, increases the evidence plus priors, and finds a ``tau`` of the right size."""
    g = torch.Generator().manual_seed(7)
    X = rand(40, 1, generator=g)
    f = 1.5 * torch.sin(6 * X[:, 0])
    pairs = random_comparisons(40, 80, g)
    d = f[pairs[:, 0]] - f[pairs[:, 1]] + 0.1 * SQRT2 * torch.randn(80, generator=g, dtype=torch.float64)
    tie = d.abs() < 0.3
    C = torch.where((d > 0).unsqueeze(-1), pairs, pairs.flip(-1))[~tie]
    cuts = torch.tensor([-1.19, -0.36, 0.36, 1.19], dtype=torch.float64)
    levels = 1 + (f[:20].unsqueeze(-1) + 0.2 * torch.randn(20, 1, generator=g, dtype=torch.float64) > cuts).sum(-1)
    model = PreferenceGP(
        X,
        C,
        levels.double(),
        torch.arange(20),
        kernel(0.3, 1.0, 1),
        ties=pairs[tie],
        rating_levels=5,
        learn_likelihood=True,
        ties_offered=True,
        comparison_noise=0.1,
    )
    model.likelihood.comparison.raw_comparison_noise.requires_grad_(False)
    mll = LaplaceMarginalLogLikelihood(model)
    before = float(mll().detach())
    tau0, c0 = float(model.likelihood.tie.tie_threshold.detach()), model.likelihood.rating.cut_points.detach().clone()
    fit_gpytorch_mll(mll)
    assert float(mll().detach()) > before
    tau = float(model.likelihood.tie.tie_threshold.detach())
    assert tau != tau0 and 0.1 < tau < 0.9, tau  # truth 0.3
    c = model.likelihood.rating.cut_points.detach()
    assert not torch.equal(c, c0) and (c.diff() > 0).all()


def test_ties_pull_utilities_together():
    """A tie between two items pulls their posterior means together; ignoring it does not."""
    X = torch.tensor([[0.1], [0.5], [0.9]], dtype=torch.float64)
    C = torch.tensor([[0, 1], [0, 2]])
    without = PreferenceGP(X, C, covar_module=kernel(0.1, 1.0, 1))
    with_tie = PreferenceGP(X, C, covar_module=kernel(0.1, 1.0, 1), ties=torch.tensor([[1, 2]]))

    def gap(m):
        return abs(float(m.mode.f[1] - m.mode.f[2]))

    assert gap(with_tie) < gap(without) + 1e-12
    model = PreferenceGP(X, torch.tensor([[0, 1]]), covar_module=kernel(0.1, 1.0, 1))
    p0 = float(model.tie_probability(X[1:2], X[2:3]).detach())
    model.add_observations(ties=torch.tensor([[2, 1]]))
    assert model.ties.tolist() == [[2, 1]]
    assert float(model.tie_probability(X[1:2], X[2:3]).detach()) > p0


def test_level_predictives_and_expected_rating():
    model = build("levels", seed=2)
    X = model.train_X[:4]
    probs = model.level_probabilities(X)
    assert probs.shape == (4, 5)
    torch.testing.assert_close(probs.sum(-1), torch.ones(4, dtype=torch.float64))
    level = model.expected_level(X)
    torch.testing.assert_close(level, (probs * torch.arange(1, 6, dtype=torch.float64)).sum(-1))
    torch.testing.assert_close(model.expected_rating(X), (level - 0.5) / 5)
    with pytest.raises(ValueError, match="rating_levels"):
        build("beta").expected_level(X)


def test_bad_input_is_refused_and_leaves_the_model_unchanged():
    model = build("levels", seed=4)
    before = (model.ties.clone(), model.ratings.clone(), model.mode.f.clone())
    with pytest.raises(ValueError, match="tied with itself"):
        model.add_observations(ties=torch.tensor([[3, 3]]))
    with pytest.raises(ValueError, match=r"1\.\.5.*6"):
        model.add_observations(ratings=torch.tensor([6.0]), rating_index=torch.tensor([0]))
    with pytest.raises(ValueError, match=r"1\.\.5.*0\.3"):
        model.add_observations(ratings=torch.tensor([0.3]), rating_index=torch.tensor([0]))
    with pytest.raises(ValueError, match="same item"):
        model.add_observations(torch.zeros(2, 2, dtype=torch.float64), ties=torch.tensor([[0, 1]]))
    assert torch.equal(model.ties, before[0]) and torch.equal(model.ratings, before[1])
    torch.testing.assert_close(model.mode.f, before[2])
    with pytest.raises(ValueError, match="tied with itself"):
        PreferenceGP(torch.rand(3, 1, dtype=torch.float64), ties=[[1, 1]])
    with pytest.raises(ValueError, match="rating_levels"):
        PreferenceGP(torch.rand(3, 1, dtype=torch.float64), ratings=[1], rating_index=[0], rating_levels=1)


def test_batched_model_with_ties_and_levels_matches_single_models():
    """Problems of different sizes in one batched model (ties and levels padded, masked) have the
    modes of the same problems fitted alone; conditioning adds levels to every problem."""
    g = torch.Generator().manual_seed(5)
    X = rand(2, 6, 1, generator=g)
    C = [torch.tensor([[0, 1]]), torch.tensor([[1, 2], [3, 4]])]
    levels, index = [torch.tensor([1.0, 4.0]), torch.tensor([5.0])], [torch.tensor([2, 3]), torch.tensor([0])]
    ties = [torch.tensor([[3, 4], [0, 5]]), torch.zeros(0, 2, dtype=torch.long)]
    batch = PreferenceGP(X, C, levels, index, kernel(0.3, 1.0, 1), ties=ties, rating_levels=5, ties_offered=True)
    for b in range(2):
        single = PreferenceGP(
            X[b], C[b], levels[b], index[b], kernel(0.3, 1.0, 1), ties=ties[b], rating_levels=5, ties_offered=True
        )
        torch.testing.assert_close(batch.mode.f[b], single.mode.f, rtol=0, atol=1e-10)
    cond = batch.condition_on_observations(
        rand(2, 1, generator=g), ratings=torch.tensor([2.0]), rating_index=torch.tensor([0])
    )
    assert cond.ratings[:, -1].tolist() == [2.0, 2.0] and cond.ties.shape == (2, 2, 2)
    with pytest.raises(ValueError, match=r"1\.\.5"):
        batch.condition_on_observations(
            rand(2, 1, generator=g), ratings=torch.tensor([0.5]), rating_index=torch.tensor([0])
        )


def test_record_answer_ties_and_levels():
    """The answer path: "equally best" rows become comparisons and ties, no preference a tie
    between every two items shown, and a rating in [0, 1] the level of its bin."""
    from torchpref.data.queries import RankingQuery, RatingQuery, record_answer

    g = torch.Generator().manual_seed(8)
    model = PreferenceGP(rand(2, 1, generator=g), torch.tensor([[0, 1]]), ties_offered=True)
    X = rand(4, 1, generator=g)
    assert record_answer(model, RankingQuery(X), [0, 2]) == [0, 2]
    assert sorted(map(tuple, model.comparisons[1:].tolist())) == [(2, 3), (2, 5), (4, 3), (4, 5)]
    assert model.ties.tolist() == [[2, 4]]
    assert record_answer(model, RankingQuery(X[:3]), None) is None
    assert model.ties.shape == (4, 2)
    with pytest.raises(ValueError, match="index"):
        record_answer(model, RankingQuery(X), [0, 9])
    assert model.ties.shape == (4, 2)  # unchanged
    levels = PreferenceGP(rand(2, 1, generator=g), rating_levels=5)
    record_answer(levels, RatingQuery(X[0]), 0.7)
    assert levels.ratings.tolist() == [4.0]


def test_checkpoint_keeps_ties_levels_and_settings(tmp_path):
    from torchpref.models.checkpoint import load_model, save_model

    model = build("levels", seed=6, offered=True)
    save_model(model, tmp_path / "m.pt")
    back = load_model(tmp_path / "m.pt", covar_module=kernel(0.4, 1.3, 2))
    assert back.rating_levels == 5 and back.ties_offered and torch.equal(back.ties, model.ties)
    torch.testing.assert_close(back.mode.f, model.mode.f, rtol=0, atol=1e-6)


@pytest.mark.parametrize("kind", ["levels", "beta"])
def test_mll_counts_each_prior_once(kind):
    """The MLL is the Laplace evidence plus each prior's log density once, the likelihood's priors
    (reachable from the MLL both as its ``likelihood`` and as ``model.likelihood``) included: the
    sum GPyTorch's exact MLL forms from ``model.named_priors()``."""
    from gpytorch.priors import GammaPrior

    model = build(kind, seed=5, learn=True)
    model.likelihood.comparison.register_prior("extra_noise_prior", GammaPrior(2.0, 4.0), lambda m: m.comparison_noise)
    mll = LaplaceMarginalLogLikelihood(model)
    priors = [(name, p.log_prob(c(mod)).sum()) for name, mod, p, c, _ in model.named_priors()]
    assert any(n.startswith("likelihood.") for n, _ in priors), priors
    expected = model.log_marginal_likelihood() + sum(v for _, v in priors)
    assert torch.allclose(mll(), expected, rtol=0, atol=1e-12)
