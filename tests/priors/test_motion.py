"""Motion priors: closed-form Gaussians, statistical moments with stated tolerances, filter integration."""

from __future__ import annotations

import math

import pytest
import torch

from priors.motion import ConstantVelocity, DampedSecondOrder
from torchpf.distributions import Dynamics
from torchpf.filters import ParticleFilter

# ----------------------------------------------------------------------------------- velocity dynamics


def test_constant_velocity_is_stateful_dynamics():
    cv = ConstantVelocity(0.1)
    assert isinstance(cv, Dynamics) and callable(cv.update_extras)
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


# --------------------------------------------------------------------------------------- angular random walk

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from priors.motion import AngularRandomWalk, ProjectedGaussian  # noqa: E402
from priors.table5 import table5_sigma  # noqa: E402
from torchpf import Skeleton  # noqa: E402
from torchpf.assets import path  # noqa: E402


@pytest.fixture(scope="module")
def f22():
    return Skeleton.from_urdf(path("fontmarty22.urdf"))


LO, HI, MU, SIG = -0.5, 0.3, 0.1, 0.4


def _walk(limits, **kw):
    f64 = {"dtype": torch.float64}
    return AngularRandomWalk(
        torch.tensor([SIG], **f64), torch.tensor([LO], **f64), torch.tensor([HI], **f64), limits=limits, **kw
    )


@pytest.mark.parametrize("limits", ["reject", "reflect"])
def test_truncated_densities_integrate_to_one(limits):
    xs = torch.linspace(LO, HI, 40001, dtype=torch.float64)[:, None]
    lp = _walk(limits).log_prob(xs, torch.full_like(xs, MU))
    assert abs(torch.trapezoid(lp.exp(), xs[:, 0]).item() - 1) < 1e-6
    outside = torch.tensor([[LO - 0.01], [HI + 0.01]], dtype=torch.float64)
    assert torch.all(_walk(limits).log_prob(outside, torch.full_like(outside, MU)) == -torch.inf)


def test_reject_log_prob_is_scipy_truncnorm():
    a, b = (LO - MU) / SIG, (HI - MU) / SIG
    xs = torch.linspace(LO, HI, 7, dtype=torch.float64)[:, None]
    ref = stats.truncnorm.logpdf(xs.numpy()[:, 0], a, b, loc=MU, scale=SIG)
    ours = _walk("reject").log_prob(xs, torch.full_like(xs, MU))
    np.testing.assert_allclose(ours.numpy(), ref, rtol=1e-10)


@pytest.mark.parametrize("how", ["sample", "noise"])
def test_reject_samples_follow_the_truncated_normal(how):
    # Kolmogorov-Smirnov against scipy's truncated normal; with n = 20000 the 1% critical value is 0.0115.
    g = torch.Generator().manual_seed(0)
    x = torch.full((20000, 1), MU, dtype=torch.float64)
    walk = _walk("reject", max_tries=3)  # few rounds: the inverse-CDF fallback is exercised too
    y = walk.sample(x, g) if how == "sample" else walk.sample_from_noise(x, torch.randn(x.shape, generator=g))
    a, b = (LO - MU) / SIG, (HI - MU) / SIG
    ks = stats.kstest(y.numpy()[:, 0], stats.truncnorm(a, b, loc=MU, scale=SIG).cdf).statistic
    assert ks < 0.0115
    assert y.min() >= LO and y.max() <= HI


def test_reflect_and_clamp_samples_and_masses():
    g = torch.Generator().manual_seed(1)
    x = torch.full((20000, 1), MU, dtype=torch.float64)
    y = _walk("reflect").sample(x, g)
    assert y.min() >= LO and y.max() <= HI
    # histogram against the folded density: 8 bins of 0.1, each count binomial with sd <= 0.0035 n
    h = torch.histc(y[:, 0], 8, LO, HI) / 20000
    mids = torch.linspace(LO + 0.05, HI - 0.05, 8, dtype=torch.float64)[:, None]
    p = _walk("reflect").log_prob(mids, torch.full_like(mids, MU)).exp() * 0.1
    assert (h - p).abs().max() < 0.02  # bin-width discretisation (~0.005) + 4 sd
    c = _walk("clamp").sample(x, g)
    mass_hi = (c == HI).double().mean().item()
    assert abs(mass_hi - stats.norm.sf((HI - MU) / SIG)) < 0.012  # 4 sd of a share out of 20000
    lp = _walk("clamp").log_prob(
        torch.tensor([[HI]], dtype=torch.float64), torch.tensor([[MU]], dtype=torch.float64)
    )
    assert abs(lp.exp().item() - stats.norm.sf((HI - MU) / SIG)) < 1e-9


def test_walk_on_a_skeleton_respects_limits_and_frozen_dofs(human):
    walk = AngularRandomWalk.from_skeleton(human, fps=5.0)
    x = human.clamp(torch.zeros(500, len(human.dof_names)))
    y = walk.sample(x, torch.Generator().manual_seed(2))
    assert human.within_limits(y).all()
    assert torch.isfinite(walk.log_prob(y, x)).all()
    sig = table5_sigma(human)
    sig[:3] = 0.0  # root translation frozen
    still = AngularRandomWalk(sig, human.lower, human.upper).sample(x, torch.Generator().manual_seed(3))
    assert torch.equal(still[:, :3], x[:, :3])


