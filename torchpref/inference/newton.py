r"""Newton's method for ``b`` Laplace modes at once, as a few named steps over a small state.

The objective is :mod:`torchpref.inference.laplace`'s whitened log posterior ``Psi(a) = log p(Y | L a) -
a^T a / 2``. One iteration of :func:`newton_mode`:

1. :meth:`Problem.factorise`: ``B = I + L^T W L`` at the current point (Fisher weights for the
   problems whose exact ``B`` is not positive definite);
2. :func:`newton_direction`: the step ``B^-1 grad`` and the Newton decrement ``grad^T B^-1 grad``;
   problems with half a decrement below ``tol`` stop (converged, their factor kept), and so do
   those whose decrement stopped contracting below the round-off floor of their dtype
   (:func:`~torchpref.inference.numerics.roundoff_floor`: a float32 log posterior of ``1e4`` cannot resolve
   a change of ``1e-6``);
3. :meth:`Problem.line_search`: Armijo backtracking, each problem with its own step length;
4. near the mode, :func:`chord_steps`: more steps with the same factor while they contract.

Far from the mode (decrement above 1) large float64 problems take step 1-3 with ``B`` in
float32 (:func:`float32_step`). All tensors are ``b x ...``; every problem's state moves only
while it is *active* (not yet converged or stuck), so each problem follows the iterates it would
follow alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchpref.inference.numerics import NotPSDError, roundoff_floor
from torchpref.inference.observations import Observations
from torchpref.inference.shapes import Latent, Matrices, PerProblem, ProblemMask, TermValues
from torchpref.inference.step_rule import STEP_RULE


@dataclass(frozen=True)
class NewtonOptions:
    max_iter: int
    tol: float
    max_chord: int  # chord steps per factorisation (0: none)
    float32_far: bool  # take the steps far from the mode with B in float32


@dataclass(frozen=True)
class NewtonPoint:
    """One iterate per problem: ``a`` (``b x n``), ``f = L a`` (``None`` where the likelihood was
    evaluated from the rows ``D L``: :meth:`Problem.utilities` forms it on demand), ``Psi(a)``
    (``b``), its gradient ``grad`` (``b x n``) and the likelihood weights there (per term, ``b x m``)."""

    a: Latent
    f: Latent | None
    psi: PerProblem
    grad: Latent
    weights: tuple[TermValues, ...]

    def where(self, take: Tensor, other: NewtonPoint) -> NewtonPoint:
        """This point for the problems in ``take`` (``b`` bool), ``other`` elsewhere."""
        if bool(take.all()):
            return self

        def pick(x: Tensor, y: Tensor) -> Tensor:
            return torch.where(take.reshape(-1, *[1] * (x.dim() - 1)), x, y)

        f = None if self.f is None or other.f is None else pick(self.f, other.f)
        return NewtonPoint(
            pick(self.a, other.a),
            f,
            pick(self.psi, other.psi),
            pick(self.grad, other.grad),
            tuple(pick(x, y) for x, y in zip(self.weights, other.weights)),
        )


@dataclass(frozen=True)
class Factor:
    """``B = I + L^T W L`` factorised at a point: Cholesky ``M`` (``b x n x n``), the weights used
    and which problems used Fisher weights."""

    M: Matrices
    weights: tuple[TermValues, ...]
    fisher: ProblemMask

    def where(self, take: Tensor, other: Factor) -> Factor:
        """Problem by problem: this factor where ``take`` (``b``) is true, ``other`` elsewhere."""
        if bool(take.all()):
            return self
        t1, t2 = take.reshape(-1, 1), take.reshape(-1, 1, 1)
        return Factor(
            torch.where(t2, self.M, other.M),
            tuple(torch.where(t1, x, y) for x, y in zip(self.weights, other.weights)),
            torch.where(take, self.fisher, other.fisher),
        )


@dataclass(frozen=True)
class NewtonResult:
    point: NewtonPoint
    factor: Factor  # exact (or Fisher where it had to be) at ``point``
    converged: ProblemMask
    decrement: PerProblem  # the last Newton decrement of each problem
    iterations: int


class Problem:
    """``b`` whitened log posteriors ``Psi`` given ``L`` (``b x n x n``) and the observations."""

    def __init__(self, L: Tensor, obs: Observations):
        self.L, self.obs = L, obs
        # L is fixed during a solve: where it pays, each term's rows D L are formed once and
        # serve the predictors, the gradient and B (Observations.whitened_rows)
        self.rows = obs.whitened_rows(L)
        self._L32: Tensor | None = None

    def whiten(self, f0: Tensor | None) -> Tensor:
        """``a = L^-1 f0`` (zeros without a start, or for problems whose start is not finite)."""
        if f0 is None:
            return self.L.new_zeros(self.L.shape[:-1])
        a = torch.linalg.solve_triangular(self.L, f0.unsqueeze(-1), upper=False).squeeze(-1)
        return torch.where(torch.isfinite(a).all(-1, keepdim=True), a, 0.0)

    def start(self, starts: tuple[Tensor, ...]) -> NewtonPoint:
        """The point of highest ``Psi`` among the candidate ``starts`` (each ``b x n`` utilities;
        zeros if none), problem by problem."""
        point = self.evaluate(self.whiten(starts[0] if starts else None))
        for start in starts[1:]:
            other = self.evaluate(self.whiten(start))
            point = _pick(other, (other.psi > point.psi).tolist(), point)
        return point

    def evaluate(self, a: Tensor) -> NewtonPoint:
        """``Psi``, its gradient ``L^T grad log p - a`` and the weights at ``a``: one likelihood
        pass serves the line search's test and, if the point is accepted, the next step."""
        if self.rows is None:
            f = (self.L @ a.unsqueeze(-1)).squeeze(-1)
            lt = self.obs.evaluate(f)
            grad = (self.L.mT @ lt.grad.unsqueeze(-1)).squeeze(-1) - a
        else:  # f is not needed on this path: formed only where asked for (utilities)
            f, lt = None, self.obs.evaluate_whitened(a, self.rows)
            grad = lt.grad - a
        return NewtonPoint(a, f, lt.log_lik - 0.5 * (a * a).sum(-1), grad, lt.weights)

    def utilities(self, point: NewtonPoint) -> Tensor:
        """``f = L a`` (``b x n``) at ``point``."""
        return point.f if point.f is not None else (self.L @ point.a.unsqueeze(-1)).squeeze(-1)

    @staticmethod
    def floor(point: NewtonPoint) -> Tensor:
        """The half decrement (``b``) below which ``point``'s dtype cannot resolve progress."""
        prior = 0.5 * (point.a * point.a).sum(-1)
        return roundoff_floor(point.psi + prior, prior)

    def factorise(self, point: NewtonPoint) -> Factor:
        """Cholesky of ``B`` at ``point``; Fisher weights for the problems where ``B`` is not PD."""
        M, info = torch.linalg.cholesky_ex(self.obs.whitened_hessian(self.L, point.weights, self.rows))
        fisher = info > 0
        if not bool(fisher.any()):
            return Factor(M, point.weights, fisher)
        weights = self.obs.evaluate(self.utilities(point), fisher).weights
        M2, info = torch.linalg.cholesky_ex(self.obs.whitened_hessian(self.L, weights, self.rows))
        if bool((info > 0).any()):
            bad = (info > 0).nonzero().reshape(-1).tolist()
            raise NotPSDError(f"the Fisher-scoring Newton matrix B of problems {bad} is not positive definite")
        return Factor(torch.where(fisher.reshape(-1, 1, 1), M2, M), weights, fisher)

    def factorise_float32(self, point: NewtonPoint) -> Tensor | None:
        """Cholesky of ``B`` in float32 at ``point`` (exact weights), or ``None`` if it fails."""
        if self._L32 is None:
            self._L32 = self.L.float()
            self._rows32 = None if self.rows is None else tuple(R.float() for R in self.rows)
        M, info = torch.linalg.cholesky_ex(
            self.obs.whitened_hessian(self._L32, tuple(w.float() for w in point.weights), self._rows32)
        )
        return None if bool((info > 0).any()) else M

    def line_search(
        self, point: NewtonPoint, step: Tensor, decrement: Tensor, active: list[bool], full: list[bool] | None = None
    ) -> tuple[NewtonPoint, list[bool]]:
        """Armijo backtracking for the ``active`` problems; the ``full`` ones take the whole step
        untested. All problems still searching share the step length (each halves it from 1 until
        its test passes), so one evaluation per length serves them all. Returns the new point and
        the problems for which no step length increased ``Psi`` (their point is unchanged)."""
        t, pending, new = 1.0, active, point
        while True:
            trial = self.evaluate(point.a + t * step)
            passed = (torch.isfinite(trial.psi) & (trial.psi >= point.psi + STEP_RULE.armijo * t * decrement)).tolist()
            ok = [p and (a or f) for p, a, f in zip(pending, passed, full or passed)]
            new = _pick(trial, ok, new)
            pending = [p and not o for p, o in zip(pending, ok)]
            if not any(pending):
                return new, pending
            t *= STEP_RULE.shrink
            if t <= STEP_RULE.min_step:
                return new, pending


