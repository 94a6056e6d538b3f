"""PreferenceGP's likelihood settings as one object (LikelihoodSettings), the keywords kept."""

import pytest
import torch

import torchpref
from torchpref.models.defaults import LikelihoodSettings


def _data(g):
    X = torch.rand(6, 2, generator=g, dtype=torch.float64)
    return X, torch.tensor([[0, 1], [2, 3], [4, 5]]), torch.tensor([0.3, 0.8], dtype=torch.float64)


def test_settings_object_and_keywords_build_the_same_model(generator):
    X, C, r = _data(generator)
    kw = dict(comparison_noise=0.1, rating_scale=0.8, rating_precision=60.0, learn_likelihood=True)
    a = torchpref.PreferenceGP(X, C, r, torch.tensor([0, 2]), **kw)
    b = torchpref.PreferenceGP(X, C, r, torch.tensor([0, 2]), likelihood=LikelihoodSettings(**kw))
    assert a.likelihood.state_dict().keys() == b.likelihood.state_dict().keys()
    for (k, va), vb in zip(a.likelihood.state_dict().items(), b.likelihood.state_dict().values(), strict=True):
        assert torch.equal(va, vb), k
    assert b.likelihood.comparison.raw_comparison_noise.requires_grad  # learn_likelihood reached it
    torch.testing.assert_close(a.posterior(X).mean, b.posterior(X).mean, rtol=0, atol=0)


def test_keywords_override_the_settings_object(generator):
    X, C, _ = _data(generator)
    m = torchpref.PreferenceGP(X, C, likelihood=LikelihoodSettings(comparison_noise=0.2), comparison_noise=0.3)
    assert float(m.likelihood.comparison.comparison_noise) == pytest.approx(0.3)


def test_an_unknown_keyword_is_named(generator):
    X, C, _ = _data(generator)
    with pytest.raises(TypeError, match="comparison_nois.*LikelihoodSettings"):
        torchpref.PreferenceGP(X, C, comparison_nois=0.1)


@pytest.mark.parametrize(
    "bad", [dict(comparison_noise=-1.0), dict(rating_precision=float("nan")), dict(learn_likelihood="yes")]
)
def test_bad_settings_are_refused_by_name(bad):
    (name,) = bad
    with pytest.raises(ValueError, match=name):
        LikelihoodSettings(**bad)


def test_the_settings_names_are_the_constructors_keywords():
    assert set(LikelihoodSettings.names()) == {
        "comparison_noise", "rating_scale", "rating_precision", "learn_likelihood", "tie_threshold",
        "cut_points", "level_noise",
    }  # fmt: skip
    assert torchpref.LikelihoodSettings is LikelihoodSettings
