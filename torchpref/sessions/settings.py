r"""What a :class:`~torchpref.sessions.session.PreferenceSession` is set up with, and how its file records it.

:class:`SessionSettings` holds a session's validated settings (candidates, bounds, seed, levels,
number of queries, names), writes them as the session file's header and checks a resumed file's
header against them (:class:`~torchpref.sessions.errors.SessionMismatchError` naming the setting). Also
here: the default model and ranking size of a session, the per-step random stream
(:func:`step_generator`) and :class:`SessionAnswer`, one answer in force.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchpref.data.queries import BoxCandidates, Candidates, FinitePool, as_integer
from torchpref.models.preference_gp import PreferenceGP
from torchpref.models.recipe import DEFAULT_MODEL
from torchpref.population.model import Population
from torchpref.selection import defaults as selection_defaults
from torchpref.sessions.errors import (
    SessionMismatchError,
)
from torchpref.sessions.journal import (
    now,
)
from torchpref.sessions.records import FORMAT_VERSION, AnswerRecord, SessionHeader, dumps_settings
from torchpref.version import __version__

__all__ = [
    "MAX_REDRAWS",
    "POOL_INLINE_MAX",
    "SessionAnswer",
    "SessionSettings",
    "as_items",
    "as_seconds",
    "as_time",
    "default_ranking_size",
    "default_session_model",
    "pool_digest",
    "pool_spec",
    "step_generator",
    "unrated_rows",
]


@dataclass(frozen=True)
class SessionAnswer:
    """One answer in force (not undone).

    Attributes:
        seq: its sequence number in the file.
        kind: ``"rating"``, ``"choice"`` or ``"no_preference"``.
        items: ``m x d`` the items' coordinates as shown (``1 x d`` for a rating).
        answer: the answer as given: a Likert level (or a rating in ``[0, 1]`` when the session
            has no levels) for a rating, the index of the chosen row of ``items`` for a choice,
            ``None`` for no preference.
        value: the rating in ``[0, 1]`` the model uses (ratings only).
        step: the query number it answered, or ``None`` if given out of turn.
        pool_indices: the items' rows in the candidate pool, where known.
        time: ISO 8601 timestamp.
        response_time: seconds from the question being shown to the answer, where the front end
            measured it (``None`` otherwise; files written before it existed have none).
    """

    seq: int
    kind: str
    items: Tensor
    answer: int | float | None
    value: float | None
    step: int | None
    pool_indices: tuple[int, ...] | None
    time: str
    response_time: float | None = None

    @classmethod
    def from_record(cls, r: dict | AnswerRecord) -> SessionAnswer:
        """The answer of an ``answer`` record of the session file (its object or typed record)."""
        rec = r if isinstance(r, AnswerRecord) else AnswerRecord.from_json(r)
        pool = rec.pool_indices
        return cls(
            rec.seq,
            rec.kind,
            torch.tensor(rec.items, dtype=torch.float64),
            rec.answer,
            rec.value,
            rec.step,
            None if pool is None else tuple(pool),
            rec.time,
            rec.response_time,
        )


def step_generator(seed: int, step: int, attempt: int = 0) -> torch.Generator:
    """The generator for query ``step`` of a session seeded ``seed``: a fresh stream per step, so a
    restarted session proposes what the uninterrupted one would have (``attempt``: a further
    stream for the same step, when the first one's query repeats the last answered one)."""
    key = f"torchpref-session:{int(seed)}:{int(step)}" + (f":{int(attempt)}" if attempt else "")
    digest = hashlib.sha256(key.encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 63) - 1))


MAX_REDRAWS = 10
"""How many further draws :meth:`PreferenceSession.ask` makes while its query repeats the last one answered."""


def default_ranking_size(num_items: int) -> int:
    """Items per ranking query for a pool of ``num_items`` distinct items: 5, or fewer than the
    pool (``num_items - 1``, at least 2), so that a small pool's rankings are not all the same set
    (:func:`torchpref.selection.defaults.default_ranking_size`)."""
    return selection_defaults.default_ranking_size(num_items)


