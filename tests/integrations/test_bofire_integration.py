"""The PreferenceGP surrogate for BoFire (``torchpref.integrations.bofire``; docs/ax.md).

Skipped, with the reason, where BoFire (``pip install 'torchpref[bofire]'``) is not installed;
BoFire's own pairwise-surrogate tests run with it in ``tests/parity/test_upstream_suites.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("bofire", reason="BoFire is not installed (pip install 'torchpref[bofire]'): untested here")

import bofire.surrogates.api as surrogates
import pandas as pd
from bofire.data_models.domain.api import Inputs, Outputs
from bofire.data_models.features.api import ContinuousInput, ContinuousOutput
from bofire.data_models.surrogates.api import PairwiseGPSurrogate
from botorch.models.pairwise_gp import PairwiseGP

from torchpref import PreferenceGP
from torchpref.integrations.bofire import PreferenceGPSurrogate


def _problem(seed=1, n=20, m=50):
    rng = np.random.default_rng(seed)
    inputs = Inputs(features=[ContinuousInput(key=f"x{i}", bounds=(0.0, 1.0)) for i in range(2)])
    outputs = Outputs(features=[ContinuousOutput(key="u")])
    X = rng.random((n, 2))
    u = np.sin(3 * X[:, 0]) + X[:, 1]
    exps = pd.DataFrame(X, columns=["x0", "x1"]).assign(labcode=[f"c{i}" for i in range(n)])
    rows = []
    for _ in range(m):
        i, j = rng.choice(n, 2, replace=False)
        rows.append((f"c{i}", f"c{j}", 1.0 if u[i] > u[j] else -1.0))
    prefs = pd.DataFrame(rows, columns=["labcode_A", "labcode_B", "preference"])
    return inputs, outputs, exps, prefs, u


def test_surrogate_fits_preference_gp_and_agrees_with_pairwise_gp():
    inputs, outputs, exps, prefs, u = _problem()
    ours = surrogates.map(PreferenceGPSurrogate(inputs=inputs, outputs=outputs))
    ours.fit(exps, prefs)
    theirs = surrogates.map(PairwiseGPSurrogate(inputs=inputs, outputs=outputs))
    theirs.fit(exps, prefs)
    assert isinstance(ours.model, PreferenceGP) and isinstance(theirs.model, PairwiseGP)
    a = ours.predict(exps[["x0", "x1"]])
    b = theirs.predict(exps[["x0", "x1"]])
    assert list(a.columns) == list(b.columns) == ["u_pred", "u_sd"]
    assert np.corrcoef(a["u_pred"], u)[0, 1] > 0.8
    # the same ranking of the items as PairwiseGP's (both fit the same probit model)
    assert np.corrcoef(a["u_pred"], b["u_pred"])[0, 1] > 0.95
    assert (a["u_sd"] > 0).all()


def test_dump_and_load_and_logit_refused():
    inputs, outputs, exps, prefs, _ = _problem(seed=2)
    s = surrogates.map(PreferenceGPSurrogate(inputs=inputs, outputs=outputs))
    s.fit(exps, prefs)
    again = surrogates.map(PreferenceGPSurrogate(inputs=inputs, outputs=outputs))
    again.loads(s.dumps())
    pd.testing.assert_frame_equal(s.predict(exps[["x0", "x1"]]), again.predict(exps[["x0", "x1"]]))
    with pytest.raises(ValueError, match="logit"):
        PreferenceGPSurrogate(inputs=inputs, outputs=outputs, likelihood="logit")
