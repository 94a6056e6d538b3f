r"""Which solver runs: the compiled small-problem path (:mod:`torchpref.inference._compiled`,
numba) or the torch solver, and the setting that forces either (docs/speed.md, "The compiled path").

The setting, in order of precedence: the context manager :class:`fast_path` (``with
torchpref.fast_path("off"): ...``, for the calling thread only), :func:`set_fast_path`
(``torchpref.set_fast_path("on")``: the whole process, at once, until changed), else the environment variable
``TORCHPREF_FAST_PATH`` (checked when read: a value other than :data:`SETTINGS` raises a
``ValueError`` naming it), else ``"auto"``:

* ``"off"``: the torch solver everywhere.
* ``"auto"``: the compiled path where it applies and is faster (up to :data:`MODE_MAX_ITEMS` items
  for a mode, :data:`FIT_MAX_ITEMS` for a fit), if the cache built for this installation loads
  (:mod:`torchpref.inference.fast_cache`; built by ``torchpref fast-path build`` or :func:`build`).
  It is loaded at the first solve it applies to, never compiled: without a usable cache the torch
  solver answers and one :class:`FastPathWarning` per process names the command.
* ``"on"``: the compiled path wherever it applies; without a usable cache it is built in the
  calling process first (about 2 minutes, with a progress line on stderr).

No fit or solve ever starts a process. Any failure of the compiled path (its cache fails to load,
a compiled call raises anything but an arithmetic error of the problem, or returns a non-finite
result) falls back to the torch solver, with one warning per process, and the compiled path is not
used again by that process. The compiled calls run BLAS and LAPACK on torch's thread count
(``torch.get_num_threads()``), restoring the libraries' own counts when the last one returns.

It applies to one problem (no batch), on the CPU, in float64, with probit comparisons (strict
choices where ties were offered too) and Beta ratings of any precision (each optionally shifted by a
prior mean: a population's person model), and, for a fit,
the stationary kernels :mod:`torchpref.models.fast_fit` lists. numba is imported on the first solve
that uses it, never at ``import torchpref``.
"""

from __future__ import annotations

import math
import os
import sys
import threading
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, TypeVar, overload

import torch
from torch import Tensor

import torchpref.inference.fast_cache as fast_cache
import torchpref.inference.fast_types as ft
from torchpref.inference.observations import Observations, Term

if TYPE_CHECKING:
    from threadpoolctl import LibController

T = TypeVar("T")

ENV = "TORCHPREF_FAST_PATH"
SETTINGS = ("auto", "on", "off")
#: ``auto`` solves modes compiled up to this many items, and fits (measured: at 300 items the
#: compiled fit took 0.84 of the torch fit's time, at 500 items 1.11; the mode 0.54 and 0.88):
#: from 500 items on ``auto`` is the torch solver, as before (docs/speed.md)
MODE_MAX_ITEMS = 400
FIT_MAX_ITEMS = 400


class FastPathWarning(UserWarning):
    """The compiled path is not used in this process (once per process, with the reason)."""


@dataclass
class PathState:
    """This process's compiled path: the loaded entry points (``None`` before a load or after a
    failure), their cache folder, why the path is off for the process (``failed``: a failure;
    ``missing``: no usable cache under ``"auto"``), the process-wide setting
    (:func:`set_fast_path`; ``None``: the environment's) and the warnings already given."""

    functions: dict[str, Any] | None = None
    folder: Path | None = None
    failed: str | None = None
    missing: str | None = None
    setting: str | None = None
    warned: set[str] = field(default_factory=set)


_lock = threading.RLock()
_local = threading.local()  # .stack: this thread's context-manager settings, innermost last
STATE = PathState()


def check_setting(value: str | None = None) -> str:
    """``value`` (default: the environment variable ``TORCHPREF_FAST_PATH``, empty meaning
    ``"auto"``) if it is a setting, else a ``ValueError`` naming the variable and the allowed values;
    for programs to call at start (``torchpref serve``, ``elicit``)."""
    if value is None:
        raw = os.environ.get(ENV, "")
        if not raw.strip():
            return "auto"
        if raw.strip().lower() not in SETTINGS:
            raise ValueError(f"{ENV}={raw!r} is not a fast-path setting: use one of {', '.join(SETTINGS)}.")
        return raw.strip().lower()
    if value not in SETTINGS:
        raise ValueError(f"the fast-path setting must be one of {SETTINGS}, got {value!r}.")
    return value


