"""Fixtures for the speed benchmarks (run apart: ``pytest benchmarks/ --benchmark-only``)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_common as bc

# One thread by default, as in speed_pairwise.py: on a shared machine, spinning OpenMP threads make
# multi-thread timings erratic. TORCHPREF_BENCH_THREADS=0 keeps torch's default.
_threads = int(os.environ.get("TORCHPREF_BENCH_THREADS", "1"))
if _threads > 0:
    torch.set_num_threads(_threads)


@pytest.fixture(scope="session", params=bc.SIZES, ids=[f"n{n}-p{p}" for n, p in bc.SIZES])
def comparisons_data(request):
    """``(X, comparisons)`` from a seeded generator, one per size in ``bc.SIZES``."""
    n, p = request.param
    return bc.make_comparisons(n, p)


@pytest.fixture(scope="session")
def fitted_models(comparisons_data):
    """Both models fitted from the same initial hyperparameters, caches warm."""
    X, C = comparisons_data
    tp, pg = bc.mode_torchpref(X, C), bc.build_pairwisegp(X, C)
    bc.fit_torchpref(tp)
    bc.fit_pairwisegp(pg)
    Xq = bc.query_points()
    bc.posterior_moments(tp, Xq)
    bc.posterior_moments(pg, Xq)
    return {"torchpref": tp, "pairwisegp": pg}