def _pick(this, take: list[bool], other):
    """``this`` (a :class:`NewtonPoint` or :class:`Factor`) for the problems in ``take``, ``other`` elsewhere."""
    if all(take):
        return this
    if not any(take):
        return other
    return this.where(torch.tensor(take, device=(this.M if isinstance(this, Factor) else this.a).device), other)


def _in_dtype(value: float, dtype: torch.dtype) -> float:
    """``value`` rounded to ``dtype``: compared with a tensor's values, a Python number is (so that
    the tests on the host below decide as the same tests on tensors would)."""
    return torch.tensor(value, dtype=dtype).item()


def newton_direction(M: Tensor, grad: Tensor) -> tuple[Tensor, Tensor]:
    """The step ``B^-1 grad`` (``b x n``) and the Newton decrement ``grad^T B^-1 grad`` (``b``)."""
    step = torch.cholesky_solve(grad.unsqueeze(-1), M).squeeze(-1)
    return step, (grad * step).sum(-1)


def float32_step(
    prob: Problem, point: NewtonPoint, active: list[bool], tol: float
) -> tuple[NewtonPoint, list[float]] | None:
    """One step with ``B`` factorised in float32: ``(new point, decrements)``, or ``None`` when
    float32 does not suffice (failed factorisation, or a step that does not increase ``Psi``)."""
    M = prob.factorise_float32(point)
    if M is None:
        return None
    step32, _ = newton_direction(M, point.grad.float())
    step = step32.to(point.grad.dtype)
    decrement = (point.grad * step).sum(-1)
    dec = decrement.tolist()
    moving = [a and d / 2 >= tol for a, d in zip(active, dec)]
    if not all(math.isfinite(d) or not a for a, d in zip(active, dec)) or not any(moving):
        return None
    new, failed = prob.line_search(point, step, decrement, moving)
    return None if any(failed) else (new, dec)


