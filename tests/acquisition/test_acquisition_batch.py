"""Trials (a leading ``T`` dim) in membership_information and greedy_choice_set: each trial's
result is that of the 2-D call on its slice."""

import pytest
import torch

import torchpref.acquisition.choice_sets as choice_sets
import torchpref.acquisition.information as information
from torchpref.acquisition.functions import (
    choice_probabilities,
    greedy_choice_set,
    membership_information,
    rating_bin_probabilities,
    top_set_membership,
)


def _trials(g, T, S, N, empty=(), single=()):
    """``T x S x N`` memberships whose per-item probabilities vary between trials (an item
    counts in some trials, not in others); trials in ``empty``: no member, so no item counts;
    in ``single``: one member sample per item (counts only with ``min_count=1``, uncorrected)."""
    prob = torch.rand(T, 1, N, generator=g, dtype=torch.float64) ** 2
    Z = torch.rand(T, S, N, generator=g, dtype=torch.float64) < prob
    for t in empty:
        Z[t] = False
    for t in single:
        Z[t] = False
        Z[t, 0, :] = True
    return Z


@pytest.fixture(params=[None, 1, 4000, 70000], ids=["chunks-default", "chunks-1", "chunks-4000", "chunks-70000"])
def chunks(request, monkeypatch):
    """The chunk budgets (elements): by default every test trial fits one chunk; 1: a trial a
    chunk; 4000 / 70000: uneven chunks of a few trials (membership / greedy)."""
    if request.param is not None:
        monkeypatch.setattr(information, "_MEMBERSHIP_CHUNK", request.param)
        monkeypatch.setattr(choice_sets, "_GREEDY_CHUNK", request.param)
    return request.param


@pytest.mark.parametrize("S", [5, 7, 8, 9, 64, 65])
@pytest.mark.parametrize("bias_correction", [True, False])
@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
def test_membership_information_trials_match_slices(S, bias_correction, batch, chunks):
    g = torch.Generator().manual_seed(10 * S + bias_correction)
    T, N, Y = 5, 12, 4
    Z = _trials(g, T, S, N, empty=(1,), single=(3,))
    P = torch.softmax(2 * torch.randn(T, *batch, S, Y, generator=g, dtype=torch.float64), -1)
    for min_count in (1, 2, 3):
        out = membership_information(P, Z, min_count, bias_correction)
        assert out.shape == (T, *batch)
        for t in range(T):
            ref = membership_information(P[t], Z[t], min_count, bias_correction)
            torch.testing.assert_close(out[t], ref.reshape(batch), rtol=1e-12, atol=1e-14)
        assert (out[1] == 0).all()  # no kept item: 0
        assert (out[3] == 0).all() == (bias_correction or min_count > 1)
        if min_count == 1 and not bias_correction:  # plug-in terms are >= 0: the other trials inform
            assert (out[0::2] > 0).all()


def test_membership_information_trials_none_kept_and_shapes():
    g = torch.Generator().manual_seed(1)
    T, S, N = 3, 16, 6
    Z = torch.zeros(T, S, N, dtype=torch.bool)
    P = torch.softmax(torch.randn(T, 2, S, 3, generator=g, dtype=torch.float64), -1)
    torch.testing.assert_close(membership_information(P, Z), torch.zeros(T, 2, dtype=torch.float64))
    # no batch dims: T x S x Y -> T; one trial alone is the 2-D call
    Z = _trials(g, T, S, N)
    P = P[:, 0]
    out = membership_information(P, Z, 2)
    assert out.shape == (T,)
    for t in range(T):
        torch.testing.assert_close(out[t], membership_information(P[t], Z[t], 2), rtol=1e-12, atol=1e-14)
    # ratings: T x K x S x G bins of T trials' samples
    from torchpref.likelihoods.pairwise_beta import BetaRatingLikelihood

    F = torch.randn(T, S, N, generator=g, dtype=torch.float64)
    lik = BetaRatingLikelihood()
    Pr = rating_bin_probabilities(F[..., :4].mT, lik, 5)  # T x 4 x S x 5
    Zt = top_set_membership(F, 2)
    out = membership_information(Pr, Zt, 2)
    for t in range(T):
        torch.testing.assert_close(out[t], membership_information(Pr[t], Zt[t], 2), rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="T x batch x S x Y"):
        membership_information(P[:2], Z)
    with pytest.raises(ValueError, match="samples"):
        membership_information(P[..., :-1, :], Z)
    with pytest.raises(ValueError, match="S x N or T x S x N"):
        membership_information(P, Z.unsqueeze(0))


