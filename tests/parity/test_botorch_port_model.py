"""BoTorch's ``PairwiseGP`` model checks (``test/models/test_pairwise_gp.py``), rewritten and run
against ``PreferenceGP`` and ``PairwiseGP`` alike (tests/parity/botorch_port.py explains the counting)."""

import copy
import warnings

import pytest
import torch
from botorch.acquisition.objective import ScalarizedPosteriorTransform
from botorch.exceptions import OptimizationWarning, UnsupportedError
from botorch.fit import fit_gpytorch_mll
from botorch.models.transforms.input import Normalize
from botorch.posteriors import GPyTorchPosterior
from botorch.sampling.pairwise_samplers import PairwiseSobolQMCNormalSampler
from botorch.utils.containers import SliceContainer
from botorch.utils.datasets import RankingDataset, SupervisedDataset
from botorch_port import _seeded, impl, make_mll, make_model, mini_data, model_class, small_problem  # noqa: F401
from gpytorch.kernels import Kernel, LinearKernel, RBFKernel, ScaleKernel
from linear_operator.utils.errors import NotPSDError

BATCHES = [(), (2,)]
DTYPES = [torch.float64, torch.float32]


def _quiet_fit(mll, maxiter=2):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OptimizationWarning)
        fit_gpytorch_mll(mll, optimizer_kwargs={"options": {"maxiter": maxiter}}, max_attempts=1)


# --------------------------------------------------------------------------- construct_inputs
def _ranking_dataset(values, indices, ranks):
    X = SliceContainer(values=values, indices=indices, event_shape=torch.Size([indices.shape[-1] * values.shape[-1]]))
    return RankingDataset(
        X=X, Y=ranks, feature_names=[f"x{i}" for i in range(values.shape[-1])], outcome_names=["rank"]
    )


def test_construct_inputs_from_ranking_dataset(impl):
    values = torch.rand(3, 2, dtype=torch.float64)
    ds = _ranking_dataset(values, torch.tensor([[0, 1], [1, 2]]), torch.tensor([[0, 1], [1, 0]]))
    inputs = model_class(impl).construct_inputs(ds)
    model = model_class(impl)(**inputs)
    assert torch.equal(model.datapoints, values)
    assert torch.equal(model.comparisons, torch.tensor([[0, 1], [2, 1]]))


def test_construct_inputs_refuses_other_datasets(impl):
    ds = SupervisedDataset(X=torch.rand(3, 2), Y=torch.rand(3, 1), feature_names=["a", "b"], outcome_names=["y"])
    with pytest.raises(UnsupportedError, match="RankingDataset"):
        model_class(impl).construct_inputs(ds)


def test_ranking_with_three_items(impl):
    values = torch.rand(4, 2, dtype=torch.float64)
    ds = _ranking_dataset(values, torch.tensor([[0, 1, 3]]), torch.tensor([[2, 0, 1]]))  # 1 > 3 > 0
    model = model_class(impl)(**model_class(impl).construct_inputs(ds))
    assert sorted(map(tuple, model.comparisons.tolist())) == [(1, 3), (3, 0)]


# --------------------------------------------------------------------------- fitting and init
@pytest.mark.parametrize("dtype", DTYPES)
def test_fit_two_iterations(impl, dtype):
    X, C = mini_data(dtype=dtype)
    model = make_model(impl, X, C)
    _quiet_fit(make_mll(impl, model))
    assert torch.isfinite(model.posterior(X).mean).all()


def test_batched_training_data_fit(impl):
    X, C = mini_data((2,))
    model = make_model(impl, X, C)
    _quiet_fit(make_mll(impl, model))
    assert model.batch_shape == torch.Size([2])