def default_session_model(train_X: Tensor) -> PreferenceGP:
    r"""The default model of a session: :data:`~torchpref.models.recipe.DEFAULT_MODEL`'s
    (:meth:`~torchpref.models.recipe.ModelSettings.session_model`): :class:`~torchpref.PreferenceGP`
    on inputs normalised to the unit cube, an RBF kernel with lengthscale 0.2 and outputscale
    ``sigma_f^2 = 1`` (eq. 1), comparison noise ``sigma_R = 1``, the Beta rating likelihood's
    ``sigma_B = 1`` and a person's ``nu = 3`` (:data:`~torchpref.models.defaults.PERSON_RATING_PRECISION`,
    calibrated on real raters: docs/real_raters.md), tie threshold ``tau = 0.1``, all fixed. A person
    can answer "no preference", so strict choices are the tie likelihood's upper category
    (``ties_offered=True``, docs/likelihoods.md); a population's person model has the same settings."""
    return DEFAULT_MODEL.session_model(train_X)


def to_unit_cube(X: Tensor, bounds: Tensor) -> Tensor:
    """Items (``... x d``) normalised by ``bounds`` (``2 x d``) to the unit cube: what a session's
    model sees (:meth:`~torchpref.PreferenceSession.transform`,
    :meth:`~torchpref.sessions.contents.SessionContents.transform`)."""
    lo, hi = bounds
    return (X.to(torch.float64) - lo) / (hi - lo)


