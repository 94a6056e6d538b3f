"""BatchedPreferenceGP and the batched active-learning loop against one model at a time."""

import pytest
import torch

from torchpref.data.queries import BoxCandidates, FinitePool
from torchpref.experiments import wave
from torchpref.inference.numerics import NotPSDError, batched_cholesky
from torchpref.models.batch import BatchedPreferenceGP
from torchpref.selection.active import run_active_learning, run_active_learning_batch
from torchpref.selection.strategies import UCBC, InformationPerEffort, RandomMixed, Selector
from torchpref.simulation.users import SimulatedUser
from torchpref.simulation.utility_functions import WaveFunction


def _random_trials(T: int, steps: int, seed: int):
    """``T`` single models and a batch of the same data, grown by mixed random answers of
    different kinds per trial (so the trials' sizes differ)."""
    g = torch.Generator().manual_seed(seed)
    models = [
        wave.make_model(torch.rand(2, 1, generator=g, dtype=torch.float64), torch.tensor([[0, 1]])) for _ in range(T)
    ]
    batch = BatchedPreferenceGP.from_models(models)
    for step in range(steps):
        for b in range(T):
            if (step + b) % 3 == 0:
                X = torch.rand(1, 1, generator=g, dtype=torch.float64)
                kw = {"ratings": [float(torch.rand((), generator=g))], "rating_index": [0]}
            else:
                X = torch.rand(4, 1, generator=g, dtype=torch.float64)
                j = int(torch.randint(4, (1,), generator=g))
                kw = {"comparisons": torch.tensor([[j, k] for k in range(4) if k != j])}
            models[b].add_observations(X, **kw)
            batch.add_observations(b, X, **kw)
    return models, batch, g


@pytest.mark.parametrize("seed", [0, 1])
def test_batch_matches_single_models(seed):
    models, batch, g = _random_trials(5, 7, seed)
    X = torch.rand(5, 40, 1, generator=g, dtype=torch.float64)
    mean, var = batch.marginals(X)
    jm, jc = batch.joint(X)
    er = batch.expected_rating(X)
    # both solvers stop at half a Newton decrement below 1e-11, i.e. within ~1e-6 of the mode
    tol = 1e-5
    for b, model in enumerate(models):
        m1, v1 = model.marginals(X[b])
        post = model.posterior(X[b : b + 1]).distribution
        assert torch.allclose(mean[b], m1, atol=tol) and torch.allclose(var[b], v1, atol=tol)
        assert torch.allclose(jm[b], post.mean.reshape(-1), atol=tol)
        assert torch.allclose(jc[b], post.covariance_matrix.reshape(40, 40), atol=tol)
        assert torch.allclose(er[b], model.expected_rating(X[b]), atol=tol)
        assert torch.allclose(batch.mode()[b], model.mode.f, atol=tol)
    assert mean.abs().max() > 0.1
    assert batch.converged.all()


def test_trial_without_observations_is_the_prior():
    g = torch.Generator().manual_seed(3)
    m0 = wave.make_model(torch.rand(3, 1, generator=g, dtype=torch.float64), torch.tensor([[0, 1], [1, 2]]))
    m1 = wave.make_model(torch.rand(2, 1, generator=g, dtype=torch.float64), None)
    batch = BatchedPreferenceGP.from_models([m0, m1])
    X = torch.rand(2, 7, 1, generator=g, dtype=torch.float64)
    mean, var = batch.marginals(X)
    assert torch.equal(mean[1], torch.zeros(7, dtype=torch.float64))
    assert torch.allclose(var[1], torch.full((7,), wave.MODEL_SETTINGS["outputscale"], dtype=torch.float64))
    assert torch.allclose(mean[0], m0.marginals(X[0])[0], atol=1e-9)


def test_trial_model_round_trip():
    models, batch, g = _random_trials(3, 4, 5)
    X = torch.rand(3, 10, 1, generator=g, dtype=torch.float64)
    for b in range(3):
        assert torch.allclose(batch.trial_model(b).expected_rating(X[b]), batch.expected_rating(X)[b], atol=1e-5)


