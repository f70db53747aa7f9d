"""Proposals and Gaussian dynamics of ``torchpf.proposals`` against torch.distributions."""

import math

import pytest
import torch
from torch.distributions import MultivariateNormal, Normal

from torchpf.filters import ParticleState
from torchpf.proposals import (
    BootstrapProposal,
    Gaussian,
    GaussianRandomWalk,
    ICondensationProposal,
    LinearGaussianDynamics,
    ObservationGaussian,
)

F64 = torch.float64


def _g(seed):
    return torch.Generator().manual_seed(seed)


def test_linear_gaussian_dynamics_density_and_sampling():
    A = torch.tensor([[0.9, 0.2], [0.0, 0.5]], dtype=F64)
    Q = torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=F64)
    dyn = LinearGaussianDynamics(A, Q, offset=torch.tensor([1.0, -1.0], dtype=F64))
    x_old = torch.randn(3, 50, 2, generator=_g(0), dtype=F64)
    x_new = torch.randn(3, 50, 2, generator=_g(1), dtype=F64)
    expected = MultivariateNormal(x_old @ A.T + torch.tensor([1.0, -1.0], dtype=F64), Q).log_prob(x_new)
    torch.testing.assert_close(dyn.log_prob(x_new, x_old), expected)
    draws = dyn.sample(torch.zeros(40_000, 2, dtype=F64), _g(2))
    torch.testing.assert_close(draws.mean(0), torch.tensor([1.0, -1.0], dtype=F64), atol=0.02, rtol=0)
    torch.testing.assert_close(torch.cov(draws.T), Q, atol=0.01, rtol=0)
    # sample() is sample_from_noise() with standard normal noise drawn from the generator
    eps = torch.randn(3, 50, 2, generator=_g(3), dtype=F64)
    torch.testing.assert_close(dyn.sample(x_old, _g(3)), dyn.sample_from_noise(x_old, eps))


def test_random_walk_and_gaussians_match_normal():
    std = torch.tensor([0.1, 0.5, 2.0], dtype=F64)
    x_old = torch.randn(4, 10, 3, generator=_g(0), dtype=F64)
    x_new = torch.randn(4, 10, 3, generator=_g(1), dtype=F64)
    rw = GaussianRandomWalk(std)
    assert rw.std.dtype == F64  # a float64 parameter is not rounded to float32
    torch.testing.assert_close(rw.log_prob(x_new, x_old), Normal(x_old, std).log_prob(x_new).sum(-1))
    p0 = Gaussian(torch.tensor([1.0, 2.0, 3.0], dtype=F64), std=2.0)
    torch.testing.assert_close(p0.log_prob(x_new), Normal(p0.mean, 2.0).log_prob(x_new).sum(-1))
    pi = ObservationGaussian(lambda z: 2 * z, std)
    z = torch.randn(4, 3, generator=_g(2), dtype=F64)
    torch.testing.assert_close(pi.log_prob(x_new, z), Normal(2 * z[:, None], std).log_prob(x_new).sum(-1))
    assert pi.sample(z, x_old, _g(3)).shape == x_old.shape


def _mixture(alpha, beta):
    dyn = GaussianRandomWalk(1.0)
    pi = ObservationGaussian(lambda z: z, 1.0)
    p0 = Gaussian(-10.0, 1.0)
    return dyn, pi, p0, ICondensationProposal(dyn, pi, p0, alpha=alpha, beta=beta)


def test_icondensation_draws_each_component_with_its_probability():
    # components sit far apart (pi at +10, dynamics at 0, p0 at -10) so each draw can be attributed
    _, _, _, q = _mixture(0.3, 0.5)
    state = ParticleState(
        torch.zeros(2, 20_000, 1, dtype=F64), torch.zeros(2, 20_000, dtype=F64), torch.zeros(2)
    )
    x, log_q = q.sample(state, torch.full((2, 1), 10.0, dtype=F64), _g(0))
    frac = torch.stack([(x > 5).to(F64).mean(), (x.abs() < 5).to(F64).mean(), (x < -5).to(F64).mean()])
    torch.testing.assert_close(frac, torch.tensor([0.3, 0.5, 0.2], dtype=F64), atol=0.01, rtol=0)
    assert log_q.shape == (2, 20_000)


def test_icondensation_log_q_is_the_full_mixture_density():
    dyn, pi, p0, q = _mixture(0.3, 0.5)
    parents = torch.randn(2, 100, 1, generator=_g(1), dtype=F64)
    state = ParticleState(parents, torch.zeros(2, 100, dtype=F64), torch.zeros(2))
    z = torch.tensor([[0.5], [-0.5]], dtype=F64)
    x, log_q = q.sample(state, z, _g(2))
    dens = 0.3 * pi.log_prob(x, z).exp() + 0.5 * dyn.log_prob(x, parents).exp() + 0.2 * p0.log_prob(x).exp()
    torch.testing.assert_close(log_q, dens.log())
    # degenerate mixtures reduce to one component
    _, _, _, only_pi = _mixture(1.0, 0.0)
    x, log_q = only_pi.sample(state, z, _g(3))
    torch.testing.assert_close(log_q, pi.log_prob(x, z))


def test_bootstrap_proposal_returns_the_dynamics_density():
    dyn = GaussianRandomWalk(0.3)
    parents = torch.randn(3, 10, 2, generator=_g(0), dtype=F64)
    state = ParticleState(parents, torch.zeros(3, 10, dtype=F64), torch.zeros(3))
    x, log_q = BootstrapProposal(dyn).sample(state, None, _g(1))
    torch.testing.assert_close(x, dyn.sample(parents, _g(1)))
    torch.testing.assert_close(log_q, dyn.log_prob(x, parents))


def test_icondensation_validates_its_weights():
    dyn, pi, p0, _ = _mixture(0.3, 0.5)
    with pytest.raises(ValueError):
        ICondensationProposal(dyn, pi, p0, alpha=0.7, beta=0.5)
    with pytest.raises(ValueError):
        ICondensationProposal(dyn, pi, None, alpha=0.3, beta=0.5)  # p0 needed for the remaining 0.2
    q = ICondensationProposal(dyn, pi, None, alpha=0.4, beta=0.6)
    assert math.isclose(q.rest, 0.0, abs_tol=1e-12)


def test_gaussians_follow_the_particles_device(device, dtype, generator):
    A = torch.tensor([[0.9, 0.2], [0.0, 0.5]], dtype=F64)
    Q = torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=F64)
    x = torch.randn(3, 50, 2, generator=_g(0), dtype=F64).to(device, dtype)
    for dyn in (LinearGaussianDynamics(A, Q).to(device), GaussianRandomWalk(torch.tensor([0.1, 0.2]))):
        y = dyn.sample(x, generator)
        lp = dyn.log_prob(y, x)
        assert y.device.type == device.type and y.dtype == dtype and lp.shape == (3, 50)
        assert lp.device.type == device.type and torch.isfinite(lp).all()
    q = ICondensationProposal(
        GaussianRandomWalk(0.1),
        ObservationGaussian(lambda o: o, 0.5),
        Gaussian(0.0, 2.0),
        alpha=0.2,
        beta=0.7,
    )
    state = ParticleState(
        x, torch.zeros(3, 50, dtype=dtype, device=device), torch.zeros(3, dtype=dtype, device=device)
    )
    new, log_q = q.sample(state, torch.zeros(3, 1, 2, dtype=dtype, device=device), generator)
    assert new.device.type == device.type and new.dtype == dtype and torch.isfinite(log_q).all()