def chord_steps(
    prob: Problem, point: NewtonPoint, M: Tensor, decrement: list[float], eligible: list[bool], opts: NewtonOptions
) -> tuple[NewtonPoint, list[float]]:
    """Up to ``opts.max_chord`` steps with the factor ``M`` of an earlier point (a new gradient,
    the old ``B``), for each ``eligible`` problem while its decrement contracts fourfold."""
    tol, tiny = _in_dtype(opts.tol, M.dtype), _in_dtype(1e-8, M.dtype)
    for _ in range(opts.max_chord):
        step, dec_t = newton_direction(M, point.grad)
        dec = dec_t.tolist()
        # not contracting (or not finite): refactorise
        eligible = [e and d < 0.25 * old for e, d, old in zip(eligible, dec, decrement)]
        if not any(eligible):
            break
        full = [d < tiny for d in dec]  # Psi would change by less than its round-off: the full step
        point, failed = prob.line_search(point, step, dec_t, eligible, full)
        eligible = [e and not f for e, f in zip(eligible, failed)]
        decrement = [d if e else old for e, d, old in zip(eligible, dec, decrement)]
        eligible = [e and d / 2 >= tol for e, d in zip(eligible, decrement)]  # converged: confirmed with a fresh B
    return point, decrement


def _stalled(prob: Problem, point, dec: list[float], newton_dec: list[float]) -> tuple[list[bool], list | None]:
    """Per problem, whether a whole iteration (step and chord steps) did not contract the decrement
    ``dec`` from the last factorisation's ``newton_dec`` while it is below the round-off floor (no
    further progress can be resolved in this dtype); and the floor, if it was formed (rarely: on
    demand)."""
    stalled = [d > 0.25 * old for d, old in zip(dec, newton_dec)]
    floor = prob.floor(point).tolist() if any(stalled) else None
    if floor is not None:
        stalled = [s and d / 2 < fl for s, d, fl in zip(stalled, dec, floor)]
    return stalled, floor


