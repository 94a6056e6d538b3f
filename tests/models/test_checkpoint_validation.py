"""Checkpoints validated like constructor input, and written through symlinks with the umask's
mode and a flushed folder (issue #26, item 2). Each case here loaded (or wrote) silently before."""

import copy
import os
import stat
import warnings

import pytest
import torch
from gpytorch.constraints import GreaterThan
from gpytorch.kernels import RBFKernel, ScaleKernel

import torchpref
from torchpref.models.checkpoint import CheckpointError, model_checkpoint

F64 = torch.float64


def _model(n=6, **kw):
    g = torch.Generator().manual_seed(0)
    X = torch.rand(n, 2, generator=g, dtype=F64)
    return torchpref.PreferenceGP(
        X, torch.tensor([[0, 1], [2, 3]]), torch.tensor([0.3, 0.8], dtype=F64), torch.tensor([4, 5]), **kw
    )


def _edited(change, model=None):
    ck = copy.deepcopy(model_checkpoint(model if model is not None else _model()))
    change(ck)
    return ck


def _setting(name, value):
    return lambda ck: ck["settings"].__setitem__(name, value)


def _hyper(name, value):
    return lambda ck: ck["state_dict"].__setitem__(name, value)


LS_LOWER = "covar_module.base_kernel.raw_lengthscale_constraint.lower_bound"


@pytest.mark.parametrize(
    "change, match",
    [
        (_setting("ties_offered", "no"), r"'ties_offered' must be True or False, got 'no' \(str\)"),
        (_setting("learn_likelihood", 1), r"'learn_likelihood' must be True or False, got 1 \(int\)"),
        (_setting("max_newton_iter", True), "'max_newton_iter' must be an integer of at least 1, got True"),
        (_setting("max_newton_iter", 2.5), "'max_newton_iter' must be an integer"),
        (_setting("rating_levels", 1), "'rating_levels' must be None or an integer of at least 2, got 1"),
        (_setting("rating_eps", 0.7), r"'rating_eps' must be a number in \(0, 0.5\), got 0.7"),
        (_setting("rating_eps", float("nan")), "'rating_eps' must be a number"),
        (_setting("laplace_dtype", "float32"), "'laplace_dtype' must be None or a torch.dtype, got 'float32'"),
        (lambda ck: ck.__setitem__("version", True), "version True is not supported"),
        (_hyper(LS_LOWER, torch.tensor(-5.0, dtype=F64)), f"constraint bound '{LS_LOWER}' is -5.0"),
        (
            _hyper("covar_module.raw_outputscale", torch.tensor(complex(float("nan"), 0.0))),
            "'covar_module.raw_outputscale' must be real, got torch.complex64",
        ),
        (
            _hyper("covar_module.outputscale_prior.rate", torch.tensor(-1.0, dtype=F64)),
            r"prior 'covar_module.outputscale_prior' has rate -1.0, outside GreaterThan\(lower_bound=0.0\)",
        ),
        (_hyper("covar_module.raw_outputscale", torch.tensor(True)), "is torch.bool; the model's is torch.float64"),
        (lambda ck: ck["data"].__setitem__("train_X", torch.rand(6, dtype=F64)), "2-dimensional real floating"),
        (
            lambda ck: ck["data"].__setitem__("comparisons", torch.tensor([[0.0, 1.0]], dtype=F64)),
            "'comparisons' must be a 2-dimensional integer tensor, got torch.float64",
        ),
        (
            lambda ck: ck["data"].__setitem__("ratings", torch.tensor([0.3 + 0j, 0.8])),
            "data 'ratings' must be real, got torch.complex64",
        ),
    ],
)
def test_a_bad_checkpoint_field_is_refused_by_name(change, match):
    with pytest.raises(CheckpointError, match=match):
        torchpref.load_model(_edited(change))


def test_an_unenforced_constraint_holds_its_value_within_its_bounds():
    kernel = ScaleKernel(RBFKernel(ard_num_dims=2, lengthscale_constraint=GreaterThan(1e-4, transform=None)))
    kernel.base_kernel.raw_lengthscale.data.fill_(0.5)  # GPyTorch starts it at 0, outside its bound
    model = _model(covar_module=kernel.to(F64))
    ck = _edited(_hyper("covar_module.base_kernel.raw_lengthscale", torch.full((1, 2), -4.3, dtype=F64)), model)
    fresh = ScaleKernel(RBFKernel(ard_num_dims=2, lengthscale_constraint=GreaterThan(1e-4, transform=None)))
    with pytest.raises(CheckpointError, match=r"'covar_module.base_kernel.raw_lengthscale' is \[\[-4.3, -4.3\]\]"):
        torchpref.load_model(ck, covar_module=fresh.to(F64))
    loaded = torchpref.load_model(model_checkpoint(model), covar_module=copy.deepcopy(fresh))  # the valid one loads
    torch.testing.assert_close(loaded.covar_module.base_kernel.lengthscale, model.covar_module.base_kernel.lengthscale)