def test_bad_input_leaves_batch_unchanged():
    models, batch, g = _random_trials(2, 2, 7)
    X = torch.rand(2, 5, 1, generator=g, dtype=torch.float64)
    before = batch.marginals(X)[0].clone()
    n = batch.data(1).n
    with pytest.raises(ValueError, match="trial must be in 0..1, got 2"):
        batch.add_observations(2, torch.rand(1, 1, dtype=torch.float64), ratings=[0.5], rating_index=[0])
    with pytest.raises(ValueError):
        batch.add_observations(1, torch.rand(2, 1, dtype=torch.float64), comparisons=torch.tensor([[0, 5]]))
    with pytest.raises(ValueError, match="rating"):
        batch.add_observations(1, torch.rand(1, 1, dtype=torch.float64), ratings=[1.5], rating_index=[0])
    assert batch.data(1).n == n
    assert torch.equal(batch.marginals(X)[0], before)
    with pytest.raises(ValueError, match="T x N x d"):
        batch.marginals(X[0])


def test_from_models_checks_hyperparameters():
    a = wave.make_model(torch.rand(2, 1, dtype=torch.float64), torch.tensor([[0, 1]]))
    b = wave.make_model(torch.rand(2, 1, dtype=torch.float64), torch.tensor([[0, 1]]))
    b.likelihood.comparison.comparison_noise = 0.3
    with pytest.raises(ValueError, match="model 1 has hyperparameters different"):
        BatchedPreferenceGP.from_models([a, b])


def test_batched_cholesky_jitter_and_failure():
    A = torch.ones(3, 4, 4, dtype=torch.float64)  # rank one: needs jitter
    A[0] = torch.eye(4, dtype=torch.float64)
    L, jitter = batched_cholesky(A)
    assert jitter[0] == 0 and (jitter[1:] > 0).all()
    assert torch.allclose(L @ L.mT, A + jitter.reshape(3, 1, 1) * torch.eye(4, dtype=torch.float64))
    A[2] = -torch.eye(4, dtype=torch.float64)
    with pytest.raises(NotPSDError, match=r"trials \[2\]"):
        batched_cholesky(A)


@pytest.mark.parametrize("strategy", wave.STRATEGIES)
def test_wave_batch_equals_one_trial_at_a_time(strategy):
    seeds = wave.trial_seeds(3, 3)
    single = [wave.run_trial(s, 6, (strategy,))[strategy] for s in seeds]
    batch = [r[strategy] for r in wave.run_trial_batch(tuple(seeds), 6, strategy)]
    for a, b in zip(single, batch):
        assert a["kinds"] == b["kinds"] and a["tp"] == b["tp"] and a["cost"] == b["cost"]
        assert max(abs(x - y) for x, y in zip(a["wrms"], b["wrms"])) < 1e-9


@pytest.mark.parametrize("pool", [False, True])
def test_batch_loop_matches_single_loop_random_mixed(pool):
    """Selectors the wave run does not use (random mixed, target 'maximizer' / 'utility'), through
    the generic loops, from a box or from a finite pool (queries then carry pool indices)."""
    g = torch.Generator().manual_seed(5)
    cands = (
        FinitePool(torch.rand(25, 1, generator=g, dtype=torch.float64))
        if pool
        else BoxCandidates(torch.tensor([[0.0], [1.0]], dtype=torch.float64), 20)
    )
    for selector in (
        RandomMixed(m=3),
        InformationPerEffort(m=3, target="maximizer", num_samples=32),
        InformationPerEffort(m=3, target="utility", num_samples=32),
        UCBC(m=3),
    ):
        truths = [WaveFunction.random(generator=torch.Generator().manual_seed(s)) for s in (1, 2)]

        def users():
            return [
                SimulatedUser.paper_wave(lambda X, t=t: t(X, noise=False), generator=torch.Generator().manual_seed(i))
                for i, t in enumerate(truths)
            ]

        def starts():
            return [
                wave.make_model(torch.tensor([[0.2], [0.7]], dtype=torch.float64), torch.tensor([[1, 0]]))
                for _ in truths
            ]

        hb = run_active_learning_batch(
            BatchedPreferenceGP.from_models(starts()),
            users(),
            cands,
            selector,
            4,
            generators=[torch.Generator().manual_seed(10 + i) for i in range(2)],
        )
        for i, (model, user) in enumerate(zip(starts(), users())):
            h = run_active_learning(model, user, cands, selector, 4, generator=torch.Generator().manual_seed(10 + i))
            assert [r.answer for r in h.records] == [r.answer for r in hb[i].records]
            for r1, r2 in zip(h.records, hb[i].records):
                assert torch.equal(r1.query.items, r2.query.items)
                assert getattr(r1.query, "indices", getattr(r1.query, "index", None)) == getattr(
                    r2.query, "indices", getattr(r2.query, "index", None)
                )
                if pool:
                    assert getattr(r2.query, "indices", getattr(r2.query, "index", None)) is not None


