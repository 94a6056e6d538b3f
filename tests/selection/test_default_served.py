"""The default selector's served question (issue 52): the per-question shortcuts (the greedy
search's own values for the prefix sizes and the rating, a pair's choice in closed form) ask the
question the previous implementation asked, on most of a set of seeded sessions."""

from __future__ import annotations

import math

import pytest
import torch

import torchpref
from torchpref.acquisition import choice_sets
from torchpref.selection.choosing import shown


def _quadrature_pair(self, Ft, j, c, sl):
    """The previous best-pair search: a pair's choice by the Gauss-Hermite rule."""
    return self.probs(self.phi(Ft[:, j] - Ft[:, c], sl).unsqueeze(2), self.phi(Ft[:, c] - Ft[:, j], sl).unsqueeze(2))


def previous_question(sel, model, X, seed):
    """The previous implementation's ``values`` for one trial: every prefix and the rating valued
    anew by the judge, the best pair by quadrature. ``("rating", row)`` or ``("ranking", rows)``."""
    gens = [torch.Generator().manual_seed(seed)]
    prep = sel._prepare(model, X.unsqueeze(0), gens)
    F, lik = prep["F"], prep["lik"]
    T, S, N = F.shape
    K = min(sel.num_plausible, N)
    cand = prep["by_max"][:, :K]
    Fc = F.gather(2, cand.unsqueeze(1).expand(T, S, K))
    rate, rank = sel._scorers(prep, prep["order"], prep["order"])
    by_value = rate(cand)
    rating_row = cand.gather(1, by_value.argmax(-1, keepdim=True))
    rating_value = float(rate(rating_row)) / sel.query_cost(1)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(choice_sets._ChoiceTerms, "pair", _quadrature_pair)
        chosen, _ = choice_sets.greedy_choice_sets(Fc, lik.comparison, sel.m, prep["order"], start=None)
    rows = cand.gather(1, chosen)
    best_q, best_v = sel.m, -math.inf
    for q in range(2, sel.m + 1):
        v = float(rank(rows[:, :q].unsqueeze(1))) / sel.query_cost(q)
        if v > best_v:
            best_q, best_v = q, v
    if best_v > rating_value:
        return "ranking", sorted(rows[0, :best_q].tolist())
    return "rating", [int(rating_row)]


def _session(seed: int, answers: int = 12) -> tuple[torchpref.PreferenceSession, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(100, 4, generator=g, dtype=torch.float64)
    w = torch.randn(4, generator=g, dtype=torch.float64)
    s = torchpref.PreferenceSession(X, num_queries=20, seed=seed)
    for _ in range(answers):
        q = s.ask()
        u = torch.sin(3 * q.items @ w)
        s.tell(q, int((1 + 4 * torch.special.ndtr(u[0])).round()) if q.kind == "rating" else int(u.argmax()))
    return s, s.transform(X)


def test_the_default_asks_what_it_asked_before_on_most_sessions():
    agree, cases = 0, 0
    for seed in range(8):
        s, X = _session(seed, answers=4 + seed % 3 * 4)
        sel = s.selector
        for k in range(2):
            with torch.no_grad():
                rating_row, rating_value, rows, ranking_value = sel.values(
                    s.model, X.unsqueeze(0), [torch.Generator().manual_seed(100 * seed + k)]
                )
                new = (
                    ("ranking", sorted(shown(rows[0]).tolist()))
                    if bool(ranking_value[0] > rating_value[0])
                    else ("rating", [int(rating_row[0])])
                )
                old = previous_question(sel, s.model, X, 100 * seed + k)
            agree += new == old
            cases += 1
    print(f"the same question in {agree} of {cases} cases")
    assert agree >= cases - 2, f"the same question in {agree} of {cases} cases"
