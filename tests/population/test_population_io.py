"""``save_population`` / ``load_population``: the same population back; damaged, crafted and
foreign files refused by name before anything is allocated."""

import os
import resource
import threading
import zipfile

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
    with pytest.raises(CheckpointError, match="is a torchpref.PreferenceGP checkpoint, not a population file"):
        torchpref.load_population(tmp_path / "model.pt")


def test_bad_tensors_are_named(pop, tmp_path):
    from torchpref.population.io import _digest

    ck = population_checkpoint(pop)
    ck["tensors"]["L_U"] = -ck["tensors"]["L_U"]
    ck["digest"] = _digest(ck)
    torch.save(ck, tmp_path / "neg.pt")
    with pytest.raises(CheckpointError, match="L_U is not a Cholesky factor"):
        torchpref.load_population(tmp_path / "neg.pt")


def _resave(ck, path):
    from torchpref.population.io import _digest

    ck["digest"] = _digest(ck)
    torch.save(ck, path)
    return path


def test_a_crafted_expanded_tensor_is_refused_before_it_is_copied(pop, tmp_path):
    """An expanded (stride-0) view of a small storage claims 3.2e8 elements: refused by the
    storage check before any check computes with it (the old loader allocated its isfinite)."""
    ck = population_checkpoint(pop)
    M = ck["tensors"]["U"].shape[0]
    ck["tensors"]["A"] = torch.zeros(1, 1, dtype=D).expand(20_000, 20_000)
    path = _resave(ck, tmp_path / "crafted.pt")
    assert os.path.getsize(path) < 100_000
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(CheckpointError, match=r"A of shape \(20000, 20000\).*expanded view"):
        torchpref.load_population(path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # KB: nothing near 3.2 GB
    assert M < 20_000


def test_a_compressed_record_and_tensors_larger_than_the_file_are_refused(pop, tmp_path, deflated_copy):
    path = tmp_path / "pop.pt"
    torchpref.save_population(pop, path)
    deflated_copy(path, tmp_path / "deflated.pt")
    with pytest.raises(CheckpointError, match="compressed or expands"):
        torchpref.load_population(tmp_path / "deflated.pt")
    g = torch.Generator().manual_seed(5)
    many = [
        PreferenceData.create(torch.rand(6, 3, generator=g, dtype=D), torch.tensor([[0, 1], [2, 3]])) for _ in range(20)
    ]
    ck = population_checkpoint(torchpref.fit_population(many, fit=False))
    shared = ck["tensors"]["L_U"]  # three entries, one storage: together three times what the file holds
    ck["tensors"]["S_chol"], ck["tensors"]["A"] = shared, shared
    with pytest.raises(CheckpointError, match="more than the file's"):
        torchpref.load_population(_resave(ck, tmp_path / "aliased.pt"))


@pytest.mark.parametrize(
    "edit, match",
    [
        (
            lambda ck: ck["k_m"]["base_kernel.raw_lengthscale"].fill_(float("nan")),
            r"k_m\.base_kernel\.raw_lengthscale is not finite",
        ),
        (lambda ck: ck["k_g"]["raw_outputscale"].fill_(float("inf")), r"k_g\.raw_outputscale is not finite"),
        (lambda ck: ck["settings"].update(comparison_noise=float("nan")), "setting 'comparison_noise' is nan"),
        (lambda ck: ck["settings"].update(rating_precision=-80.0), "setting 'rating_precision' is -80.0"),
        (lambda ck: ck["settings"].update(rating_levels=1), "setting 'rating_levels' is 1"),
        (lambda ck: ck["k_m"]["base_kernel.raw_lengthscale_constraint.lower_bound"].fill_(-1.0), "constraint bound"),
        (lambda ck: ck["stats"].update(people=[1, 2]), "stats must map names to numbers or strings"),
    ],
)
def test_bad_hyperparameters_and_settings_are_named(pop, tmp_path, edit, match):
    ck = population_checkpoint(pop)
    ck["k_m"] = {k: v.clone() for k, v in ck["k_m"].items()}
    ck["k_g"] = {k: v.clone() for k, v in ck["k_g"].items()}
    edit(ck)
    with pytest.raises(CheckpointError, match=match):
        torchpref.load_population(_resave(ck, tmp_path / "edited.pt"))


def test_a_damaged_file_is_called_a_damaged_population_file(pop, tmp_path):
    path = tmp_path / "pop.pt"
    torchpref.save_population(pop, path)
    raw = bytearray(path.read_bytes())
    (tmp_path / "cut.pt").write_bytes(bytes(raw[: len(raw) // 2]))
    with pytest.raises(CheckpointError, match="cut.pt is a damaged population file"):
        torchpref.load_population(tmp_path / "cut.pt")
    with zipfile.ZipFile(path) as z:
        start = z.getinfo(next(n for n in z.namelist() if n.endswith("data.pkl"))).header_offset
    start += (
        30
        + int.from_bytes(raw[start + 26 : start + 28], "little")
        + int.from_bytes(raw[start + 28 : start + 30], "little")
    )
    raw[start + 10 : start + 30] = b"\x00" * 20  # inside the pickle's record
    (tmp_path / "flipped.pt").write_bytes(bytes(raw))
    with pytest.raises(CheckpointError, match="flipped.pt is a damaged population file"):
        torchpref.load_population(tmp_path / "flipped.pt")
    (tmp_path / "text.pt").write_text("not a population")
    with pytest.raises(CheckpointError, match="text.pt is not a population file"):
        torchpref.load_population(tmp_path / "text.pt")


def test_a_missing_file_and_a_fifo_are_named_without_blocking(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no population file.*'nope.pt'"):
        torchpref.load_population("nope.pt")
    fifo = tmp_path / "pop.fifo"
    os.mkfifo(fifo)
    outcome = []

    def load():
        try:
            torchpref.load_population(fifo)
        except CheckpointError as err:
            outcome.append(str(err))

    worker = threading.Thread(target=load, daemon=True)
    worker.start()
    worker.join(timeout=20)
    assert outcome and "not a regular file (a FIFO)" in outcome[0]
    with pytest.raises(IsADirectoryError, match="not a population file"):
        torchpref.load_population(tmp_path)


def test_a_version_1_file_still_loads(pop, tmp_path):
    """Files written before A was kept: loaded, A computed once, the same person model."""
    ck = population_checkpoint(pop)
    ck["version"] = 1
    del ck["tensors"]["A"]
    ck["stats"] = {k: v for k, v in ck["stats"].items() if k in ("people", "items", "answers", "evidence")}
    back = torchpref.load_population(_resave(ck, tmp_path / "v1.pt"))
    assert back.mean_kind == "exact"
    torch.testing.assert_close(back.A, pop.A, rtol=0, atol=1e-12)


def test_as_population_points_to_load_population(pop):
    from torchpref.population.io import NotAPopulation, as_population

    assert as_population(pop) is pop
    with pytest.raises(TypeError, match=r"torchpref.load_population\('pop.pt'\)"):
        as_population("pop.pt")
    with pytest.raises(ValueError, match="must be a torchpref.Population"):
        as_population(3)
    assert issubclass(NotAPopulation, TypeError) and issubclass(NotAPopulation, ValueError)


def test_feature_names_are_saved_and_checked(tmp_path):
    g = torch.Generator().manual_seed(3)
    people = [PreferenceData.create(torch.rand(5, 2, generator=g, dtype=D), torch.tensor([[0, 1], [2, 3]]))]
    pop = torchpref.fit_population(people, fit=False, feature_names=["price", "time"])
    torchpref.save_population(pop, tmp_path / "p.pt")
    assert torchpref.load_population(tmp_path / "p.pt").names == ("price", "time")
    with pytest.raises(ValueError, match="feature_names must name the 2 features"):
        torchpref.fit_population(people, fit=False, feature_names=["price"])
