"""Angular random walk within the joint limits: exact truncated normals, log_prob normalised, QRS map."""

import math

import pytest
import torch
from scipy import stats

from priors.random_walk import AngularRandomWalk

LO = torch.tensor([-0.5, -math.inf, 0.0, -1.0], dtype=torch.float64)
HI = torch.tensor([0.4, math.inf, 2.6, 1.0], dtype=torch.float64)
SIGMA = torch.tensor([0.3, 0.2, 0.5, 0.0], dtype=torch.float64)


def test_reject_draws_exact_truncated_normals():
    walk = AngularRandomWalk(SIGMA, LO, HI)
    x_old = torch.tensor([0.35, 1.0, 0.05, 0.3], dtype=torch.float64).expand(20000, 4)
    x = walk.sample(x_old, torch.Generator().manual_seed(0))
    assert torch.all((x >= LO) & (x <= HI))
    assert torch.all(x[:, 3] == 0.3)  # sigma 0: frozen
    assert int(walk.stats["rejected"]) > 1000  # the first DOF sits next to its upper limit
    for d in range(3):
        a, b = (LO[d] - x_old[0, d]) / SIGMA[d], (HI[d] - x_old[0, d]) / SIGMA[d]
        ref = stats.truncnorm(float(a), float(b), loc=float(x_old[0, d]), scale=float(SIGMA[d]))
        assert stats.kstest(x[:, d].numpy(), ref.cdf).pvalue > 1e-3


@pytest.mark.parametrize("limits", ["reject", "reflect"])
def test_log_prob_is_a_normalised_density(limits):
    walk = AngularRandomWalk(SIGMA[:1], LO[:1], HI[:1], limits=limits)
    grid = torch.linspace(-0.5, 0.4, 20001, dtype=torch.float64)[:, None]
    old = torch.full_like(grid, 0.3)
    dens = walk.log_prob(grid, old).exp()
    assert float(torch.trapezoid(dens, grid[:, 0])) == pytest.approx(1.0, abs=2e-3)
    # and it is the density the samples follow
    x = walk.sample(torch.full((40000, 1), 0.3, dtype=torch.float64), torch.Generator().manual_seed(1))
    hist = torch.histc(x[:, 0], bins=9, min=-0.5, max=0.4) / (40000 * 0.1)
    centres = torch.linspace(-0.45, 0.35, 9, dtype=torch.float64)[:, None]
    torch.testing.assert_close(
        hist, walk.log_prob(centres, torch.full_like(centres, 0.3)).exp(), atol=0.08, rtol=0.05
    )


def test_outside_limits_is_impossible_and_clamp_mode():
    walk = AngularRandomWalk(SIGMA, LO, HI)
    old = torch.zeros(1, 4, dtype=torch.float64)
    assert walk.log_prob(torch.tensor([[0.5, 0.0, 0.1, 0.0]], dtype=torch.float64), old) == -math.inf
    clamp = AngularRandomWalk(SIGMA, LO, HI, limits="clamp")
    x = clamp.sample(torch.full((1000, 4), 0.39, dtype=torch.float64), torch.Generator().manual_seed(2))
    assert torch.all(x <= HI) and float((x[:, 0] == 0.4).double().mean()) > 0.3


@pytest.mark.parametrize("limits", ["reject", "reflect", "clamp"])
def test_sample_from_noise_maps_normal_noise_into_the_box(limits):
    walk = AngularRandomWalk(SIGMA, LO, HI, limits=limits)
    x_old = torch.tensor([0.35, 1.0, 0.05, 0.3], dtype=torch.float64).expand(5000, 4)
    eps = torch.randn(5000, 4, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    x = walk.sample_from_noise(x_old, eps)
    assert torch.all((x >= LO) & (x <= HI))
    if limits != "reflect":  # monotone in the noise: the order of quasi-random points is kept
        order = eps[:, 2].argsort()
        assert torch.all(x[order, 2][1:] >= x[order, 2][:-1])
    if limits == "reject":
        ref = stats.truncnorm((0 - 0.05) / 0.5, (2.6 - 0.05) / 0.5, loc=0.05, scale=0.5)
        assert stats.kstest(x[:, 2].numpy(), ref.cdf).pvalue > 1e-3


def test_float32_and_bad_arguments():
    walk = AngularRandomWalk(0.1, LO, HI)
    x = walk.sample(torch.zeros(3, 8, 4), torch.Generator().manual_seed(0))
    assert x.dtype == torch.float32 and walk.log_prob(x, torch.zeros(3, 8, 4)).shape == (3, 8)
    with pytest.raises(ValueError, match="limits"):
        AngularRandomWalk(0.1, LO, HI, limits="wrap")
    with pytest.raises(ValueError, match="sigma"):
        AngularRandomWalk(-0.1, LO, HI)
