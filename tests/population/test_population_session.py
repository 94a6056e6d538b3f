"""``PreferenceSession(..., population=pop)``: a new person starts from the population."""

import json

import pytest
import torch

import torchpref
from torchpref.data.preference_data import PreferenceData

D = torch.float64


@pytest.fixture(scope="module")
def pool_and_pop():
    g = torch.Generator().manual_seed(5)
    pool = torch.rand(12, 2, generator=g, dtype=D)
    pool[0] = 0.0
    pool[1] = 1.0  # the session normalises by the pool's range: the unit cube is the pool's own
    u = pool[:, 0] - pool[:, 1]
    people = []
    for _ in range(10):
        idx = torch.randperm(12, generator=g)[:6]
        pairs = [(0, 1), (2, 3), (4, 5), (1, 2)]
        C = [[i, j] if u[idx[i]] > u[idx[j]] else [j, i] for i, j in pairs]
        people.append(PreferenceData.create(pool[idx], torch.tensor(C)))
    return pool, torchpref.fit_population(people, max_iter=5, names=["a", "b"])


def test_session_starts_from_the_population(pool_and_pop, tmp_path):
    pool, pop = pool_and_pop
    path = tmp_path / "s.jsonl"
    s = torchpref.PreferenceSession(pool, population=pop, session_file=path, names=["a", "b"])
    mean, _ = s.predict(pool)
    expected = pop.person_model(pool).posterior(pool).mean.squeeze(-1).detach()
    torch.testing.assert_close(mean, expected, rtol=0, atol=1e-9)
    q = s.ask()
    s.tell(q, 3 if q.kind == "rating" else 0)
    s.close()
    header = json.loads(path.read_text().splitlines()[0])
    assert header["model"]["mean"].startswith("PopulationMean")
    assert len(path.read_text()) < 200_000  # large buffers recorded by digest
    again = torchpref.PreferenceSession(pool, population=pop, session_file=path, names=["a", "b"])
    assert again.step == 1
    again.close()
    with pytest.raises(torchpref.sessions.SessionSettingsError):
        torchpref.PreferenceSession(pool, session_file=path, names=["a", "b"])


def test_session_refuses_a_population_of_another_space(pool_and_pop):
    pool, pop = pool_and_pop
    with pytest.raises(ValueError, match="objective space"):
        torchpref.PreferenceSession(pool, population=pop, names=["price", "time"])
    with pytest.raises(ValueError, match="not both"):
        torchpref.PreferenceSession(pool, population=pop, model_factory=pop.person_model)
    with pytest.raises(ValueError, match="must be a torchpref.Population"):
        torchpref.PreferenceSession(pool, population="pop.pt")


def test_serve_store_starts_each_session_from_the_population(pool_and_pop, tmp_path):
    pytest.importorskip("starlette", reason="the serve extra (starlette) is not installed")
    from torchpref.frontends.serve.items import ServeItems
    from torchpref.frontends.serve.store import SessionStore

    pool, pop = pool_and_pop
    store = SessionStore(ServeItems(pool, ["a", "b"], None), tmp_path, population=pop)
    try:
        sid = store.create()
        session = store.entry(sid).session
        mean, _ = session.predict(pool)
        expected = pop.person_model(pool).posterior(pool).mean.squeeze(-1).detach()
        torch.testing.assert_close(mean, expected, rtol=0, atol=1e-9)
    finally:
        store.close()


def test_cli_takes_a_population_file(pool_and_pop, tmp_path):
    from torchpref.cli import build_parser

    args = build_parser().parse_args(["serve", "--features", "items.csv", "--population", str(tmp_path / "p.pt")])
    assert args.population == str(tmp_path / "p.pt")


def test_large_buffers_are_recorded_by_digest():
    from torchpref.sessions.recorded import RECORDED_VALUES_MAX, describe_model, same_description

    g = torch.Generator().manual_seed(8)
    people = [
        PreferenceData.create(torch.rand(40, 2, generator=g, dtype=D), torch.tensor([[0, 1], [2, 3]])) for _ in range(3)
    ]
    pop = torchpref.fit_population(people, fit=False)
    assert pop.U.shape[0] ** 2 > RECORDED_VALUES_MAX
    X = torch.rand(2, 2, generator=g, dtype=D)
    a, b = describe_model(pop.person_model(X)), describe_model(pop.person_model(X))
    big = a["state"]["covar_module.A"]
    assert "sha256" in big and "values" not in big and big["shape"] == [120, 120]
    assert same_description(a, b)
    other = torchpref.fit_population(people[:2], fit=False)
    assert not same_description(a, describe_model(other.person_model(X)))


def test_a_population_path_points_to_load_population(tmp_path):
    import torch

    from torchpref.sessions.session import PreferenceSession

    X = torch.rand(6, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="load_population"):
        PreferenceSession(X, population=str(tmp_path / "pop.pt"))
    with pytest.raises(ValueError, match="load_population"):
        PreferenceSession(X, population=tmp_path / "pop.pt")


def test_serve_refuses_a_population_file_without_feature_names(tmp_path, monkeypatch):
    """``serve --population`` with a file that records no feature names cannot check it against the
    items: refused, naming the way out, unless --population-without-names says so."""
    pytest.importorskip("starlette")
    from torchpref.cli import build_parser
    from torchpref.frontends.serve import app
    from torchpref.frontends.serve.app import ServeError
    from torchpref.testing.serve import write_items

    g = torch.Generator().manual_seed(3)
    people = [
        PreferenceData.create(torch.rand(5, 2, generator=g, dtype=D), torch.tensor([[0, 1], [2, 3]])) for _ in range(3)
    ]
    torchpref.save_population(torchpref.fit_population(people, fit=False), tmp_path / "p.pt")
    items = write_items(tmp_path, n=8, d=2, pictures=False)
    args = build_parser().parse_args(
        ["serve", "--features", str(items), "--population", str(tmp_path / "p.pt"), "--port", "0"]
    )
    with pytest.raises(ServeError, match="no feature names.*--population-without-names"):
        app.run(args)
    args.population_without_names = True
    served = []
    monkeypatch.setattr(app, "serve", lambda items, **kw: served.append(kw["new"].population))
    assert app.run(args) == 0 and served and served[0] is not None
