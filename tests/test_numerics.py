"""Numerical helpers."""

import pytest
import torch

from torchpref.numerics import lower_t_matmul


@pytest.mark.parametrize("n,blocks", [(5, 4), (256, 4), (301, 3), (300, 7)])
def test_lower_t_matmul_is_the_full_product(n, blocks, generator):
    L = torch.tril(torch.randn(n, n, generator=generator, dtype=torch.float64))
    X = torch.randn(n, 9 if n < 100 else n, generator=generator, dtype=torch.float64)
    torch.testing.assert_close(lower_t_matmul(L, X, blocks=blocks), L.T @ X, rtol=1e-12, atol=1e-12)
