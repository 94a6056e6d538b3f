"""PreferenceGP inside Ax (``torchpref.integrations.ax``; docs/ax.md).

Skipped, with the reason, where Ax (``pip install 'torchpref[ax]'``) is not installed. Ax's own
test files for its preference path, run with the model swapped, are checked in
``tests/parity/test_upstream_suites.py``.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch


def test_import_torchpref_imports_no_ax():
    code = "import sys, torchpref, torchpref.models; print(sorted(m for m in sys.modules if m.split('.')[0] in ('ax', 'bofire')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


ax = pytest.importorskip(
    "ax", reason="Ax is not installed (pip install 'torchpref[ax]'): the Ax integration is untested here"
)

from ax.adapter.torch import TorchAdapter  # noqa: E402
from ax.core import Arm, GeneratorRun  # noqa: E402
from ax.core.metric import Metric  # noqa: E402
from ax.core.objective import Objective  # noqa: E402
from ax.core.optimization_config import OptimizationConfig  # noqa: E402
from ax.generators.torch.botorch_modular import utils as _ax_utils  # noqa: E402
from ax.generators.torch.botorch_modular.generator import BoTorchGenerator  # noqa: E402
from ax.generators.torch.botorch_modular.surrogate import ModelConfig, SurrogateSpec  # noqa: E402
from ax.utils.testing.preference_stubs import get_pbo_experiment  # noqa: E402
from botorch.models.pairwise_gp import PairwiseGP  # noqa: E402
from botorch.models.transforms.input import Normalize  # noqa: E402

import torchpref.integrations.ax as tax  # noqa: E402

_ORIGINAL_CHOOSE = _ax_utils.choose_model_class
from torchpref import LaplaceMarginalLogLikelihood, PreferenceGP  # noqa: E402

PREF = "pairwise_pref_query"


def _experiment(ratings: dict | None = None):
    """Ax's PBO test experiment (2 parameters in [10, 30], 4 compared pairs); with ``ratings``,
    a tracking metric "rating" and one single-arm trial per rated arm."""
    exp = get_pbo_experiment(
        num_parameters=2,
        num_experimental_metrics=1 if ratings else 0,
        tracking_metric_names=["rating"] if ratings else None,
        num_experimental_trials=0,
        num_preference_trials=4,
        num_preference_trials_w_repeated_arm=0,
        include_sq=False,
    )
    for params, value in (ratings or {}).items():
        trial = exp.new_batch_trial(generator_run=GeneratorRun([Arm(parameters=dict(params))]))
        trial.attach_batch_trial_data(raw_data={trial.arms[0].name: {"rating": (value, 0.0)}})
        trial.mark_running(no_runner_required=True)
        trial.mark_completed()
    return exp


def _adapter(exp, spec, fit_tracking_metrics=False):
    return TorchAdapter(
        experiment=exp,
        generator=BoTorchGenerator(surrogate_spec=spec),
        optimization_config=OptimizationConfig(Objective(metric=Metric(PREF), minimize=False)),
        fit_tracking_metrics=fit_tracking_metrics,
        transforms=[],
    )


def _preference_model(adapter):
    return adapter.generator.surrogate._submodels[(PREF,)]


def _config(**kw):
    return ModelConfig(
        botorch_model_class=PreferenceGP,
        input_transform_classes=[Normalize],
        input_transform_options={"Normalize": {"d": 2}},
        **kw,
    )


def test_metric_to_model_configs_fits_preference_gp():
    exp = _experiment()
    model = _preference_model(_adapter(exp, SurrogateSpec(metric_to_model_configs={PREF: [_config()]})))
    assert isinstance(model, PreferenceGP)
    assert isinstance(model.input_transform, Normalize)
    assert model.comparisons.shape == (4, 2)
    # fitted: the Laplace evidence went up from the default hyperparameters'
    fresh = PreferenceGP(
        model.train_X, model.comparisons, covar_module=tax.pairwise_gp_kernel(2), input_transform=Normalize(2)
    )
    assert float(LaplaceMarginalLogLikelihood(model)()) > float(LaplaceMarginalLogLikelihood(fresh)()) - 1e-9


def test_import_changes_no_ax_type_or_function():
    """import torchpref.integrations.ax alone rebinds nothing in Ax's modules: ModelConfig stays a
    dataclass (isinstance, dataclasses.fields); only Ax's dispatchers learn PreferenceGP."""
    code = (
        "import dataclasses, sys\n"
        "from ax.generators.torch.botorch_modular import surrogate as s, utils as u\n"
        "from ax.utils.preference import preference_utils as p\n"
        "from ax.service.utils import best_point as b\n"
        "mods = (s, u, p, b)\n"
        "before = [dict(vars(m)) for m in mods]\n"
        "fit_before = dict(s.Surrogate.__dict__)\n"
        "import torchpref.integrations.ax\n"
        "changed = [k for m, old in zip(mods, before) for k in set(vars(m)) | set(old) if vars(m).get(k) is not old.get(k)]\n"
        "changed += [k for k in fit_before if s.Surrogate.__dict__.get(k) is not fit_before[k]]\n"
        "cfg = s.ModelConfig()\n"
        "print(changed, isinstance(cfg, s.ModelConfig), len(dataclasses.fields(s.ModelConfig)) > 0)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[] True True"


def test_ax_default_builds_pairwise_gp_without_the_opt_in():
    """Ax sends a preference metric that metric_to_model_configs does not name to ModelConfig(),
    i.e. PairwiseGP, even with a PreferenceGP config in model_configs: without the opt-in that
    is Ax's own behaviour, and the integration does not change it at import."""
    exp = _experiment()
    assert _ax_utils.choose_model_class is _ORIGINAL_CHOOSE
    assert isinstance(_preference_model(_adapter(exp, SurrogateSpec())), PairwiseGP)
    assert isinstance(_preference_model(_adapter(exp, SurrogateSpec(model_configs=[_config()]))), PairwiseGP)


def test_use_preference_gp_and_undo():
    exp = _experiment()
    handle = tax.use_preference_gp()
    try:
        assert handle.active
        model = _preference_model(_adapter(exp, SurrogateSpec()))
        assert isinstance(model, PreferenceGP) and model.comparisons.shape == (4, 2)
        assert isinstance(model.input_transform, Normalize)  # Ax's default input transform, as for PairwiseGP
        assert isinstance(_preference_model(_adapter(exp, SurrogateSpec(model_configs=[_config()]))), PreferenceGP)
        # PairwiseGP named explicitly is still built
        explicit = SurrogateSpec(metric_to_model_configs={PREF: [ModelConfig(botorch_model_class=PairwiseGP)]})
        assert isinstance(_preference_model(_adapter(exp, explicit)), PairwiseGP)
        # the model Ax fitted is fitted: the Laplace evidence went up from the default hyperparameters'
        fresh = PreferenceGP(model.train_X, model.comparisons, covar_module=tax.pairwise_gp_kernel(2))
        assert float(LaplaceMarginalLogLikelihood(model)()) > float(LaplaceMarginalLogLikelihood(fresh)()) - 1e-9
    finally:
        handle.undo()
    assert not handle.active
    handle.undo()  # a second undo is a no-op
    assert _ax_utils.choose_model_class is _ORIGINAL_CHOOSE
    assert isinstance(_preference_model(_adapter(exp, SurrogateSpec())), PairwiseGP)


def test_get_preference_adapter_follows_the_opt_in():
    """Ax's get_preference_adapter (BOPE's utility trace and best point) builds PairwiseGP, and
    PreferenceGP inside the opt-in."""
    from ax.utils.preference.preference_utils import get_preference_adapter

    exp = _experiment()
    data = exp.lookup_data()
    assert isinstance(_preference_model(get_preference_adapter(experiment=exp, data=data)), PairwiseGP)
    with tax.use_preference_gp():
        assert isinstance(_preference_model(get_preference_adapter(experiment=exp, data=data)), PreferenceGP)
    assert isinstance(_preference_model(get_preference_adapter(experiment=exp, data=data)), PairwiseGP)


def test_preference_model_config():
    config = tax.preference_model_config(2, model_options={tax.RATING_METRICS_OPTION: ["rating"]})
    assert isinstance(config, ModelConfig)
    assert config.botorch_model_class is PreferenceGP and config.mll_class is LaplaceMarginalLogLikelihood
    assert config.input_transform_classes == [Normalize] and config.input_transform_options["Normalize"]["d"] == 2
    assert tax.preference_model_config().input_transform_classes is not None  # Ax's default (DEFAULT)
    spec = SurrogateSpec(metric_to_model_configs={PREF: [tax.preference_model_config(2)]})
    model = _preference_model(_adapter(_experiment(), spec))
    assert isinstance(model, PreferenceGP) and isinstance(model.input_transform, Normalize)


def test_context_manager_restores_on_exception_and_nesting():
    with pytest.raises(RuntimeError, match="boom"):
        with tax.use_preference_gp():
            assert _ax_utils.choose_model_class is not _ORIGINAL_CHOOSE
            raise RuntimeError("boom")
    assert _ax_utils.choose_model_class is _ORIGINAL_CHOOSE
    outer = tax.use_preference_gp()
    with tax.use_preference_gp():
        pass
    assert _ax_utils.choose_model_class is not _ORIGINAL_CHOOSE  # the outer opt-in still holds
    outer.undo()
    assert _ax_utils.choose_model_class is _ORIGINAL_CHOOSE


def test_mll_classes():
    from botorch.models.pairwise_gp import PairwiseLaplaceMarginalLogLikelihood
    from gpytorch.mlls import ExactMarginalLogLikelihood, LeaveOneOutPseudoLikelihood

    for given in (None, ExactMarginalLogLikelihood, PairwiseLaplaceMarginalLogLikelihood, LaplaceMarginalLogLikelihood):
        assert tax.laplace_mll_class(given) is LaplaceMarginalLogLikelihood
    with pytest.raises(ValueError, match="LeaveOneOutPseudoLikelihood"):
        tax.laplace_mll_class(LeaveOneOutPseudoLikelihood)
    exp = _experiment()
    model = _preference_model(
        _adapter(
            exp,
            SurrogateSpec(metric_to_model_configs={PREF: [_config(mll_class=PairwiseLaplaceMarginalLogLikelihood)]}),
        )
    )
    assert isinstance(model, PreferenceGP)


def test_rating_metric_reaches_the_model():
    rated = {(("x1", 12.0), ("x2", 12.0)): 0.9, (("x1", 28.0), ("x2", 13.0)): 0.1, (("x1", 20.0), ("x2", 27.0)): 0.6}
    exp = _experiment(rated)
    configs = {PREF: [_config(model_options={tax.RATING_METRICS_OPTION: ["rating"]})]}
    with_ratings = _preference_model(_adapter(exp, SurrogateSpec(metric_to_model_configs=configs), True))
    without = _preference_model(_adapter(exp, SurrogateSpec(metric_to_model_configs={PREF: [_config()]}), True))
    assert isinstance(with_ratings, PreferenceGP) and without.ratings.numel() == 0
    # each rated arm is an item, and its rating is at its row
    got = {
        tuple(with_ratings.train_X[i].tolist()): float(r)
        for r, i in zip(with_ratings.ratings, with_ratings.rating_index, strict=True)
    }
    want = {tuple(v for _, v in k): r for k, r in rated.items()}
    assert got.keys() == want.keys()
    for k in want:
        assert got[k] == pytest.approx(want[k])
    X = torch.tensor(list(want), dtype=with_ratings.train_X.dtype)
    with torch.no_grad():
        m_with = with_ratings.posterior(X).mean.reshape(-1)
        m_without = without.posterior(X).mean.reshape(-1)
    assert not torch.allclose(m_with, m_without, atol=1e-3)
    assert m_with[0] > m_with[1]  # the arm rated 0.9 above the arm rated 0.1


def test_bad_ratings_are_named():
    exp = _experiment({(("x1", 12.0), ("x2", 12.0)): 3.0})
    configs = {PREF: [_config(model_options={tax.RATING_METRICS_OPTION: ["rating"]})]}
    with pytest.raises(ValueError, match="rating"):
        _adapter(exp, SurrogateSpec(metric_to_model_configs=configs), True)
    with pytest.raises(ValueError, match="no data"):
        _adapter(exp, SurrogateSpec(metric_to_model_configs=configs), False)


def test_rating_inputs_reuse_rows():
    from botorch.utils.datasets import SupervisedDataset

    X = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    ds = SupervisedDataset(
        X=torch.tensor([[1.0, 1.0], [0.5, 0.5]], dtype=torch.float64),
        Y=torch.tensor([[0.2], [0.7]], dtype=torch.float64),
        feature_names=["a", "b"],
        outcome_names=["rating"],
    )
    items, ratings, index = tax.rating_inputs(X, [ds])
    assert items.shape == (3, 2) and torch.equal(items[2], ds.X[1])
    assert index.tolist() == [1, 2] and torch.allclose(ratings, torch.tensor([0.2, 0.7], dtype=torch.float64))


def test_kernel_priors_inside_ax():
    """Inside Ax, PreferenceGP gets PairwiseGP's kernel priors by default (docs/decisions.md), on
    the opt-in's default path too, and then fits the hyperparameters PairwiseGP fits (the same
    probit, the same Laplace evidence, the same priors: an independent reference);
    model_options={"kernel_priors": "preference_gp"} keeps torchpref's own; anything else is refused."""
    from gpytorch.priors import GammaPrior, LogNormalPrior, SmoothedBoxPrior

    exp = _experiment()
    spec = SurrogateSpec(metric_to_model_configs={PREF: [tax.preference_model_config(2)]})
    model = _preference_model(_adapter(exp, spec))
    assert isinstance(model.covar_module.base_kernel.lengthscale_prior, GammaPrior)
    assert isinstance(model.covar_module.outputscale_prior, SmoothedBoxPrior)
    pairwise_spec = SurrogateSpec(
        metric_to_model_configs={
            PREF: [
                ModelConfig(
                    botorch_model_class=PairwiseGP,
                    input_transform_classes=[Normalize],
                    input_transform_options={"Normalize": {"d": 2, "bounds": None, "indices": None}},
                )
            ]
        }
    )
    reference = _preference_model(_adapter(exp, pairwise_spec))
    assert isinstance(reference, PairwiseGP)
    assert float(model.covar_module.outputscale) == pytest.approx(float(reference.covar_module.outputscale), rel=1e-3)
    assert torch.allclose(
        model.covar_module.base_kernel.lengthscale, reference.covar_module.base_kernel.lengthscale, rtol=1e-3
    )
    with tax.use_preference_gp():
        model = _preference_model(_adapter(exp, SurrogateSpec()))
        assert isinstance(model.covar_module.outputscale_prior, SmoothedBoxPrior)
    own = tax.preference_model_config(2, model_options={tax.KERNEL_PRIORS_OPTION: "preference_gp"})
    model = _preference_model(_adapter(exp, SurrogateSpec(metric_to_model_configs={PREF: [own]})))
    assert isinstance(model.covar_module.base_kernel.lengthscale_prior, LogNormalPrior)
    assert isinstance(model.covar_module.outputscale_prior, GammaPrior)
    bad = tax.preference_model_config(2, model_options={tax.KERNEL_PRIORS_OPTION: "gamma"})
    with pytest.raises(ValueError, match="kernel_priors.*must be one of.*'gamma'"):
        _adapter(exp, SurrogateSpec(metric_to_model_configs={PREF: [bad]}))
    with pytest.raises(ValueError, match="d must be a positive int"):
        tax.pairwise_gp_kernel(0)


def test_pairwise_gp_kernel_fits_where_the_wall_stopped_it():
    """BOPE seed 2's first preference fit (9 outcome vectors, 9 noiseless comparisons): with
    PairwiseGP's exact kernel (outputscale up to 200) every L-BFGS-B restart stopped "ABNORMAL" on
    the SmoothedBox prior's wall at 100; pairwise_gp_kernel holds the outputscale at most 100 and
    the fit succeeds, at the wall."""
    from botorch.fit import fit_gpytorch_mll

    X = torch.tensor(
        [
            [0.540955675406233, 0.2929559393924536],
            [0.7728255352131905, 0.683471514627593],
            [0.8421514948203525, 0.7738835343882678],
            [0.6637348770923923, 0.6364518911241861],
            [0.8881720348223809, 0.5359749883582827],
            [0.5830898457359502, 0.8431066873268755],
            [0.7879904268583646, 0.8028414777769275],
            [0.841759514362164, 0.7912818399956677],
            [0.7378533846363313, 0.7177974156801414],
        ],
        dtype=torch.float64,
    )
    C = torch.tensor([[1, 0], [2, 0], [3, 4], [2, 3], [2, 3], [2, 5], [2, 1], [6, 2], [7, 8]])
    model = PreferenceGP(X, C, covar_module=tax.pairwise_gp_kernel(2), input_transform=Normalize(2))
    fit_gpytorch_mll(LaplaceMarginalLogLikelihood(model))
    outputscale = float(model.covar_module.outputscale)
    assert 50.0 < outputscale <= 100.0