def setting() -> str:
    """The current setting for the calling thread: ``"auto"``, ``"on"`` or ``"off"``."""
    stack = getattr(_local, "stack", None)
    if stack:
        return stack[-1]
    return STATE.setting or check_setting()


def set_fast_path(mode: str | None) -> None:
    """Set the whole process's setting (every thread outside a :func:`fast_path` block) at once,
    until changed; ``None``: back to the environment variable's (``"auto"`` without one)."""
    checked = None if mode is None else check_setting(mode)
    with _lock:
        STATE.setting = checked


class fast_path:  # lower case: a context manager used like torch.no_grad
    """Inside the block, force the compiled path (``"on"``), the torch solver (``"off"``) or let each
    call choose (``"auto"``), for the calling thread only (other threads keep theirs); the whole
    process's setting is :func:`set_fast_path`'s. The mode is checked when the object is made (a
    ``ValueError`` naming it); nothing changes until the block is entered."""

    def __init__(self, mode: str):
        self.mode = check_setting(mode)

    def __enter__(self) -> str:
        stack = getattr(_local, "stack", None)
        if stack is None:
            stack = _local.stack = []
        stack.append(self.mode)
        return self.mode

    def __exit__(self, *exc: object) -> None:
        _local.stack.pop()


def available() -> bool:
    """Whether the compiled path can be loaded here: numba and threadpoolctl (the ``fast`` extra)
    installed, not blocked, and numba not shadowed by the working directory."""
    return fast_cache.problem() is None


def _warn_once(key: str, message: str) -> None:
    if key in STATE.warned:
        return
    STATE.warned.add(key)
    warnings.warn(message, FastPathWarning, stacklevel=4)


def _disable(reason: str) -> None:
    """The compiled path is off for the rest of this process (one warning)."""
    with _lock:
        STATE.functions, STATE.failed = None, reason
    _warn_once("failed", f"the compiled fast path is off in this process: {reason}; the torch solver answers")


def compiled() -> dict[str, Any] | None:
    """The compiled entry points if the setting and the installation allow them now, else
    ``None``: for ``"off"``, without numba, after a failure, or under ``"auto"`` without a usable
    cache. ``"on"`` builds the cache first where none is usable."""
    mode = setting()
    if mode == "off":
        return None
    functions = STATE.functions
    if functions is not None or STATE.failed is not None:
        return functions
    if mode == "auto" and STATE.missing is not None:
        return None
    if not available():
        if fast_cache.installed():  # installed, but shadowed or blocked: said once
            _warn_once(
                "missing", f"the compiled fast path is not used: {fast_cache.problem()}; the torch solver answers"
            )
        return None
    with _lock:
        if STATE.functions is None and STATE.failed is None:
            _load(mode)
    return STATE.functions


def _load(mode: str) -> None:
    try:
        STATE.functions, STATE.folder = fast_cache.load()
        return
    except fast_cache.CacheUnusable as err:
        reason = str(err)
    if mode == "auto":
        STATE.missing = reason
        _warn_once(
            "missing",
            f"the compiled fast path is not used: {reason}. Run `{fast_cache.COMMAND}` (or "
            "torchpref.inference.fast_path.build()) once to compile it for this installation (about 2 minutes); "
            "the torch solver answers",
        )
        return
    print(f"torchpref: {reason}; compiling the fast path in this process (about 2 minutes) ...", file=sys.stderr)
    try:
        build(progress=None)
    except Exception as err:
        _disable(f"it could not be built ({type(err).__name__}: {err})")


def build(progress: Callable[[str], None] | None = print) -> fast_cache.Built:
    """Compile the compiled path for this installation into numba's cache folder (its old files
    there replaced), showing progress (``progress(line)``; ``None``: quiet) and saying where the
    cache is; the path is then used by this process and, under ``"auto"``, by every later one.

    Raises:
        fast_cache.CacheUnusable: numba is not usable here, or the cache folder cannot be written.
    """
    with _lock:
        built, functions = fast_cache.build(progress)
        STATE.functions, STATE.folder, STATE.failed, STATE.missing = functions, built.folder, None, None
    if progress is not None:
        progress(f"the compiled fast path is built: {sum(built.seconds.values()):.0f} s; cache in {built.folder}")
    return built


