"""The twins experiment (torchpref.experiments.twins): its scores against brute force, the looked-up
prior against the person model, a run of twins end to end, and the summary's counts."""

import itertools
import math
from pathlib import Path

import pytest
import torch

import torchpref
from torchpref.data.preference_data import PreferenceData
from torchpref.experiments import twins as tw
from torchpref.experiments.twins_report import _reach, read_rows, summarise
from torchpref.models.batch import BatchedPreferenceGP

D = torch.float64
DATA = Path(__file__).resolve().parents[2] / "benchmarks" / "studies" / "data"


@pytest.fixture(scope="module")
def pop_and_items():
    g = torch.Generator().manual_seed(7)
    items = torch.rand(14, 2, generator=g, dtype=D)
    u = items[:, 0] - items[:, 1] ** 2
    people = []
    for _ in range(12):
        idx = torch.randperm(14, generator=g)[:6]
        C = [[i, j] if u[idx[i]] > u[idx[j]] else [j, i] for i, j in [(0, 1), (2, 3), (4, 5), (1, 2), (3, 4)]]
        people.append(PreferenceData.create(items[idx], torch.tensor(C)))
    return torchpref.fit_population(people, max_iter=5), items


def test_scores_are_the_brute_force_ones(pop_and_items):
    pop, items = pop_and_items
    twins = tw.make_twins(pop, items, "electricity", 0, 2, seed=1)
    model = tw.learner(pop, twins, "population", twins[0].profile.rating_scale)
    model.add_observations(0, items[[2, 5]], torch.tensor([[0, 1]]))
    model.add_observations(1, items[[3]], ratings=torch.tensor([0.7], dtype=D), rating_index=torch.tensor([0]))
    scores = tw.twin_metrics(twins, 1.0)(model)
    mean, cov = model.joint(torch.stack([t.X for t in twins]))
    for b, t in enumerate(twins):
        f, mu, S = t.utility.f, mean[b], cov[b]
        agree = [
            0.5 if abs(float(mu[i] - mu[j])) < 1e-12 else float((mu[i] > mu[j]) == (f[i] > f[j]))
            for i, j in itertools.combinations(range(len(f)), 2)
        ]
        assert math.isclose(float(scores["concordance"][b]), sum(agree) / len(agree), rel_tol=1e-12)
        rec = float(f[int(mu.argmax())])
        med = float(f.median())
        assert math.isclose(float(scores["value"][b]), (rec - med) / (float(f.max()) - med), rel_tol=1e-12)
        losses = []
        for w, lo in t.fresh.tolist():
            var = float(S[w, w] + S[lo, lo] - 2 * S[w, lo])
            p = 0.5 * math.erfc(-float(mu[w] - mu[lo]) / math.sqrt(2 * (2.0 + var)))
            losses.append(-math.log(p))
        assert math.isclose(float(scores["log_loss"][b]), sum(losses) / len(losses), rel_tol=1e-9)


def test_the_looked_up_prior_is_the_person_models(pop_and_items):
    pop, items = pop_and_items
    twins = tw.make_twins(pop, items, "rail", 0, 2, seed=2)  # rail: a pool per twin (here all 14 items)
    ours = tw.learner(pop, twins, "population", 1.3)
    direct = BatchedPreferenceGP.from_models(
        [pop.person_model(PreferenceData.create(t.X), rating_scale=1.3, rating_precision=20.0) for t in twins]
    )
    for model in (ours, direct):
        model.add_observations(
            0, items[[1, 4]], torch.tensor([[1, 0]]), torch.tensor([0.2], dtype=D), torch.tensor([0])
        )
    X = torch.stack([t.X for t in twins])
    for a, b in zip(ours.joint(X), direct.joint(X)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)
    prior = tw.PriorAtItems(pop.person_model, items)
    with pytest.raises(ValueError, match="not one of the prior's items"):
        prior.rows(items[:1] + 0.5)


def test_twin_batch_runs_and_random_repeats_average(pop_and_items):
    pop, items = pop_and_items
    twins = tw.make_twins(pop, items, "electricity", 0, 3, seed=3)
    recs = tw.twin_batch(pop, twins, "no population", "random mixed", "plain", queries=3, repeats=2)
    assert len(recs) == 3 and all(len(r["concordance"]) == 4 and len(r["repeats"]) == 2 for r in recs)
    for r in recs:
        mean = [(a + b) / 2 for a, b in zip(r["repeats"][0]["concordance"], r["repeats"][1]["concordance"])]
        assert r["concordance"] == pytest.approx(mean, abs=1e-15)
    assert recs[0]["concordance"][0] == 0.5  # a zero mean orders no pair


def test_reach_and_the_summary_count_what_they_say():
    assert _reach([0.5, 0.6, 0.7], 0.6) == 1 and _reach([0.5, 0.6], 0.9) == 2
    rows = []
    for twin in range(8):
        base = [0.5 + 0.01 * k for k in range(5)]
        fast = [0.5 + 0.02 * k + 0.001 * twin for k in range(5)]
        for s, curve, kinds in (("random mixed", base, ["ranking"] * 4), ("fast", fast, ["rating"] * 4)):
            rows.append(dict(dataset="d", fold=0, twin=twin, condition="population", strategy=s, effort="plain",
                             concordance=curve, value=curve, log_loss=[1 - c for c in curve], kinds=kinds))  # fmt: skip
    s = summarise(rows, "random mixed")["plain"]
    e = s["cells"]["d/population"]["strategies"]["fast"]
    assert e["reach"]["median"] == 2 and e["concordance"]["p_wilcoxon"] < 0.05 and e["fraction_ratings"] == 1.0
    assert s["best_or_tied"]["fast"][0] >= 4


@pytest.mark.slow
def test_a_small_twins_run_end_to_end(tmp_path):
    """The command line: two twins per fold of electricity, two questions; the rows resume."""
    args = ["reproduce", "twins", "--twins", "2", "--datasets", "electricity", "--queries", "2"]
    args += ["--strategies", "random mixed", "utility info", "--out", str(tmp_path), "--cache", str(tmp_path / "c")]
    assert torchpref.cli.main(args) == 0
    rows = read_rows(tmp_path / "twins_rows.jsonl")
    assert len(rows) == 3 * 2 * 3  # folds x conditions x (random, info plain, info trajectories)
    assert (tmp_path / "twins.json").is_file() and (tmp_path / "twins.png").is_file()
    assert torchpref.cli.main(args) == 0  # resumed: nothing run again
    assert read_rows(tmp_path / "twins_rows.jsonl") == rows
