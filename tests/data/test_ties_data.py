"""Ties and rating levels in PreferenceData: validation, mapping through new items, best-of-m ties."""

import pytest
import torch

from torchpref.data.preference_data import PreferenceData, best_of_m, best_of_m_with_ties

T = dict(dtype=torch.float64)


def test_best_of_m_with_ties():
    C, ties = best_of_m_with_ties([3, 1], [0, 1, 2, 3])
    assert sorted(map(tuple, C.tolist())) == [(1, 0), (1, 2), (3, 0), (3, 2)]
    assert sorted(map(sorted, ties.tolist())) == [[1, 3]]
    C1, t1 = best_of_m_with_ties([2], [0, 1, 2])
    assert torch.equal(C1, best_of_m(2, [0, 1, 2])) and t1.shape == (0, 2)
    C3, t3 = best_of_m_with_ties([0, 1, 2], [0, 1, 2])  # all equally good: ties only
    assert C3.shape == (0, 2) and t3.tolist() == [[0, 1], [0, 2], [1, 2]]
    with pytest.raises(ValueError, match=r"\[5\] are not among"):
        best_of_m_with_ties([1, 5], [0, 1, 2])
    with pytest.raises(ValueError, match="distinct"):
        best_of_m_with_ties([1, 1], [0, 1, 2])
    with pytest.raises(ValueError, match="distinct"):
        best_of_m_with_ties([0], [0, 1, 1])


def test_ties_are_validated_and_mapped_through_new_items():
    X = torch.tensor([[0.0], [0.5], [1.0]], **T)
    data = PreferenceData.create(X, [[0, 1]], ties=[[1, 2]])
    assert data.ties.tolist() == [[1, 2]] and data.num_observations == 2
    # indices refer to the rows of the new X; a row equal to an existing item reuses its index
    new = data.add(torch.tensor([[0.25], [1.0]], **T), ties=[[0, 1]])
    assert new.ties.tolist() == [[1, 2], [3, 2]] and new.n == 4
    assert data.ties.tolist() == [[1, 2]]  # immutable
    for bad, msg in [
        ([[1, 1]], "tied with itself"),
        ([[0, 3]], "out of range"),
        ([0, 1, 2], "p x 2"),
        ([[0.5, 1]], "integer"),
    ]:
        with pytest.raises(ValueError, match=msg):
            PreferenceData.create(X, ties=bad)
    with pytest.raises(ValueError, match="same item"):
        data.add(torch.tensor([[0.5], [0.5]], **T), ties=[[0, 1]])
    assert data.to(torch.float32).ties.tolist() == [[1, 2]]


def test_rating_levels_are_validated():
    X = torch.rand(4, 1, **T)
    data = PreferenceData.create(X, ratings=[1, 5, 3], rating_index=[0, 1, 2], rating_levels=5)
    assert data.ratings.tolist() == [1.0, 5.0, 3.0] and data.rating_levels == 5
    assert data.add(ratings=[2], rating_index=[3]).rating_levels == 5
    for bad in ([0], [6], [2.5], [float("nan")]):
        with pytest.raises(ValueError, match="1..5|finite"):
            PreferenceData.create(X, ratings=bad, rating_index=[0], rating_levels=5)
    with pytest.raises(ValueError, match=r"1\.\.5.*0\.7"):
        data.add(ratings=[0.7], rating_index=[3])
    with pytest.raises(ValueError, match="at least 2"):
        PreferenceData.create(X, rating_levels=1)
