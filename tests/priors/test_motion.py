"""Motion priors: closed-form Gaussians, statistical moments with stated tolerances, filter integration."""

from __future__ import annotations

import math

import pytest
import torch

from priors.motion import ConstantVelocity, DampedSecondOrder
from torchpf.filters import ParticleFilter, StatefulDynamics

# ----------------------------------------------------------------------------------- velocity dynamics


def test_constant_velocity_is_stateful_dynamics():
    cv = ConstantVelocity(0.1)
    assert isinstance(cv, StatefulDynamics)
    x0 = torch.randn(3, 7, 4)
    assert cv.init_extras(x0)["velocity"].shape == (3, 7, 4)
    assert torch.equal(cv.init_extras(x0)["velocity"], torch.zeros(3, 7, 4))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_constant_velocity_log_prob_matches_closed_form(dtype):
    g = torch.Generator().manual_seed(0)
    sigma = torch.tensor([0.1, 0.2, 0.05])
    cv = ConstantVelocity(sigma, alpha=0.3, dt=0.5)
    x_old = torch.randn(2, 6, 3, generator=g, dtype=dtype)
    v = torch.randn(2, 6, 3, generator=g, dtype=dtype)
    x_new = torch.randn(2, 6, 3, generator=g, dtype=dtype)
    lp = cv.log_prob(x_new, x_old, extras={"velocity": v})
    ref = torch.distributions.Normal(x_old.double() + 0.5 * v.double(), sigma.double()).log_prob(
        x_new.double()
    )
    assert lp.dtype == dtype and lp.shape == (2, 6)
    torch.testing.assert_close(lp.double(), ref.sum(-1), rtol=1e-5, atol=1e-5)


def test_constant_velocity_sample_moments():
    # Mean x + dt v and std sigma; with n = 200k draws the standard error of the mean is sigma / 447 and of
    # the std about sigma / 632, so 5 standard errors are well inside the tolerances below.
    g = torch.Generator().manual_seed(1)
    sigma = torch.tensor([0.1, 0.3])
    cv = ConstantVelocity(sigma, alpha=0.5, dt=2.0)
    x = torch.tensor([[1.0, -1.0]]).expand(200_000, 2)
    v = torch.tensor([[0.25, 0.5]]).expand(200_000, 2)
    xs = cv.sample(x, g, extras={"velocity": v})
    torch.testing.assert_close(xs.mean(0), torch.tensor([1.5, 0.0]), atol=5 * 0.3 / 447, rtol=0)
    torch.testing.assert_close(xs.std(0), sigma, atol=5 * 0.3 / 632, rtol=0)


def test_constant_velocity_update_is_rius_eq3():
    x_old, x_new = torch.randn(5, 3), torch.randn(5, 3)
    v = torch.randn(5, 3)
    for alpha in (0.0, 0.5, 1.0):
        cv = ConstantVelocity(0.1, alpha=alpha, dt=1.0)
        out = cv.update_extras(x_new, x_old, {"velocity": v, "phase": torch.ones(5)})
        torch.testing.assert_close(out["velocity"], alpha * v + (1 - alpha) * (x_new - x_old))
        assert torch.equal(out["phase"], torch.ones(5))  # other extras pass through


def test_constant_velocity_tracks_a_linear_motion_noiselessly():
    # sigma = 0, alpha = 0: after one frame the prior extrapolates a constant-velocity trajectory exactly.
    cv = ConstantVelocity(0.0, alpha=0.0)
    traj = torch.arange(6.0)[:, None] * torch.tensor([0.1, -0.2])  # (T, D)
    extras = cv.update_extras(traj[1:2], traj[0:1], cv.init_extras(traj[0:1]))
    x = traj[1:2]
    for t in range(2, 6):
        x_new = cv.sample(x, None, extras=extras)
        torch.testing.assert_close(x_new, traj[t : t + 1])
        extras = cv.update_extras(x_new, x, extras)
        x = x_new


def test_sample_from_noise_matches_sample():
    cv = ConstantVelocity(torch.tensor([0.1, 0.2, 0.3]), alpha=0.2)
    x, v = torch.randn(4, 3), torch.randn(4, 3)
    eps = torch.randn(4, 3, generator=torch.Generator().manual_seed(3))
    a = cv.sample(x, torch.Generator().manual_seed(3), extras={"velocity": v})
    b = cv.sample_from_noise(x, eps, extras={"velocity": v})
    torch.testing.assert_close(a, b)


def test_zero_sigma_dofs_are_deterministic_and_left_out_of_log_prob():
    cv = ConstantVelocity(torch.tensor([0.0, 0.2]))
    x = torch.zeros(1000, 2)
    xs = cv.sample(x, torch.Generator().manual_seed(0), extras=cv.init_extras(x))
    assert torch.equal(xs[:, 0], torch.zeros(1000))
    lp = cv.log_prob(xs, x, extras=cv.init_extras(x))
    ref = torch.distributions.Normal(0.0, 0.2).log_prob(xs[:, 1])
    torch.testing.assert_close(lp, ref)


def test_damped_second_order_is_brubaker_eq13():
    dyn = DampedSecondOrder(0.0, kappa=0.7)
    s_prev, s = torch.randn(3, 2), torch.randn(3, 2)
    extras = dyn.update_extras(s, s_prev, dyn.init_extras(s_prev))
    torch.testing.assert_close(dyn.sample(s, None, extras=extras), s + 0.7 * (s - s_prev))
    dyn = DampedSecondOrder(0.2, kappa=0.7)
    x_new = torch.randn(3, 2)
    ref = torch.distributions.Normal(s + 0.7 * (s - s_prev), 0.2).log_prob(x_new).sum(-1)
    torch.testing.assert_close(dyn.log_prob(x_new, s, extras=extras), ref)


def test_bad_arguments_raise():
    with pytest.raises(ValueError):
        ConstantVelocity(-0.1)
    with pytest.raises(ValueError):
        ConstantVelocity(0.1, alpha=1.5)
    with pytest.raises(ValueError):
        ConstantVelocity(0.1, dt=0.0)
    with pytest.raises(ValueError):
        ConstantVelocity(torch.ones(3)).sample(torch.zeros(2, 4), None)


def test_constant_velocity_in_a_particle_filter_carries_velocity():
    # Linear 1-D motion observed with a tight Gaussian likelihood: the velocity extras converge to the true
    # per-frame velocity (0.1), which a random walk would not carry.
    truth = 0.1 * torch.arange(1, 16.0)

    def likelihood(x, z):
        return -0.5 * ((x[..., 0] - z) / 0.02) ** 2

    cv = ConstantVelocity(0.03, alpha=0.5)
    pf = ParticleFilter(cv, likelihood, n_particles=500, progress=False)
    state = pf.init(torch.zeros(1, 1))
    g = torch.Generator().manual_seed(0)
    for z in truth:
        state = pf.step(state, z, generator=g)
    v = (state.weights()[:, None] * state.extras["velocity"]).sum(0)
    assert state.extras["velocity"].shape == (500, 1)
    assert abs(v.item() - 0.1) < 0.03
    assert abs(state.mean().item() - truth[-1].item()) < 0.05
    assert math.isfinite(state.log_evidence.item())