def status() -> str:
    """Where the compiled path stands in this process, in a few lines: the setting, whether it can
    be loaded here, its cache folder and whether the cache there is this installation's."""
    lines = [f"setting: {setting()} ({ENV}={os.environ.get(ENV, '')!r})"]
    why = fast_cache.problem()
    if why is not None:
        return "\n".join([*lines, f"not available: {why}; the torch solver answers"])
    try:
        path = fast_cache.folder(fast_cache.functions())
        lines.append(f"cache folder: {path}")
        fast_cache.check_manifest(path)
        lines.append(f"cache: built for this installation ({', '.join(fast_cache.identity().values())})")
    except fast_cache.CacheUnusable as err:
        lines.append(f"cache: not usable: {err}; run `{fast_cache.COMMAND}`")
    if STATE.failed is not None:
        lines.append(f"off in this process: {STATE.failed}")
    return "\n".join(lines)


def loads() -> bool:
    """Whether this installation's cache loads (loading it into this process if it does)."""
    try:
        functions, path = fast_cache.load()
    except fast_cache.CacheUnusable:
        return False
    with _lock:
        STATE.functions, STATE.folder, STATE.failed, STATE.missing = functions, path, None, None
    return True


def cache_folder() -> Path | None:
    """The loaded cache's folder (``None`` before a load)."""
    return STATE.folder


def warm_up() -> dict[str, Any] | None:
    """Load the compiled path now, as the setting says (``"on"``: building it if need be), e.g.
    before timing; its entry points, or ``None`` where it is not used."""
    return compiled()


class _BlasThreads:
    """BLAS and LAPACK (numpy's and SciPy's OpenBLAS, which numba calls) on torch's thread count
    while compiled calls run. A library with one process-wide pool (OpenBLAS's own threads): the
    first caller saves its count and sets it, the last one to return restores it (a count of
    callers under a lock, so that threads overlapping in compiled calls cannot leave it changed; set
    through the library itself, which works from any thread, where threadpoolctl's own call acts
    only from the first thread that used it). A library with per-thread counts (OpenMP's): set and
    restored around each call in the calling thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._depth = 0
        self._saved: list[tuple[LibController, int]] = []
        self._libraries: list[LibController] | None = None
        self.limited: list[str] = []

    def _libs(self) -> list[LibController]:
        if self._libraries is None:
            from threadpoolctl import ThreadpoolController

            self._libraries = list(ThreadpoolController().select(user_api="blas").lib_controllers)
        return self._libraries

    @staticmethod
    def _set(lib: LibController, n: int) -> None:
        getattr(lib, "_real_set_num_threads", lib.set_num_threads)(n)

    def _shared(self) -> list[LibController]:
        return [lib for lib in self._libs() if getattr(lib, "threading_layer", "") != "openmp"]

    def __enter__(self) -> list[tuple[LibController, int]]:
        n = torch.get_num_threads()
        with self._lock:
            if self._depth == 0:
                self._saved = [(lib, lib.get_num_threads()) for lib in self._shared()]
                for lib, count in self._saved:
                    if count != n:
                        self._set(lib, n)
                self.limited = [f"{lib.internal_api} {os.path.basename(lib.filepath)}: {n}" for lib in self._libs()]
            self._depth += 1
        own = [(lib, lib.get_num_threads()) for lib in self._libs() if lib not in self._shared()]
        for lib, count in own:
            if count != n:
                self._set(lib, n)
        return own

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self._depth -= 1
            if self._depth == 0:
                for lib, count in self._saved:
                    if lib.get_num_threads() != count:
                        self._set(lib, count)

    def run(self, fn: Callable[..., T], *args: object) -> T:
        """``fn(*args)`` with the libraries limited."""
        own = self.__enter__()
        try:
            return fn(*args)
        finally:
            for lib, count in own:
                self._set(lib, count)
            self.__exit__()


BLAS_THREADS = _BlasThreads()


@overload
def call(name: Literal["newton"], *args: object) -> ft.NewtonResult | None: ...
@overload
def call(name: Literal["fit_loss"], *args: object) -> ft.LossResult | None: ...
@overload
def call(name: Literal["fit_lbfgs"], *args: object) -> ft.FitResult | None: ...
def call(name: str, *args: object) -> Any:
    """Entry point ``name``'s result on ``args`` as its named result (:data:`~torchpref.inference.fast_types.RESULTS`),
    or ``None`` where the torch solver must answer:
    the path is not loaded, the problem met an arithmetic error (``ArithmeticError``, ``ValueError``
    from numba's arithmetic, where torch gives inf or NaN: silently, for this call), or the call
    failed otherwise (any other exception, or a non-finite result with a successful status: the path
    is off for the rest of the process, with one warning)."""
    functions = STATE.functions
    if functions is None:
        return None
    try:
        out = ft.RESULTS[name](*BLAS_THREADS.run(functions[name], *args))
    except (ArithmeticError, ValueError):
        return None
    except Exception as err:
        _disable(f"its {name} raised {type(err).__name__}: {err}")
        return None
    if out.status in ft.SUCCESS and not _finite(out):
        _disable(f"its {name} returned non-finite values with an OK status")
        return None
    return out


def _finite(values: Iterable[object]) -> bool:
    import numpy as np

    for v in values:
        if isinstance(v, tuple):
            if not _finite(v):
                return False
        elif isinstance(v, (np.ndarray, float)) and not np.all(np.isfinite(v)):
            return False
    return True


def known(likelihood: object, kind: str) -> bool:
    """Whether ``likelihood`` is one the compiled path computes as ``kind``: its class declares
    ``compiled_kind = kind`` itself (not inherited: a subclass may change its derivatives or link,
    as :class:`~torchpref.likelihoods.person.PersonRatingLikelihood` does) and no derivative is
    replaced on the object."""
    if type(likelihood).__dict__.get("compiled_kind") != kind:
        return False
    own = getattr(likelihood, "__dict__", {})
    replaced = ("derivatives", "third_derivative", "scale", "log_prob", "_link", "fisher", "_bounds")
    return not any(name in own for name in replaced)


class Rows(NamedTuple):
    """One observation term's compiled rows (:class:`~torchpref.inference.fast_types.Answers`'
    columns, ``m`` each): its kind, items, offsets (the prior mean's, and a strict choice's
    ``-tau``), targets, scales, interval bounds and lapse rates; ``beta``: a rating likelihood's
    ``(link scale, precision)`` (``None`` for any other kind)."""

    kind: int
    first: Tensor
    second: Tensor
    offset: Tensor
    target: Tensor
    scale: Tensor
    lower: Tensor
    upper: Tensor
    lapse: Tensor
    beta: tuple[float, float] | None = None


def _value(x: Tensor | float) -> float:
    """A likelihood's scalar parameter as a float (detached: it may be trainable)."""
    return float(torch.as_tensor(x).detach())


