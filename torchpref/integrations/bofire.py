r"""A ``PreferenceGP`` surrogate for BoFire, where BoFire uses its ``PairwiseGPSurrogate``.

``pip install 'torchpref[bofire]'`` (tested with BoFire 0.5.0). The data model
:class:`PreferenceGPSurrogate` takes the fields of BoFire's ``PairwiseGPSurrogate`` (inputs, one
output, kernel, scaler, likelihood) and is registered with BoFire's surrogate mapper on import,
so ``bofire.surrogates.api.map(PreferenceGPSurrogate(inputs=..., outputs=...))`` gives a surrogate
fitted from BoFire's ``experiments`` / ``preferences`` DataFrames as BoFire's own is
(``fit(experiments, preferences)``), with ``PreferenceGP`` and
``LaplaceMarginalLogLikelihood`` in place of ``PairwiseGP`` and its MLL::

    import torchpref.integrations.bofire as tb
    surrogate = surrogates.map(tb.PreferenceGPSurrogate(inputs=inputs, outputs=outputs))
    surrogate.fit(experiments, preferences)

Differences from BoFire's surrogate: ``likelihood="logit"`` is refused at construction (the
logistic link is not implemented; ``"probit"``, the default, is BoTorch's probit, eq. 3 with
``sigma_R = 1``); ``predict`` gives the latent utility's posterior standard deviation, as
``PairwiseGP`` does (whose ``posterior`` ignores ``observation_noise``), not the perceived
utility's. Nothing here is imported by ``import torchpref``.
"""

from __future__ import annotations

from typing import Literal

try:
    import bofire.kernels.api as _kernels
    from bofire.data_models.surrogates.api import PairwiseGPSurrogate as _PairwiseGPSurrogateData
    from bofire.surrogates import mapper as _mapper
    from bofire.surrogates.pairwise_gp import PairwiseGPSurrogate as _PairwiseGPSurrogate
except ImportError as err:  # pragma: no cover - exercised where BoFire is absent
    raise ImportError("torchpref.integrations.bofire needs BoFire: pip install 'torchpref[bofire]'") from err

import numpy as np
import torch
from botorch.fit import fit_gpytorch_mll
from botorch.models.likelihoods.pairwise import PairwiseProbitLikelihood
from pydantic import model_validator

from torchpref.models.preference_gp import LaplaceMarginalLogLikelihood, PreferenceGP

__all__ = ["PreferenceGPSurrogate", "PreferenceGPSurrogateModel"]


class PreferenceGPSurrogate(_PairwiseGPSurrogateData):
    """BoFire data model of a :class:`~torchpref.models.preference_gp.PreferenceGP` surrogate: the
    fields and checks of BoFire's ``PairwiseGPSurrogate`` (one output, a ``ScaleKernel``), and
    ``likelihood="probit"`` only."""

    type: Literal["PreferenceGPSurrogate"] = "PreferenceGPSurrogate"

    @model_validator(mode="after")
    def validate_probit(self):
        if self.likelihood != "probit":
            raise ValueError(
                f"PreferenceGPSurrogate: likelihood={self.likelihood!r} is not supported (comparisons are scored "
                "with the probit of eq. 3, BoTorch's PairwiseProbitLikelihood); use likelihood='probit'."
            )
        return self


class PreferenceGPSurrogateModel(_PairwiseGPSurrogate):
    """The functional surrogate: BoFire's pairwise surrogate with ``PreferenceGP`` as its model."""

    model: PreferenceGP | None = None

    def _fit_pairwise(self, datapoints, comparisons, input_transform=None, **kwargs):
        n_dim = input_transform(datapoints).shape[-1] if input_transform is not None else datapoints.shape[-1]
        self.model = PreferenceGP(
            datapoints=datapoints,
            comparisons=comparisons,
            likelihood=PairwiseProbitLikelihood(),
            covar_module=_kernels.map(
                self.kernel,
                batch_shape=torch.Size(),
                active_dims=list(range(n_dim)),
                features_to_idx_mapper=self.get_feature_indices,
            ),
            input_transform=input_transform,
        )
        mll = LaplaceMarginalLogLikelihood(likelihood=self.model.likelihood, model=self.model)
        fit_gpytorch_mll(mll, options=self.training_specs, max_attempts=50)

    def _predict(self, transformed_X):
        X = torch.from_numpy(transformed_X.values).to(self.model.train_X)
        with torch.no_grad():
            post = self.model.posterior(X)  # the latent utility, as PairwiseGP's posterior gives
            return post.mean.cpu().numpy(), np.sqrt(post.variance.cpu().numpy())


_mapper.register(PreferenceGPSurrogate, PreferenceGPSurrogateModel)
