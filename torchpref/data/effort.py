r"""What a question costs the person: one effort model, in seconds, priced by every selector,
the replays, the docs and the study (:class:`EffortModel`).

The figures are FIRE's online measurements (Gaillard et al. 2025, "Reliable and Valid Rating Data in
Less Time with the Fast Image Rating Experiment"): a 1-7 Likert rating 3.3-3.5 s, pick 1 of 2
3.4 s, pick 1 of a 12-image grid 12.2-12.5 s, about 0.9 s per extra option shown. Where each option
must be watched (trajectories, robot behaviours), looking dominates: one viewing per option shown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

__all__ = ["CHOICE_SECONDS", "PER_EXTRA_OPTION_SECONDS", "RATING_SECONDS", "TRAJECTORY_VIEW_SECONDS", "EffortModel"]

#: a 1-7 Likert rating: 3.3-3.5 s; pick 1 of 2: 3.4 s; pick 1 of 12: 12.2-12.5 s (Gaillard et al. 2025, FIRE)
RATING_SECONDS = 3.4
CHOICE_SECONDS = 3.4
PER_EXTRA_OPTION_SECONDS = 0.9
#: the trajectory-viewing effort model's seconds per option shown (an assumption: watching one
#: short path or behaviour; ROIAL's exoskeleton trials took ~87 s each, Li, Tucker et al. 2021)
TRAJECTORY_VIEW_SECONDS = 10.0


def _check(name: str, value: float, low: float = 0.0, high: float = math.inf, closed: bool = True) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}.") from None
    ok = (low <= v if closed else low < v) and v <= high and math.isfinite(v)
    if not ok:
        raise ValueError(f"{name} must lie in {'[' if closed else '('}{low}, {high}], got {value!r}.")
    return v


@dataclass(frozen=True)
class EffortModel:
    r"""Seconds per answer: a rating ``r + v``, a best-of-``m`` choice ``c + e (m - 2) + v m``.

    ``r`` (``rating_seconds``), ``c`` (``choice_seconds``, a pair) and ``e``
    (``per_extra_option``) are FIRE's online measurements (a 1-7 rating 3.3-3.5 s, a pair 3.4 s,
    a 12-image grid 12.2-12.5 s: about 0.9 s per extra option); ``v`` (``view_seconds``) is the
    time to look at one option, zero for a plain stimulus (an image seen at a glance), the viewing
    time of a trajectory or behaviour where each option must be watched.

    Example:
        >>> EffortModel.plain().ranking(5), EffortModel.trajectories().ranking(5)
        (6.1, 56.1)
    """

    rating_seconds: float = RATING_SECONDS
    choice_seconds: float = CHOICE_SECONDS
    per_extra_option: float = PER_EXTRA_OPTION_SECONDS
    view_seconds: float = 0.0

    def __post_init__(self):
        for name in ("rating_seconds", "choice_seconds", "per_extra_option", "view_seconds"):
            _check(name, getattr(self, name))
        if self.rating_seconds + self.view_seconds <= 0 or self.choice_seconds + 2 * self.view_seconds <= 0:
            raise ValueError(f"an answer must take some time, got {self}.")

    @classmethod
    def plain(cls) -> EffortModel:
        """Plain stimuli: FIRE's seconds, no viewing time."""
        return cls()

    @classmethod
    def trajectories(cls, view_seconds: float = TRAJECTORY_VIEW_SECONDS) -> EffortModel:
        """Options that must be watched: FIRE's seconds plus ``view_seconds`` per option shown."""
        return cls(view_seconds=view_seconds)

    def rating(self) -> float:
        """Seconds of one rating (one option shown)."""
        return round(self.rating_seconds + self.view_seconds, 12)

    def ranking(self, m: int) -> float:
        """Seconds of one best-of-``m`` choice (``m`` options shown)."""
        if int(m) != m or m < 2:
            raise ValueError(f"a choice shows m >= 2 options, got m={m!r}.")
        return round(self.choice_seconds + self.per_extra_option * (m - 2) + self.view_seconds * m, 12)

    @classmethod
    def of(cls, value: object) -> EffortModel:
        """``value`` as an effort model: one, or the dictionary of its fields (:meth:`as_dict`, as a
        session file records a selector's effort model).

        Raises:
            ValueError: anything else, or fields out of range, naming the value.
        """
        if isinstance(value, cls):
            return value
        if isinstance(value, dict) and set(value) <= {f.name for f in fields(cls)}:
            return cls(**value)
        raise ValueError(f"effort must be a torchpref EffortModel or a dictionary of its fields, got {value!r:.120}.")

    def as_dict(self) -> dict[str, float]:
        """The fields, as JSON records them."""
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    def costs(self, m: int) -> dict[str, float]:
        """``{"rating": seconds, "ranking": seconds of a best-of-m}``, as the loop's ``costs``."""
        return {"rating": self.rating(), "ranking": self.ranking(m)}
