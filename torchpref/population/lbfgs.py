r"""The population fit's L-BFGS (strong Wolfe line search), guarded: an evaluation whose evidence or
gradient is not finite, or whose matrices are not positive definite, rejects the step instead of
handing torch's line search a NaN (where it fails with an ``IndexError`` deep inside): the fit
keeps the best point evaluated so far. A start that is itself not finite fails by name.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Protocol

import torch
from linear_operator.utils.errors import NotPSDError
from torch import Tensor

__all__ = ["FitStartError", "minimise"]

log = logging.getLogger("torchpref.population")


class Progress(Protocol):
    """What counts the evaluations (a tqdm bar): ``update()`` once per evaluation."""

    def update(self) -> object: ...


class FitStartError(ValueError):
    """The population's evidence (or its gradient) is not finite at the starting hyperparameters."""


class _Rejected(Exception):
    pass


RESTARTS = 3
"""How many times a search whose step was rejected starts again from the best point (each with half the step)."""


def minimise(
    loss_fn: Callable[[], Tensor], params: list[Tensor], max_iter: int, bar: Progress, describe: Callable[[], str]
) -> int:
    """Minimise ``loss_fn()`` in ``params`` with L-BFGS; returns the number of steps rejected. After a
    rejected step the search starts again from the best point so far, with half the step length, at
    most :data:`RESTARTS` times (then it stops there).

    ``loss_fn`` may keep state of its last evaluation in ``loss_fn.last`` (the population's
    :class:`~torchpref.population.fit.Objective` does: the next mode's warm start); it is put back
    to the best evaluation's with the parameters.

    Raises:
        FitStartError: the first evaluation is not finite (or not positive definite), naming
            ``describe()`` (the starting hyperparameters) and the way out.
    """
    best: list = []  # [loss, parameter values, loss_fn.last]
    evaluations = [0]
    rejected = 0
    while True:
        opt = torch.optim.LBFGS(
            params,
            lr=0.5**rejected,
            max_iter=max(1, max_iter - evaluations[0]),
            line_search_fn="strong_wolfe",
            tolerance_change=1e-9,
        )
        try:
            _step(opt, loss_fn, params, bar, best, evaluations)
            return rejected
        except _Rejected as why:
            if not best:
                raise FitStartError(
                    f"the population fit cannot start: {why} at the starting hyperparameters ({describe()}). "
                    "Start from longer lengthscales (a kernel's lengthscale at its lower bound makes its raw "
                    "value -inf), or from the default kernels."
                ) from None
            with torch.no_grad():
                for p, v in zip(params, best[1]):
                    p.copy_(v)
            if hasattr(loss_fn, "last"):
                loss_fn.last = best[2]
            rejected += 1
            log.warning("fit_population: the line search met %s; the step was rejected (the best point kept).", why)
            if rejected > RESTARTS or evaluations[0] >= max_iter:
                return rejected


def _step(opt, loss_fn, params: list[Tensor], bar: Progress, best: list, evaluations: list[int]) -> None:
    """One L-BFGS run of ``opt``; every finite evaluation better than ``best`` is kept there."""

    def closure() -> Tensor:
        opt.zero_grad()
        try:
            loss = loss_fn()
        except NotPSDError as err:
            raise _Rejected(f"a matrix that is not positive definite ({str(err)[:160]})") from None
        if not bool(torch.isfinite(loss)):
            raise _Rejected(f"an evidence that is not finite ({float(loss.detach())})")
        loss.backward()
        if not all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in params):
            raise _Rejected("a gradient that is not finite")
        bar.update()
        evaluations[0] += 1
        if not best or float(loss.detach()) < best[0]:
            best[:] = [float(loss.detach()), [p.detach().clone() for p in params], getattr(loss_fn, "last", None)]
        return loss

    opt.step(closure)
