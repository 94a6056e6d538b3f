"""A small sample of the hostile-problem fuzz (``benchmarks/fuzz.py`` runs a thousand and more):
extreme hyperparameters, contradictory and duplicated data, n = 1 to 1,500, float32 and float64."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import fuzz_problems as fp  # noqa: E402

SEEDS = range(40)


@pytest.fixture(scope="module")
def records():
    rows = [fp.check(fp.make_problem(seed, max_n=150)) for seed in SEEDS]
    rows.append(fp.check(fp.make_problem(0, max_n=1500), pairwisegp=False))  # n = 1,205 comparisons
    return rows


def test_sample_spans_the_problem_space(records):
    assert {r["kind"] for r in records} == set(fp.KINDS)
    assert min(r["n"] for r in records) == 1 and max(r["n"] for r in records) > 1000


def test_float64_never_fails(records):
    bad = [r for r in records if r["f64_error"] or r["f64_nan"] or not r["f64_converged"]]
    assert not bad, bad


def test_float32_has_no_nan_and_fails_no_more_often_than_pairwisegp(records):
    assert not [r for r in records if r["f32_nan"]]
    comp = [r for r in records if r["kind"] == "comparisons" and r["pairwisegp_nan"] is not None]
    assert sum(r["f32_error"] is not None for r in comp) <= sum(r["pairwisegp_error"] is not None for r in comp)
    # any float32 failure is a named numerical error, never a crash of another kind
    assert all(r["f32_error"].startswith("NotPSDError") for r in records if r["f32_error"])


def test_float32_posterior_agrees_with_float64_with_autograd_on_and_off(records):
    both = [r for r in records if r["gap_mean_nograd"] is not None]
    assert len(both) >= 0.9 * len(records)
    gaps = {tag: [max(r[f"gap_mean_{tag}"], r[f"gap_cov_{tag}"]) for r in both] for tag in ("nograd", "grad")}
    for tag, g in gaps.items():
        assert sorted(g)[len(g) // 2] < 1e-4, tag  # the median problem agrees to float32's resolution
        assert sum(x <= 1e-3 for x in g) >= 0.8 * len(g), (tag, sorted(g)[-8:])
    # autograd changes nothing: the kernel is exact at coincident points either way
    for a, b in zip(gaps["nograd"], gaps["grad"]):
        assert b <= a + 1e-6
