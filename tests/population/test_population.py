"""``fit_population`` and ``Population.person_model``: the hierarchical model against exact references."""

import pytest
import torch
from gpytorch.kernels import AdditiveKernel

import torchpref
from torchpref.data.preference_data import PreferenceData
from torchpref.models.defaults import default_covar_module
from torchpref.models.recipe import DEFAULT_MODEL
from torchpref.population.fit import fit_population, population_objective
from torchpref.population.joint import newton
from torchpref.population.shards import Basis

D = torch.float64


def _kernels(d=2, ls_m=0.4, ls_g=0.7, s_m=1.3, s_g=0.6):
    k_m, k_g = default_covar_module(d).double(), default_covar_module(d).double()
    k_m.base_kernel.lengthscale = ls_m
    k_m.outputscale = s_m
    k_g.base_kernel.lengthscale = ls_g
    k_g.outputscale = s_g
    return k_m, k_g


def _person(seed, n=7, ratings=False, X=None):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 2, generator=g, dtype=D) if X is None else X
    C = torch.tensor([[0, 1], [2, 3], [4, 5], [1, 6], [3, 0], [5, 2]])
    if ratings:
        r = torch.tensor([0.8, 0.25, 0.6], dtype=D)
        return PreferenceData.create(X, C, r, torch.tensor([0, 4, 6]))
    return PreferenceData.create(X, C)


def _reference(person, k_m, k_g):
    """Today's model of the one person with the kernel k_m + k_g (the hierarchical prior of f)."""
    model = torchpref.PreferenceGP(
        person.train_X,
        person.comparisons,
        person.ratings,
        person.rating_index,
        covar_module=AdditiveKernel(k_m, k_g),
        **DEFAULT_MODEL.model_kwargs(),  # a population's person model is a session's (ModelSettings)
    )
    return model


def _polished_mode(ref, person, K):
    """The reference model's mode after two more dense Newton steps (its solver stops at a half
    decrement of 1e-11, a few 1e-7 from the mode in f): the mode to round-off."""
    from torchpref.inference.padding import PaddedData

    lik = ref.likelihood
    comparison = lik.strict if ref.ties_offered else lik.comparison
    obs = PaddedData.single(person).observations(comparison, lik.rating, lik.tie)
    f = ref.mode.f.reshape(1, -1)
    for _ in range(2):
        _, r, weights = obs.evaluate(f)
        W = obs.W_dense(f.shape[-1], weights)[0]
        f = f + torch.linalg.solve(torch.linalg.inv(K) + W, r[0] - torch.linalg.solve(K, f[0]))
    return f[0]


@pytest.mark.parametrize("ratings", [False, True])
def test_one_person_is_todays_model(ratings):
    """A population of one person: its evidence is today's model's with the kernel k_m + k_g, and
    its E[m | D], Cov[m | D] are the dense formulas from that model's mode and W."""
    person = _person(0, ratings=ratings)
    k_m, k_g = _kernels()
    pop = fit_population([person], k_m=k_m, k_g=k_g, fit=False)
    ref = _reference(person, k_m, k_g)
    assert pop.stats["evidence"] == pytest.approx(float(ref.log_marginal_likelihood().detach()), abs=1e-8)
    X = person.train_X
    Xt = torch.rand(5, 2, generator=torch.Generator().manual_seed(9), dtype=D)
    with torch.no_grad():
        K = AdditiveKernel(k_m, k_g)(X).to_dense()
        W = ref.W()
        alpha = torch.linalg.solve(K, _polished_mode(ref, person, K))
        Kmx = k_m(X, Xt).to_dense()
        mean_ref = Kmx.mT @ alpha
        cov_ref = k_m(Xt).to_dense() - Kmx.mT @ (W @ torch.linalg.solve(torch.eye(7, dtype=D) + K @ W, Kmx))
        new = pop.person_model(Xt)
        post = new.posterior(Xt)
    torch.testing.assert_close(post.mean.squeeze(-1), mean_ref, rtol=0, atol=1e-7)
    torch.testing.assert_close(post.distribution.covariance_matrix, cov_ref + k_g(Xt).to_dense(), rtol=0, atol=1e-7)


def test_population_of_copies_predicts_the_shared_taste():
    """Many people who answer alike: the population mean ranks the items as they do, and a new
    person with no answers predicts their preferences."""
    g = torch.Generator().manual_seed(2)
    pool = torch.rand(12, 2, generator=g, dtype=D)
    u = pool[:, 0] - pool[:, 1]
    people = []
    for _ in range(15):
        idx = torch.randperm(12, generator=g)[:8]
        C = [
            [int(i), int(j)] if u[idx[i]] > u[idx[j]] else [int(j), int(i)]
            for i, j in [(0, 1), (2, 3), (4, 5), (6, 7), (1, 2)]
        ]
        people.append(PreferenceData.create(pool[idx], torch.tensor(C)))
    pop = fit_population(people, max_iter=30)
    model = pop.person_model(pool)
    with torch.no_grad():
        mean = model.posterior(pool).mean.squeeze(-1)
    assert torch.corrcoef(torch.stack([mean, u]))[0, 1] > 0.9


def assert_gradient_matches_finite_differences(make, h=1e-5):
    """``make()``'s objective: its gradient against central differences of fresh objectives."""
    objective = make()
    params = [p for p in objective.kernels.parameters()]
    grads = torch.autograd.grad(objective(), params)
    for i, gr in enumerate(grads):
        for k in range(params[i].numel()):
            values = []
            for step in (h, -h):
                fresh = make()
                with torch.no_grad():
                    list(fresh.kernels.parameters())[i].view(-1)[k] += step
                values.append(float(fresh(with_gradient=False)))
            fd = (values[0] - values[1]) / (2 * h)
            assert float(gr.reshape(-1)[k]) == pytest.approx(fd, rel=1e-4, abs=1e-6)


