r"""Users that answer queries: the protocol and a simulated user following the paper's model.

A *user* is anything with two methods (:class:`User`):

* ``rate(x) -> float``: an absolute query; ``x`` is a ``d`` tensor, the answer a rating in
  ``[0, 1]`` (Sec. III.A);
* ``choose(X) -> int``: a relative query; ``X`` is ``m x d``, the answer the index of the
  preferred row (best-of-``m``, Sec. III.A).

A person at a prompt, a lake operator model or :class:`SimulatedUser` all fit.

:class:`SimulatedUser` answers with exactly the noise model the GP assumes:

* choices: each shown item's latent value gets i.i.d. ``N(0, sigma_R^2)`` noise and the
  largest noisy value wins. For ``m = 2`` this is eq. 3,
  ``P(a > b) = Phi((f_a - f_b) / (sigma_R sqrt 2))``;
* ratings: ``u ~ Beta(nu mu, nu (1 - mu))`` with ``mu = Phi(f / (sigma_B sqrt 2))``
  (eqs. 4-7, with the shape parameters of docs/decisions.md: the printed eq. 6 is a typo).

All randomness comes from one ``torch.Generator``; :func:`sample_beta` and
:func:`sample_log_gamma` draw Gamma variates by Marsaglia and Tsang's method from that
generator's normal and uniform streams, since ``torch._standard_gamma`` takes no generator.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from torchpref.data.preference_data import likert_to_unit, unit_to_likert
from torchpref.likelihoods.pairwise_beta import rating_link

__all__ = ["User", "SimulatedUser", "LikertUser", "sample_beta", "sample_log_gamma", "RATING_CLAMP"]

#: Simulated ratings are clamped to ``[RATING_CLAMP, 1 - RATING_CLAMP]`` so that they lie
#: strictly inside the Beta likelihood's support (0, 1).
RATING_CLAMP = 1e-6


@runtime_checkable
class User(Protocol):
    """Anything that answers absolute (rating) and relative (best-of-``m``) queries."""

    def rate(self, x: Tensor) -> float:
        """Rate one item.

        Args:
            x: the item's features, a ``d`` tensor.

        Returns:
            A rating in ``[0, 1]`` (higher is better).
        """
        ...

    def choose(self, X: Tensor) -> int:
        """Pick the best of ``m`` items.

        Args:
            X: the items shown, ``m x d``.

        Returns:
            The index (``0..m-1``) of the preferred row.
        """
        ...


def sample_log_gamma(concentration: Tensor, generator: torch.Generator | None = None) -> Tensor:
    r"""Log of Gamma(``concentration``, 1) variates, drawn from ``generator``.

    Marsaglia & Tsang (2000): for ``a >= 1``, with ``d = a - 1/3``, ``c = 1 / sqrt(9 d)``,
    propose ``v = (1 + c z)^3`` with ``z ~ N(0, 1)`` and accept when ``v > 0`` and
    ``log U < z^2 / 2 + d - d v + d log v``; then ``G = d v``. For ``a < 1`` the boost
    ``G_a = G_{a+1} U^{1/a}`` is applied in log space, so tiny shapes do not underflow.

    Args:
        concentration: shape parameters ``a > 0``, any shape (floating point).
        generator: the random-number generator (``None``: torch's global one).

    Returns:
        ``log G``, the shape and dtype of ``concentration``.

    Raises:
        ValueError: if some concentration is not positive and finite.
    """
    a = torch.as_tensor(concentration)
    if not a.is_floating_point():
        a = a.to(torch.float64)
    if not (torch.isfinite(a).all() and (a > 0).all()):
        raise ValueError(f"concentration must be positive and finite, got {a.flatten()[:5].tolist()}.")
    flat = a.reshape(-1)
    if flat.numel() == 1 and flat.device.type == "cpu":
        return _log_gamma_scalar(float(flat), flat.dtype, generator).reshape(a.shape)
    return _log_gamma_tensor(flat, generator).reshape(a.shape)


def _log_gamma_tensor(flat: Tensor, generator: torch.Generator | None) -> Tensor:
    """:func:`sample_log_gamma` for a 1-D tensor of valid shapes."""
    small = flat < 1
    a1 = torch.where(small, flat + 1, flat)
    d = a1 - 1.0 / 3.0
    c = 1.0 / torch.sqrt(9.0 * d)
    out = torch.empty_like(flat)
    todo = torch.arange(flat.numel(), device=flat.device)
    while todo.numel() > 0:
        z = torch.randn(todo.numel(), generator=generator, dtype=flat.dtype, device=flat.device)
        u = torch.rand(todo.numel(), generator=generator, dtype=flat.dtype, device=flat.device)
        dd, cc = d[todo], c[todo]
        v = (1 + cc * z) ** 3
        ok = v > 0
        log_v = torch.log(torch.where(ok, v, torch.ones_like(v)))
        accept = ok & (torch.log(u) < 0.5 * z.square() + dd - dd * v + dd * log_v)
        out[todo[accept]] = torch.log(dd[accept]) + log_v[accept]  # log(d v)
        todo = todo[~accept]
    if small.any():
        idx = small.nonzero().squeeze(-1)
        u = torch.rand(idx.numel(), generator=generator, dtype=flat.dtype, device=flat.device)
        out[idx] = out[idx] + torch.log(u) / flat[idx]  # G_a = G_{a+1} U^{1/a}
    return out


def _log_gamma_scalar(a: float, dtype: torch.dtype, generator: torch.Generator | None) -> Tensor:
    """:func:`sample_log_gamma` for one shape on the CPU, in Python floats: the same draws from
    ``generator`` in the same order (a simulated user's one rating costs microseconds, not a
    dozen tensor operations)."""
    small = a < 1
    d = (a + 1 if small else a) - 1.0 / 3.0
    c = 1.0 / math.sqrt(9.0 * d)
    while True:
        z = float(torch.randn(1, generator=generator, dtype=dtype))
        u = float(torch.rand(1, generator=generator, dtype=dtype))
        v = (1 + c * z) ** 3
        if v > 0:
            log_v = math.log(v)
            if (math.log(u) if u > 0 else -math.inf) < 0.5 * z * z + d - d * v + d * log_v:
                out = math.log(d) + log_v
                break
    if small:
        u = float(torch.rand(1, generator=generator, dtype=dtype))
        out += (math.log(u) if u > 0 else -math.inf) / a
    return torch.tensor(out, dtype=dtype)


def sample_beta(
    alpha: Tensor,
    beta: Tensor,
    generator: torch.Generator | None = None,
) -> Tensor:
    r"""Beta(``alpha``, ``beta``) variates drawn from ``generator``.

    ``X = G_a / (G_a + G_b)`` with independent Gamma variates, computed as
    ``sigmoid(log G_a - log G_b)`` (see :func:`sample_log_gamma`). No clamping is done here.

    Args:
        alpha: first shape parameters (positive), any shape.
        beta: second shape parameters (positive), broadcastable with ``alpha``.
        generator: the random-number generator.

    Returns:
        Samples in ``[0, 1]`` of the broadcast shape of ``alpha`` and ``beta``.

    Raises:
        ValueError: if a shape parameter is not positive and finite.
    """
    alpha, beta = torch.as_tensor(alpha), torch.as_tensor(beta)
    dtype = torch.promote_types(alpha.dtype, beta.dtype)
    if not dtype.is_floating_point:
        dtype = torch.float64
    alpha, beta = torch.broadcast_tensors(alpha.to(dtype), beta.to(dtype))
    for name, p in (("alpha", alpha), ("beta", beta)):
        if not (torch.isfinite(p).all() and (p > 0).all()):
            raise ValueError(f"{name} must be positive and finite, got {p.flatten()[:5].tolist()}.")
    log_a = sample_log_gamma(alpha, generator)
    log_b = sample_log_gamma(beta, generator)
    return torch.sigmoid(log_a - log_b)


def _positive(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}.") from None
    if not (v > 0 and math.isfinite(v)):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}.")
    return v


class SimulatedUser:
    r"""A simulated user who answers with the paper's observation model.

    * :meth:`choose` (eq. 3, generalised to ``m`` items): the item with the largest
      ``f(x_i) + e_i``, ``e_i ~ N(0, sigma_R^2)`` i.i.d.; for two items
      ``P(a chosen) = Phi((f_a - f_b) / (sigma_R sqrt 2))``.
    * :meth:`rate` (eqs. 4-7): ``u ~ Beta(nu mu, nu (1 - mu))``,
      ``mu = Phi(f(x) / (sigma_B sqrt 2))``, clamped to
      ``[RATING_CLAMP, 1 - RATING_CLAMP]`` (``1e-6``) so it is strictly inside ``(0, 1)``.

    With ``noiseless=True``, :meth:`rate` returns ``mu`` exactly and :meth:`choose` the index
    of the largest latent value (the first one on ties), and no random numbers are drawn.

    Attributes:
        n_ratings: number of :meth:`rate` queries answered so far.
        n_choices: number of :meth:`choose` queries answered so far.

    Example:
        >>> from torchpref.simulation.utility_functions import WaveFunction
        >>> g = torch.Generator().manual_seed(0)
        >>> truth = WaveFunction.random(generator=g)
        >>> user = SimulatedUser.paper_wave(lambda X: truth(X, noise=False), generator=g)
        >>> user.choose(torch.rand(5, 1, generator=g, dtype=torch.float64))  # doctest: +SKIP
        3
    """

    def __init__(
        self,
        utility: Callable[[Tensor], Tensor],
        comparison_noise: float,
        rating_scale: float,
        rating_precision: float,
        generator: torch.Generator | None = None,
        *,
        noiseless: bool = False,
    ) -> None:
        r"""
        Args:
            utility: the user's latent function ``f``: maps ``n x d`` to ``n``.
            comparison_noise: ``sigma_R`` (eq. 3), the standard deviation of the noise on
                each item's latent value in a choice.
            rating_scale: ``sigma_B`` (eq. 7), the probit link's scale.
            rating_precision: ``nu`` (eqs. 5-6), the Beta precision ``alpha + beta``.
            generator: the source of all randomness. ``None`` creates a fresh
                ``torch.Generator`` with torch's fixed default seed (reproducible, but the
                same stream for every such user: pass your own).
            noiseless: answer with the exact ``mu`` and the exact best item.

        Raises:
            ValueError: if ``utility`` is not callable or a noise parameter is not
                positive and finite.
        """
        if not callable(utility):
            raise ValueError(f"utility must be callable (n x d -> n), got {utility!r}.")
        self.utility = utility
        self.comparison_noise = _positive("comparison_noise", comparison_noise)
        self.rating_scale = _positive("rating_scale", rating_scale)
        self.rating_precision = _positive("rating_precision", rating_precision)
        self.generator = generator if generator is not None else torch.Generator()
        self.noiseless = bool(noiseless)
        self.n_ratings = 0
        self.n_choices = 0

    @classmethod
    def paper_wave(
        cls,
        utility: Callable[[Tensor], Tensor],
        generator: torch.Generator | None = None,
        *,
        noiseless: bool = False,
    ) -> SimulatedUser:
        r"""The user of the authors' 1-D wave experiment (docs/decisions.md, from their code).

        ``comparison_noise`` ``sigma_R = 0.05``, ``rating_scale`` ``sigma_B = 0.8`` and
        ``rating_precision`` ``nu = 80``. (The *model* in that experiment used
        ``sigma_R = 0.2``, ``sigma_B = 0.8``, ``nu = 60``.)

        Args:
            utility: the latent function, ``n x 1`` to ``n`` (e.g. a
                :class:`~torchpref.simulation.utility_functions.WaveFunction`).
            generator: the source of randomness.
            noiseless: as in the constructor.

        Returns:
            A :class:`SimulatedUser`.
        """
        return cls(
            utility,
            comparison_noise=0.05,
            rating_scale=0.8,
            rating_precision=80.0,
            generator=generator,
            noiseless=noiseless,
        )

    # -- helpers -------------------------------------------------------------------------
    def latent(self, X: Tensor) -> Tensor:
        """The true latent values ``f(X)``.

        Args:
            X: ``n x d`` items.

        Returns:
            A ``n`` tensor.

        Raises:
            ValueError: if ``X`` is not ``n x d`` or the utility returns a wrong shape or
                non-finite values.
        """
        X = torch.as_tensor(X)
        if X.dim() != 2 or X.shape[0] == 0:
            raise ValueError(f"X must be a non-empty n x d tensor, got shape {tuple(X.shape)}.")
        f = torch.as_tensor(self.utility(X))
        if f.shape != (X.shape[0],):
            raise ValueError(
                f"utility must map n x d to n values: got shape {tuple(f.shape)} for input {tuple(X.shape)}."
            )
        if not torch.isfinite(f).all():
            raise ValueError(f"utility returned non-finite values {f.tolist()}.")
        return f.detach()

    def mean_rating(self, X: Tensor) -> Tensor:
        r"""The mean rating ``mu = Phi(f / (sigma_B sqrt 2))`` (eq. 7) of each item.

        Args:
            X: ``n x d`` items.

        Returns:
            A ``n`` tensor in ``(0, 1)``.
        """
        f = self.latent(X)
        return rating_link(f, self.rating_scale)

    # -- the user protocol ---------------------------------------------------------------
    def rate(self, x: Tensor) -> float:
        r"""Rate one item: ``u ~ Beta(nu mu, nu (1 - mu))``, ``mu = Phi(f / (sigma_B sqrt 2))``.

        The draw is clamped to ``[1e-6, 1 - 1e-6]`` (:data:`RATING_CLAMP`) to stay strictly
        inside ``(0, 1)``. ``mu`` itself is also clamped there before forming the shape
        parameters, which matters only for ``|f| > 6.7 sigma_B``.

        Args:
            x: the item, a ``d`` tensor (a ``1 x d`` tensor is also accepted).

        Returns:
            The rating, a float in ``(0, 1)``.

        Raises:
            ValueError: if ``x`` is not a ``d`` or ``1 x d`` tensor.
        """
        x = torch.as_tensor(x)
        if x.dim() == 2 and x.shape[0] == 1:
            x = x[0]
        if x.dim() != 1:
            raise ValueError(f"x must be a single item (a d tensor), got shape {tuple(x.shape)}.")
        mu = self.mean_rating(x.unsqueeze(0))
        self.n_ratings += 1
        if self.noiseless:
            return float(mu[0])
        mu = mu.to(torch.float64).clamp(RATING_CLAMP, 1 - RATING_CLAMP)
        nu = self.rating_precision
        u = sample_beta(nu * mu, nu * (1 - mu), self.generator)  # eqs. 5-6 (docs/decisions.md)
        return float(u.clamp(RATING_CLAMP, 1 - RATING_CLAMP)[0])

    def choose(self, X: Tensor) -> int:
        r"""Pick the best of ``m`` items: ``argmax_i f(x_i) + e_i``, ``e_i ~ N(0, sigma_R^2)``.

        Args:
            X: the items shown, ``m x d`` with ``m >= 2``.

        Returns:
            The index of the chosen row.

        Raises:
            ValueError: if ``X`` is not ``m x d`` with ``m >= 2``.
        """
        X = torch.as_tensor(X)
        if X.dim() != 2 or X.shape[0] < 2:
            raise ValueError(f"X must be an m x d tensor with m >= 2 items, got shape {tuple(X.shape)}.")
        f = self.latent(X).to(torch.float64)
        self.n_choices += 1
        if not self.noiseless:
            # eq. 3: each item's value is seen through N(0, sigma_R^2) noise
            f = f + self.comparison_noise * torch.randn(f.shape, generator=self.generator, dtype=f.dtype)
        return int(f.argmax())

    def reset_counts(self) -> None:
        """Set :attr:`n_ratings` and :attr:`n_choices` back to zero."""
        self.n_ratings = 0
        self.n_choices = 0

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(comparison_noise={self.comparison_noise}, "
            f"rating_scale={self.rating_scale}, rating_precision={self.rating_precision}, "
            f"noiseless={self.noiseless}, n_ratings={self.n_ratings}, n_choices={self.n_choices})"
        )


class LikertUser:
    r"""A :class:`SimulatedUser` whose ratings are quantised to a Likert scale, as a person ticking
    one of ``num_levels`` boxes: the simulated rating ``u`` becomes level ``k = ceil(K u)``,
    answered as the centre of its bin, ``(k - 1/2) / K`` (:func:`~torchpref.data.preference_data.likert_to_unit`).
    Choices are the wrapped user's.

    Args:
        user: the underlying simulated user (its Beta ratings are quantised).
        num_levels: ``K`` (default 5).
    """

    def __init__(self, user: SimulatedUser, num_levels: int = 5):
        if not isinstance(num_levels, int) or num_levels < 2:
            raise ValueError(f"num_levels must be an integer >= 2, got {num_levels!r}.")
        self.user, self.num_levels = user, num_levels

    def rate(self, x: Tensor) -> float:
        """A rating of ``x`` (``d``) on the Likert scale, mapped to ``[0, 1]``."""
        level = unit_to_likert(self.user.rate(x), self.num_levels)
        return float(likert_to_unit(level, self.num_levels))

    def choose(self, X: Tensor) -> int:
        """The wrapped user's best of ``m`` items (``m x d``)."""
        return self.user.choose(X)
