"""Hundreds of small random problems, extreme hyperparameters included: the mode converges and
nothing is NaN (mode, posterior mean / variance, evidence and its gradient). Damaged, truncated
and foreign checkpoint files: a named error, nothing half-loaded."""

import warnings

import pytest
import torch
from gpytorch.kernels import RBFKernel, ScaleKernel

from torchpref.models.preference_gp import PreferenceGP
from torchpref.testing.problems import random_config

F64 = torch.float64


def check(seed):
    cfg, X, C, u, ri = random_config(seed)
    k = ScaleKernel(RBFKernel(ard_num_dims=cfg["d"])).to(F64)
    k.base_kernel.lengthscale = cfg["lengthscale"]
    k.outputscale = cfg["outputscale"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # jitter / boundary warnings are expected here
        model = PreferenceGP(
            X,
            C if len(C) else None,
            u if len(u) else None,
            ri if len(u) else None,
            covar_module=k,
            comparison_noise=cfg["comparison_noise"],
            rating_scale=cfg["rating_scale"],
            rating_precision=cfg["rating_precision"],
            learn_likelihood=True,
        )
        mode = model.mode
        problems = []
        if not mode.converged:
            problems.append(f"not converged after {mode.iterations} iterations")
        if not torch.isfinite(mode.f).all():
            problems.append("non-finite mode")
        Xs = torch.rand(4, cfg["d"], generator=torch.Generator().manual_seed(seed + 1), dtype=F64)
        post = model.posterior(torch.cat([Xs, X[:2]]))
        if not (torch.isfinite(post.mean).all() and torch.isfinite(post.variance).all()):
            problems.append("non-finite posterior")
        if (post.variance < -1e-9 * cfg["outputscale"]).any():
            problems.append(f"negative variance {float(post.variance.min()):.3g}")
        ev = model.log_marginal_likelihood()
        params = [p for p in model.parameters() if p.requires_grad]
        grads = torch.autograd.grad(ev, params, allow_unused=True)
        if not torch.isfinite(ev):
            problems.append("non-finite evidence")
        if not all(g is None or torch.isfinite(g).all() for g in grads):
            problems.append("non-finite evidence gradient")
    return cfg, problems


CHUNKS = 6
PER_CHUNK = 50


@pytest.mark.parametrize("chunk", range(CHUNKS))
def test_random_problems(chunk):
    failures = []
    for seed in range(chunk * PER_CHUNK, (chunk + 1) * PER_CHUNK):
        try:
            cfg, problems = check(seed)
        except Exception as e:
            cfg, problems = random_config(seed)[0], [f"{type(e).__name__}: {e}"]
        if problems:
            failures.append(f"{cfg}: {'; '.join(problems)}")
    assert not failures, f"{len(failures)} of {PER_CHUNK} configurations failed:\n" + "\n".join(failures)


# ------------------------------------------------------------------ damaged and foreign checkpoints
def _saved(tmp_path):
    import torchpref

    g = torch.Generator().manual_seed(0)
    model = PreferenceGP(
        torch.rand(5, 2, generator=g, dtype=F64),
        torch.tensor([[0, 1], [2, 3]]),
        torch.tensor([0.3, 0.8], dtype=F64),
        torch.tensor([1, 4]),
    )
    path = tmp_path / "model.pt"
    torchpref.save_model(model, path)
    return model, path


class _Code:
    def __reduce__(self):
        return (print, ("this must never run",))


def _foreign_files(raw: bytes) -> dict:
    import io

    code = io.BytesIO()
    torch.save({"format": "torchpref.PreferenceGP", "x": _Code()}, code)
    return {
        "truncated to half": raw[: len(raw) // 2],
        "truncated to 10 bytes": raw[:10],
        "empty": b"",
        "json": b'{"a": 1}',
        "a session file": b'{"type":"header","version":1}\n',
        "random bytes": bytes(range(256)) * 8,
        "a pickle holding code": code.getvalue(),
    }


def test_damaged_or_foreign_checkpoint_files_are_named(tmp_path, capfd):
    import torchpref

    _, path = _saved(tmp_path)
    for data in _foreign_files(path.read_bytes()).values():
        bad = tmp_path / "bad.pt"
        bad.write_bytes(data)
        with pytest.raises(torchpref.CheckpointError, match="bad.pt"):
            torchpref.load_model(bad)
    assert "must never run" not in capfd.readouterr().out


def _edited(ck, change):
    import copy

    ck = copy.deepcopy(ck)
    change(ck)
    return ck


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda c: c.pop("data"), "'data' is missing"),
        (lambda c: c.__setitem__("settings", [1]), "'settings' is missing or not a dictionary"),
        (lambda c: c["settings"].__setitem__("evil", 1), r"unknown settings entries \['evil'\]"),
        (lambda c: c["data"].__setitem__("evil", 1), r"unknown data entries \['evil'\]"),
        (lambda c: c["data"].__setitem__("train_X", "abc"), "no train_X tensor"),
        (lambda c: c["data"].__setitem__("ratings", [0.5]), "data 'ratings' must be a tensor"),
        (
            lambda c: c["state_dict"].__setitem__(
                "covar_module.raw_outputscale", torch.tensor(float("nan"), dtype=F64)
            ),
            "'covar_module.raw_outputscale' is not finite",
        ),
        (lambda c: c["state_dict"].__setitem__("covar_module.raw_outputscale", "x"), "must be a tensor, got str"),
        (
            lambda c: c["state_dict"].__setitem__(
                "covar_module.base_kernel.raw_lengthscale", torch.zeros(1, 5, dtype=F64)
            ),
            "do not fit .*size mismatch",
        ),
        (lambda c: c["data"].__setitem__("comparisons", torch.tensor([[0, 9]])), "comparisons out of range"),
    ],
)
def test_checkpoint_contents_are_checked_by_name(tmp_path, change, match):
    import torchpref

    model, path = _saved(tmp_path)
    ck = torch.load(path, weights_only=True)
    with pytest.raises(ValueError, match=match):
        torchpref.load_model(_edited(ck, change))
    loaded = torchpref.load_model(ck)  # the checkpoint itself was not touched
    torch.testing.assert_close(loaded.posterior(model.train_X).mean, model.posterior(model.train_X).mean)


