"""The population's evidence over shards of people on an executor: the same value, gradient and
fitted model as in process (threads here; processes and a local Dask cluster where available)."""

import importlib.util
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import pytest
import torch

from torchpref.data.preference_data import PreferenceData
from torchpref.models.defaults import PreferenceLikelihood, default_covar_module
from torchpref.population.fit import _Kernels, _objective, check_people, fit_population, population_layout
from torchpref.population.shards import ShardedProblem, shard_layouts, sharded_objective

D = torch.float64


def _kernels():
    k_m, k_g = default_covar_module(2).double(), default_covar_module(2).double()
    k_m.base_kernel.lengthscale, k_m.outputscale = 0.4, 1.3
    k_g.base_kernel.lengthscale, k_g.outputscale = 0.7, 0.6
    return k_m, k_g


def _person(seed, ratings=False):
    X = torch.rand(7, 2, generator=torch.Generator().manual_seed(seed), dtype=D)
    C = torch.tensor([[0, 1], [2, 3], [4, 5], [1, 6], [3, 0], [5, 2]])
    if ratings:
        return PreferenceData.create(X, C, torch.tensor([0.8, 0.25, 0.6], dtype=D), torch.tensor([0, 4, 6]))
    return PreferenceData.create(X, C)


def _people():
    shared = _person(3).train_X[:4]
    extra = _person(9)
    mixed = PreferenceData.create(torch.cat([shared, extra.train_X[:3]]), extra.comparisons[:3])
    return check_people([_person(s, ratings=s % 2 == 0) for s in range(5)] + [mixed])


@pytest.mark.parametrize("shards", [1, 2, 4])
def test_sharded_value_and_gradient_are_the_in_process_ones(shards):
    people = _people()
    lik = PreferenceLikelihood.create(1.0, 1.0, 80.0, False, 0.1).double()
    kernels = _Kernels(*_kernels())
    params = list(kernels.parameters())
    here = _objective(kernels, population_layout(people, lik), {})
    g_here = torch.autograd.grad(here, params)
    U, parts = shard_layouts(people, lambda ps: population_layout(ps, lik), shards)
    assert len(parts) == min(shards, len(people))
    with ThreadPoolExecutor(2) as ex:
        there = sharded_objective(ShardedProblem(U, parts, ex), kernels, {})
        g_there = torch.autograd.grad(there, params)
    assert float(there) == pytest.approx(float(here), abs=1e-8)
    for a, b in zip(g_here, g_there):
        torch.testing.assert_close(b, a, rtol=1e-6, atol=1e-8)


def _same_population(a, b, tol):
    for p, q in zip(a.k_m.parameters(), b.k_m.parameters()):
        torch.testing.assert_close(p, q, rtol=tol, atol=tol)
    for p, q in zip(a.k_g.parameters(), b.k_g.parameters()):
        torch.testing.assert_close(p, q, rtol=tol, atol=tol)
    X = torch.rand(6, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(
            a.person_model(X).posterior(X).mean, b.person_model(X).posterior(X).mean, rtol=tol, atol=tol
        )


def test_sharded_fit_on_threads_is_the_in_process_fit():
    people = _people()
    here = fit_population(people, max_iter=15)
    with ThreadPoolExecutor(2) as ex:
        there = fit_population(people, max_iter=15, executor=ex, shards=3)
    _same_population(here, there, 1e-4)


@pytest.mark.slow
def test_sharded_fit_on_processes_is_the_in_process_fit():
    people = _people()
    here = fit_population(people, max_iter=10)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as ex:
        there = fit_population(people, max_iter=10, executor=ex, shards=2)
    _same_population(here, there, 1e-4)


def test_a_forking_process_pool_is_refused_by_name():
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as ex:
        with pytest.raises(ValueError, match="spawn"):
            fit_population(_people(), max_iter=1, executor=ex)


@pytest.mark.slow
@pytest.mark.skipif(
    importlib.util.find_spec("distributed") is None,
    reason="dask.distributed is not installed (the 'dask' extra): no local Dask cluster to run on",
)
def test_sharded_fit_on_a_local_dask_cluster():
    from distributed import Client, LocalCluster

    people = _people()
    here = fit_population(people, max_iter=10)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True) as cluster, Client(cluster) as client:
        there = fit_population(people, max_iter=10, executor=client.get_executor(), shards=2)
    _same_population(here, there, 1e-4)
