r"""Ask what this person answers best: the expected reduction of the rating profile's variance per
expected second of their time.

:class:`ProfilePerSecond` is :class:`~torchpref.selection.top_profile.ProfileVariancePerEffort`
(the module notes of :mod:`torchpref.selection.top_profile`: an answer's value is the expected
reduction of a rating profile's posterior variance, estimated from joint posterior samples
reweighted by each answer's likelihood) with three changes:

* **its cost is seconds**: a rating costs the :class:`~torchpref.simulation.raters.EffortModel`'s
  ``rating()`` seconds and a best-of-``m`` its ``ranking(m)``, or, once the person has answered
  ``min_answers`` of a kind, their own mean measured seconds for it (:meth:`record_seconds`; the
  browser front end records response times). A person who rates slowly is asked fewer ratings;
  options that must be watched (trajectories) make a ranking of ``m`` cost ``m`` viewings;
* **the person's reliabilities enter the value**: answers are valued under the model's own
  likelihoods, so a model calibrated to the person (:func:`~torchpref.models.calibration.calibrate_person`)
  values a rating with their learned offset, gain and noise (``nu``), and a ranking with their
  learned lapse rate ``eps``: a choice's probabilities become ``eps / m + (1 - eps) P`` (a lapse
  picks uniformly), which lowers what a ranking can tell;
* **its target is both profiles**: the top-set profile ``r(f) 1[top]`` (which items are best:
  true positives, regret) and the clipped profile ``max(r(f), tau)`` (the levels of the top and
  the threshold: WRMS), concatenated, so a query's value is the sum of the two reductions, both in
  rating units (``target="both"``, the default; ``"top"`` or ``"clipped"`` for one of them).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchpref.data.effort import EffortModel
from torchpref.models.defaults import preference_likelihood
from torchpref.selection.samples import SelectorModel, joint_posterior, joint_samples
from torchpref.selection.top_profile import ProfileVariancePerEffort, _Moments, _reduction, top_profile

__all__ = ["ProfilePerSecond"]

TARGETS = ("both", "top", "clipped")


class ProfilePerSecond(ProfileVariancePerEffort):
    r"""The query of largest expected profile-variance reduction per expected second (module notes).

    Args:
        m: items per ranking query.
        effort: the seconds model (default :meth:`EffortModel.plain`).
        rating_seconds, ranking_seconds: explicit seconds of a rating and of a best-of-``m``
            (instead of ``effort``'s; another size of ranking then costs the same).
        target: ``"both"`` (default), ``"top"`` or ``"clipped"``.
        min_answers: measured answers of a kind before their mean replaces the effort model's seconds.
        num_samples, top_fraction, num_plausible, num_bins: as
            :class:`~torchpref.selection.top_profile.ProfileVariancePerEffort`.

    Raises:
        ValueError: for an unknown target or a ``min_answers`` below 1.
    """

    name = "profile per second"

    def __init__(
        self,
        m: int = 5,
        effort: EffortModel | dict[str, float] | None = None,
        target: str = "both",
        min_answers: int = 3,
        num_samples: int = 256,
        top_fraction: float = 0.2,
        num_plausible: int = 15,
        num_bins: int = 10,
        *,
        rating_seconds: float | None = None,
        ranking_seconds: float | None = None,
    ):
        effort = EffortModel.plain() if effort is None else EffortModel.of(effort)
        if rating_seconds is not None or ranking_seconds is not None:  # explicit seconds of this m
            rating = effort.rating() if rating_seconds is None else float(rating_seconds)
            ranking = effort.ranking(m) if ranking_seconds is None else float(ranking_seconds)
            if not (rating > 0 and ranking > 0):
                raise ValueError(f"seconds must be positive, got {rating} and {ranking}.")
            # the same seconds as an effort model: a rating r, a best-of-m c + 0 (m - 2) with no viewing
            effort = EffortModel(rating_seconds=rating, choice_seconds=ranking, per_extra_option=0.0, view_seconds=0.0)
        if target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {target!r}.")
        if int(min_answers) != min_answers or min_answers < 1:
            raise ValueError(f"min_answers must be a positive integer, got {min_answers!r}.")
        super().__init__(
            m,
            effort.rating(),
            effort.ranking(m),
            num_samples=num_samples,
            top_fraction=top_fraction,
            num_plausible=num_plausible,
            num_bins=num_bins,
            clipped=target == "clipped",
        )
        self._effort = effort
        self.effort, self.target, self.min_answers = effort.as_dict(), target, int(min_answers)
        self._measured: dict[str, list[float]] = {"rating": [], "ranking": []}

    # -------------------------------------------------------------- seconds
    def record_seconds(self, kind: str, seconds: float, m: int | None = None) -> None:
        """Record a measured answer: ``kind`` ``"rating"`` or ``"ranking"`` (of ``m`` options,
        default this selector's ``m``) took ``seconds``. A ranking of another size is rescaled to
        ``m`` options by the effort model's ratio."""
        if kind not in self._measured:
            raise ValueError(f"kind must be 'rating' or 'ranking', got {kind!r}.")
        s = float(seconds)
        if not (s > 0 and s < float("inf")):
            raise ValueError(f"seconds must be positive and finite, got {seconds!r}.")
        if kind == "ranking" and m is not None and m != self.m:
            s *= self._effort.ranking(self.m) / self._effort.ranking(m)
        self._measured[kind].append(s)

    def seconds(self) -> dict[str, float]:
        """The seconds a rating and a ranking are valued at now: measured means where there are
        ``min_answers`` of a kind, else the effort model's."""
        model = {"rating": self._effort.rating(), "ranking": self._effort.ranking(self.m)}
        return {k: (sum(v) / len(v) if len(v) >= self.min_answers else model[k]) for k, v in self._measured.items()}

    # -------------------------------------------------------------- values
    def _profile(self, F: Tensor, k: int, rating_likelihood) -> tuple[Tensor, Tensor]:
        """``T x S x C`` profile columns and the item of each column (``C``)."""
        N = F.shape[-1]
        items = torch.arange(N, device=F.device)
        if self.target != "both":
            return top_profile(F, k, rating_likelihood, self.target == "clipped"), items
        V = torch.cat([top_profile(F, k, rating_likelihood, False), top_profile(F, k, rating_likelihood, True)], -1)
        return V, items.repeat(2)

    def query_cost(self, q: int) -> float:
        """The seconds of a rating (``q = 1``) or of a best-of-``q`` (:meth:`seconds`; another size
        than ``m`` by the effort model's ratio)."""
        sec = self.seconds()
        if q == 1:
            return sec["rating"]
        return sec["ranking"] * (1.0 if q == self.m else self._effort.ranking(q) / self._effort.ranking(self.m))

    def _prepare(
        self, model: SelectorModel, X: Tensor, generators: Sequence[torch.Generator]
    ) -> tuple[Tensor, Tensor, Any]:
        """As :meth:`ProfileVariancePerEffort._prepare`, on this selector's profile (``target``);
        the candidates by the summed variance of their columns."""
        mean, cov = joint_posterior(model, X)
        F, _ = joint_samples(mean, cov, generators, self.num_samples)
        T, S, N = F.shape
        V, item_of = self._profile(F, max(1, min(N, round(self.top_fraction * N))), preference_likelihood(model).rating)
        var = V.var(-2)  # T x C
        cols = var.argsort(-1, descending=True)
        n = max(1, int((var > 0).sum(-1).max()))  # the columns that matter (zero columns add nothing)
        mom = _Moments.of(V.gather(2, cols[:, :n].unsqueeze(1).expand(T, S, n)))
        item_var = var.new_zeros(T, N).index_add_(1, item_of, var)

        def value(P: Tensor) -> Tensor:  # T x R x S x Y -> T x R
            return _reduction(P, mom, True)

        return F, item_var.argsort(-1, descending=True), value
