r"""The Newton-Armijo step rule, named once for every Newton loop of the library.

The torch solver (:mod:`torchpref.inference.newton`), the compiled one
(:mod:`torchpref.inference._compiled`) and the population's joint mode
(:mod:`torchpref.population.joint`, in process and sharded) all take a Newton step ``s`` from
``a`` and accept the first length ``t = 1, 1/2, 1/4, ...`` with the sufficient increase

    ``Psi(a + t s) >= Psi(a) + armijo * t * grad^T s``

giving up below ``min_step``. A problem whose half-decrement is below ``stuck_tol`` when no length
increases ``Psi`` counts as converged (its mode is as good as round-off allows).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class StepRule:
    """Armijo backtracking's constants: the sufficient-increase factor, the factor a rejected
    length is multiplied by, the shortest length tried, and the stuck-but-converged tolerance."""

    armijo: float = 1e-4
    shrink: float = 0.5
    min_step: float = 1e-12
    stuck_tol: float = 1e-6

    def lengths(self) -> Iterator[float]:
        """The step lengths tried, longest first: ``1, shrink, shrink^2, ...`` above ``min_step``."""
        t = 1.0
        while t > self.min_step:
            yield t
            t *= self.shrink

    def accepts(self, psi_new: float, psi: float, t: float, decrement: float) -> bool:
        """Whether length ``t`` gives a finite ``Psi`` with the sufficient increase."""
        return math.isfinite(psi_new) and psi_new >= psi + self.armijo * t * decrement

    def backtrack(
        self, trial: Callable[[float], T], psi_of: Callable[[T], float], psi: float, decrement: float
    ) -> T | None:
        """The first accepted trial point ``trial(t)`` over :meth:`lengths`, or ``None`` if none is."""
        for t in self.lengths():
            point = trial(t)
            if self.accepts(psi_of(point), psi, t, decrement):
                return point
        return None


STEP_RULE = StepRule()
"""The one instance every Newton loop reads."""
