"""A session does not ask for a second rating of an item while items without a rating are left
(issue #34: a served session asked the same item for a rating twice). A person rating an item
again mostly recalls their first answer, which the model would count as independent evidence."""

from __future__ import annotations

import collections

import pytest
import torch

from torchpref.selection.strategies import UCBC
from torchpref.sessions.session import PreferenceSession
from torchpref.sessions.settings import default_ranking_size
from torchpref.testing.serve import choose


@pytest.mark.parametrize("n, seed", [(30, 0), (40, 1)])
def test_no_second_rating_of_an_item_while_unrated_ones_are_left(n, seed):
    g = torch.Generator().manual_seed(seed)
    X = torch.rand(n, 3, generator=g, dtype=torch.float64)
    m = default_ranking_size(n)
    s = PreferenceSession(X, selector=UCBC(m=m), num_queries=20, seed=0, num_levels=5)
    rated: collections.Counter = collections.Counter()
    for k in range(20):  # the browser tests' scripted answers: levels and choices in turn
        q = s.ask()
        if q.kind == "rating":
            assert rated[q.index] == 0 or n - len(rated) < m, (k, q.index, dict(rated))
            rated[q.index] += 1
        shown = {"kind": q.kind, "levels": 5, "ties": True, "options": [0] * (1 if q.kind == "rating" else m)}
        s.tell(q, choose(shown, k))
    assert len(rated) >= 10  # ratings were asked, each of another item
    assert s.step == 20


def test_an_undone_rating_is_asked_again():
    """The rule counts ratings in force: an undone rating's item is asked again (undo's promise)."""
    g = torch.Generator().manual_seed(2)
    X = torch.rand(30, 2, generator=g, dtype=torch.float64)
    s = PreferenceSession(X, selector=UCBC(m=5), num_queries=10, seed=0, num_levels=5)
    while (q := s.ask()).kind != "rating":
        s.tell(q, 0)
    s.tell(q, 3)
    s.undo()
    again = s.ask()
    assert again.kind == "rating" and again.index == q.index