def test_num_outputs_and_batch_shape(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    assert model.num_outputs == 1 and model.batch_shape == torch.Size([])


def test_pairwise_gp_attributes(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    assert torch.equal(model.datapoints, X) and torch.equal(model.comparisons, C)
    assert model.dim == X.shape[-1] and model.utility.shape == (X.shape[0],)


def test_utility_orders_compared_items(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    u = model.utility
    assert bool(u[C[0, 0]] > u[C[0, 1]])


def test_scale_linear_kernel(impl):
    X, C = small_problem()
    model = make_model(impl, X, C, covar_module=ScaleKernel(LinearKernel()).to(X))
    assert isinstance(model.covar_module.base_kernel, LinearKernel)
    post = model.posterior(torch.rand(5, 3, dtype=torch.float64))
    assert torch.isfinite(post.mean).all() and (post.variance > 0).all()


@pytest.mark.parametrize("name", ["linear", "rbf+linear"])
def test_non_scale_kernels(impl, name):
    X, C = small_problem()
    k = LinearKernel() if name == "linear" else RBFKernel() + LinearKernel()
    model = make_model(impl, X, C, covar_module=k.to(X))
    assert torch.isfinite(model.posterior(X).mean).all()


# --------------------------------------------------------------------------- prior-only models
def test_prior_model_posterior(impl):
    X, _ = mini_data()
    prior = model_class(impl)(None, None).to(dtype=torch.float64)
    prior.eval()
    post = prior.posterior(X)
    assert isinstance(post, GPyTorchPosterior) and post.mean.shape == (2, 1)
    torch.testing.assert_close(post.mean, torch.zeros(2, 1, dtype=torch.float64))


@pytest.mark.parametrize("batch", BATCHES)
def test_condition_prior_model(impl, batch):
    X, C = mini_data(batch)
    prior = model_class(impl)(None, None).to(dtype=torch.float64)
    cond = prior.condition_on_observations(X, C)
    assert torch.equal(cond.datapoints, X) and torch.equal(cond.comparisons, C)
    assert cond.batch_shape == torch.Size(batch)
    assert cond.posterior(torch.rand(4, 2, dtype=torch.float64)).mean.shape == (*batch, 4, 1)


def test_prior_model_with_ratings_keyword(impl):
    X, _ = mini_data()
    prior = model_class(impl)(None, None).to(dtype=torch.float64)
    cond = prior.condition_on_observations(X, ratings=torch.tensor([0.8, 0.3], dtype=torch.float64))
    assert bool(cond.utility[0] > cond.utility[1])


# --------------------------------------------------------------------------- posterior
@pytest.mark.parametrize("dtype", DTYPES)
def test_posterior_shapes(impl, dtype):
    X, C = mini_data(dtype=dtype)
    model = make_model(impl, X, C)
    for shape in [(3, 2), (4, 3, 2), (2, 4, 3, 2)]:
        post = model.posterior(torch.rand(*shape, dtype=dtype))
        assert isinstance(post, GPyTorchPosterior)
        assert post.mean.shape == shape[:-1] + (1,) and post.variance.shape == shape[:-1] + (1,)
        assert post.mean.dtype == dtype


def test_batched_training_data_posterior_shapes(impl):
    X, C = mini_data((2,))
    model = make_model(impl, X, C)
    assert model.posterior(torch.rand(2, 3, 2, dtype=torch.float64)).mean.shape == (2, 3, 1)
    assert model.posterior(torch.rand(5, 2, 3, 2, dtype=torch.float64)).mean.shape == (5, 2, 3, 1)


def test_posterior_transform(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    Xt = torch.rand(3, 2, dtype=torch.float64)
    tf = ScalarizedPosteriorTransform(weights=torch.ones(1, dtype=torch.float64))
    torch.testing.assert_close(model.posterior(Xt, posterior_transform=tf).mean, model.posterior(Xt).mean)


def test_output_indices_zero(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    Xt = torch.rand(3, 2, dtype=torch.float64)
    torch.testing.assert_close(model.posterior(Xt, output_indices=[0]).mean, model.posterior(Xt).mean)


def test_subset_output_single(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    Xt = torch.rand(3, 2, dtype=torch.float64)
    torch.testing.assert_close(model.subset_output([0]).posterior(Xt).mean, model.posterior(Xt).mean)


def test_observation_noise_accepted(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    Xt = torch.rand(3, 2, dtype=torch.float64)
    noisy, plain = model.posterior(Xt, observation_noise=True), model.posterior(Xt)
    assert noisy.mean.shape == plain.mean.shape and (noisy.variance >= plain.variance - 1e-12).all()


def test_observation_noise_adds_variance(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    Xt = torch.rand(3, 2, dtype=torch.float64)
    assert (model.posterior(Xt, observation_noise=True).variance > model.posterior(Xt).variance).all()


def test_input_transform_keeps_raw_datapoints(impl):
    X, C = mini_data()
    tf = Normalize(d=2, bounds=torch.tensor([[0.0, 0.0], [0.5, 1.5]], dtype=torch.float64))
    model = make_model(impl, X, C, input_transform=tf)
    assert torch.equal(model.datapoints, X)


# --------------------------------------------------------------------------- set_train_data
def test_set_train_data_strict_refuses_new_shapes(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    with pytest.raises(RuntimeError):
        model.set_train_data(X.unsqueeze(0), C.unsqueeze(0), strict=True)
    with pytest.raises(RuntimeError):
        model.set_train_data(X, C.unsqueeze(0), strict=True)


def test_set_train_data_strict_same_shapes(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    before = model.posterior(X).mean.detach().clone()
    model.set_train_data(X, C.flip(-1), strict=True)
    assert not torch.allclose(model.posterior(X).mean, before)


# --------------------------------------------------------------------------- duplicates
def test_duplicate_items(impl):
    X, C = mini_data()
    n = X.shape[0]
    Xd = torch.cat([X, X])  # every item twice, a comparison among the copies
    Cd = torch.cat([C, torch.tensor([[n, n + 1]])])
    model = make_model(impl, Xd, Cd)
    mean = model.posterior(Xd).mean.squeeze(-1)
    torch.testing.assert_close(mean[:n], mean[n:], atol=1e-6, rtol=0)
    mll = make_mll(impl, model)
    model.train()
    value = mll(model(Xd), Cd) if impl == "PairwiseGP" else mll()
    assert torch.isfinite(value).all()


# --------------------------------------------------------------------------- conditioning
def test_condition_on_comparisons(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    Xn = torch.rand(2, 3, dtype=torch.float64)
    cond = model.condition_on_observations(Xn, torch.tensor([[1, 0]]))
    assert cond is not model and model.datapoints.shape[0] == X.shape[0]
    assert cond.datapoints.shape[0] == X.shape[0] + 2
    u = cond.posterior(Xn).mean.squeeze(-1)
    u0 = model.posterior(Xn).mean.squeeze(-1)
    assert bool(u[1] - u[0] > u0[1] - u0[0])  # item 1 was preferred: their gap grows


def test_condition_non_comparison_Y_refused(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    Xf, Cf = mini_data()
    with pytest.raises((ValueError, RuntimeError)):
        model.condition_on_observations(Xf, Cf[..., 0])


def test_condition_float_Y_refused(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    with pytest.raises((ValueError, RuntimeError)):
        model.condition_on_observations(X, torch.tensor([[0.0, 1.0]], dtype=torch.float64))


def test_condition_on_fantasy_batch(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    Xf, Cf = mini_data((2,))
    cm = model.condition_on_observations(Xf, Cf)
    for shape in [(4, 2), (2, 4, 2)]:
        assert cm.posterior(torch.rand(*shape, dtype=torch.float64)).mean.shape == (2, 4, 1)


def test_condition_same_inputs_broadcast_over_fantasies(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    Xf, Cf = mini_data((2,))
    cm = model.condition_on_observations(Xf[0], Cf)
    assert cm.posterior(torch.rand(4, 2, dtype=torch.float64)).mean.shape == (2, 4, 1)


def test_batched_fantasy_equals_unbatched(impl):
    X, C = mini_data((2,))
    model = make_model(impl, X, C)
    Xf, Cf = mini_data((3, 2))
    batched = model.condition_on_observations(Xf[0], Cf)
    single = make_model(impl, X[0], C[0]).condition_on_observations(Xf[0][0], Cf[:, 0])
    Xt = torch.rand(4, 2, dtype=torch.float64)
    torch.testing.assert_close(batched.posterior(Xt).mean[:, 0], single.posterior(Xt).mean, atol=1e-3, rtol=0)


def test_fantasize_returns_same_class(impl):
    X, C = mini_data()
    model = make_model(impl, X, C)
    fm = model.fantasize(torch.rand(4, 2, dtype=torch.float64), PairwiseSobolQMCNormalSampler(torch.Size([3])))
    assert isinstance(fm, model_class(impl))
    assert fm.posterior(torch.rand(5, 2, dtype=torch.float64)).mean.shape == (3, 5, 1)


# --------------------------------------------------------------------------- state and copies
def test_state_dict_round_trip(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    _quiet_fit(make_mll(impl, model), maxiter=5)
    other = make_model(impl, X, C)
    other.load_state_dict(model.state_dict())
    # the modes are solved to a Newton decrement of 1e-11 from different warm starts
    torch.testing.assert_close(other.posterior(X).mean, model.posterior(X).mean, rtol=1e-5, atol=1e-6)


def test_load_state_dict_strict(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    make_model(impl, X, C).load_state_dict(model.state_dict(), strict=True)


def test_hyperparameter_change_in_eval_mode(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    before = model.posterior(X).variance.detach().clone()
    model.covar_module.outputscale = 2.5
    after = model.posterior(X).variance
    assert torch.isfinite(after).all() and not torch.allclose(after, before)


def test_deepcopy_independent(impl):
    X, C = small_problem()
    model = make_model(impl, X, C)
    twin = copy.deepcopy(model)
    twin.covar_module.outputscale = 5.0
    assert not torch.allclose(twin.posterior(X).variance, model.posterior(X).variance)


def test_to_float32(impl):
    X, C = small_problem()
    model = make_model(impl, X, C).to(torch.float32)
    assert model.posterior(X.float()).mean.dtype == torch.float32


# --------------------------------------------------------------------------- numerical errors
class _IndefiniteKernel(Kernel):
    """``k(x, x') = 1 - 3 |x_0 - x'_0|``: not positive definite."""

    def forward(self, x1, x2, diag=False, **params):
        K = 1 - 3 * (x1[..., :, None, 0] - x2[..., None, :, 0]).abs()
        return K.diagonal(dim1=-2, dim2=-1) if diag else K


def test_indefinite_kernel_raises_linear_operator_error(impl):
    X = torch.tensor([[0.0], [0.5], [1.0]], dtype=torch.float64)
    C = torch.tensor([[0, 1], [1, 2]])
    with pytest.raises(NotPSDError):
        make_model(impl, X, C, covar_module=ScaleKernel(_IndefiniteKernel())).posterior(X)