def as_items(X: object, dim: int, name: str) -> Tensor:
    """``X`` as an ``m x dim`` float64 tensor of finite numbers (a ``dim`` vector is one row).

    Raises:
        ValueError: ``X`` (named ``name``) is not numbers, not of that shape or not finite.
    """
    try:
        t = torch.as_tensor(X, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{name} must be numbers, got {X!r}.") from None
    if t.dim() == 1:
        t = t.unsqueeze(0)
    if t.dim() != 2 or t.shape[-1] != dim:
        raise ValueError(f"{name} must be m x {dim}, got shape {tuple(t.shape)}.")
    finite = torch.isfinite(t).all(-1)
    if not finite.all():
        bad = torch.nonzero(~finite).reshape(-1)
        more = f" ({bad.numel()} rows are not)" if bad.numel() > 1 else ""
        raise ValueError(f"{name} must be finite: row {int(bad[0])} is {t[bad[0]].tolist()}{more}.")
    return t


def _whole(name: str, value, lo: int | None) -> int:
    """``value`` as an int (an integer, not a bool, float or text) of at least ``lo``."""
    v = as_integer(value)
    if v is None or (lo is not None and v < lo):
        raise ValueError(f"{name} must be an integer{'' if lo is None else f' >= {lo}'}, got {value!r}.")
    return v


def _candidates_spec(candidates) -> tuple[Candidates, dict, Tensor, Tensor]:
    """``(candidates, header spec, lower, upper)``: float64 candidates, their description for the
    file's header, and their range."""
    if isinstance(candidates, Tensor):
        candidates = FinitePool(as_items(candidates, candidates.shape[-1], "candidates"))
    if isinstance(candidates, FinitePool):
        pool = as_items(candidates.X, candidates.X.shape[-1], "the pool's items").to(torch.float64)
        if pool is not candidates.X:  # not already float64 N x d: a pool of the converted items
            candidates = FinitePool(pool)
        return candidates, pool_spec(pool), pool.min(0).values, pool.max(0).values
    if isinstance(candidates, BoxCandidates):
        b = candidates.bounds.to(torch.float64)
        spec = {"kind": "box", "bounds": b.tolist(), "num": candidates.num}
        return BoxCandidates(b, candidates.num), spec, b[0], b[1]
    raise TypeError(f"candidates must be a tensor, FinitePool or BoxCandidates, got {type(candidates).__name__}.")


POOL_INLINE_MAX = 10_000
"""A session file's header writes out a pool of at most this many items; a larger pool is recorded
by reference (:func:`pool_spec`): its size, first item and digest."""


def pool_digest(pool: Tensor) -> str:
    """The SHA-256 of a pool's float64 values (row by row, little-endian): what a header records
    of a pool larger than :data:`POOL_INLINE_MAX`."""
    data = pool.to(torch.float64).contiguous().numpy()
    return hashlib.sha256(data.astype("<f8", copy=False).tobytes()).hexdigest()


def pool_spec(pool: Tensor) -> dict:
    """A pool as a header records it: its items, or for more than :data:`POOL_INLINE_MAX` items
    ``{"kind": "pool", "num_items": N, "first_item": [...], "sha256": ...}`` (a 100,000-item pool
    written out is 8 MB per session file and as much again in memory per open session; the items
    are given again when the session is resumed, and checked against the digest)."""
    if pool.shape[0] <= POOL_INLINE_MAX:
        return {"kind": "pool", "items": pool.tolist()}
    return {"kind": "pool", "num_items": pool.shape[0], "first_item": pool[0].tolist(), "sha256": pool_digest(pool)}


def _describe(spec) -> str:
    """A header's candidates in a few words (a pool by its size and digest)."""
    if not isinstance(spec, dict):
        return repr(spec)
    if spec.get("kind") == "pool" and "items" not in spec:
        return f"(a pool of {spec.get('num_items')} items, digest {str(spec.get('sha256'))[:10]})"
    if spec.get("kind") == "pool":
        items = spec.get("items") or []
        digest = hashlib.sha256(json.dumps(items).encode()).hexdigest()[:10]
        return f"(a pool of {len(items)} items, digest {digest})"
    return f"(a box {spec.get('bounds')} x {spec.get('num')})"


def candidates_from_header(header: SessionHeader) -> Tensor | BoxCandidates:
    """The candidates a session file's header describes: a pool's items or a box."""
    spec = header.candidates
    if spec["kind"] == "pool" and "items" not in spec:
        raise ValueError(
            f"this session file records its pool of {spec['num_items']} items by reference (digest "
            f"{spec['sha256'][:10]}), not its items: pass them, PreferenceSession.load(path, candidates=X)."
        )
    if header.pool is not None:
        return torch.tensor(header.pool, dtype=torch.float64)
    return BoxCandidates(torch.tensor(spec["bounds"], dtype=torch.float64), spec["num"])


@dataclass(frozen=True)
class SessionSettings:
    """A session's validated settings (see :class:`~torchpref.sessions.session.PreferenceSession`'s arguments).

    Attributes:
        candidates: float64 candidates (a :class:`~torchpref.FinitePool` or
            :class:`~torchpref.BoxCandidates`).
        spec: the candidates as the header records them.
        dim: the items' dimension ``d``.
        bounds: ``2 x d`` lower and upper bounds of the model's unit cube.
        seed, num_queries, num_levels, names: as given, validated.
    """

    candidates: Candidates
    spec: dict
    dim: int
    bounds: Tensor
    seed: int
    num_queries: int
    num_levels: int | None
    names: list[str] | None

    @classmethod
    def validated(
        cls,
        candidates: Tensor | Candidates,
        bounds: Tensor | None,
        seed: int,
        num_queries: int,
        num_levels: int | None,
        names: Sequence[str] | None,
    ) -> SessionSettings:
        """Check and convert a session's arguments (bounds default to the candidates' range).

        Raises:
            ValueError: a setting out of range, naming it and its value.
            TypeError: ``candidates`` of another type.
        """
        candidates, spec, lo, hi = _candidates_spec(candidates)
        dim = int(lo.shape[0])
        if bounds is None:
            bounds = torch.stack([lo, torch.where(hi > lo, hi, lo + 1.0)])
        bounds = torch.as_tensor(bounds, dtype=torch.float64)
        if bounds.shape != (2, dim) or not torch.isfinite(bounds).all() or not (bounds[1] > bounds[0]).all():
            raise ValueError(f"bounds must be 2 x {dim} finite with lower < upper, got {bounds.tolist()}.")
        if names is not None and len(names) != dim:
            raise ValueError(f"names must give {dim} names, got {list(names)}.")
        levels = None if num_levels is None else _whole("num_levels", num_levels, 2)
        num_queries = _whole("num_queries", num_queries, 1)
        return cls(
            candidates,
            spec,
            dim,
            bounds,
            _whole("seed", seed, None),
            num_queries,
            levels,
            None if names is None else [str(n) for n in names],
        )

    def header(
        self,
        metadata: dict | None,
        model: dict | None = None,
        selector: dict | None = None,
        queries: list | None = None,
    ) -> dict:
        """A new session file's header record (:class:`~torchpref.sessions.records.SessionHeader`'s
        object), with the descriptions of the ``model`` and ``selector`` it starts with and its
        fixed question list (``queries``), where given.

        Raises:
            ValueError: ``metadata`` is not a dictionary that JSON writes and reads back
                (strings, finite numbers, booleans, ``None``, lists and dictionaries of them).
        """
        if metadata is not None and not isinstance(metadata, dict):
            raise ValueError(f"metadata must be a dictionary, got {type(metadata).__name__}.")
        try:
            json.loads(json.dumps(metadata or {}, allow_nan=False))
        except (TypeError, ValueError, RecursionError) as err:
            raise ValueError(
                f"metadata must hold only JSON values (strings, finite numbers, booleans, None, "
                f"lists, dictionaries): {err}"
            ) from None
        lo, hi = self.bounds.tolist()
        return SessionHeader(
            version=FORMAT_VERSION,
            dim=self.dim,
            seed=self.seed,
            num_queries=self.num_queries,
            num_levels=self.num_levels,
            bounds=(tuple(lo), tuple(hi)),
            names=None if self.names is None else tuple(self.names),
            candidates=self.spec,
            metadata=metadata or {},
            model=model,
            selector=selector,
            queries=queries,
            created=now(),
            torchpref=__version__,
        ).to_json()

    def transform(self, X: Tensor) -> Tensor:
        """Items in the unit cube of :attr:`bounds` (:func:`to_unit_cube`)."""
        return to_unit_cube(X, self.bounds)

    def check_header(self, h: SessionHeader, path: object) -> None:
        """Raise :class:`~torchpref.sessions.errors.SessionMismatchError` where the header ``h`` of the file
        ``path`` was written with other items, candidates, bounds, seed or levels."""
        if h.dim != self.dim:
            raise SessionMismatchError(
                f"session file {path} was written for {h.dim}-dimensional items, but these items have "
                f"{self.dim} dimensions.",
                "dim",
                str(h.dim),
                str(self.dim),
            )
        settings: tuple[tuple[str, Any, Any], ...] = (
            ("candidates", h.candidates, self.spec),
            ("bounds", [list(h.bounds[0]), list(h.bounds[1])], self.bounds.tolist()),
            ("seed", h.seed, self.seed),
            ("num_levels", h.num_levels, self.num_levels),
        )
        for key, theirs, mine in settings:
            if key == "candidates" and _same_pool(theirs, self):
                continue
            if dumps_settings(theirs) != dumps_settings(mine):
                if key == "candidates":
                    theirs, mine = _describe(theirs), _describe(mine)
                raise SessionMismatchError(
                    f"session file {path} was written with {key} {theirs}, but this session has {key} {mine}; "
                    f"open it with PreferenceSession.load({str(path)!r}) to use the file's settings.",
                    key,
                    str(theirs),
                    str(mine),
                )


def _same_pool(recorded: object, settings: SessionSettings) -> bool:
    """Whether a header's pool is this session's when one of the two specs is by reference and
    the other written out (a large pool's file from before references, or the other way round)."""
    if not (
        isinstance(recorded, dict) and recorded.get("kind") == "pool" and isinstance(settings.candidates, FinitePool)
    ):
        return False
    if ("items" in recorded) == ("items" in settings.spec):
        return False  # the same form: compared as they are
    pool = settings.candidates.X
    if "items" in recorded:
        return dumps_settings(recorded) == dumps_settings({"kind": "pool", "items": pool.tolist()})
    return recorded.get("sha256") == pool_digest(pool) and recorded.get("num_items") == pool.shape[0]


def unrated_rows(pool_rows: Tensor, in_force: Iterable[AnswerRecord], chosen: int, m: int) -> Tensor | None:
    """Where a selector chose to ask for a rating of ``pool_rows[chosen]``, an item that already has
    a rating in force: the positions of the candidates with none, to choose among instead (as long
    as at least ``max(2, m)`` are left: a ranking of ``m`` can still be asked); else ``None``.

    A second rating of the same item is not asked: a person rating an item again mostly recalls
    their first answer, which the model would count as independent evidence, and the question is
    better spent on an item with no rating (docs/sessions.md).
    """
    rated = {rec.pool_indices[0] for rec in in_force if rec.kind == "rating" and rec.pool_indices}
    if int(pool_rows[chosen]) not in rated:
        return None
    keep = [k for k, i in enumerate(pool_rows.tolist()) if int(i) not in rated]
    return torch.tensor(keep, dtype=torch.long) if len(keep) >= max(2, m) else None


def as_seconds(value: object) -> float | None:
    """A response time as float seconds (``None`` stays ``None``).

    Raises:
        ValueError: not a finite real number >= 0 (a bool or text included), naming it.
    """
    if value is None:
        return None
    number: object = value
    if isinstance(value, Tensor) and value.numel() == 1 and not value.dtype.is_complex and value.dtype != torch.bool:
        number = value.item()
    ok = isinstance(number, (int, float)) and not isinstance(number, bool)
    try:
        seconds = float(number) if ok and isinstance(number, (int, float)) else math.nan
    except OverflowError:  # an integer too large for a float
        seconds = math.inf
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"response_time must be None or a finite number of seconds >= 0, got {value!r:.80}.")
    return seconds


