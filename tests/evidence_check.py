"""A shared check: the Laplace evidence's gradient against central finite differences."""

from __future__ import annotations

import torch


def assert_evidence_gradient(model, params: dict, h: float = 1e-5, rtol: float = 1e-5) -> None:
    """Autograd's gradient of ``model.log_marginal_likelihood()`` in each raw parameter of
    ``params`` (name -> tensor) against central differences of the re-solved evidence, element by
    element; each parameter is put back, so the evidence is unchanged afterwards."""
    value = model.log_marginal_likelihood()
    grads = torch.autograd.grad(value, list(params.values()), allow_unused=True)
    for (name, p), g in zip(params.items(), grads):
        assert g is not None, f"no gradient for {name}"
        for k in range(p.numel()):
            with torch.no_grad():
                p.view(-1)[k] += h
                up = float(model.log_marginal_likelihood().detach())  # re-solves the mode
                p.view(-1)[k] -= 2 * h
                down = float(model.log_marginal_likelihood().detach())
                p.view(-1)[k] += h
            fd = (up - down) / (2 * h)
            gk = float(g.reshape(-1)[k])
            assert abs(gk - fd) <= rtol * max(abs(fd), 1e-2), f"{name}[{k}]: autograd {gk} vs FD {fd}"
    assert abs(float(model.log_marginal_likelihood().detach()) - float(value.detach())) < 1e-10  # restored
