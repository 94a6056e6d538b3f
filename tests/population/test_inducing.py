"""The population mean at inducing items: M = N is the exact fit, M < N is the GP given the mean at
the inducing items (checked against today's model with that kernel), chosen visibly by size;
memory estimated and refused before anything large is allocated; a person model from kept factors."""

import pytest
import torch
from botorch.exceptions.warnings import InputDataWarning
from gpytorch.kernels import AdditiveKernel, Kernel

import torchpref
import torchpref.population.fit as fit_module
from torchpref.data.preference_data import PreferenceData
from torchpref.models.defaults import default_covar_module
from torchpref.population.fit import fit_population, population_objective
from torchpref.population.inducing import choose_items
from torchpref.population.model import Population

D = torch.float64


def _kernels():
    k_m, k_g = default_covar_module(2).double(), default_covar_module(2).double()
    k_m.base_kernel.lengthscale, k_m.outputscale = 0.4, 1.3
    k_g.base_kernel.lengthscale, k_g.outputscale = 0.7, 0.6
    return k_m, k_g


def _person(seed, n=7, ratings=False):
    X = torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=D)
    C = torch.tensor([[0, 1], [2, 3], [4, 5], [1, 6], [3, 0], [5, 2]])
    if ratings:
        return PreferenceData.create(X, C, torch.tensor([0.8, 0.25, 0.6], dtype=D), torch.tensor([0, 4, 6]))
    return PreferenceData.create(X, C)


def _people():
    people = [_person(s, ratings=s % 2 == 0) for s in range(5)]
    shared = people[0].train_X[:3]
    return people + [PreferenceData.create(torch.cat([shared, people[1].train_X[:4]]), people[0].comparisons[:3])]


def test_M_equal_to_N_is_the_exact_fit():
    """Every item as an inducing item, in the greedy-variance order (not U's): the exact fit's
    evidence, fitted hyperparameters and new person's posterior, to 1e-8."""
    people = _people()
    exact = fit_population(people, k_m=_kernels()[0], k_g=_kernels()[1], fit=False, inducing=None)
    N = exact.stats["items"]
    order = choose_items(exact.U, N, "variance", _kernels()[0])
    assert sorted(order.tolist()) == list(range(N)) and order.tolist() != list(range(N))
    full = fit_population(
        people, k_m=_kernels()[0], k_g=_kernels()[1], fit=False, inducing=N, inducing_method="variance"
    )
    assert (exact.mean_kind, full.mean_kind, full.stats["inducing_items"]) == ("exact", "inducing", N)
    assert full.stats["evidence"] == pytest.approx(exact.stats["evidence"], abs=1e-8)
    fitted = [fit_population(people, max_iter=15, inducing=m, inducing_method="variance") for m in (None, N)]
    for p, q in zip(fitted[0].k_m.parameters(), fitted[1].k_m.parameters()):
        torch.testing.assert_close(p, q, rtol=0, atol=1e-8)
    X = torch.rand(5, 2, generator=torch.Generator().manual_seed(4), dtype=D)
    with torch.no_grad():
        a, b = (pop.person_model(X).posterior(X) for pop in fitted)
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=1e-8)
    torch.testing.assert_close(a.variance, b.variance, rtol=0, atol=1e-8)


class _GivenInducing(Kernel):
    """``k_m(x, Z) k_m(Z, Z)^{-1} k_m(Z, x') + k_g(x, x')``: the prior of f when m is the GP given
    its values at Z (a dense reference, independent of the population code)."""

    def __init__(self, k_m, k_g, Z):
        super().__init__()
        self.k_m, self.k_g, self.Z = k_m, k_g, Z

    def forward(self, x1, x2, diag=False, **kw):
        K1 = self.k_m(x1, self.Z).to_dense()
        K2 = self.k_m(self.Z, x2).to_dense()
        Q = K1 @ torch.linalg.solve(self.k_m(self.Z).to_dense(), K2)
        out = Q + self.k_g(x1, x2).to_dense()
        return out.diagonal(dim1=-2, dim2=-1) if diag else out


@pytest.mark.parametrize("ratings", [False, True])
def test_one_person_at_inducing_items_is_todays_model_with_that_kernel(ratings):
    person = _person(0, n=9, ratings=ratings)
    k_m, k_g = _kernels()
    pop = fit_population([person], k_m=k_m, k_g=k_g, fit=False, inducing=4, inducing_method="variance")
    assert pop.mean_kind == "inducing" and pop.U.shape == (4, 2)
    ref = torchpref.PreferenceGP(
        person.train_X, person.comparisons, person.ratings, person.rating_index,
        covar_module=_GivenInducing(k_m, k_g, pop.U), **pop.model_settings.model_kwargs(),
    )  # fmt: skip
    assert pop.stats["evidence"] == pytest.approx(float(ref.log_marginal_likelihood().detach()), abs=1e-7)


def test_inducing_evidence_gradient_matches_finite_differences():
    from tests.population.test_population import assert_gradient_matches_finite_differences

    people = _people()
    assert_gradient_matches_finite_differences(lambda: population_objective(people, *_kernels(), inducing=9)[0])


