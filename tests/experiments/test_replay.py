"""The real-people replay: the data load as published (people, choices, option counts), a replay
reveals every pool answer once and scores the held-out choices, and the summary's paired tests
see a selector that is always better."""

import math

import pytest
import torch

from torchpref.experiments import replay
from torchpref.selection.robust import EpsilonExplore
from torchpref.selection.strategies import UCBC, RandomRankings

DATA = replay.Path(__file__).resolve().parents[2] / "benchmarks" / "studies" / "data"


@pytest.mark.parametrize("name,people,choices,m", [("electricity", 361, 4308, 4), ("rail", 235, 2929, 2)])
def test_data_load_as_published(name, people, choices, m):
    ps = replay.load(name, DATA)
    assert len(ps) == people
    assert sum(len(p.choices) for p in ps) <= choices  # a choice between identical options is dropped
    assert sum(len(p.choices) for p in ps) >= 0.99 * choices
    for p in ps[:20]:
        assert p.X.min() >= 0 and p.X.max() <= 1
        assert all(2 <= len(rows) <= m and 0 <= j < len(rows) for rows, j in p.choices)
        assert len({tuple(x) for x in p.X.tolist()}) == p.X.shape[0]  # distinct items


def test_a_replay_reveals_the_pool_and_scores_held_out_choices():
    person = next(p for p in replay.load("electricity", DATA) if len(p.choices) == 12)
    out = replay.replay_person(person, 0, UCBC(m=4), seed=0)
    n_train = 12 - 4
    assert all(len(v) == n_train + 1 for v in out.values())
    assert out["accuracy"][0] == 0.5 and out["top1"][0] == pytest.approx(0.25)  # no answers: all tied
    assert out["log_loss"][0] == pytest.approx(math.log(2))
    assert all(0 <= a <= 1 for a in out["accuracy"])


def test_summary_pairs_and_tests_against_random():
    rows = []
    for i in range(12):
        for name, shift in (("random", 0.0), ("better", 0.1)):
            curve = [0.5] + [0.6 + shift + 0.01 * i] * 4
            rows.append(
                dict(dataset="d", person=str(i), split=0, selector=name, accuracy=curve, log_loss=curve, top1=curve)
            )
    s = replay.summarise(rows)["d"]["better"]["accuracy"]
    assert s["diff"] == pytest.approx(0.1) and s["wins"] == 12 and s["losses"] == 0 and s["p"] < 0.01


def test_epsilon_explore():
    torch.manual_seed(0)
    with pytest.raises(ValueError, match="epsilon"):
        EpsilonExplore(UCBC(), 1.5)
    person = replay.load("rail", DATA)[0]
    queries = [replay.RankingQuery(person.X[list(r)], r) for r, _ in person.choices]
    model = replay._model(person.X, [])
    never = EpsilonExplore(UCBC(m=2), 0.0)
    for seed in range(5):
        after_coin = torch.Generator().manual_seed(seed)
        torch.rand((), generator=after_coin, dtype=torch.float64)  # the exploration coin comes first
        mine = never.choose(model, queries, generator=torch.Generator().manual_seed(seed))
        assert mine == UCBC(m=2).choose(model, queries, generator=after_coin)
    always = EpsilonExplore(RandomRankings(m=2), 1.0)
    picks = {always.choose(model, queries, generator=torch.Generator().manual_seed(s)) for s in range(200)}
    assert picks == set(range(len(queries)))
