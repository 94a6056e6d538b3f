"""BoTorch acquisition functions over queries: UCB and the expected information of an answer."""

from __future__ import annotations

from torchpref.acquisition.choice_sets import greedy_choice_set
from torchpref.acquisition.functions import (
    QueryInformation,
    QueryUCB,
    choice_probabilities,
    item_ucb,
    latent_ucb,
    rating_bin_probabilities,
)
from torchpref.acquisition.information import entropy, membership_information, sample_information, top_set_membership

__all__ = [
    'QueryInformation',
    'QueryUCB',
    'choice_probabilities',
    'entropy',
    'greedy_choice_set',
    'item_ucb',
    'latent_ucb',
    'membership_information',
    'rating_bin_probabilities',
    'sample_information',
    'top_set_membership',
]
