"""``save_population`` / ``load_population``: the same population back; damaged and foreign files refused."""

import pytest
import torch

import torchpref
from torchpref.data.preference_data import PreferenceData
from torchpref.models.checkpoint import CheckpointError
from torchpref.population.io import population_checkpoint

D = torch.float64


@pytest.fixture(scope="module")
def pop():
    g = torch.Generator().manual_seed(0)
    people = []
    for _ in range(4):
        X = torch.rand(6, 3, generator=g, dtype=D)
        people.append(PreferenceData.create(X, torch.tensor([[0, 1], [2, 3], [4, 5], [1, 2]])))
    return torchpref.fit_population(people, max_iter=5, names=["price", "time", "comfort"])


def test_round_trip(pop, tmp_path):
    path = tmp_path / "pop.pt"
    torchpref.save_population(pop, path)
    back = torchpref.load_population(path, names=["price", "time", "comfort"])
    X = torch.rand(5, 3, generator=torch.Generator().manual_seed(1), dtype=D)
    with torch.no_grad():
        a, b = pop.person_model(X).posterior(X), back.person_model(X).posterior(X)
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(a.variance, b.variance, rtol=0, atol=1e-12)
    assert back.names == ("price", "time", "comfort") and back.stats["people"] == 4


def test_another_objective_space_is_refused_by_name(pop, tmp_path):
    path = tmp_path / "pop.pt"
    torchpref.save_population(pop, path)
    with pytest.raises(CheckpointError, match=r"fitted on the objective space \['price', 'time', 'comfort'\]"):
        torchpref.load_population(path, names=["price", "time", "changes"])
    with pytest.raises(CheckpointError, match="d = 3 features, the items 4"):
        torchpref.load_population(path, dim=4)
    with pytest.raises(ValueError, match="objective space"):
        pop.check_space(names=("a", "b", "c"))


def test_corrupted_file_is_refused_before_loading(pop, tmp_path):
    path = tmp_path / "pop.pt"
    torchpref.save_population(pop, path)
    raw = bytearray(path.read_bytes())
    (tmp_path / "cut.pt").write_bytes(bytes(raw[: len(raw) // 2]))
    with pytest.raises(CheckpointError, match="cut.pt"):
        torchpref.load_population(tmp_path / "cut.pt")
    ck = population_checkpoint(pop)
    ck["tensors"]["alpha"] = ck["tensors"]["alpha"] + 1.0  # a value changed, the digest not
    torch.save(ck, tmp_path / "edited.pt")
    with pytest.raises(CheckpointError, match="digest"):
        torchpref.load_population(tmp_path / "edited.pt")
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not a torchpref.Population file"):
        torchpref.load_population(tmp_path / "other.pt")
    (tmp_path / "model.pt").write_bytes(b"")
    torchpref.save_model(pop.person_model(torch.rand(3, 3, dtype=D)), tmp_path / "model.pt")
    with pytest.raises(CheckpointError, match="not a torchpref.Population file"):
        torchpref.load_population(tmp_path / "model.pt")


def test_bad_tensors_are_named(pop, tmp_path):
    from torchpref.population.io import _digest

    ck = population_checkpoint(pop)
    ck["tensors"]["L_U"] = -ck["tensors"]["L_U"]
    ck["digest"] = _digest(ck)
    torch.save(ck, tmp_path / "neg.pt")
    with pytest.raises(CheckpointError, match="L_U is not a Cholesky factor"):
        torchpref.load_population(tmp_path / "neg.pt")