def test_an_expanded_train_x_is_refused_before_it_is_copied(tmp_path):
    """An 11 KB file whose stride-0 train_X claims 3,000 items (10^6 would ask for 8 TB)."""
    wide = dict(
        train_X=torch.rand(1, 2, dtype=F64).expand(3000, 2),
        comparisons=torch.tensor([[0, 1]]),
        ratings=None,
        rating_index=None,
    )
    ck = _edited(lambda c: c["data"].update(wide))
    path = tmp_path / "wide.pt"
    torch.save(ck, path)
    assert path.stat().st_size < 20_000
    with pytest.raises(CheckpointError, match=r"'train_X' of shape \(3000, 2\) \(strides \(0, 1\)\) has 6000 elements"):
        torchpref.load_model(path)
    big = _edited(lambda c: c["data"].__setitem__("comparisons", torch.tensor([[0, 1]]).expand(10**6, 2)))
    with pytest.raises(CheckpointError, match="'comparisons' of shape"):
        torchpref.load_model(big)


def test_the_number_of_items_is_bounded():
    ck = model_checkpoint(_model(n=40))
    with pytest.raises(CheckpointError, match="holds 40 items, more than max_items=39"):
        torchpref.load_model(ck, max_items=39)
    assert torchpref.load_model(ck, max_items=None).train_X.shape == (40, 2)
    with pytest.raises(ValueError, match="max_items must be a positive integer or None, got 0"):
        torchpref.load_model(ck, max_items=0)


def test_save_model_writes_through_a_symlink(tmp_path):
    model = _model()
    target = tmp_path / "target.pt"
    torchpref.save_model(_model(n=7), target)
    link = tmp_path / "link.pt"
    link.symlink_to(target)
    torchpref.save_model(model, link)
    assert link.is_symlink() and link.resolve() == target.resolve()
    assert torchpref.load_model(target).train_X.shape == (6, 2)  # the target holds the new model
    dangling = tmp_path / "dangling.pt"
    dangling.symlink_to(tmp_path / "new.pt")
    torchpref.save_model(model, dangling)
    assert dangling.is_symlink() and (tmp_path / "new.pt").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dangling.pt", "link.pt", "new.pt", "target.pt"]


def test_save_model_keeps_the_umask_mode_and_an_existing_files_mode(tmp_path):
    model = _model()
    old = os.umask(0o027)
    try:
        torchpref.save_model(model, tmp_path / "a.pt")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.pt").stat().st_mode) == 0o640
    (tmp_path / "a.pt").chmod(0o604)
    torchpref.save_model(model, tmp_path / "a.pt")
    assert stat.S_IMODE((tmp_path / "a.pt").stat().st_mode) == 0o604


def test_save_model_flushes_the_file_and_then_its_folder(tmp_path, monkeypatch):
    synced = []
    real = os.fsync

    def record(fd):
        synced.append(stat.S_ISDIR(os.fstat(fd).st_mode))
        real(fd)

    monkeypatch.setattr(os, "fsync", record)
    torchpref.save_model(_model(), tmp_path / "m.pt")
    assert synced == [False, True]


def test_a_good_checkpoint_still_loads_to_the_same_posterior(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = _model(rating_levels=None, ties_offered=True, learn_likelihood=True)
    torchpref.save_model(model, tmp_path / "m.pt")
    loaded = torchpref.load_model(tmp_path / "m.pt")
    X = torch.rand(4, 2, dtype=F64, generator=torch.Generator().manual_seed(2))
    assert loaded.ties_offered is True
    torch.testing.assert_close(loaded.posterior(X).mean, model.posterior(X).mean, atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", ["m" * 252 + ".pt", "\u00e9" * 126 + ".pt"])  # 255 bytes: the longest legal name
def test_save_model_onto_the_longest_legal_file_name(tmp_path, name):
    assert len(os.fsencode(name)) == 255
    model = _model()
    torchpref.save_model(model, tmp_path / name)
    torchpref.save_model(model, tmp_path / name)  # and over it
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # no temporary file left
    loaded = torchpref.load_model(tmp_path / name)
    assert torch.equal(loaded.train_inputs[0], model.train_inputs[0])


def test_load_model_refuses_a_compressed_archive_a_fifo_and_a_directory_before_reading(tmp_path, deflated_copy):
    """A checkpoint whose records are compressed (a few kilobytes that expand to gigabytes under
    ``torch.load``), a FIFO (``torch.load`` would wait on it forever), a directory and a file that
    is no archive are each refused by name, without reading them; the file save_model wrote loads."""
    model = _model()
    path = tmp_path / "m.pt"
    torchpref.save_model(model, path)
    deflated_copy(path, tmp_path / "deflated.pt")
    with pytest.raises(CheckpointError, match="deflated.pt is not a file save_model wrote: .* compressed"):
        torchpref.load_model(tmp_path / "deflated.pt")
    os.mkfifo(tmp_path / "fifo.pt")
    with pytest.raises(CheckpointError, match=r"fifo.pt is not a regular file \(a FIFO\)"):
        torchpref.load_model(tmp_path / "fifo.pt")
    with pytest.raises(IsADirectoryError, match="not a torchpref.PreferenceGP checkpoint"):
        torchpref.load_model(tmp_path)
    with pytest.raises(FileNotFoundError, match="save_model writes one"):
        torchpref.load_model(tmp_path / "none.pt")
    (tmp_path / "text.pt").write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match="text.pt is not a torchpref.PreferenceGP checkpoint: not an archive"):
        torchpref.load_model(tmp_path / "text.pt")
    (tmp_path / "cut.pt").write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(CheckpointError, match="cut.pt is a damaged torchpref.PreferenceGP checkpoint"):
        torchpref.load_model(tmp_path / "cut.pt")
    loaded = torchpref.load_model(path)
    assert torch.equal(loaded.train_inputs[0], model.train_inputs[0])