def test_save_model_names_a_folder_or_a_missing_folder(tmp_path):
    import torchpref

    model, path = _saved(tmp_path)
    with pytest.raises(ValueError, match="is a directory"):
        torchpref.save_model(model, tmp_path)
    with pytest.raises(FileNotFoundError, match="the folder .*nowhere does not exist"):
        torchpref.save_model(model, tmp_path / "nowhere" / "model.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.pt"]


# ------------------------------------------------------------------ hostile inputs to the model
def _model():
    g = torch.Generator().manual_seed(1)
    return PreferenceGP(
        torch.rand(5, 2, generator=g, dtype=F64),
        torch.tensor([[0, 1], [2, 3]]),
        torch.tensor([0.3, 0.8], dtype=F64),
        torch.tensor([1, 4]),
    )


@pytest.mark.parametrize(
    "noise, match",
    [
        (torch.ones(3, dtype=F64), r"shape \(5, 1\)"),
        (-torch.ones(5, 1, dtype=F64), "finite variances >= 0, got \\[-1.0"),
        (torch.full((5, 1), float("nan"), dtype=F64), "finite variances >= 0, got \\[nan"),
    ],
)
def test_observation_noise_of_the_wrong_shape_or_sign_is_named(noise, match):
    model = _model()
    with pytest.raises(ValueError, match=match):
        model.posterior(model.train_X, observation_noise=noise)


def test_items_too_large_for_the_kernel_are_named_not_nan():
    from botorch.sampling.pairwise_samplers import PairwiseSobolQMCNormalSampler

    model = _model()
    huge = model.train_X[:2] * 1e300  # finite, but (x / lengthscale)^2 is inf and inf - inf NaN
    with pytest.raises(ValueError, match="too large for the kernel"):
        model.posterior(huge)
    with pytest.raises(ValueError, match="too large for the kernel"):
        model.fantasize(huge, PairwiseSobolQMCNormalSampler(torch.Size([2])))
    assert torch.isfinite(model.posterior(model.train_X * 1e100).mean).all()  # large but representable
    ints = torch.tensor([[0, 1], [1, 0]])  # integer items are numbers too (the check broke them once)
    torch.testing.assert_close(model.posterior(ints).mean, model.posterior(ints.to(F64)).mean)


def test_conditioning_on_batches_that_do_not_broadcast_is_named():
    model = _model()
    before = model.posterior(model.train_X).mean.detach().clone()
    X = torch.rand(3, 2, 2, dtype=F64)
    with pytest.raises(ValueError, match=r"do not broadcast: X \(3,\), the model \(\), comparisons \(4,\)"):
        model.condition_on_observations(X, torch.tensor([[0, 1]]).expand(4, 1, 2))
    with pytest.raises(ValueError, match="do not broadcast"):
        PreferenceGP(None, None).condition_on_observations(X, torch.tensor([[0, 1]]).expand(4, 1, 2))
    assert torch.equal(model.posterior(model.train_X).mean.detach(), before)