# ---------------------------------------------------------------------------------------- projected prior


def _chain_std(skel, particles, names):
    P = skel.fk(particles)
    return [P[:, skel.joint_names.index(n)].var(0).sum().sqrt().item() for n in names]


def test_projected_prior_spread_does_not_grow_along_the_chain(human):
    # Hauberg §1.2: with the angular walk the hand spreads more than the shoulder; with the projected prior
    # (same isotropic 5 cm per joint) every joint's spread stays near the prescribed one. Standing pose,
    # root fixed (σ = 0), 1000 draws: the standard errors of these stds are ~2 %.
    chain = ["LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand"]
    x = human.clamp(torch.zeros(1000, len(human.dof_names)))
    g = torch.Generator().manual_seed(4)
    sig = table5_sigma(human, fps=5.0)
    sig[:6] = 0.0
    walk = AngularRandomWalk(sig, human.lower, human.upper).sample(x, g)
    proj = ProjectedGaussian(human, 0.05, ik_options={"free": sig > 0}).sample(x, g)
    s_walk, s_proj = _chain_std(human, walk, chain), _chain_std(human, proj, chain)
    # angular walk: the spread grows at every joint down the arm, the hand ~4x the upper arm (2.0, 3.6, 8.1,
    # 14.5 cm with these seeds)
    assert all(b > 1.2 * a for a, b in zip(s_walk, s_walk[1:], strict=False))
    assert s_walk[-1] > 3.0 * s_walk[1]
    # projected (2.2, 4.1, 4.4, 3.4 cm): the hand spreads no more than the upper arm, and no joint more than
    # an unconstrained 3-D Gaussian of 5 cm per axis would (sqrt(3) x 5 cm)
    assert s_proj[-1] < 1.2 * s_proj[1]
    assert max(s_proj) < 1.05 * 3**0.5 * 0.05
    assert human.within_limits(proj).all()


def test_projected_prior_log_prob_is_the_embedding_gaussian(f22):
    J = len(f22.joint_names)
    A = torch.randn(J, 3, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    cov = 1e-3 * (A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=torch.float64))
    prior = ProjectedGaussian(f22, cov)
    x_old = f22.clamp(torch.zeros(4, len(f22.dof_names), dtype=torch.float64))
    joints = prior.sample_joints(x_old, torch.Generator().manual_seed(6))
    ref = (
        torch.distributions.MultivariateNormal(f22.fk(x_old), covariance_matrix=cov).log_prob(joints).sum(-1)
    )
    torch.testing.assert_close(prior.log_prob_joints(joints, x_old), ref)
    x_new = prior.project(joints, x_old)
    torch.testing.assert_close(prior.log_prob(x_new, x_old), prior.log_prob_joints(f22.fk(x_new), x_old))
    # zero spread: the projection returns the parent pose (its joints are on the manifold already)
    still = ProjectedGaussian(f22, 0.0).sample(x_old, torch.Generator().manual_seed(7))
    torch.testing.assert_close(f22.fk(still), f22.fk(x_old), atol=1e-6, rtol=0)


def test_priors_follow_the_particles_device(device, dtype, generator):
    f22 = Skeleton.from_urdf(path("fontmarty22.urdf")).to(device)  # own copy: the fixture stays on the CPU
    x = f22.clamp(torch.zeros(64, len(f22.dof_names), dtype=dtype, device=device))
    walk = AngularRandomWalk.from_skeleton(f22).to(device)
    y = walk.sample(x, generator)
    assert y.device.type == device.type and y.dtype == dtype and torch.isfinite(walk.log_prob(y, x)).all()
    cv = ConstantVelocity(0.1).to(device)
    z = cv.sample(x, generator, extras=cv.init_extras(x))
    assert z.device.type == device.type and z.dtype == dtype
    p = ProjectedGaussian(f22, 0.03).sample(x, generator)
    assert p.device.type == device.type and p.dtype == dtype and f22.within_limits(p).all()


def test_every_prior_is_a_dynamics_with_one_signature(human):
    from priors.motion import ConstantVelocity, DampedSecondOrder
    from torchpf.distributions import Dynamics

    x = human.clamp(torch.zeros(2, 3, len(human.dof_names), dtype=torch.float64))
    priors = (
        AngularRandomWalk.from_skeleton(human),
        AngularRandomWalk(0.1, limits="none"),
        ConstantVelocity(0.1),
        DampedSecondOrder(0.1),
        ProjectedGaussian(human, 0.03),
    )
    for prior in priors:
        assert isinstance(prior, Dynamics)
        g = torch.Generator().manual_seed(0)
        extras = prior.init_extras(x)
        y = prior.sample(x, g, extras=extras)
        assert y.shape == x.shape and prior.log_prob(y, x, extras=extras).shape == (2, 3)
        eps = torch.randn(2, 3, prior.noise_size(x.shape[-1]), generator=g, dtype=x.dtype)
        assert prior.sample_from_noise(x, eps, extras=extras).shape == x.shape
        assert set(prior.update_extras(y, x, extras)) == set(extras)