def test_chosen_items_are_distinct_rows_of_the_data():
    U = torch.rand(300, 3, generator=torch.Generator().manual_seed(0), dtype=D)
    for method in ("kmeans", "variance"):
        rows = choose_items(U, 40, method, default_covar_module(3).double())
        assert rows.shape == (40,) and len(set(rows.tolist())) == 40 and int(rows.max()) < 300
    far = choose_items(U, 40, "kmeans", default_covar_module(3).double())
    spread = torch.cdist(U, U[far]).min(-1).values.max()
    assert float(spread) < 0.35  # every item near an inducing item (a random pick leaves ~0.4)
    with pytest.raises(ValueError, match="inducing_method must be one of"):
        choose_items(U, 4, "random", default_covar_module(3).double())


def test_the_default_switches_by_size_and_says_so(monkeypatch, capsys):
    people = _people()
    small = fit_population(people, fit=False)
    assert small.mean_kind == "exact" and small.stats["inducing_items"] == small.stats["items"]
    monkeypatch.setattr(fit_module, "EXACT_ITEMS", 20)
    monkeypatch.setattr(fit_module, "DEFAULT_INDUCING", 8)
    big = fit_population(people, fit=False, progress=True)
    assert big.mean_kind == "inducing" and big.stats["inducing_items"] == 8 and big.U.shape[0] == 8
    first = capsys.readouterr().err.strip().splitlines()[0]
    assert "mean at M = 8 of N = 35 items" in first and "peak about" in first


def test_memory_is_estimated_and_refused_before_anything_large(monkeypatch):
    people = [_person(100 + s) for s in range(40)]

    def no_shards(*args, **kwargs):
        raise AssertionError("a shard was built before the memory was checked")

    monkeypatch.setattr(fit_module, "shard_data", no_shards)
    with pytest.raises(ValueError, match=r"about .* GB at its peak .*M = 280.*memory_limit\): fit with inducing=70"):
        fit_population(people, inducing=None, memory_limit=10**6)
    monkeypatch.setattr("torchpref.population.memory.machine_memory", lambda: 10**6)
    with pytest.raises(ValueError, match="75% of this machine's"):
        fit_population(people, inducing=None)


def test_items_outside_the_unit_cube_warn_as_preference_gp_does():
    person = _person(0)
    far = PreferenceData.create(person.train_X * 5, person.comparisons)
    with pytest.warns(InputDataWarning, match="not contained in the unit cube"):
        fit_population([person, far], fit=False)


def test_a_person_model_needs_no_cubic_work(monkeypatch):
    """What a person model needs of the population (A = I - S^-1) is computed once, with it."""
    pop = fit_population(_people(), fit=False)
    A = pop.A.clone()

    def refuse(*args):
        raise AssertionError("A recomputed for a person model")

    monkeypatch.setattr(Population, "covariance_update", staticmethod(refuse))
    X = torch.rand(4, 2, dtype=D)
    model = pop.person_model(X)
    torch.testing.assert_close(model.covar_module.A, A)
    with torch.no_grad():
        assert bool(torch.isfinite(model.posterior(X).mean).all())


def test_inducing_population_ranks_like_the_exact_one():
    """Many people with their own items: the mean at 30 inducing items ranks held-out items as
    the exact mean (all 240 items) does."""
    g = torch.Generator().manual_seed(7)
    truth = lambda X: torch.sin(4 * X[:, 0]) + X[:, 1]  # noqa: E731
    people = []
    for _ in range(40):
        X = torch.rand(6, 2, generator=g, dtype=D)
        pairs = torch.tensor([[0, 1], [2, 3], [4, 5], [1, 2], [3, 4]])
        win = truth(X)[pairs[:, 0]] > truth(X)[pairs[:, 1]]
        people.append(PreferenceData.create(X, torch.where(win.unsqueeze(-1), pairs, pairs.flip(-1))))
    exact = fit_population(people, max_iter=15, inducing=None)
    small = fit_population(people, max_iter=15, inducing=30)
    Xt = torch.rand(200, 2, generator=g, dtype=D)
    with torch.no_grad():
        a, b = exact.mean()(Xt), small.mean()(Xt)
    assert float(torch.corrcoef(torch.stack([a, b]))[0, 1]) > 0.98
    assert float(torch.corrcoef(torch.stack([b, truth(Xt)]))[0, 1]) > 0.9


def test_bad_inducing_settings_are_named():
    with pytest.raises(ValueError, match="inducing must be 'auto', None"):
        fit_population(_people(), inducing=0)
    with pytest.raises(ValueError, match="inducing_method must be one of"):
        fit_population(_people(), inducing=3, inducing_method="nearest")
    with pytest.raises(ValueError, match="comparison_noise must be a finite positive number"):
        fit_population(_people(), comparison_noise=float("nan"))


def test_kernels_of_a_fit_are_not_the_reference_kernels():
    """The reference kernel above adds k_m's Nystrom part to k_g: sanity of the reference itself."""
    k_m, k_g = _kernels()
    X = torch.rand(5, 2, dtype=D)
    ref = _GivenInducing(k_m, k_g, X)(X).to_dense()
    torch.testing.assert_close(ref, AdditiveKernel(k_m, k_g)(X).to_dense(), rtol=1e-8, atol=1e-8)
