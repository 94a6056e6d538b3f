"""One person-model recipe (ModelSettings): a session's default model and a population's person
model agree on every likelihood setting, a population file records the recipe, and an older
population file (which recorded only the likelihood's three numbers) is read with the settings it
was fitted with."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torchpref.data.preference_data import PreferenceData
from torchpref.models.recipe import DEFAULT_MODEL, ModelSettings
from torchpref.population.fit import fit_population
from torchpref.population.io import load_population, save_population
from torchpref.sessions.recorded import describe_model
from torchpref.sessions.settings import default_session_model


def _people() -> list[PreferenceData]:
    g = torch.Generator().manual_seed(1)
    C = torch.tensor([[0, 1], [2, 3], [4, 5], [1, 4]])
    return [
        PreferenceData.create(torch.rand(6, 2, generator=g, dtype=torch.float64), C, ties=torch.tensor([[3, 5]]))
        for _ in range(3)
    ]


def _likelihood_state(model) -> dict:
    return {k: v for k, v in describe_model(model)["state"].items() if k.startswith("likelihood.")}


def test_a_session_and_a_population_person_agree_on_every_likelihood_setting(tmp_path):
    pop = fit_population(_people(), max_iter=2)
    x = torch.rand(1, 2, dtype=torch.float64)
    session, person = default_session_model(x), pop.person_model(x)
    assert person.ties_offered is True and session.ties_offered is True
    assert describe_model(session)["settings"] == describe_model(person)["settings"]
    assert _likelihood_state(session) == _likelihood_state(person)
    assert describe_model(session)["likelihood"] == describe_model(person)["likelihood"]
    assert pop.model_settings == DEFAULT_MODEL
    save_population(pop, tmp_path / "p.pt")
    again = load_population(tmp_path / "p.pt")
    assert again.model_settings == pop.model_settings
    assert _likelihood_state(again.person_model(x)) == _likelihood_state(session)


def test_the_recipe_is_the_one_place_of_the_defaults():
    other = DEFAULT_MODEL.with_(rating_precision=20.0, comparison_noise=0.5)
    pop = fit_population(_people(), model=other, max_iter=1)
    lik = pop.person_model(torch.rand(1, 2, dtype=torch.float64)).likelihood
    assert float(lik.rating.rating_precision) == pytest.approx(20.0)
    assert float(lik.comparison.comparison_noise) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="rating_precision must be a finite positive number, got -1"):
        ModelSettings(rating_precision=-1)
    with pytest.raises(ValueError, match="unknown model setting"):
        ModelSettings.from_json({"lapse": 0.1})


def test_an_older_population_file_is_read_with_what_it_was_fitted_with():
    old = {"comparison_noise": 1.0, "rating_scale": 1.0, "rating_precision": 80.0, "rating_levels": None}
    settings = ModelSettings.from_json(old)
    assert settings.ties_offered is False and settings.tie_threshold == 0.1
    assert settings.rating_precision == 80.0  # what it was fitted with, not today's person's
    assert (
        dataclasses.replace(settings, ties_offered=True, rating_precision=DEFAULT_MODEL.rating_precision)
        == DEFAULT_MODEL
    )
