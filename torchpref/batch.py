r"""Many independent preference models at once: one batched Laplace solve for ``T`` trials.

A simulation study (the wave experiment: 100 trials x 20 queries x 5 strategies) asks the
same kind of question of many independent models, each small (tens of items). Solved one by
one, such models cost mostly Python overhead; :class:`BatchedPreferenceGP` holds ``T`` of
them, with shared fixed hyperparameters (one kernel, one pair of likelihoods), pads their
items and observations to common sizes and solves all the Laplace modes (eq. 2) with one
batched Newton iteration. Each trial keeps its own validated :class:`~torchpref.data.PreferenceData`,
so adding answers works (and fails) exactly as on a :class:`~torchpref.PreferenceGP`.

Padding is exact: a padded item has prior variance 1, no correlation with anything and no
observation, so its mode is 0 and it changes nothing; padded observations have zero weight.

The per-trial results equal those of ``T`` separate :class:`~torchpref.PreferenceGP` models
(same mode to the Newton tolerance, same predictions); ``tests/test_batch.py`` checks this.
Hyperparameters are fixed (no fitting): use a :class:`~torchpref.PreferenceGP` to fit them.
"""

from __future__ import annotations

import copy
import warnings
from typing import Sequence

import torch
from torch import Tensor

from torchpref.data import PreferenceData
from torchpref.laplace import LaplaceConvergenceWarning
from torchpref.models import PreferenceGP
from torchpref.numerics import NotPSDError, batched_cholesky


def _pad(tensors: Sequence[Tensor], length: int, fill) -> Tensor:
    """Stack 1-D or 2-D tensors along a new first dim, padding their first dim to ``length``."""
    out = tensors[0].new_full((len(tensors), length, *tensors[0].shape[1:]), fill)
    for b, t in enumerate(tensors):
        out[b, : t.shape[0]] = t
    return out


