"""torchpf.filters.weights: the one home of normalisation, ESS, reweighting and tempering."""

import math

import pytest
import torch

from torchpf.filters import weights


def _ref_ess(w):
    w = w / w.sum(-1, keepdim=True)
    return 1.0 / (w * w).sum(-1)


def test_ess_matches_definition_for_unnormalised_weights():
    g = torch.Generator().manual_seed(0)
    w = torch.rand(3, 50, generator=g, dtype=torch.float64)
    torch.testing.assert_close(weights.ess(w.log() + 5.0), _ref_ess(w))
    torch.testing.assert_close(weights.survival_fraction(w.log()), _ref_ess(w) / 50)
    n = 7
    assert float(weights.ess(torch.zeros(n))) == pytest.approx(n)
    assert float(weights.ess(torch.tensor([0.0] + [-math.inf] * (n - 1)))) == pytest.approx(1.0)


def test_dead_rows_have_zero_ess_and_fail_reweighting_with_uniform_weights():
    dead = torch.tensor([[-math.inf, math.nan, -math.inf], [0.0, 1.0, 2.0]])
    assert weights.ess(dead)[0] == 0 and weights.survival_fraction(dead)[0] == 0
    new, lse, failed = weights.reweight(torch.full((2, 3), -math.log(3)), dead)
    assert failed.tolist() == [True, False]
    torch.testing.assert_close(new[0].exp(), torch.full((3,), 1 / 3))
    torch.testing.assert_close(torch.logsumexp(new[1], -1), torch.tensor(0.0))
    # the evidence increment is the log of the weighted mean of the incremental weights
    torch.testing.assert_close(lse[1], torch.log(torch.tensor([1.0, math.e, math.e**2]).mean()))


def test_normalise_and_probabilities():
    lw = torch.tensor([1.0, 2.0, math.nan, -math.inf])
    p = weights.probabilities(lw)
    torch.testing.assert_close(p, torch.tensor([1.0, math.e, 0.0, 0.0]) / (1 + math.e))
    torch.testing.assert_close(weights.normalise(lw).exp(), p)


def test_temper_keeps_impossible_particles_impossible():
    energy = torch.tensor([[-2.0, -math.inf, math.nan]])
    out = weights.temper(torch.tensor([0.0]), energy)
    assert out[0, 0] == 0 and out[0, 1] == -math.inf and out[0, 2] == -math.inf
    torch.testing.assert_close(weights.temper(torch.tensor([0.5]), energy)[0, 0], torch.tensor(-1.0))