def test_evidence_called_with_other_comparisons_is_named_not_ignored():
    from torchpref import LaplaceMarginalLogLikelihood, TrainDataMismatchError

    model = _model()
    mll = LaplaceMarginalLogLikelihood(model)
    torch.testing.assert_close(mll(model(model.train_X), model.comparisons.clone()), mll())  # PairwiseGP's call
    for other in (torch.tensor([[1, 0], [2, 3]]), torch.tensor([[0, 1]])):
        with pytest.raises(TrainDataMismatchError, match="other comparisons"):
            mll(model(model.train_X), other)


def test_condition_on_observations_takes_lists_as_the_rest_of_the_api_does():
    model = _model()
    X = model.train_X[:2] + 0.01
    by_tensor = model.condition_on_observations(X, torch.tensor([[0, 1]]))
    for cond in (
        model.condition_on_observations(X.tolist(), torch.tensor([[0, 1]])),
        model.condition_on_observations(X, comparisons=[[0, 1]]),
    ):  # an AttributeError before
        torch.testing.assert_close(cond.posterior(X).mean, by_tensor.posterior(X).mean)
    prior = PreferenceGP(None, None).condition_on_observations(X, comparisons=[[0, 1]])
    assert prior.comparisons.tolist() == [[0, 1]]


def test_a_saved_prior_only_model_loads(tmp_path):
    from gpytorch.kernels import RBFKernel, ScaleKernel

    import torchpref

    prior = PreferenceGP(None, None)
    prior.covar_module.outputscale = 2.5
    torchpref.save_model(prior, tmp_path / "prior.pt")  # it saved, and then would not load
    loaded = torchpref.load_model(tmp_path / "prior.pt")
    X = torch.rand(3, 2, dtype=F64)
    torch.testing.assert_close(loaded.posterior(X).variance, prior.posterior(X).variance)
    assert float(loaded.posterior(X).variance.detach().max()) == pytest.approx(2.5)
    fitted = loaded.condition_on_observations(X, torch.tensor([[0, 1]]))
    assert fitted.train_X.shape == (3, 2)
    assert isinstance(loaded.covar_module, ScaleKernel) and isinstance(loaded.covar_module.base_kernel, RBFKernel)


@pytest.mark.parametrize("sampler", [None, "sobol"])
def test_fantasize_without_a_sampler_is_named(sampler):
    model = _model()
    with pytest.raises(TypeError, match="sampler must be a BoTorch MCSampler"):
        model.fantasize(model.train_X[:2], sampler)  # "'NoneType' object is not callable" before


@pytest.mark.parametrize("model", [PreferenceGP(None, None), PreferenceGP(torch.zeros(0, 2, dtype=F64))])
def test_fitting_a_model_without_items_is_named(model):
    from botorch.fit import fit_gpytorch_mll

    from torchpref import LaplaceMarginalLogLikelihood

    with pytest.raises(ValueError, match="no items"):  # a RuntimeError from a reshape before
        fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))


@pytest.mark.parametrize("gamma", [-1.0, float("nan"), float("inf")])
def test_latent_ucb_refuses_a_gamma_it_would_silently_change(gamma):
    import torchpref

    with pytest.raises(ValueError, match="gamma must be a finite number >= 0"):
        torchpref.latent_ucb(_model(), gamma=gamma)  # -1 became beta = 1 (an upper bound), NaN gave NaN


def test_editing_the_callers_tensors_in_place_does_not_edit_the_model():
    g = torch.Generator().manual_seed(0)
    X, C = torch.rand(6, 2, generator=g, dtype=F64), torch.tensor([[0, 1], [2, 3], [4, 5]])
    r, ri = torch.tensor([0.3, 0.9], dtype=F64), torch.tensor([1, 2])
    model = PreferenceGP(X, C, r, ri)
    Xt = torch.rand(3, 2, generator=g, dtype=F64)
    before = model.posterior(Xt).mean.detach().clone()
    X[0] += 0.3  # the posterior was neither the old model's nor the edited data's (off by 0.013)
    C[0] = torch.tensor([1, 0])
    r[0], ri[0] = 0.8, 4
    torch.testing.assert_close(model.posterior(Xt).mean.detach(), before, rtol=0, atol=0)
    assert model.train_X[0].tolist() != X[0].tolist() and model.comparisons[0].tolist() == [0, 1]
