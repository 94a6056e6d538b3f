r"""Newton's method for ``B`` Laplace modes at once, as a few named steps over a small state.

The objective is :mod:`torchpref.laplace`'s whitened log posterior ``Psi(a) = log p(Y | L a) -
a^T a / 2``. One iteration of :func:`newton_mode`:

1. :meth:`Problem.factorise`: ``B = I + L^T W L`` at the current point (Fisher weights for the
   problems whose exact ``B`` is not positive definite);
2. :func:`newton_direction`: the step ``B^-1 grad`` and the Newton decrement ``grad^T B^-1 grad``;
   problems with half a decrement below ``tol`` stop (converged, their factor kept), and so do
   those whose decrement stopped contracting below the round-off floor of their dtype
   (:func:`~torchpref.numerics.roundoff_floor`: a float32 log posterior of ``1e4`` cannot resolve
   a change of ``1e-6``);
3. :meth:`Problem.line_search`: Armijo backtracking, each problem with its own step length;
4. near the mode, :func:`chord_steps`: more steps with the same factor while they contract.

Far from the mode (decrement above 1) large float64 problems take step 1-3 with ``B`` in
float32 (:func:`float32_step`). All tensors are ``B x ...``; every problem's state moves only
while it is *active* (not yet converged or stuck), so each problem follows the iterates it would
follow alone.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchpref.numerics import NotPSDError, roundoff_floor
from torchpref.observations import Observations

ARMIJO = 1e-4  # sufficient increase: Psi(a + t s) >= Psi(a) + ARMIJO t grad^T s
MIN_STEP = 1e-12  # backtracking gives up below this step length
STUCK_TOL = 1e-6  # half-decrement below which a problem with no ascent left counts as converged


@dataclass(frozen=True)
class NewtonOptions:
    max_iter: int
    tol: float
    max_chord: int  # chord steps per factorisation (0: none)
    float32_far: bool  # take the steps far from the mode with B in float32


@dataclass(frozen=True)
class NewtonPoint:
    """One iterate per problem: ``a`` (``B x n``), ``f = L a`` (``None`` where the likelihood was
    evaluated from the rows ``D L``: :meth:`Problem.utilities` forms it on demand), ``Psi(a)``
    (``B``), its gradient ``grad`` (``B x n``) and the likelihood weights there (per term, ``B x m``)."""

    a: Tensor
    f: Tensor | None
    psi: Tensor
    grad: Tensor
    weights: tuple[Tensor, ...]

    def where(self, take: Tensor, other: "NewtonPoint") -> "NewtonPoint":
        """This point for the problems in ``take`` (``B`` bool), ``other`` elsewhere."""
        if bool(take.all()):
            return self

        def pick(x: Tensor, y: Tensor) -> Tensor:
            return torch.where(take.reshape(-1, *[1] * (x.dim() - 1)), x, y)
        f = None if self.f is None or other.f is None else pick(self.f, other.f)
        return NewtonPoint(pick(self.a, other.a), f, pick(self.psi, other.psi),
                           pick(self.grad, other.grad),
                           tuple(pick(x, y) for x, y in zip(self.weights, other.weights)))


@dataclass(frozen=True)
class Factor:
    """``B = I + L^T W L`` factorised at a point: Cholesky ``M`` (``B x n x n``), the weights used
    and which problems used Fisher weights."""

    M: Tensor
    weights: tuple[Tensor, ...]
    fisher: Tensor

    def where(self, take: Tensor, other: "Factor") -> "Factor":
        """Problem by problem: this factor where ``take`` (``B``) is true, ``other`` elsewhere."""
        if bool(take.all()):
            return self
        t1, t2 = take.reshape(-1, 1), take.reshape(-1, 1, 1)
        return Factor(torch.where(t2, self.M, other.M),
                      tuple(torch.where(t1, x, y) for x, y in zip(self.weights, other.weights)),
                      torch.where(take, self.fisher, other.fisher))


@dataclass(frozen=True)
class NewtonResult:
    point: NewtonPoint
    factor: Factor  # exact (or Fisher where it had to be) at ``point``
    converged: Tensor  # B bool
    decrement: Tensor  # B, the last Newton decrement of each problem
    iterations: int


class Problem:
    """``B`` whitened log posteriors ``Psi`` given ``L`` (``B x n x n``) and the observations."""

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
        """``f = L a`` (``B x n``) at ``point``."""
        return point.f if point.f is not None else (self.L @ point.a.unsqueeze(-1)).squeeze(-1)

    @staticmethod
    def floor(point: NewtonPoint) -> Tensor:
        """The half decrement (``B``) below which ``point``'s dtype cannot resolve progress."""
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
            self.obs.whitened_hessian(self._L32, tuple(w.float() for w in point.weights), self._rows32))
        return None if bool((info > 0).any()) else M

    def line_search(self, point: NewtonPoint, step: Tensor, decrement: Tensor, active: Tensor,
                    full: Tensor | None = None) -> tuple[NewtonPoint, Tensor]:
        """Armijo backtracking for the ``active`` problems; the ``full`` ones take the whole step
        untested. All problems still searching share the step length (each halves it from 1 until
        its test passes), so one evaluation per length serves them all. Returns the new point and
        the problems for which no step length increased ``Psi`` (their point is unchanged)."""
        t, pending, new = 1.0, active, point
        while True:
            trial = self.evaluate(point.a + t * step)
            ok = pending & torch.isfinite(trial.psi) & (trial.psi >= point.psi + ARMIJO * t * decrement)
            if full is not None:
                ok |= pending & full
            new = trial.where(ok, new)
            pending = pending & ~ok
            if not bool(pending.any()):
                return new, pending
            t *= 0.5
            if t <= MIN_STEP:
                return new, pending


