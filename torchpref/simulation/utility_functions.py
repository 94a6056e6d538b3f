r"""Users' hidden utilities: the paper's random wave functions (Sec. IV.A, eq. 13) and the
shapes of the user-family suite (:class:`GaussianBumps`, :class:`Plateau`,
:class:`RescaledUtility` of BoTorch test functions; :mod:`torchpref.experiments.suite`).

The wave functions:

.. math::

    f(x) = \sum_{k=1}^{3} a_k \cos(\pi f_k (x - o_k)) \exp(-d_k (x - o_k)^2),
    \qquad x \in [0, 1],

with frequency ``f_k ~ U[10, 30]``, amplitude ``a_k ~ U[0.6, 1.2]``, offset
``o_k ~ U[0.1, 0.9]`` and damping ``d_k ~ U[250, 350]``. A new function is drawn for every
trial of the experiment.

:class:`WaveFunction` is a BoTorch test problem (a
:class:`~botorch.test_functions.synthetic.SyntheticTestFunction`) to be *maximised*: it can
be used wherever BoTorch expects one, and it is also the ``utility`` of a
:class:`~torchpref.simulation.users.SimulatedUser` (``n x 1`` inputs to ``n`` latent values).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from botorch.test_functions.synthetic import SyntheticTestFunction
from torch import Tensor

__all__ = ["WaveFunction", "evaluation_grid", "GaussianBumps", "Plateau", "RescaledUtility"]

# Grid used to locate the maximum numerically: coarse pass, then a fine pass around the best
# coarse point. With a coarse spacing of 5e-5 and a fine spacing of 5e-8 the value is exact
# to ~1e-12 for the paper's ranges.
_COARSE_POINTS = 20_001
_FINE_POINTS = 2_001


def _as_parameter(name: str, value: Sequence[float] | Tensor) -> Tensor:
    t = torch.as_tensor(value, dtype=torch.float64).detach().clone()
    if t.dim() != 1 or t.numel() == 0:
        raise ValueError(f"{name} must be a non-empty 1-D sequence, got shape {tuple(t.shape)}.")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite, got {t.tolist()}.")
    return t


def _wave(x: Tensor, frequencies: Tensor, amplitudes: Tensor, offsets: Tensor, dampings: Tensor) -> Tensor:
    """Eq. 13 for ``x`` of shape ``batch`` (scalars); returns ``batch``."""
    z = x.unsqueeze(-1) - offsets  # x - o_k, ``batch x K``
    terms = amplitudes * torch.cos(math.pi * frequencies * z) * torch.exp(-dampings * z.square())
    return terms.sum(dim=-1)


class WaveFunction(SyntheticTestFunction):
    r"""A sum of damped cosine "wave" features on ``[0, 1]`` (paper eq. 13).

    .. math::

        f(x) = \sum_k a_k \cos(\pi f_k (x - o_k)) \exp(-d_k (x - o_k)^2)

    The parameters are float64 buffers ``frequencies`` (``f_k``), ``amplitudes`` (``a_k``),
    ``offsets`` (``o_k``) and ``dampings`` (``d_k``), each of shape ``K`` (``K = 3`` in the
    paper). The problem is a maximisation problem (``is_minimization_problem`` is ``False``
    unless ``negate=True``). ``optimal_value`` and ``optimizers`` are computed numerically at
    construction: a grid of 20,001 points on ``[0, 1]`` then a grid of 2,001 points around the
    best one (accurate to about ``1e-12`` for the paper's parameter ranges).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> problem = WaveFunction.random(generator=g)
        >>> X = evaluation_grid()                # ``101 x 1``
        >>> f = problem(X, noise=False)          # ``101``
    """

    frequencies: Tensor  # buffers
    amplitudes: Tensor
    offsets: Tensor
    dampings: Tensor
    noise_std: float | None

    dim = 1
    continuous_inds = [0]
    _is_minimization_by_default = False
    _check_grad_at_opt = False

    #: ranges of eq. 13's uniform draws (Sec. IV.A)
    FREQUENCY_RANGE = (10.0, 30.0)
    AMPLITUDE_RANGE = (0.6, 1.2)
    OFFSET_RANGE = (0.1, 0.9)
    DAMPING_RANGE = (250.0, 350.0)

    def __init__(
        self,
        frequencies: Sequence[float] | Tensor,
        amplitudes: Sequence[float] | Tensor,
        offsets: Sequence[float] | Tensor,
        dampings: Sequence[float] | Tensor,
        *,
        noise_std: float | None = None,
        negate: bool = False,
        bounds: list[tuple[float, float]] | None = None,
        dtype: torch.dtype = torch.float64,
        generator: torch.Generator | None = None,
    ) -> None:
        r"""
        Args:
            frequencies: ``f_k`` (``K``), the cosine frequencies (eq. 13).
            amplitudes: ``a_k`` (``K``), the feature amplitudes.
            offsets: ``o_k`` (``K``), the feature centres.
            dampings: ``d_k`` (``K``), the Gaussian envelope dampings.
            noise_std: standard deviation of additive Gaussian observation noise used by
                ``forward(X, noise=True)``; ``None`` (default) for none.
            negate: if ``True``, return ``-f``.
            bounds: custom domain as ``[(lower, upper)]``; default ``[(0, 1)]``.
            dtype: dtype of the ``bounds`` buffer (the parameters are always float64).
            generator: the default random-number generator for observation noise (see
                :meth:`forward`).

        Raises:
            ValueError: if the parameters are not finite 1-D sequences of equal length, or
                ``noise_std`` is negative.
        """
        params = {
            "frequencies": _as_parameter("frequencies", frequencies),
            "amplitudes": _as_parameter("amplitudes", amplitudes),
            "offsets": _as_parameter("offsets", offsets),
            "dampings": _as_parameter("dampings", dampings),
        }
        lengths = {name: p.numel() for name, p in params.items()}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"Wave parameters must all have the same length, got {lengths}.")
        if noise_std is not None and not (noise_std >= 0 and math.isfinite(noise_std)):
            raise ValueError(f"noise_std must be a non-negative number, got {noise_std}.")
        if bounds is None:
            bounds = [(0.0, 1.0)]
        x_opt, f_opt = self._locate_maximum(params, bounds[0])
        self._optimizers = [(x_opt,)]
        self._optimal_value = f_opt
        super().__init__(noise_std=noise_std, negate=negate, bounds=bounds, dtype=dtype)
        for name, p in params.items():
            self.register_buffer(name, p)
        self.generator = generator

    @classmethod
    def random(
        cls,
        generator: torch.Generator | None = None,
        *,
        n_components: int = 3,
        **kwargs,
    ) -> WaveFunction:
        r"""Draw a wave function with the paper's parameter ranges (Sec. IV.A, eq. 13).

        Draws, in this order, ``n_components`` frequencies ``f_k ~ U[10, 30]``, amplitudes
        ``a_k ~ U[0.6, 1.2]``, offsets ``o_k ~ U[0.1, 0.9]`` and dampings
        ``d_k ~ U[250, 350]``, all from ``generator`` (float64).

        Args:
            generator: a seeded ``torch.Generator``; ``None`` uses a fresh generator with
                torch's fixed default seed (so the result is still reproducible).
            n_components: ``K``, the number of wave features (3 in the paper).
            **kwargs: passed on to the constructor (``noise_std``, ``negate``, ...).

        Returns:
            A new :class:`WaveFunction`.

        Raises:
            ValueError: if ``n_components`` is not a positive integer.
        """
        if not isinstance(n_components, int) or n_components < 1:
            raise ValueError(f"n_components must be a positive integer, got {n_components!r}.")
        if generator is None:
            generator = torch.Generator()

        def uniform(lo_hi: tuple[float, float]) -> Tensor:
            lo, hi = lo_hi
            return lo + (hi - lo) * torch.rand(n_components, generator=generator, dtype=torch.float64)

        return cls(
            frequencies=uniform(cls.FREQUENCY_RANGE),
            amplitudes=uniform(cls.AMPLITUDE_RANGE),
            offsets=uniform(cls.OFFSET_RANGE),
            dampings=uniform(cls.DAMPING_RANGE),
            **kwargs,
        )

    @staticmethod
    def _locate_maximum(params: dict[str, Tensor], bound: tuple[float, float]) -> tuple[float, float]:
        lo, hi = float(bound[0]), float(bound[1])
        if not hi > lo:
            raise ValueError(f"bounds must satisfy lower < upper, got {bound}.")
        x = torch.linspace(lo, hi, _COARSE_POINTS, dtype=torch.float64)
        i = int(_wave(x, **params).argmax())
        step = (hi - lo) / (_COARSE_POINTS - 1)
        x = torch.linspace(max(lo, x[i].item() - step), min(hi, x[i].item() + step), _FINE_POINTS, dtype=torch.float64)
        f = _wave(x, **params)
        j = int(f.argmax())
        return x[j].item(), f[j].item()

    def _evaluate_true(self, X: Tensor) -> Tensor:
        r"""Evaluate eq. 13 without noise.

        Args:
            X: ``batch_shape x 1`` inputs in the bounds.

        Returns:
            ``batch_shape`` values, in the dtype of ``X`` promoted with float64 parameters
            cast to ``X``'s dtype.
        """
        return _wave(
            X[..., 0],
            self.frequencies.to(X),
            self.amplitudes.to(X),
            self.offsets.to(X),
            self.dampings.to(X),
        )

    def forward(self, X: Tensor, noise: bool = True, generator: torch.Generator | None = None) -> Tensor:
        r"""Evaluate the function, with observation noise if ``noise_std`` is set.

        Args:
            X: ``batch_shape x 1`` inputs in the bounds.
            noise: if ``True`` and ``noise_std`` is not ``None``, add
                ``N(0, noise_std^2)`` noise.
            generator: the generator for the noise; defaults to the one given at
                construction, and only if both are ``None`` to torch's global generator
                (BoTorch's behaviour).

        Returns:
            ``batch_shape`` values (negated if ``negate=True``).
        """
        f = self.evaluate_true(X=X)
        if noise and self.noise_std is not None:
            gen = generator if generator is not None else self.generator
            eps = torch.randn(f.shape, generator=gen, dtype=f.dtype, device=f.device)
            f = f + self.noise_std * eps
        return -f if self.negate else f

    def extra_repr(self) -> str:
        fmt = lambda t: "[" + ", ".join(f"{v:.4g}" for v in t.tolist()) + "]"  # noqa: E731
        return (
            f"frequencies={fmt(self.frequencies)}, amplitudes={fmt(self.amplitudes)}, "
            f"offsets={fmt(self.offsets)}, dampings={fmt(self.dampings)}"
        )


def evaluation_grid(
    n: int = 101,
    *,
    bounds: tuple[float, float] = (0.0, 1.0),
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Tensor:
    r"""Evenly spaced test points for the 1-D experiment's metrics (Sec. IV.A).

    The paper's text says ``n = 100`` uniformly distributed test points; the authors' code
    used 101 evenly spaced points including both ends (``0, 0.01, ..., 1``), which is the
    default here. Pass ``n=100`` for the paper's count.

    Args:
        n: number of points (at least 2).
        bounds: ``(lower, upper)`` end points, both included.
        dtype: the dtype of the result.
        device: the device of the result.

    Returns:
        A ``n x 1`` tensor.

    Raises:
        ValueError: if ``n < 2`` or ``bounds`` is not increasing.
    """
    if not isinstance(n, int) or n < 2:
        raise ValueError(f"n must be an integer >= 2, got {n!r}.")
    lo, hi = float(bounds[0]), float(bounds[1])
    if not hi > lo:
        raise ValueError(f"bounds must satisfy lower < upper, got {bounds}.")
    return torch.linspace(lo, hi, n, dtype=dtype, device=device).unsqueeze(-1)


class GaussianBumps:
    r"""A sum of Gaussian bumps on the unit cube: ``f(x) = sum_k h_k exp(-|x - c_k|^2 / (2 w_k^2))``.

    Args:
        centres: ``K x d`` bump centres.
        heights: ``K`` heights ``h_k``.
        widths: ``K`` widths ``w_k``.
    """

    def __init__(self, centres: Tensor, heights: Sequence[float] | Tensor, widths: Sequence[float] | Tensor):
        self.centres = torch.as_tensor(centres, dtype=torch.float64)
        self.heights = _as_parameter("heights", heights)
        self.widths = _as_parameter("widths", widths)
        if self.centres.dim() != 2 or not self.centres.shape[0] == self.heights.numel() == self.widths.numel():
            raise ValueError(
                f"need K x d centres and K heights and widths, got shapes {tuple(self.centres.shape)}, "
                f"{tuple(self.heights.shape)}, {tuple(self.widths.shape)}."
            )

    def __call__(self, X: Tensor) -> Tensor:
        """``n x d`` -> ``n`` values."""
        d2 = (X.unsqueeze(-2) - self.centres.to(X)).square().sum(-1)  # n x K
        return (self.heights.to(X) * torch.exp(-0.5 * d2 / self.widths.to(X).square())).sum(-1)


class Plateau:
    r"""A broad flat-topped bump with a gentle tilt: ``sigmoid((r - |x - c|) / e) + s (x - c) . v``.

    Many items are nearly as good as the best (the top is flat to within the tilt ``s``): finding
    *a* good item is easy, ranking the plateau's items is hard.

    Args:
        centre: ``d`` centre ``c``.
        radius: the plateau's radius ``r``.
        edge: the width ``e`` of its edge.
        tilt: ``d`` vector ``s v``, the slope across the plateau.
    """

    def __init__(self, centre: Tensor, radius: float, edge: float, tilt: Tensor):
        self.centre, self.tilt = (
            torch.as_tensor(centre, dtype=torch.float64),
            torch.as_tensor(tilt, dtype=torch.float64),
        )
        if not (radius > 0 and edge > 0):
            raise ValueError(f"radius and edge must be positive, got {radius} and {edge}.")
        self.radius, self.edge = float(radius), float(edge)

    def __call__(self, X: Tensor) -> Tensor:
        """``n x d`` -> ``n`` values."""
        z = X - self.centre.to(X)
        return torch.sigmoid((self.radius - z.norm(dim=-1)) / self.edge) + z @ self.tilt.to(X)


class RescaledUtility:
    r"""A function of the unit cube rescaled into a utility: ``u(x) = 2 (g(T x) - med) / (max - med)``.

    ``g`` is any function to maximise on a box (e.g. the negative of a BoTorch test function);
    ``T`` maps the unit cube onto its box after flipping the axes in ``flips``, so that one test
    function gives several users. ``med`` and ``max`` are the median and maximum of ``g`` over
    ``reference`` points of the unit cube: the typical item has utility 0, the best about 2,
    about the scale of the rating link (eq. 7 with ``sigma_B`` near 1).

    Args:
        g: ``n x D`` (in ``bounds``) -> ``n``.
        bounds: ``2 x D`` box of ``g``.
        reference: ``r x D`` points of the unit cube for the median and maximum.
        flips: ``D`` booleans: axes to reverse.
    """

    def __init__(self, g: Callable[[Tensor], Tensor], bounds: Tensor, reference: Tensor, flips: Tensor | None = None):
        self.g, self.bounds = g, torch.as_tensor(bounds, dtype=torch.float64)
        D = self.bounds.shape[-1]
        self.flips = torch.zeros(D, dtype=torch.bool) if flips is None else torch.as_tensor(flips, dtype=torch.bool)
        with torch.no_grad():
            v = self._raw(reference.to(torch.float64))
        self.median, self.maximum = float(v.median()), float(v.max())
        if not self.maximum > self.median:
            raise ValueError(f"g is constant on the reference points (median {self.median}, max {self.maximum}).")

    def _raw(self, X: Tensor) -> Tensor:
        X = torch.where(self.flips.to(X.device), 1 - X, X)
        lo, hi = self.bounds.to(X)
        return self.g(lo + (hi - lo) * X)

    def __call__(self, X: Tensor) -> Tensor:
        """``n x D`` in the unit cube -> ``n`` utilities."""
        return 2 * (self._raw(X) - self.median) / (self.maximum - self.median)