def _f64(x: Tensor | float, m: int) -> Tensor:
    return torch.as_tensor(x, dtype=torch.float64).detach().expand(m).clone()


def _term_rows(term: Term) -> Rows | None:
    """One unmasked term of one problem as compiled rows, or ``None`` where the compiled path does
    not compute its likelihood: probit comparisons, strict choices where ties were offered
    (``Phi((eta - tau) / s)``: a probit shifted by ``-tau``), comparisons with lapses, ties and
    ordinal levels (Gaussian intervals), and Beta ratings of any precision, a person's gain ``g``
    and offset ``b`` on their link included (``Phi((g eta + b) / c0)`` is ``Phi((eta + b / g) / (c0 / g))``)."""
    lik: Any = term.likelihood
    if term.mask is not None and not bool(term.mask.all()):
        return None
    m = term.size
    offset = _f64(0.0, m) if term.offset is None else term.offset[0].detach().to(torch.float64).clone()
    item = term.index[0, :, 0]
    pair = term.coef == (1.0, -1.0) and term.target is None
    second = term.index[0, :, 1] if pair else torch.full_like(item, -1)
    zero, lo, hi = _f64(0.0, m), _f64(-math.inf, m), _f64(math.inf, m)
    if pair and known(lik, "probit"):
        return Rows(ft.PROBIT, item, second, offset, zero, _f64(lik.scale, m), lo, hi, zero)
    if pair and known(lik, "strict"):
        tau, scale = _value(lik.tie.tie_threshold), lik.tie.comparison.scale
        return Rows(ft.PROBIT, item, second, offset - tau, zero, _f64(scale, m), lo, hi, zero)
    if pair and known(lik, "lapse"):
        return Rows(ft.LAPSE, item, second, offset, zero, _f64(lik.scale, m), lo, hi, _f64(lik.lapse_rate, m))
    if pair and known(lik, "tie"):
        tau = _value(lik.tie_threshold)
        return Rows(
            ft.INTERVAL, item, second, offset, zero, _f64(lik.comparison.scale, m), -tau + zero, tau + zero, zero
        )
    given = term.target
    single = term.coef == (1.0,) and given is not None
    if single and given is not None and known(lik, "ordinal"):
        levels = lik.check_levels(given[0].detach())
        cuts = torch.cat([lo[:1], lik.cut_points.detach().to(torch.float64), hi[:1]])
        return Rows(
            ft.INTERVAL, item, second, offset, zero, _f64(lik.level_noise, m), cuts[levels - 1], cuts[levels], zero
        )
    target = None if given is None else given[0].detach().to(torch.float64)
    if single and target is not None and known(lik, "beta"):
        beta = (math.sqrt(2.0) * _value(lik.rating_scale), _value(lik.rating_precision))
        return Rows(ft.BETA, item, second, offset, target, zero, lo, hi, zero, beta)
    if single and target is not None and known(lik, "person_rating"):
        g, b = _value(lik.rating_gain), _value(lik.rating_offset)
        if not g > 0.0:
            return None  # a gain constrained otherwise: the torch solver
        beta = (math.sqrt(2.0) * _value(lik.rating_scale) / g, _value(lik.rating_precision))
        return Rows(ft.BETA, item, second, offset + b / g, target, zero, lo, hi, zero, beta)
    return None


