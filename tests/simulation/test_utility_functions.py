"""Tests for torchpref.simulation.utility_functions: the random wave functions of eq. 13."""

import math

import numpy as np
import pytest
import torch
from botorch.test_functions.synthetic import SyntheticTestFunction

from torchpref.simulation.utility_functions import WaveFunction, evaluation_grid

PARAMS = dict(
    frequencies=[12.0, 21.5, 28.0],
    amplitudes=[0.7, 1.1, 0.9],
    offsets=[0.2, 0.55, 0.8],
    dampings=[260.0, 300.0, 340.0],
)


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(1234)


def numpy_wave(x, frequencies, amplitudes, offsets, dampings):
    """Eq. 13 written out term by term in numpy."""
    out = np.zeros_like(x)
    for f, a, o, d in zip(frequencies, amplitudes, offsets, dampings):
        out += a * np.cos(np.pi * f * (x - o)) * np.exp(-d * (x - o) ** 2)
    return out


def test_matches_eq13_by_hand():
    problem = WaveFunction(**PARAMS)
    x = np.linspace(0.0, 1.0, 257)
    got = problem(torch.from_numpy(x).unsqueeze(-1), noise=False)
    assert got.shape == (257,) and got.dtype == torch.float64
    np.testing.assert_allclose(got.numpy(), numpy_wave(x, **PARAMS), rtol=0, atol=5e-13)
    # a single point by hand: at x = o_2 the second term is exactly a_2
    x0 = 0.55
    expected = sum(
        a * math.cos(math.pi * f * (x0 - o)) * math.exp(-d * (x0 - o) ** 2) for f, a, o, d in zip(*PARAMS.values())
    )
    assert problem(torch.tensor([[x0]], dtype=torch.float64), noise=False).item() == pytest.approx(expected, abs=1e-14)


def test_batch_shapes_and_float32():
    problem = WaveFunction(**PARAMS)
    X = torch.rand(4, 7, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    f = problem(X)
    assert f.shape == (4, 7)
    np.testing.assert_allclose(f.numpy(), numpy_wave(X[..., 0].numpy(), **PARAMS), atol=1e-13)
    f32 = problem(X.float())
    assert f32.dtype == torch.float32
    torch.testing.assert_close(f32.double(), f, atol=1e-5, rtol=0)


def test_is_a_botorch_maximisation_problem():
    problem = WaveFunction(**PARAMS)
    assert isinstance(problem, SyntheticTestFunction)
    assert problem.dim == 1 and not problem.is_minimization_problem
    torch.testing.assert_close(problem.bounds, torch.tensor([[0.0], [1.0]], dtype=torch.float64))
    for name in ("frequencies", "amplitudes", "offsets", "dampings"):
        buf = dict(problem.named_buffers())[name]
        assert buf.dtype == torch.float64
        assert buf.tolist() == PARAMS[name]
    with pytest.raises(ValueError):  # BoTorch's bounds check
        problem(torch.tensor([[1.5]], dtype=torch.float64))
    negated = WaveFunction(**PARAMS, negate=True)
    assert negated.is_minimization_problem
    X = evaluation_grid()
    torch.testing.assert_close(negated(X), -problem(X))
    assert negated.optimal_value == -problem.optimal_value


def test_optimal_value_is_the_maximum():
    problem = WaveFunction(**PARAMS)
    x = np.linspace(0.0, 1.0, 1_000_001)
    y = numpy_wave(x, **PARAMS)
    assert problem.optimal_value == pytest.approx(y.max(), abs=1e-9)
    assert problem.optimal_value >= y.max() - 1e-12
    x_opt = problem.optimizers[0, 0].item()
    assert x_opt == pytest.approx(x[y.argmax()], abs=1e-5)
    assert problem(problem.optimizers, noise=False).item() == pytest.approx(problem.optimal_value, abs=1e-14)


def test_random_ranges_and_reproducibility(generator):
    problems = [WaveFunction.random(generator=generator) for _ in range(200)]
    for name, (lo, hi) in [
        ("frequencies", WaveFunction.FREQUENCY_RANGE),
        ("amplitudes", WaveFunction.AMPLITUDE_RANGE),
        ("offsets", WaveFunction.OFFSET_RANGE),
        ("dampings", WaveFunction.DAMPING_RANGE),
    ]:
        values = torch.stack([getattr(p, name) for p in problems])
        assert values.shape == (200, 3) and values.dtype == torch.float64
        assert (values >= lo).all() and (values <= hi).all()
        # the draws cover the range (not e.g. stuck at one end)
        assert values.min() < lo + 0.05 * (hi - lo) and values.max() > hi - 0.05 * (hi - lo)
        assert values.mean().item() == pytest.approx((lo + hi) / 2, abs=0.06 * (hi - lo))
    assert (WaveFunction.FREQUENCY_RANGE, WaveFunction.AMPLITUDE_RANGE) == ((10.0, 30.0), (0.6, 1.2))
    assert (WaveFunction.OFFSET_RANGE, WaveFunction.DAMPING_RANGE) == ((0.1, 0.9), (250.0, 350.0))

    a = WaveFunction.random(generator=torch.Generator().manual_seed(7))
    b = WaveFunction.random(generator=torch.Generator().manual_seed(7))
    c = WaveFunction.random(generator=torch.Generator().manual_seed(8))
    X = evaluation_grid()
    assert torch.equal(a(X), b(X))
    assert not torch.allclose(a(X), c(X))
    assert WaveFunction.random(generator=generator, n_components=5).offsets.shape == (5,)


def test_random_does_not_touch_global_rng():
    state = torch.get_rng_state()
    WaveFunction.random(generator=torch.Generator().manual_seed(0))
    assert torch.equal(state, torch.get_rng_state())


def test_noise_uses_generator():
    problem = WaveFunction(**PARAMS, noise_std=0.1)
    X = evaluation_grid()
    n1 = problem(X, generator=torch.Generator().manual_seed(3))
    n2 = problem(X, generator=torch.Generator().manual_seed(3))
    assert torch.equal(n1, n2)
    resid = n1 - problem(X, noise=False)
    assert 0.05 < resid.std().item() < 0.15
    own = WaveFunction(**PARAMS, noise_std=0.1, generator=torch.Generator().manual_seed(3))
    assert torch.equal(own(X), n1)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(PARAMS, frequencies=[1.0, 2.0]), "same length"),
        (dict(PARAMS, offsets=[0.1, float("nan"), 0.3]), "offsets"),
        (dict(PARAMS, amplitudes=[]), "amplitudes"),
        (dict(PARAMS, noise_std=-1.0), "noise_std"),
    ],
)
def test_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        WaveFunction(**kwargs)


def test_evaluation_grid():
    X = evaluation_grid()
    assert X.shape == (101, 1) and X.dtype == torch.float64
    assert X[0, 0] == 0.0 and X[-1, 0] == 1.0
    torch.testing.assert_close(X[1:, 0] - X[:-1, 0], torch.full((100,), 0.01, dtype=torch.float64))
    assert evaluation_grid(100).shape == (100, 1)
    with pytest.raises(ValueError, match="n must"):
        evaluation_grid(1)
    with pytest.raises(ValueError, match="bounds"):
        evaluation_grid(10, bounds=(1.0, 0.0))
