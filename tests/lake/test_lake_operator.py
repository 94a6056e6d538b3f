import pytest
import torch

from torchpref.lake import LakeOperator


@pytest.mark.parametrize(
    "distance, info, level",
    [
        (400.0, 124.9, 1),
        (400.0, 125.0, 2),
        (400.0, 149.9, 2),
        (400.0, 150.0, 5),
        (450.0, 150.0, 5),
        (499.9, 160.0, 5),
        (500.0, 160.0, 4),
        (500.1, 160.0, 4),
        (549.9, 160.0, 4),
        (550.0, 160.0, 3),
        (600.0, 160.0, 2),
        (649.9, 160.0, 2),
        (650.0, 160.0, 1),
        (650.1, 160.0, 1),
        (900.0, 300.0, 1),
        (900.0, 130.0, 2),
        (300.0, 10.0, 1),
    ],
)
def test_levels_at_thresholds(distance, info, level):
    op = LakeOperator()
    assert int(op.level(torch.tensor([distance, info]))) == level
    assert op.rate(torch.tensor([distance, info])) == pytest.approx((level - 0.5) / 5)


def test_level_batch_and_formula():
    op = LakeOperator()
    d = torch.linspace(380, 720, 50, dtype=torch.float64)
    X = torch.stack([d, torch.full_like(d, 170.0)], -1)
    expected = torch.ceil(5 - (d - 450) / 50).clamp(1, 5).long()
    assert torch.equal(op.level(X), expected)
    assert op.level(X.view(5, 10, 2)).shape == (5, 10)


def test_choose_best_level_and_ties():
    op = LakeOperator()
    X = torch.tensor([[420.0, 140.0], [560.0, 155.0], [540.0, 151.0], [700.0, 300.0]])
    assert op.choose(X) == 2  # level 4 beats 3, 2 and 1
    # two level-5 paths: the shorter wins
    assert op.choose(torch.tensor([[480.0, 200.0], [430.0, 151.0]])) == 1
    # two level-2 paths: more information wins
    assert op.choose(torch.tensor([[400.0, 130.0], [400.0, 140.0]])) == 1
    # level 1: enough information (but too long) beats too little information
    assert op.choose(torch.tensor([[400.0, 100.0], [700.0, 160.0]])) == 1
    # exact tie: the lowest index
    assert op.choose(torch.tensor([[450.0, 160.0], [450.0, 160.0]])) == 0


def test_operator_validates():
    op = LakeOperator()
    with pytest.raises(ValueError, match="shape"):
        op.rate(torch.tensor([1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match="finite"):
        op.level(torch.tensor([float("nan"), 1.0]))
    with pytest.raises(ValueError, match="info_poor"):
        LakeOperator(info_poor=200.0)


def test_realistic_operator_offsets_drifts_and_lapses():
    """A realistic operator: ratings moved by its offset (in levels) and clipped to the scale, a
    drift that walks over the answers, and random choices at its lapse rate."""
    import torch

    from torchpref.lake.operator import LakeOperator, RealisticLakeOperator

    paper = LakeOperator()
    x = torch.tensor([520.0, 160.0])  # level 4
    up = RealisticLakeOperator(paper, torch.Generator().manual_seed(0), level_offset=1.0, drift_sd=0.0, level_noise=0.0)
    assert up.rate(x) == 0.9 and up.rate(torch.tensor([400.0, 200.0])) == 0.9  # 4 + 1 = 5; 5 + 1 clipped to 5
    noisy = RealisticLakeOperator(paper, torch.Generator().manual_seed(1), level_offset=0.0, drift_sd=0.2)
    levels = [round(noisy.rate(x) * 5 + 0.5) for _ in range(300)]
    assert set(levels) - {1, 2, 3, 4, 5} == set() and len(set(levels)) >= 3 and noisy.drift != 0.0
    X = torch.tensor([[400.0, 200.0], [700.0, 200.0], [650.0, 100.0], [600.0, 140.0]])  # row 0 is best
    for eps in (0.0, 0.5):
        op = RealisticLakeOperator(paper, torch.Generator().manual_seed(2), lapse_rate=eps)
        wrong = sum(op.choose(X) != 0 for _ in range(2000)) / 2000
        assert abs(wrong - eps * 0.75) < 0.04