def test_batch_loop_input_checks():
    model = BatchedPreferenceGP.from_models(
        [wave.make_model(torch.rand(2, 1, dtype=torch.float64), torch.tensor([[0, 1]])) for _ in range(2)]
    )
    cands = BoxCandidates(torch.tensor([[0.0], [1.0]], dtype=torch.float64), 10)
    with pytest.raises(ValueError, match="one user and one generator per trial"):
        run_active_learning_batch(model, [None], cands, UCBC(), 2, generators=[torch.Generator()] * 2)

    class OneAtATime(Selector):
        def select(self, model, X, indices, step, num_steps, generator):
            raise AssertionError

    with pytest.raises(NotImplementedError, match="select_batch"):
        run_active_learning_batch(model, [None, None], cands, OneAtATime(), 1, generators=[torch.Generator()] * 2)


@pytest.mark.parametrize("hyper_seed", range(6))
def test_batch_random_extreme_problems(hyper_seed):
    """The robustness suite's random problems (duplicated items, contradictory comparisons,
    extreme ratings), 12 of one dimension at a time under one draw of extreme hyperparameters:
    batched modes finite, converged and equal to the single models' (one model at a time)."""
    import warnings

    from gpytorch.kernels import RBFKernel, ScaleKernel

    from torchpref.models.preference_gp import PreferenceGP
    from torchpref.testing.problems import random_config

    hyper = random_config(1000 + hyper_seed)[0]
    problems = [random_config(s) for s in range(hyper_seed * 40, hyper_seed * 40 + 40)]
    d = problems[0][0]["d"]
    problems = [p for p in problems if p[0]["d"] == d][:12]
    k = ScaleKernel(RBFKernel()).to(torch.float64)
    k.base_kernel.lengthscale = hyper["lengthscale"]
    k.outputscale = hyper["outputscale"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # jitter / boundary warnings are expected here
        models = [
            PreferenceGP(
                X,
                C if len(C) else None,
                u if len(u) else None,
                ri if len(u) else None,
                covar_module=k,
                comparison_noise=hyper["comparison_noise"],
                rating_scale=hyper["rating_scale"],
                rating_precision=hyper["rating_precision"],
            )
            for _, X, C, u, ri in problems
        ]
        batch = BatchedPreferenceGP.from_models(models)
        modes = batch.mode()
        assert batch.converged.all()
        Xs = torch.rand(len(models), 5, d, generator=torch.Generator().manual_seed(hyper_seed), dtype=torch.float64)
        mean, var = batch.marginals(Xs)
        assert torch.isfinite(mean).all() and torch.isfinite(var).all()
        for b, model in enumerate(models):
            f = model.mode.f
            assert torch.isfinite(modes[b]).all()
            assert (modes[b] - f).abs().max() <= 1e-5 * max(1.0, float(f.abs().max()))


def test_trial_model_is_independent():
    models, batch, g = _random_trials(2, 2, 11)
    X = torch.rand(2, 6, 1, generator=g, dtype=torch.float64)
    before = batch.marginals(X)[0].clone()
    single = batch.trial_model(0)
    single.covar_module.outputscale = 2.0
    single.likelihood.comparison.comparison_noise = 0.5
    batch.add_observations(1, torch.rand(1, 1, dtype=torch.float64), ratings=[0.3], rating_index=[0])
    assert torch.allclose(batch.marginals(X)[0][0], before[0], atol=1e-9)


def test_fisher_steps_where_the_hessian_is_not_negative_definite():
    """Started where a Beta rating's log-likelihood is convex (nu = 2, u = 0.02, f = 2, prior
    variance 10: B = I + L^T W L < 0), the batched Newton takes Fisher-scoring steps and reaches
    the same mode as each problem alone from the same start."""
    from gpytorch.kernels import RBFKernel, ScaleKernel

    from torchpref.inference.laplace import find_mode
    from torchpref.models.preference_gp import PreferenceGP

    k = ScaleKernel(RBFKernel()).to(torch.float64)
    k.outputscale = 10.0
    X = torch.tensor([[0.3], [0.9]], dtype=torch.float64)
    models = [
        PreferenceGP(
            X, ratings=[0.02, 0.6], rating_index=[0, 1], covar_module=k, rating_scale=1.0, rating_precision=2.0
        )
        for _ in range(2)
    ]
    batch = BatchedPreferenceGP.from_models(models)
    padded = batch.model.data
    obs = batch.model._observations()
    L = torch.linalg.cholesky(k.forward(padded.X, padded.X))
    f0 = torch.tensor([[2.0, 0.0], [0.0, 0.0]], dtype=torch.float64)
    weights = obs.evaluate(f0).weights
    assert torch.linalg.cholesky_ex(obs.whitened_hessian(L, weights))[1][0] > 0  # not PD at the start
    out = find_mode(L, obs, f0=f0)
    assert out.converged.all()
    for b in range(2):
        ref = find_mode(L[b], models[b]._observations(), f0=f0[b])
        assert torch.allclose(out.f[b], ref.f, atol=1e-6)


def test_batch_copies_hyperparameters():
    models, batch, g = _random_trials(2, 2, 13)
    X = torch.rand(2, 6, 1, generator=g, dtype=torch.float64)
    before = batch.marginals(X)[1].clone()
    models[0].covar_module.outputscale = 3.0  # the models' kernel is not the batch's
    batch.add_observations(1, torch.rand(1, 1, dtype=torch.float64), ratings=[0.3], rating_index=[0])
    batch.add_observations(1, torch.rand(1, 1, dtype=torch.float64), ratings=[0.4], rating_index=[0])
    assert torch.allclose(batch.marginals(X)[1][0], before[0], atol=1e-9)


def test_ties_levels_and_prior_mean_go_through_the_batch_and_its_trial_models():
    """A batch of models with 5 rating levels, "no preference" answers and a prior mean: ties
    added per trial (and by the batched loop, where a user says "no preference") give each trial
    the model one would get alone, and ``trial_model`` keeps the levels, the tie likelihood and the
    mean."""
    from gpytorch.means import LinearMean

    from torchpref.models.preference_gp import PreferenceGP

    g = torch.Generator().manual_seed(5)

    def model():
        mean = LinearMean(1).double()
        mean.weights.data.fill_(1.5)
        mean.bias.data.fill_(0.2)
        X = torch.rand(3, 1, generator=g, dtype=torch.float64)
        return PreferenceGP(
            X,
            torch.tensor([[0, 1]]),
            torch.tensor([4.0]),
            torch.tensor([2]),
            rating_levels=5,
            ties=torch.tensor([[1, 2]]),
            mean_module=mean,
        )

    models = [model(), model()]
    batch = BatchedPreferenceGP.from_models(models)
    X_new = torch.rand(3, 1, generator=g, dtype=torch.float64)
    for b, m in enumerate(models):
        m.add_observations(
            X_new, ties=torch.tensor([[0, 1 + b]]), ratings=torch.tensor([b + 1.0]), rating_index=torch.tensor([2])
        )
        batch.add_observations(
            b, X_new, ties=torch.tensor([[0, 1 + b]]), ratings=torch.tensor([b + 1.0]), rating_index=torch.tensor([2])
        )
    X = torch.rand(2, 9, 1, generator=g, dtype=torch.float64)
    mean, var = batch.marginals(X)
    for b, m in enumerate(models):
        single = batch.trial_model(b)
        assert single.rating_levels == 5 and single.data.ties.shape[0] == 2
        assert isinstance(single.mean_module, LinearMean) and single.mean_module is not batch.model.mean_module
        for ref in (m, single):
            m1, v1 = ref.marginals(X[b])
            assert torch.allclose(mean[b], m1, atol=1e-6) and torch.allclose(var[b], v1, atol=1e-6)
    assert (mean - X.squeeze(-1) * 1.5).abs().max() < 3  # the prior mean is in force, not zero


def test_the_batched_loop_records_no_preference_answers():
    class Indifferent:
        def rate(self, x):
            return 0.5

        def choose(self, X):
            return None  # "no preference" among the items shown

    g = torch.Generator().manual_seed(0)
    models = [
        wave.make_model(torch.rand(2, 1, generator=g, dtype=torch.float64), torch.tensor([[0, 1]])) for _ in range(2)
    ]
    batch = BatchedPreferenceGP.from_models(models)
    pool = FinitePool(torch.linspace(0, 1, 12, dtype=torch.float64).unsqueeze(-1))
    gens = [torch.Generator().manual_seed(k) for k in range(2)]
    hist = run_active_learning_batch(
        batch, [Indifferent(), Indifferent()], pool, RandomMixed(m=3, p_ranking=1.0), 3, generators=gens
    )
    for b in range(2):
        assert len(hist[b].records) == 3 and batch.data(b).ties.shape[0] == 9  # 3 pairs per best-of-3
    assert torch.isfinite(batch.marginals(torch.rand(2, 4, 1, dtype=torch.float64))[0]).all()
