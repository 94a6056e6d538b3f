"""The population's evidence over shards of people on an executor: the same value, gradient and
fitted model as in process (threads here; processes and a local Dask cluster where available),
through the same Newton loop, with O(M^2) numbers per Newton step crossing."""

import importlib.util
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import pytest
import torch

import torchpref.population.joint as joint
from torchpref.data.preference_data import PreferenceData
from torchpref.models.defaults import default_covar_module
from torchpref.population.fit import check_people, fit_population, population_objective

D = torch.float64
NEEDS_DASK = pytest.mark.skipif(
    importlib.util.find_spec("distributed") is None,
    reason="dask.distributed is not installed (the 'dask' extra): no local Dask cluster to run on",
)


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


def _people(count=5):
    shared = _person(3).train_X[:4]
    extra = _person(9)
    mixed = PreferenceData.create(torch.cat([shared, extra.train_X[:3]]), extra.comparisons[:3])
    return check_people([_person(s, ratings=s % 2 == 0) for s in range(count)] + [mixed])


def _value_and_gradient(people, inducing, executor=None, shards=None):
    objective, _ = population_objective(people, *_kernels(), inducing=inducing, executor=executor, shards=shards)
    loss = objective()
    return float(loss), torch.autograd.grad(loss, list(objective.kernels.parameters())), objective


@pytest.mark.parametrize("inducing", [None, 12])
@pytest.mark.parametrize("shards", [1, 2, 4])
def test_sharded_value_and_gradient_are_the_in_process_ones(shards, inducing):
    people = _people()
    here, g_here, _ = _value_and_gradient(people, inducing)
    with ThreadPoolExecutor(2) as ex:
        there, g_there, objective = _value_and_gradient(people, inducing, ex, shards)
    assert len(objective.problem.handles) == min(shards, len(people))
    assert there == pytest.approx(here, abs=1e-8)
    for a, b in zip(g_here, g_there):
        torch.testing.assert_close(b, a, rtol=1e-6, atol=1e-8)


def test_in_process_and_sharded_fits_run_the_same_newton_loop(monkeypatch):
    """One loop: joint.newton is what both paths call (counted), with a Host in between."""
    calls = []
    original = joint.newton

    def counted(problem, start, max_iter=100):
        calls.append(type(problem.host).__name__)
        return original(problem, start, max_iter)

    monkeypatch.setattr("torchpref.population.fit.newton", counted)
    fit_population(_people(), max_iter=2)
    with ThreadPoolExecutor(2) as ex:
        fit_population(_people(), max_iter=2, executor=ex, shards=2)
    assert "InProcess" in calls and "OnExecutor" in calls


def test_a_newton_step_sends_order_M_squared_numbers_whatever_the_people():
    """Bytes per Newton step on 2 shards: the same (to the last step's extra S) for 12 and for 60
    people with their own items (the M x M blocks and M-vectors), not growing with the people."""
    per_step = []
    for count in (12, 60):
        people = [_person(100 + s, ratings=True) for s in range(count)]
        with ThreadPoolExecutor(2) as ex:
            pop = fit_population(people, fit=False, inducing=10, executor=ex, shards=2)
        per_step.append(pop.stats["bytes_per_newton_step"])
    M = 10
    bound = 2 * 8 * (2 * M * M + 5 * M + 8)  # 2 shards: S_s (twice at the last step), ga, coupled, a, da, scalars
    assert max(per_step) <= bound and abs(per_step[1] - per_step[0]) <= 0.1 * per_step[0]


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


def test_a_forking_process_pool_and_a_non_executor_are_refused_by_name():
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as ex:
        with pytest.raises(ValueError, match="spawn"):
            fit_population(_people(), max_iter=1, executor=ex)
    with pytest.raises(ValueError, match="executor must be a concurrent.futures.Executor or a Dask client, got int"):
        fit_population(_people(), max_iter=1, executor=5)


@pytest.mark.slow
@NEEDS_DASK
def test_sharded_fit_on_a_local_dask_cluster():
    """Dask's executor (and the client itself): the in-process fit, the shards' states kept on the
    workers (only summaries gathered: O(M^2) bytes per Newton step, as in process)."""
    from distributed import Client, LocalCluster

    people = _people()
    here = fit_population(people, max_iter=10, inducing=12)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True) as cluster, Client(cluster) as client:
        there = fit_population(people, max_iter=10, inducing=12, executor=client.get_executor(), shards=2)
        direct = fit_population(people, fit=False, inducing=12, executor=client, shards=2)
    _same_population(here, there, 1e-4)
    assert direct.stats["bytes_per_newton_step"] <= 2 * 8 * (2 * 12 * 12 + 5 * 12 + 8)
