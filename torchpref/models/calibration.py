r"""Calibrate the person: give a :class:`~torchpref.models.preference_gp.PreferenceGP` the likelihoods
of :mod:`torchpref.likelihoods.person` (a rating link with a learned offset and gain, comparisons
with a learned lapse rate, the ratings' learned noise) and fit them by the Laplace evidence.

.. code-block:: python

    model = PreferenceGP(X, comparisons, ratings, rating_index, comparison_noise=0.1, rating_scale=0.8)
    calibrate_person(model)                  # swaps in the person's likelihoods (g = 1, b = 0, eps = 0.05)
    fit_person(model)                        # MAP of b, g, nu, eps (the kernel kept), priors included
    model.likelihood.rating.rating_offset    # b

What is learned from which answers: :mod:`torchpref.likelihoods.person` (both kinds identify all
four; ratings only leave ``g`` and ``b`` to their priors, comparisons only leave ``g``, ``b``, ``nu``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from torchpref.likelihoods.ordinal import OrdinalRatingLikelihood, TieLikelihood
from torchpref.likelihoods.person import LapseProbitLikelihood, PersonRatingLikelihood
from torchpref.models.defaults import PreferenceLikelihood

if TYPE_CHECKING:
    from torchpref.models.preference_gp import PreferenceGP

__all__ = ["calibrate_person", "fit_person", "person_parameters"]

#: the names of the person's parameters in ``model.likelihood``
PERSON_PARAMETERS = (
    "rating.raw_rating_offset",
    "rating.raw_rating_gain",
    "rating.raw_rating_precision",
    "comparison.raw_lapse_rate",
)


def calibrate_person(
    model: PreferenceGP,
    *,
    rating_offset: float = 0.0,
    rating_gain: float = 1.0,
    lapse_rate: float = 0.05,
    learn_precision: bool = True,
) -> PreferenceGP:
    r"""Replace ``model``'s rating and comparison likelihoods by the person's (in place), keeping its
    ``sigma_B``, ``nu`` and ``sigma_R``; returns ``model``. The posterior is re-solved on next use.

    Raises:
        ValueError: for a model whose ratings are Likert levels (ordinal likelihood), which has its
            own learned cut points, or a model that offers ties.
    """
    lik = model.likelihood
    if isinstance(lik.rating, OrdinalRatingLikelihood):
        raise ValueError("calibrate_person needs a Beta rating likelihood; this model scores ratings as levels.")
    if getattr(model, "ties_offered", False):
        raise ValueError("calibrate_person does not support models that offer ties.")
    like = lik.comparison.raw_comparison_noise
    rating = PersonRatingLikelihood(
        float(lik.rating.rating_scale),
        float(lik.rating.rating_precision),
        rating_offset,
        rating_gain,
        learn_precision=learn_precision,
    )
    comparison = LapseProbitLikelihood(float(lik.comparison.comparison_noise), lapse_rate)
    rating, comparison = (m.to(dtype=like.dtype, device=like.device) for m in (rating, comparison))
    tie = TieLikelihood(float(lik.tie.tie_threshold), comparison).to(dtype=like.dtype, device=like.device)
    # a new container: the model's cached observations hold the old likelihoods and are rebuilt for a new one
    model.likelihood = PreferenceLikelihood(comparison, rating, tie)
    try:
        model.posterior(model.train_X[..., :1, :])  # re-solves the mode now: a failure leaves the old model
    except BaseException:
        model.likelihood = lik
        raise
    return model


def person_parameters(model: PreferenceGP) -> dict[str, torch.Tensor]:
    """The raw parameters of the person's likelihoods that are trainable, by name (``likelihood.``...)."""
    named = dict(model.likelihood.named_parameters())
    return {f"likelihood.{k}": named[k] for k in PERSON_PARAMETERS if k in named and named[k].requires_grad}


def fit_person(model: PreferenceGP, *, max_iter: int = 50) -> PreferenceGP:
    r"""Fit the person's parameters (:func:`person_parameters`) by the Laplace evidence plus their log
    priors (L-BFGS, the kernel and ``sigma_R`` kept); returns ``model``. The model must have been
    through :func:`calibrate_person`. A fit that fails numerically puts the old values back and
    re-raises."""
    from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood

    params = person_parameters(model)
    if not params:
        raise ValueError("the model has no person parameters to fit: call calibrate_person(model) first.")
    saved = {k: p.detach().clone() for k, p in params.items()}
    others = [p for p in model.parameters() if p.requires_grad and all(p is not q for q in params.values())]
    for p in others:
        p.requires_grad_(False)
    mll = LaplaceMarginalLogLikelihood(model)
    opt = torch.optim.LBFGS(list(params.values()), lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = -mll(None, None)
        loss.backward()
        return loss

    try:
        model.train()
        opt.step(closure)
        bad = [k for k, p in params.items() if not bool(torch.isfinite(p).all())]
        if bad:
            raise FloatingPointError(f"fit_person: non-finite values of {bad}")
    except BaseException:
        with torch.no_grad():
            for k, q in params.items():
                q.copy_(saved[k])
        raise
    finally:
        for p in others:
            p.requires_grad_(True)
        model.eval()
    return model
