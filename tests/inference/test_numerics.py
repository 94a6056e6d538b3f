"""Numerical helpers."""

import pytest
import torch

from torchpref.inference.numerics import lower_t_matmul


@pytest.mark.parametrize("n,blocks", [(5, 4), (256, 4), (301, 3), (300, 7)])
def test_lower_t_matmul_is_the_full_product(n, blocks, generator):
    L = torch.tril(torch.randn(n, n, generator=generator, dtype=torch.float64))
    X = torch.randn(n, 9 if n < 100 else n, generator=generator, dtype=torch.float64)
    torch.testing.assert_close(lower_t_matmul(L, X, blocks=blocks), L.T @ X, rtol=1e-12, atol=1e-12)


def test_cholesky_jittered_names_the_failure():
    from torchpref.inference.numerics import NotPSDError, cholesky_jittered

    A = torch.eye(4, dtype=torch.float64)
    A[1, 2] = A[2, 1] = float("nan")
    with pytest.raises(NotPSDError, match="non-finite"):
        cholesky_jittered(A)
    with pytest.raises(NotPSDError, match="not positive definite even with jitter"):
        cholesky_jittered(-torch.eye(3, dtype=torch.float64))
    # singular (rank one) but positive semi-definite: a small jitter suffices and is reported
    v = torch.arange(1.0, 4.0, dtype=torch.float64)
    L, j = cholesky_jittered(torch.outer(v, v), jitter=None)
    assert 0 < j <= 1e-6
    torch.testing.assert_close(L @ L.T, torch.outer(v, v) + j * torch.eye(3, dtype=torch.float64))


def test_cholesky_batch_per_matrix_schedules():
    from torchpref.inference.numerics import cholesky_batch

    eye = torch.eye(3, dtype=torch.float64)
    A = torch.stack([eye, torch.ones(3, 3, dtype=torch.float64), -eye])  # fine, singular, negative definite
    J = torch.tensor([[0.0, 0.0, 0.0], [1e-3, 1e-1, 1e-3], [1e-2, 1.0, 1e-2]], dtype=torch.float64)  # k x T
    L, jitter, failed = cholesky_batch(A, J)
    assert failed.tolist() == [False, False, True]
    assert jitter[:2].tolist() == [0.0, 0.1]  # the second matrix: its own schedule's first success
    assert torch.allclose(L[:2] @ L[:2].mT, A[:2] + jitter[:2].reshape(2, 1, 1) * eye)


def test_gauss_hermite_moments():
    import math

    from torchpref.inference.numerics import gauss_hermite

    x, w = gauss_hermite(10, torch.zeros((), dtype=torch.float64))
    m, v = 0.3, 2.0
    z = m + math.sqrt(2 * v) * x
    # E[Z^2] = m^2 + v and E[Z^4] = m^4 + 6 m^2 v + 3 v^2 under N(m, v): exact for 10 nodes
    assert float((w * z**2).sum()) == pytest.approx(m**2 + v, rel=1e-12)
    assert float((w * z**4).sum()) == pytest.approx(m**4 + 6 * m**2 * v + 3 * v**2, rel=1e-12)
    x2, w2 = gauss_hermite(10, x, expectation=False)
    assert float((w2 * x2**2).sum()) == pytest.approx(math.sqrt(math.pi) / 2, rel=1e-12)