def as_time(value: object, name: str) -> str:
    """A time stamp kept in an answer record (``shown_at``, ``answered_at``): an ISO 8601 date and
    time, as :meth:`datetime.datetime.fromisoformat` reads it, of at most 40 characters.

    Raises:
        ValueError: anything else, naming ``name`` and the value.
    """
    import datetime as _dt

    if isinstance(value, str) and len(value) <= 40:
        try:
            _dt.datetime.fromisoformat(value)
            return value
        except ValueError:
            pass
    raise ValueError(f"{name} must be an ISO 8601 date and time, got {value!r:.80}.")


def check_callables(selector: object, model_factory: object) -> None:
    """A selector with ``select`` and a callable model factory (or ``None``), else ``TypeError``."""
    if selector is not None and not callable(getattr(selector, "select", None)):
        raise TypeError(f"selector must be a Selector (with select(model, candidates, ...)), got {selector!r:.80}.")
    if model_factory is not None and not callable(model_factory):
        raise TypeError(f"model_factory must be callable(X) -> PreferenceGP, got {model_factory!r:.80}.")


def population_factory(
    population: Population | None,
    model_factory: Callable[[Tensor], PreferenceGP] | None,
    dim: int,
    names: list[str] | None,
) -> Callable[[Tensor], PreferenceGP] | None:
    """``model_factory``, or for a ``population`` its :meth:`~torchpref.Population.person_model`.

    Raises:
        ValueError: both given, a ``population`` that is not one, or of another objective space.
    """
    if population is None:
        return model_factory
    if isinstance(population, (str, bytes, os.PathLike)):
        raise ValueError(
            f"population must be a torchpref.Population, got the path {population!r:.80}: load a saved one "
            "with torchpref.load_population(path) and pass that."
        )
    if not isinstance(population, Population):
        raise ValueError(f"population must be a torchpref.Population, got {type(population).__name__}.")
    if model_factory is not None:
        raise ValueError("give population or model_factory, not both: the population builds the person's model.")
    population.check_space(names=names, dim=dim)
    return population.person_model