def answers(obs: Observations) -> ft.Answers | None:
    """One problem's unmasked observations as :class:`~torchpref.inference.fast_types.Answers` (the
    kinds :func:`_term_rows` knows, with their prior-mean offsets), or ``None`` where any term is
    of another kind or masked, or two rating likelihoods differ."""
    if obs.batch != 1 or not obs.terms:
        return None
    rows: list[Rows] = []
    for term in obs.terms:  # the terms' order: the weights come back in it
        found = _term_rows(term)
        if found is None:
            return None
        rows.append(found)
    betas = {r.beta for r in rows if r.beta is not None}
    if len(betas) > 1:
        return None  # two rating likelihoods of different links or precisions
    c, nu = betas.pop() if betas else (1.0, 1.0)
    cols = [torch.cat([getattr(r, name) for r in rows]).numpy() for name in Rows._fields[1:9]]
    kinds = torch.cat([torch.full((r.first.shape[0],), r.kind) for r in rows]).numpy()
    first, second, offset, target, scale, lower, upper, lapse = cols
    return ft.answers(first, second, kinds, offset, target, scale, lower, upper, lapse, c, nu)


def mode_applies(L: Tensor, obs: Observations) -> bool:
    """Whether the mode of ``L`` (``1 x n x n``) and ``obs`` may be solved compiled (before the
    setting's cache is asked)."""
    n = L.shape[-1]
    if L.dtype != torch.float64 or L.device.type != "cpu" or L.shape[0] != 1 or n == 0:
        return False
    return setting() == "on" or n <= MODE_MAX_ITEMS


class CompiledMode(NamedTuple):
    """A mode solved on the compiled path, as tensors: whitened ``a``, ``f = L a``, ``B``'s factor
    ``M``, the weights of each observation term and Newton's iterations."""

    a: Tensor
    f: Tensor
    M: Tensor
    weights: tuple[Tensor, ...]
    iterations: int


def solve_mode(
    L: Tensor, obs: Observations, starts: tuple[Tensor, ...], max_iter: int, tol: float
) -> CompiledMode | None:
    """The Laplace mode of one problem (``L``: ``1 x n x n``) on the compiled path, or ``None`` where the torch solver answers (the
    path does not apply or is not loaded, or the compiled Newton did not converge, met a non-finite
    step or needed Fisher weights at its end: the torch solver's warnings and errors are then its own)."""
    mode = setting()
    if mode == "off" or STATE.failed is not None or (mode == "auto" and STATE.missing is not None):
        return None
    if not mode_applies(L, obs):
        return None
    ans = answers(obs)
    if ans is None or compiled() is None:
        return None
    import numpy as np

    n = L.shape[-1]
    Ln = ft.floats(L[0].detach().numpy(), 2)
    S = np.stack([f.detach().to(L).reshape(n).numpy() for f in starts]) if starts else np.empty((0, n))
    out = call("newton", Ln, ans, ft.floats(S, 2), float(tol), int(max_iter))
    if out is None or out.status != ft.OK:
        return None
    sizes = [t.size for t in obs.terms]
    weights = tuple(torch.from_numpy(part) for part in np.split(out.weights, np.cumsum(sizes)[:-1]))
    return CompiledMode(
        torch.from_numpy(out.a), torch.from_numpy(Ln @ out.a), torch.from_numpy(out.M), weights, int(out.iterations)
    )
