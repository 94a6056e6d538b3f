"""Where a person answers: the terminal and the notebook widget."""

from __future__ import annotations

from torchpref.frontends.elicit import FeaturesError, FeaturesWorld, LakeWorld, plot_paths, read_features_csv, run
from torchpref.frontends.widgets import PreferenceWidget, as_picture, lake_renderer, table_picture

__all__ = [
    'FeaturesError',
    'FeaturesWorld',
    'LakeWorld',
    'PreferenceWidget',
    'as_picture',
    'lake_renderer',
    'plot_paths',
    'read_features_csv',
    'run',
    'table_picture',
]
