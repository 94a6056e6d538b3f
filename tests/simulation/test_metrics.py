"""Tests for torchpref.simulation.metrics against hand-written numpy / scipy values."""

import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from torchpref.simulation.metrics import (
    error_on_best,
    expected_rating,
    rating_from_latent,
    true_positives,
    wrms,
    wrms_authors,
)


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(2024)


def rand(*shape, generator):
    return torch.rand(*shape, generator=generator, dtype=torch.float64)


def test_wrms_eq14_by_hand():
    est = np.array([0.1, 0.9, 0.5, 0.3])
    true = np.array([0.2, 0.6, 0.5, 0.8])
    # eq. 14 term by term
    terms = [(e - t) ** 2 * max(e, t) for e, t in zip(est, true)]
    expected = math.sqrt(sum(terms) / 4)
    got = wrms(torch.tensor(est), torch.tensor(true))
    assert got.shape == () and got.item() == pytest.approx(expected, abs=1e-15)
    # symmetric in est/true (max weight), which the authors' variant is not
    assert wrms(torch.tensor(true), torch.tensor(est)).item() == pytest.approx(expected, abs=1e-15)


def test_wrms_authors_by_hand():
    est = np.array([0.1, 0.9, 0.5, 0.3])
    true = np.array([0.2, 0.6, 0.5, 0.8])
    expected = math.sqrt(np.mean((true * (est - true)) ** 2))
    got = wrms_authors(torch.tensor(est), torch.tensor(true))
    assert got.item() == pytest.approx(expected, abs=1e-15)
    assert got.item() != pytest.approx(wrms(torch.tensor(est), torch.tensor(true)).item(), abs=1e-3)
    # an over-estimate where the truth is 0 costs nothing in the code's form, but does in eq. 14
    z = torch.zeros(3, dtype=torch.float64)
    assert wrms_authors(torch.ones(3, dtype=torch.float64), z).item() == 0.0
    assert wrms(torch.ones(3, dtype=torch.float64), z).item() == pytest.approx(1.0)


@pytest.mark.parametrize("batch", [(), (3,), (2, 5)])
def test_wrms_batch_and_perfect(batch, generator):
    est, true = rand(*batch, 11, generator=generator), rand(*batch, 11, generator=generator)
    for fn in (wrms, wrms_authors):
        out = fn(est, true)
        assert out.shape == batch
        flat_e, flat_t = est.reshape(-1, 11), true.reshape(-1, 11)
        rows = torch.stack([fn(e, t) for e, t in zip(flat_e, flat_t)])
        torch.testing.assert_close(out.reshape(-1), rows)
        assert (fn(true, true) == 0).all()
    # broadcasting one truth over several estimates
    assert wrms(rand(4, 11, generator=generator), true.reshape(-1, 11)[0]).shape == (4,)


def test_wrms_bad_shapes():
    with pytest.raises(ValueError, match="same non-zero number"):
        wrms(torch.zeros(3), torch.zeros(4))
    with pytest.raises(ValueError, match="last"):
        wrms(torch.tensor(0.5), torch.tensor(0.5))
    with pytest.raises(ValueError, match="broadcast"):
        wrms(torch.zeros(2, 3), torch.zeros(4, 3))


def test_true_positives_by_hand():
    true = torch.tensor([0.9, 0.1, 0.8, 0.7, 0.2, 0.3], dtype=torch.float64)  # top-3: {0, 2, 3}
    est = torch.tensor([0.5, 0.9, 0.8, 0.1, 0.2, 0.6], dtype=torch.float64)  # top-3: {1, 2, 5}
    assert true_positives(est, true, k=3).item() == 1
    assert true_positives(true, true, k=3).item() == 3
    assert true_positives(-true, true, k=3).item() == 0
    # only the order matters: a monotone map of the estimate changes nothing
    assert true_positives(torch.exp(5 * est), true, k=3).item() == 1
    assert true_positives(est, true, k=6).item() == 6