class BatchedPreferenceGP:
    r"""``T`` independent mixed ratings + comparisons models with shared fixed hyperparameters.

    Build it from ``T`` :class:`~torchpref.PreferenceGP` models (:meth:`from_models`) that share
    their kernel's and likelihoods' values; each trial starts with its model's data, and the
    hyperparameters are copied (changing the models afterwards changes no trial). Answers go
    in per trial (:meth:`add_observations`); modes are re-solved, all at once and warm-started,
    when a prediction is next asked for.

    Shapes: ``T`` trials, ``X`` of shape ``T x N x d`` (``N`` points per trial).
    """

    def __init__(self, template: PreferenceGP, data: Sequence[PreferenceData], tol: float = 1e-11):
        if getattr(template, "input_transform", None) is not None:
            raise ValueError("BatchedPreferenceGP does not support input transforms; transform the items first.")
        if len(data) < 1:
            raise ValueError("need at least one trial.")
        self.template = copy.deepcopy(template)  # the hyperparameters as they are now
        self.covar_module = self.template.covar_module
        self.likelihood = self.template.likelihood
        self.rating_eps = template.rating_eps
        self.max_newton_iter = template.max_newton_iter
        self.tol = tol
        self._data = list(data)
        self._cache: dict | None = None
        self._stale: dict | None = None  # the last solved state, for warm starts

    @classmethod
    def from_models(cls, models: Sequence[PreferenceGP]) -> "BatchedPreferenceGP":
        """One trial per model; all must hold the same hyperparameter values (a ``ValueError``
        names the first that does not). The first model's kernel and likelihoods are used."""
        if len(models) < 1:
            raise ValueError("need at least one model.")
        ref = models[0].state_dict()
        for b, m in enumerate(models[1:], start=1):
            sd = m.state_dict()
            if sd.keys() != ref.keys() or not all(torch.equal(sd[k], ref[k]) for k in ref):
                raise ValueError(f"model {b} has hyperparameters different from model 0's.")
        return cls(models[0], [m.data for m in models])

    # ------------------------------------------------------------------ data
    @property
    def num_trials(self) -> int:
        return len(self._data)

    def data(self, trial: int) -> PreferenceData:
        """The observations of one trial."""
        return self._data[trial]

    def add_observations(self, trial: int, X: Tensor | None = None, comparisons: Tensor | None = None,
                         ratings: Tensor | None = None, rating_index: Tensor | None = None) -> None:
        r"""Add items and observations to one trial, as :meth:`PreferenceGP.add_observations`
        (validated first: on error nothing changes)."""
        if not 0 <= trial < self.num_trials:
            raise ValueError(f"trial must be in 0..{self.num_trials - 1}, got {trial}.")
        self._data[trial] = self._data[trial].add(X, comparisons, ratings, rating_index, rating_eps=self.rating_eps)
        if self._cache is not None:
            self._stale, self._cache = self._cache, None

    def trial_model(self, trial: int) -> PreferenceGP:
        """A stand-alone :class:`~torchpref.PreferenceGP` of one trial (same hyperparameters)."""
        d, t, lik = self._data[trial], self.template, self.likelihood
        return PreferenceGP(d.train_X, d.comparisons, d.ratings, d.rating_index,
                            covar_module=copy.deepcopy(t.covar_module),  # its own: fitting it changes no trial
                            comparison_noise=float(lik.comparison.comparison_noise),
                            rating_scale=float(lik.rating.rating_scale),
                            rating_precision=float(lik.rating.rating_precision),
                            rating_eps=t.rating_eps, max_newton_iter=t.max_newton_iter)

    # ------------------------------------------------------------------ inference
    def _kernel(self, X1: Tensor, X2: Tensor | None = None, diag: bool = False) -> Tensor:
        return self.template._kernel(X1, X2, diag=diag)

    def _padded(self) -> dict:
        """Items and observations padded to common sizes (see the module docstring)."""
        D = self._data
        n = torch.tensor([d.n for d in D])
        N = int(n.max())
        X = _pad([d.train_X for d in D], N, 0.0)
        mask = torch.arange(N).unsqueeze(0) < n.unsqueeze(1)  # T x N
        mask = mask.to(X.device)
        P = max(d.comparisons.shape[0] for d in D)
        Q = max(d.ratings.shape[0] for d in D)
        C = _pad([d.comparisons for d in D], P, 0)
        cmask = _pad([torch.ones(d.comparisons.shape[0], dtype=torch.bool, device=X.device) for d in D], P, False)
        u = _pad([d.ratings for d in D], Q, 0.5)
        ri = _pad([d.rating_index for d in D], Q, 0)
        rmask = _pad([torch.ones(d.ratings.shape[0], dtype=torch.bool, device=X.device) for d in D], Q, False)
        return {"n": n, "X": X, "mask": mask, "C": C, "cmask": cmask, "u": u, "ri": ri, "rmask": rmask}

    def _terms(self, s: dict, f: Tensor, fisher: Tensor | None = None):
        r"""Per-trial ``(log p(Y|f), grad_f log p, lambda, w)`` at ``f`` (``T x N``); ``fisher``
        (``T`` bool) swaps in the Fisher weights of the ratings for those trials."""
        C, u, ri = s["C"], s["u"], s["ri"]
        lik = self.likelihood
        T = f.shape[0]
        ll = f.new_zeros(T)
        grad = torch.zeros_like(f)
        lam = f.new_zeros(C.shape[:2])
        w = f.new_zeros(u.shape)
        if C.shape[1]:
            i, j = C[..., 0], C[..., 1]
            lp, d1, d2 = lik.comparison.derivatives(f.gather(1, i) - f.gather(1, j))
            cm = s["cmask"]
            ll = ll + torch.where(cm, lp, 0.0).sum(-1)
            d1 = torch.where(cm, d1, 0.0)
            lam = torch.where(cm, -d2, 0.0)
            grad = grad.scatter_add(1, i, d1).scatter_add(1, j, -d1)
        if u.shape[1]:
            fr = f.gather(1, ri)
            lp, d1, d2 = lik.rating.derivatives(fr, u)
            rm = s["rmask"]
            ll = ll + torch.where(rm, lp, 0.0).sum(-1)
            d1 = torch.where(rm, d1, 0.0)
            w = -d2
            if fisher is not None and bool(fisher.any()):
                w = torch.where(fisher.unsqueeze(-1), lik.rating.fisher(fr), w)
            w = torch.where(rm, w, 0.0)
            grad = grad.scatter_add(1, ri, d1)
        return ll, grad, lam, w

    @staticmethod
    def _hessian(s: dict, L: Tensor, lam: Tensor, w: Tensor) -> Tensor:
        r"""``B = I + L^T W L`` per trial, as ``(D L)^T diag(lambda) (D L) + (R L)^T diag(w) (R L)``."""
        N = L.shape[-1]
        B = torch.eye(N, dtype=L.dtype, device=L.device).expand_as(L).clone()
        if s["C"].shape[1]:
            C = s["C"]
            DL = L.gather(1, C[..., 0:1].expand(-1, -1, N)) - L.gather(1, C[..., 1:2].expand(-1, -1, N))
            B = B + DL.mT @ (lam.unsqueeze(-1) * DL)
        if s["ri"].shape[1]:
            RL = L.gather(1, s["ri"].unsqueeze(-1).expand(-1, -1, N))
            B = B + RL.mT @ (w.unsqueeze(-1) * RL)
        return B

    def _find_modes(self, s: dict, L: Tensor, f0: Tensor) -> dict:
        r"""Newton's method with Armijo backtracking, all trials at once (as
        :func:`~torchpref.laplace.find_mode` without its large-``n`` accelerations): a trial stops
        moving once half its Newton decrement is below ``tol``."""
        T, N = f0.shape
        a = torch.linalg.solve_triangular(L, f0.unsqueeze(-1), upper=False).squeeze(-1)
        a = torch.where(torch.isfinite(a).all(-1, keepdim=True), a, 0.0)

        def evaluate(a_: Tensor):
            f_ = (L @ a_.unsqueeze(-1)).squeeze(-1)
            ll_, g_, lam_, w_ = self._terms(s, f_)
            return ll_ - 0.5 * (a_ * a_).sum(-1), f_, (L.mT @ g_.unsqueeze(-1)).squeeze(-1) - a_, lam_, w_

        psi, f, grad, lam, w = evaluate(a)
        frozen = torch.zeros(T, dtype=torch.bool, device=a.device)
        converged = torch.zeros_like(frozen)
        for it in range(1, self.max_newton_iter + 1):
            M, info = torch.linalg.cholesky_ex(self._hessian(s, L, lam, w))
            fisher = info > 0
            if bool(fisher.any()):  # exact Hessian not negative definite: Fisher scoring there
                _, _, lam, w = self._terms(s, f, fisher)
                M, info = torch.linalg.cholesky_ex(self._hessian(s, L, lam, w))
                if bool((info > 0).any()):
                    bad = (info > 0).nonzero().reshape(-1).tolist()
                    raise NotPSDError(f"the Fisher-scoring Newton matrix B of trials {bad} is not positive definite")
            step = torch.cholesky_solve(grad.unsqueeze(-1), M).squeeze(-1)
            dec = (grad * step).sum(-1)
            if not bool(torch.isfinite(dec).all()):
                bad = (~torch.isfinite(dec)).nonzero().reshape(-1).tolist()
                raise FloatingPointError(f"non-finite Newton step while finding the Laplace modes of trials {bad}")
            newly = ~frozen & (dec / 2 < self.tol)
            converged |= newly
            frozen |= newly
            if bool(frozen.all()):
                break
            # Armijo backtracking for the moving trials, each with its own step length
            t = torch.where(frozen, 0.0, 1.0).to(a)
            pending = ~frozen
            new_a, new = a.clone(), [psi.clone(), f.clone(), grad.clone(), lam.clone(), w.clone()]
            while bool(pending.any()):
                a_try = a + t.unsqueeze(-1) * step
                vals = evaluate(a_try)
                ok = pending & torch.isfinite(vals[0]) & (vals[0] >= psi + 1e-4 * t * dec)
                new_a = torch.where(ok.unsqueeze(-1), a_try, new_a)
                for k in range(5):
                    sel = ok if vals[k].dim() == 1 else ok.unsqueeze(-1)
                    new[k] = torch.where(sel, vals[k], new[k])
                pending = pending & ~ok
                t = torch.where(pending, 0.5 * t, t)
                stuck = pending & (t <= 1e-12)
                if bool(stuck.any()):  # no ascent in floating point: at the optimum up to round-off
                    converged |= stuck & (dec / 2 < 1e-6)
                    frozen |= stuck
                    pending &= ~stuck
            a, (psi, f, grad, lam, w) = new_a, new
        else:  # out of iterations: the factor at the final points
            M, info = torch.linalg.cholesky_ex(self._hessian(s, L, lam, w))
            fisher = info > 0
            if bool(fisher.any()):
                _, _, lam, w = self._terms(s, f, fisher)
                M = torch.linalg.cholesky(self._hessian(s, L, lam, w))
        fisher_final = fisher
        if bool(fisher_final.any()):
            warnings.warn(
                f"the Laplace Hessian is not positive definite at the returned modes of trials "
                f"{fisher_final.nonzero().reshape(-1).tolist()}; their predictive covariance uses the Fisher W",
                LaplaceConvergenceWarning, stacklevel=3)
        if not bool(converged.all()):
            warnings.warn(
                f"Newton's method for the Laplace modes of trials {(~converged).nonzero().reshape(-1).tolist()} "
                f"did not converge in {it} iterations", LaplaceConvergenceWarning, stacklevel=3)
        return {"a": a, "f": f, "M": M, "iterations": it, "converged": converged}

    def _state(self) -> dict:
        """Padded data, kernel factor, modes and prediction terms for the current data (cached)."""
        if self._cache is not None:
            return self._cache
        with torch.no_grad():
            s = self._padded()
            X, mask = s["X"], s["mask"]
            pair = mask.unsqueeze(-1) & mask.unsqueeze(-2)
            K = torch.where(pair, self._kernel(X), 0.0)
            K = K + torch.diag_embed((~mask).to(K))  # padded items: independent, unit variance
            L, _ = batched_cholesky(K, name="kernel matrix")
            f0 = X.new_zeros(mask.shape)
            old = self._stale
            if old is not None:  # warm start: the old modes, the old predictive means for new items
                f0 = self._mean(old, self._cross(old, X))  # items are only appended: old ones keep their rows
                f_old, n_old = old["f"], old["n"].to(X.device)
                keep = torch.arange(f_old.shape[1], device=X.device).unsqueeze(0) < n_old.unsqueeze(1)
                f0[:, : f_old.shape[1]] = torch.where(keep, f_old, f0[:, : f_old.shape[1]])
                f0 = torch.where(mask, f0, 0.0)
            mode = self._find_modes(s, L, f0)
            alpha = torch.linalg.solve_triangular(L.mT, mode["a"].unsqueeze(-1), upper=True).squeeze(-1)
            eye = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device)
            A = eye - torch.cholesky_inverse(mode["M"])
            s.update(L=L, f=mode["f"], a=mode["a"], alpha=alpha, A=0.5 * (A + A.mT), mode=mode)
        self._cache, self._stale = s, None
        return s

    def _cross(self, s: dict, X: Tensor) -> Tensor:
        """``T x n x N`` kernel between a state's padded items (rows of padding: 0) and ``X``."""
        return torch.where(s["mask"].unsqueeze(-1), self._kernel(s["X"], X), 0.0)

    @staticmethod
    def _mean(s: dict, Kxs: Tensor) -> Tensor:
        """Posterior mean ``K_*X K^-1 f_hat`` (eq. 9) from :meth:`_cross`'s ``Kxs``."""
        return (s["alpha"].unsqueeze(-2) @ Kxs).squeeze(-2)

    def _check_X(self, X: Tensor) -> Tensor:
        d = self._data[0].dim
        if X.dim() != 3 or X.shape[0] != self.num_trials or X.shape[-1] != d:
            raise ValueError(f"X must be T x N x d = {self.num_trials} x N x {d}, got shape {tuple(X.shape)}.")
        return X.to(self._data[0].train_X)

    def _predict(self, X: Tensor) -> tuple[dict, Tensor, Tensor]:
        """The state, the posterior mean at (checked) ``X`` and ``v = L^-1 K_X*`` (eq. 10's projection)."""
        s = self._state()
        Kxs = self._cross(s, X)
        return s, self._mean(s, Kxs), torch.linalg.solve_triangular(s["L"], Kxs, upper=False)

    def marginals(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""Posterior mean and variance of each trial's latent utility at its points (``X``:
        ``T x N x d``; returns two ``T x N``), eqs. 9-10."""
        X = self._check_X(X)
        with torch.no_grad():
            s, mean, v = self._predict(X)
            var = self._kernel(X, diag=True) - (v * (s["A"] @ v)).sum(-2)
        return mean, var

    def joint(self, X: Tensor) -> tuple[Tensor, Tensor]:
        r"""Posterior mean ``T x N`` and covariance ``T x N x N`` of each trial's utility at its points."""
        X = self._check_X(X)
        with torch.no_grad():
            s, mean, v = self._predict(X)
            cov = self._kernel(X) - v.mT @ (s["A"] @ v)
        return mean, cov

    def expected_rating(self, X: Tensor) -> Tensor:
        r"""Expected rating ``Phi(m / sqrt(2 sigma_B^2 + v))`` per trial and point (``T x N``)."""
        mean, var = self.marginals(X)
        return self.likelihood.rating.expected_rating(mean, var)

    def mode(self) -> list[Tensor]:
        """Each trial's posterior mode over its own items."""
        s = self._state()
        return [s["f"][b, : int(s["n"][b])] for b in range(self.num_trials)]
