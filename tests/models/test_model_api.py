"""Small API promises: ``PreferenceGP.best_item``, ranking sizes checked at construction, ``py.typed``."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from botorch.models.transforms.input import Normalize

import torchpref
from torchpref import UCBC, InformationPerEffort, PreferenceGP, RandomMixed, RandomRankings


def _model(generator, input_transform=None, scale=1.0):
    X = scale * torch.rand(15, 2, generator=generator, dtype=torch.float64)
    u = torch.sin(5 * X[:, 0] / scale) + X[:, 1] / scale
    pairs = torch.randint(0, 15, (30, 2), generator=generator)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    better = torch.where((u[pairs[:, 0]] > u[pairs[:, 1]]).unsqueeze(-1), pairs, pairs.flip(-1))
    return PreferenceGP(X, comparisons=better, input_transform=input_transform)


@pytest.mark.parametrize("transformed", [False, True])
def test_best_item_is_the_argmax_of_the_posterior_mean(generator, transformed):
    tf = Normalize(d=2, bounds=torch.tensor([[0.0, 0.0], [100.0, 100.0]], dtype=torch.float64)) if transformed else None
    model = _model(generator, tf, scale=100.0 if transformed else 1.0)
    with torch.no_grad():
        mean = model.posterior(model.train_X.unsqueeze(-2)).mean.reshape(-1)
    row, item = model.best_item()
    assert row == int(mean.argmax()) and torch.equal(item, model.train_X[row])
    # among other candidates, in the caller's coordinates
    C = torch.rand(40, 2, generator=generator, dtype=torch.float64) * (100.0 if transformed else 1.0)
    with torch.no_grad():
        mc = model.posterior(C.unsqueeze(-2)).mean.reshape(-1)
    row, item = model.best_item(C)
    assert row == int(mc.argmax()) and torch.equal(item, C[row])


def test_best_item_rejects_bad_candidates(generator):
    model = _model(generator)
    with pytest.raises(ValueError, match="n x 2"):
        model.best_item(torch.rand(4, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="n x 2"):
        model.best_item(torch.empty(0, 2, dtype=torch.float64))


@pytest.mark.parametrize(
    "make",
    [
        lambda m: UCBC(m=m),
        lambda m: RandomRankings(m=m),
        lambda m: RandomMixed(m=m),
        lambda m: InformationPerEffort(m=m),
    ],
)
@pytest.mark.parametrize("m", [1, 0, 2.5, True])
def test_ranking_size_checked_at_construction(make, m):
    with pytest.raises(ValueError, match=f"m={m!r}"):
        make(m)


def test_ranking_size_two_is_fine():
    assert UCBC(m=2).m == 2 and RandomRankings(m=2.0).m == 2


def test_package_ships_py_typed():
    assert (Path(torchpref.__file__).parent / "py.typed").is_file()
    pyproject = (Path(__file__).resolve().parents[2] / "pyproject.toml").read_text()
    assert 'torchpref = ["py.typed"]' in pyproject


def test_a_model_first_built_in_inference_mode_leaves_later_models_loadable():
    """The likelihoods' shared default constraints are made on first use: made inside
    ``torch.inference_mode`` (a simulation's block), they were inference tensors, and every later
    ``load_model`` failed ("Inplace update to inference tensor"). A fresh process, so that this
    test makes them first."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(
        """
        import pathlib, tempfile, torch, torchpref
        def model():
            X = torch.rand(4, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
            c, u, i = torch.tensor([[0, 1]]), torch.tensor([0.5]), torch.tensor([2])
            return torchpref.PreferenceGP(X, comparisons=c, ratings=u, rating_index=i)
        with torch.inference_mode():
            model()
        path = pathlib.Path(tempfile.mkdtemp()) / "m.pt"
        torchpref.save_model(model(), path)
        torchpref.load_model(path)
        """
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