def newton_direction(M: Tensor, grad: Tensor) -> tuple[Tensor, Tensor]:
    """The step ``B^-1 grad`` (``B x n``) and the Newton decrement ``grad^T B^-1 grad`` (``B``)."""
    step = torch.cholesky_solve(grad.unsqueeze(-1), M).squeeze(-1)
    return step, (grad * step).sum(-1)


def float32_step(prob: Problem, point: NewtonPoint, active: Tensor, tol: float):
    """One step with ``B`` factorised in float32: ``(new point, decrements)``, or ``None`` when
    float32 does not suffice (failed factorisation, or a step that does not increase ``Psi``)."""
    M = prob.factorise_float32(point)
    if M is None:
        return None
    step32, _ = newton_direction(M, point.grad.float())
    step = step32.to(point.grad.dtype)
    decrement = (point.grad * step).sum(-1)
    moving = active & (decrement / 2 >= tol)
    if not bool((torch.isfinite(decrement) | ~active).all()) or not bool(moving.any()):
        return None
    new, failed = prob.line_search(point, step, decrement, moving)
    return None if bool(failed.any()) else (new, decrement)


def chord_steps(prob: Problem, point: NewtonPoint, M: Tensor, decrement: Tensor, eligible: Tensor,
                opts: NewtonOptions) -> tuple[NewtonPoint, Tensor]:
    """Up to ``opts.max_chord`` steps with the factor ``M`` of an earlier point (a new gradient,
    the old ``B``), for each ``eligible`` problem while its decrement contracts fourfold."""
    for _ in range(opts.max_chord):
        step, dec = newton_direction(M, point.grad)
        eligible = eligible & (dec < 0.25 * decrement)  # not contracting (or not finite): refactorise
        if not bool(eligible.any()):
            break
        full = dec < 1e-8  # Psi would change by less than its round-off: the full step
        point, failed = prob.line_search(point, step, dec, eligible, full)
        eligible = eligible & ~failed
        decrement = torch.where(eligible, dec, decrement)
        eligible = eligible & (decrement / 2 >= opts.tol)  # converged: confirmed with a fresh B
    return point, decrement


def newton_mode(L: Tensor, obs: Observations, starts: tuple[Tensor, ...], opts: NewtonOptions) -> NewtonResult:
    """The modes of ``B`` problems (see the module docstring), each from the candidate start (``B x n``
    each; zeros if none) of highest ``Psi``; all inputs detached."""
    prob = Problem(L, obs)
    point = prob.evaluate(prob.whiten(starts[0] if starts else None))
    for start in starts[1:]:
        other = prob.evaluate(prob.whiten(start))
        point = other.where(other.psi > point.psi, point)
    B = L.shape[0]
    active = torch.ones(B, dtype=torch.bool, device=L.device)
    converged, has_factor = torch.zeros_like(active), torch.zeros_like(active)
    decrement = torch.full((B,), float("inf"), dtype=L.dtype, device=L.device)
    newton_dec = decrement  # the decrement of each problem's last factorisation
    final: Factor | None = None
    far = far_allowed = opts.float32_far
    it = 0
    for it in range(1, opts.max_iter + 1):
        if far:
            taken = float32_step(prob, point, active, opts.tol)
            if taken is not None:
                point, dec32 = taken
                far = bool((dec32[active] > 1.0).any())
                continue
            far = far_allowed = False  # float32 does not suffice for these problems
        factor = prob.factorise(point)
        step, dec = newton_direction(factor.M, point.grad)
        if not bool(torch.isfinite(dec).all()) and not bool((torch.isfinite(dec) | ~active).all()):
            bad = (active & ~torch.isfinite(dec)).nonzero().reshape(-1).tolist()
            raise FloatingPointError(f"non-finite Newton step while finding the Laplace modes of problems {bad}")
        decrement = torch.where(active, dec, decrement)
        # stalled: a whole iteration (step and chord steps) did not contract the decrement, which
        # is below the round-off floor: no further progress can be resolved in this dtype
        stalled = dec > 0.25 * newton_dec
        floor = prob.floor(point) if bool(stalled.any()) else None  # rarely needed: formed on demand
        stalled = stalled if floor is None else stalled & (dec / 2 < floor)
        newton_dec = torch.where(active, dec, newton_dec)
        done = active & ((dec / 2 < opts.tol) | stalled)  # the point stays: keep this factorisation
        if bool(done.any()):
            final = factor if final is None else factor.where(done, final)
        converged, has_factor, active = converged | done, has_factor | done, active & ~done
        if not bool(active.any()):
            break
        point, stuck = prob.line_search(point, step, dec, active)
        if bool(stuck.any()):  # no ascent possible in floating point: at the optimum up to round-off
            floor = prob.floor(point) if floor is None else floor
            converged, active = converged | (stuck & (dec / 2 < floor.clamp(min=STUCK_TOL))), active & ~stuck
        # far from the mode the old B is a poor model: refactorise (in float32 where allowed)
        far = far_allowed and bool((dec[active] > 1.0).any())
        near = active & (dec <= 1.0) if opts.max_chord else None
        if near is not None and bool(near.any()):
            point, chord_dec = chord_steps(prob, point, factor.M, dec, near, opts)
            decrement = torch.where(near, chord_dec, decrement)
    if not bool(has_factor.all()):  # stuck or out of iterations: a factor at the final points
        fresh = prob.factorise(point)
        final = fresh if final is None else final.where(has_factor, fresh)
    return NewtonResult(replace(point, f=prob.utilities(point)), final, converged, decrement, it)