def _entropy_of_mean(P):
    Pm = P.mean(-2)
    return -torch.special.xlogy(Pm, Pm).sum(-1)


@pytest.mark.parametrize("start", [None, 0, "tensor"])
def test_greedy_choice_set_trials_match_slices(start, chunks):
    g = torch.Generator().manual_seed(7)
    T, S, N, K, m = 7, 64, 40, 9, 4
    F = torch.randn(T, S, N, generator=g, dtype=torch.float64) + torch.linspace(-1, 1, N, dtype=torch.float64)
    Z = top_set_membership(F, 8)
    Fc = F[..., :K]
    starts = torch.randint(0, K, (T,), generator=g) if start == "tensor" else start
    noise = torch.tensor([0.1, 0.2, 0.3, 0.2, 0.5, 1.0, 0.05], dtype=torch.float64)
    for value in (lambda P: membership_information(P, Z, 4), _entropy_of_mean):
        chosen, best = greedy_choice_set(Fc, noise, m, value, start=starts)
        assert chosen.shape == (T, m) and chosen.dtype == torch.long and best.shape == (T,)
        for t in range(T):
            value_t = (lambda P, t=t: membership_information(P, Z[t], 4)) if value is not _entropy_of_mean else value
            st = int(starts[t]) if start == "tensor" else start
            ref_chosen, ref_best = greedy_choice_set(Fc[t], float(noise[t]), m, value_t, start=st)
            assert chosen[t].tolist() == ref_chosen
            assert float(best[t]) == pytest.approx(ref_best, rel=1e-12, abs=1e-15)
            if st is not None:
                assert ref_chosen[0] == st
            # the final value is that of choice_probabilities' set (log space)
            P_final = choice_probabilities(Fc[t][:, ref_chosen].unsqueeze(0), float(noise[t]))
            assert ref_best == pytest.approx(float(value_t(P_final)), rel=1e-9)


def test_greedy_choice_set_trials_scalar_noise_full_set_and_errors():
    g = torch.Generator().manual_seed(8)
    T, S, K = 3, 32, 5
    F = torch.randn(T, S, K, generator=g, dtype=torch.float64)
    chosen, best = greedy_choice_set(F, 0.2, K, _entropy_of_mean, start=2)  # m = K: every item
    assert (chosen[:, 0] == 2).all()
    assert (chosen.sort(-1).values == torch.arange(K)).all()
    for t in range(T):
        c, b = greedy_choice_set(F[t], torch.tensor(0.2, dtype=torch.float64), K, _entropy_of_mean, start=2)
        assert chosen[t].tolist() == c and float(best[t]) == pytest.approx(b, rel=1e-12)
    with pytest.raises(ValueError, match="m="):
        greedy_choice_set(F, 0.2, K + 1, _entropy_of_mean)
    with pytest.raises(ValueError, match="start"):
        greedy_choice_set(F, 0.2, 2, _entropy_of_mean, start=torch.tensor([0, K, 1]))
    with pytest.raises(ValueError, match="start"):
        greedy_choice_set(F, 0.2, 2, _entropy_of_mean, start=torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="comparison_noise"):
        greedy_choice_set(F, torch.ones(T + 1, dtype=torch.float64), 2, _entropy_of_mean)
    with pytest.raises(ValueError, match="value must map"):
        greedy_choice_set(F, 0.2, 2, lambda P: _entropy_of_mean(P).sum(0))