def newton_mode(L: Tensor, obs: Observations, starts: tuple[Tensor, ...], opts: NewtonOptions) -> NewtonResult:
    """The modes of ``b`` problems (see the module docstring), each from the candidate start (``b x n``
    each; zeros if none) of highest ``Psi``; all inputs detached. The per-problem tests run on the
    host, on one copy of each iteration's decrements (a few numbers)."""
    prob = Problem(L, obs)
    point = prob.start(starts)
    b = L.shape[0]
    tol, stuck_tol = _in_dtype(opts.tol, L.dtype), _in_dtype(STEP_RULE.stuck_tol, L.dtype)
    active, converged, has_factor = [True] * b, [False] * b, [False] * b
    decrement = [math.inf] * b
    newton_dec = decrement  # the decrement of each problem's last factorisation
    final: Factor | None = None
    far = far_allowed = opts.float32_far
    it = 0
    for it in range(1, opts.max_iter + 1):  # noqa: B007 (the count is read after the loop)
        if far:
            taken = float32_step(prob, point, active, opts.tol)
            if taken is not None:
                point, dec32 = taken
                far = any(d > 1.0 for a, d in zip(active, dec32) if a)
                continue
            far = far_allowed = False  # float32 does not suffice for these problems
        factor = prob.factorise(point)
        step, dec_t = newton_direction(factor.M, point.grad)
        dec = dec_t.tolist()
        bad = [i for i, (a, d) in enumerate(zip(active, dec)) if a and not math.isfinite(d)]
        if bad:
            raise FloatingPointError(f"non-finite Newton step while finding the Laplace modes of problems {bad}")
        decrement = [d if a else old for a, d, old in zip(active, dec, decrement)]
        stalled, floor = _stalled(prob, point, dec, newton_dec)
        newton_dec = [d if a else old for a, d, old in zip(active, dec, newton_dec)]
        done = [a and (d / 2 < tol or s) for a, d, s in zip(active, dec, stalled)]  # the point stays: keep B
        if any(done):
            final = factor if final is None else _pick(factor, done, final)
        converged = [c or d for c, d in zip(converged, done)]
        has_factor = [h or d for h, d in zip(has_factor, done)]
        active = [a and not d for a, d in zip(active, done)]
        if not any(active):
            break
        point, stuck = prob.line_search(point, step, dec_t, active)
        if any(stuck):  # no ascent possible in floating point: at the optimum up to round-off
            floor = prob.floor(point).tolist() if floor is None else floor
            converged = [c or (s and d / 2 < max(fl, stuck_tol)) for c, s, d, fl in zip(converged, stuck, dec, floor)]
            active = [a and not s for a, s in zip(active, stuck)]
        # far from the mode the old B is a poor model: refactorise (in float32 where allowed)
        far = far_allowed and any(d > 1.0 for a, d in zip(active, dec) if a)
        near = [a and d <= 1.0 for a, d in zip(active, dec)] if opts.max_chord else None
        if near is not None and any(near):
            point, chord_dec = chord_steps(prob, point, factor.M, dec, near, opts)
            decrement = [c if nr else old for nr, c, old in zip(near, chord_dec, decrement)]
    if not all(has_factor):  # stuck or out of iterations: a factor at the final points
        fresh = prob.factorise(point)
        final = fresh if final is None else _pick(final, has_factor, fresh)
    assert final is not None  # a factor at the final points of every problem
    return NewtonResult(
        replace(point, f=prob.utilities(point)),
        final,
        torch.tensor(converged, device=L.device),
        torch.tensor(decrement, dtype=L.dtype, device=L.device),
        it,
    )