def test_true_positives_batch_matches_sets(generator):
    est, true = rand(4, 3, 101, generator=generator), rand(4, 3, 101, generator=generator)
    tp = true_positives(est, true)  # k = 15, as in the paper
    assert tp.shape == (4, 3) and tp.dtype == torch.long
    e, t = est.numpy().reshape(-1, 101), true.numpy().reshape(-1, 101)
    expected = [len(set(np.argsort(-a)[:15]) & set(np.argsort(-b)[:15])) for a, b in zip(e, t)]
    assert tp.reshape(-1).tolist() == expected
    assert (true_positives(true, true) == 15).all()
    # identical orderings with different values
    assert (true_positives(2 * true + 1, true) == 15).all()


@pytest.mark.parametrize("k", [0, 7, 2.0])
def test_true_positives_bad_k(k):
    with pytest.raises(ValueError, match="k must"):
        true_positives(torch.zeros(6), torch.zeros(6), k=k)


def test_error_on_best():
    true = torch.tensor([0.9, 0.1, 0.9, 0.5], dtype=torch.float64)
    est = torch.tensor([0.7, 0.0, 1.0, 0.0], dtype=torch.float64)
    # default: items at the true maximum (0 and 2): (0.2 + 0.1) / 2
    assert error_on_best(est, true).item() == pytest.approx(0.15)
    mask = torch.tensor([False, True, False, True])
    assert error_on_best(est, true, mask).item() == pytest.approx((0.1 + 0.5) / 2)
    assert error_on_best(est, true, threshold=0.5).item() == pytest.approx((0.2 + 0.1 + 0.5) / 3)
    assert error_on_best(true, true).item() == 0.0
    # batch: one mask per row, broadcast truth
    est_b = torch.stack([est, true])
    mask_b = torch.tensor([[True, False, False, False], [False, False, True, True]])
    torch.testing.assert_close(error_on_best(est_b, true, mask_b), torch.tensor([0.2, 0.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="select no item"):
        error_on_best(est, true, torch.zeros(4, dtype=torch.bool))
    with pytest.raises(ValueError, match="boolean"):
        error_on_best(est, true, torch.ones(4))
    with pytest.raises(ValueError, match="not both"):
        error_on_best(est, true, mask, threshold=0.5)


def test_rating_from_latent():
    f = torch.linspace(-3, 3, 13, dtype=torch.float64)
    got = rating_from_latent(f, 0.8)
    np.testing.assert_allclose(got.numpy(), norm.cdf(f.numpy() / (0.8 * np.sqrt(2))), rtol=1e-14)
    assert rating_from_latent(torch.zeros(1, dtype=torch.float64), 0.3).item() == 0.5
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="rating_scale"):
            rating_from_latent(f, bad)


def test_expected_rating_closed_form_and_quadrature():
    mean = torch.tensor([-1.5, -0.2, 0.0, 0.4, 2.0], dtype=torch.float64)
    var = torch.tensor([0.0, 0.3, 1.0, 2.5, 0.05], dtype=torch.float64)
    sigma_b = 0.8
    got = expected_rating(mean, var, sigma_b)
    np.testing.assert_allclose(got.numpy(), norm.cdf(mean.numpy() / np.sqrt(2 * sigma_b**2 + var.numpy())), rtol=1e-14)
    # eq. 11: integrate Phi(f / (sigma_B sqrt 2)) against N(f; m, v) by Gauss-Hermite quadrature
    nodes, weights = np.polynomial.hermite_e.hermegauss(80)
    for m, v, g in zip(mean.numpy(), var.numpy(), got.numpy()):
        f = m + np.sqrt(v) * nodes
        integral = np.sum(weights * norm.cdf(f / (sigma_b * np.sqrt(2)))) / np.sqrt(2 * np.pi)
        assert g == pytest.approx(integral, abs=1e-10)
    # zero variance gives the plain link; batch broadcasting
    torch.testing.assert_close(expected_rating(mean, torch.zeros(()), sigma_b), rating_from_latent(mean, sigma_b))
    assert expected_rating(mean.expand(3, 5), var, sigma_b).shape == (3, 5)
    with pytest.raises(ValueError, match="var"):
        expected_rating(mean, -var - 1, sigma_b)
    with pytest.raises(ValueError, match="rating_scale"):
        expected_rating(mean, var, 0.0)