def test_evidence_gradient_matches_finite_differences():
    people = [_person(s, ratings=s % 2 == 0) for s in range(4)]
    assert_gradient_matches_finite_differences(lambda: population_objective(people, *_kernels(), inducing=None)[0])


def test_joint_mode_is_stationary_and_unique_items_are_shared():
    people = [_person(s) for s in range(3)]
    shared = people[0].train_X[:3]
    people.append(PreferenceData.create(torch.cat([shared, people[1].train_X[:4]]), people[0].comparisons[:3]))
    objective, plan = population_objective(people, *_kernels(), inducing=None)
    assert plan.items.U.shape[0] == 21  # 28 items, 7 repeated
    k, Z = objective.kernels, objective.Z
    with torch.no_grad():
        L_Z = torch.linalg.cholesky(k.k_m(Z).to_dense())
        start = objective.problem.start(Basis(Z, L_Z, k.k_m, k.k_g), torch.zeros(Z.shape[0], dtype=D))
        mode = newton(objective.problem, start)
    assert mode.converged
    assert float(mode.point.ga.abs().max()) < 1e-6
    assert all(float(s.gb.abs().max()) < 1e-6 for s in mode.point.handles)  # in process: the shards' states


def test_person_model_is_a_botorch_model_and_learns_the_person():
    people = [_person(s) for s in range(5)]
    pop = fit_population(people, max_iter=10)
    X = _person(11).train_X
    person = PreferenceData.create(X, torch.tensor([[0, 1], [0, 1], [0, 1]]))
    model = pop.person_model(person)
    assert isinstance(model, torchpref.PreferenceGP)
    ucb = torchpref.latent_ucb(model, gamma=1.0)
    val = ucb(person.train_X[:3].unsqueeze(-2))
    assert val.shape == (3,) and bool(torch.isfinite(val).all())
    prior = pop.person_model(person.train_X)
    with torch.no_grad():
        p_after = model.preference_probability(person.train_X[:1], person.train_X[1:2])
        p_before = prior.preference_probability(person.train_X[:1], person.train_X[1:2])
    assert float(p_after) > float(p_before)  # the person said 0 beats 1


@pytest.mark.parametrize(
    "people, match",
    [
        ([], "people is empty"),
        ("abc", "sequence of PreferenceData"),
        ([_person(0), PreferenceData.create(torch.rand(4, 3, dtype=D), torch.tensor([[0, 1]]))], r"people\[1\].*d = 2"),
        ([_person(0), 5], r"people\[1\] must be a PreferenceData"),
        ([PreferenceData.create(torch.rand(4, 2, dtype=D))], "no answers"),
    ],
)
def test_bad_people_are_named(people, match):
    with pytest.raises(ValueError, match=match):
        fit_population(people)


def test_nan_items_are_named():
    bad = _person(0)
    X = bad.train_X.clone()
    X[2, 1] = float("nan")
    nan_person = PreferenceData(X, bad.comparisons, bad.ratings, bad.rating_index)
    with pytest.raises(ValueError, match=r"people\[1\] has items that are not finite"):
        fit_population([_person(1), nan_person])


def test_person_model_refuses_another_dimension():
    pop = fit_population([_person(0)], fit=False)
    with pytest.raises(ValueError, match="d = 2"):
        pop.person_model(torch.rand(3, 4, dtype=D))


def test_ordinal_people_and_a_mix_refused():
    g = torch.Generator().manual_seed(4)
    people = []
    for _ in range(4):
        X = torch.rand(5, 2, generator=g, dtype=D)
        levels = torch.tensor([5.0, 1.0, 3.0])
        people.append(
            PreferenceData.create(X, torch.tensor([[0, 1]]), levels, torch.tensor([0, 1, 2]), rating_levels=5)
        )
    pop = fit_population(people, max_iter=3)
    assert pop.settings["rating_levels"] == 5
    model = pop.person_model(people[0])
    assert model.rating_levels == 5
    with torch.no_grad():
        assert float(model.expected_level(people[0].train_X[:1])) > float(model.expected_level(people[0].train_X[1:2]))
    beta = _person(0, ratings=True)
    with pytest.raises(ValueError, match=r"people\[1\] has rating_levels=None"):
        fit_population([people[0], beta])


def test_person_model_in_botorch_loops():
    """EUBO, conditioning and batched fantasies work on a person model with its prior mean."""
    from botorch.acquisition.preference import AnalyticExpectedUtilityOfBestOption

    pop = fit_population([_person(s) for s in range(3)], max_iter=3)
    person = _person(20)
    model = pop.person_model(person)
    eubo = AnalyticExpectedUtilityOfBestOption(pref_model=model)
    X = torch.rand(4, 2, 2, generator=torch.Generator().manual_seed(3), dtype=D)
    assert bool(torch.isfinite(eubo(X)).all())
    new = model.condition_on_observations(X[0], comparisons=torch.tensor([[0, 1]]))
    assert new.train_X.shape[0] == person.n + 2
    batched = model.condition_on_observations(X, comparisons=torch.tensor([[0, 1]]).expand(4, 1, 2))
    mean = batched.posterior(X).mean
    assert mean.shape == (4, 2, 1) and bool(torch.isfinite(mean).all())
    one = model.condition_on_observations(X[2], comparisons=torch.tensor([[0, 1]]))
    torch.testing.assert_close(mean[2], one.posterior(X[2]).mean, rtol=0, atol=1e-6)
