"""IK projection (Hauberg eq. 7): Jacobian and solver against autograd / dense references, recovery of exact
targets, least-squares optimum against scipy's bound-constrained solver in float64, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares

from torchpf import Skeleton, ik
from torchpf.assets import path
from torchpf.kinematics import aba, jacobian


@pytest.fixture(scope="module")
def f22():
    return Skeleton.from_urdf(path("fontmarty22.urdf"))


def _interior_poses(skel, n, seed, dtype=torch.float64, spread=0.8):
    """Random poses in the central ``spread`` of every DOF's range (root translation within 1 m)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = skel.lower.clamp(-1.0, 1.0), skel.upper.clamp(-1.0, 1.0)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    u = 2 * torch.rand(n, len(skel.dof_names), generator=g, dtype=torch.float64) - 1
    return (mid + spread * half * u).to(dtype)


# A run mixing revolute and prismatic DOFs (shoulder, telescoping extension, wrist between two links), so that
# a revolute DOF's pivot is not its run's origin; a rotated root slider; a fixed end site.
TELESCOPE_URDF = """<?xml version="1.0"?>
<robot name="telescope">
  <link name="base"/><link name="slide"/><link name="torso"/><link name="s1"/><link name="s2"/>
  <link name="hand"/><link name="tip"/>
  <joint name="px" type="prismatic"><parent link="base"/><child link="slide"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.3 -0.2 0.5"/><axis xyz="1 0 0"/>
    <limit lower="-5" upper="5" effort="1" velocity="1"/></joint>
  <joint name="yaw" type="revolute"><parent link="slide"/><child link="torso"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="shoulder" type="revolute"><parent link="torso"/><child link="s1"/>
    <origin xyz="0.2 0 0.4" rpy="0 0.4 0"/><axis xyz="1 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="extend" type="prismatic"><parent link="s1"/><child link="s2"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0.2 -0.5 0.8"/>
    <limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="wrist" type="revolute"><parent link="s2"/><child link="hand"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="tip_fixed" type="fixed"><parent link="hand"/><child link="tip"/>
    <origin xyz="0.15 0 0" rpy="0 0 0"/></joint>
</robot>
"""


@pytest.fixture(scope="module")
def telescope():
    return Skeleton.from_urdf(TELESCOPE_URDF, joint_names=["slide", "torso", "hand", "tip"])


def test_dof_axes_are_the_motion_of_each_dof(telescope):
    # Closed form: moving one DOF by h moves a point below it by h (axis x (y - pivot)) (revolute) or
    # h axis (prismatic), to first order; checked by central differences of FK.
    theta = torch.tensor([[0.3, 0.4, -0.7, 0.25, 0.6]], dtype=torch.float64)
    axes, pivots = telescope.dof_axes(theta)
    x = telescope.fk(theta)[0]
    revolute = [False, True, True, False, True]
    h = 1e-6
    for d in range(5):
        step = torch.zeros_like(theta)
        step[0, d] = h
        fd = (telescope.fk(theta + step) - telescope.fk(theta - step))[0] / (2 * h)
        a, p = axes[0, d], pivots[0, d]
        pred = torch.linalg.cross(a.expand_as(x), x - p, dim=-1) if revolute[d] else a.expand_as(x)
        moved = fd.norm(dim=-1) > 0
        # 1e-7: pytorch-kinematics keeps the normalised URDF axes in float32 (|a|² = 1 +- 1e-8)
        torch.testing.assert_close(fd[moved], pred[moved], atol=1e-7, rtol=0)


@pytest.mark.parametrize("name", ["human", "f22", "telescope"])
def test_tree_jacobian_matches_autograd(name, request):
    skel = request.getfixturevalue(name)
    theta = _interior_poses(skel, 3, seed=1)
    # the telescope's non-unit axes are normalised in float32 by pytorch-kinematics: 1e-8 relative
    atol = 1e-7 if name == "telescope" else 1e-12
    torch.testing.assert_close(
        jacobian.tree_jacobian(skel, theta), jacobian.autograd_jacobian(skel, theta), atol=atol, rtol=0
    )


@pytest.mark.parametrize("fused", [True, False], ids=["fused-kernel", "eager"])
@pytest.mark.parametrize("name", ["human", "f22", "telescope"])
def test_articulated_body_solve_matches_dense_cholesky(name, fused, request, monkeypatch):
    # (JᵀWJ + diag(arm)) δ = JᵀW r + tau with random weights, frozen DOFs and right-hand side, by the fused
    # CPU kernel and by the eager tensor code
    if fused:
        pytest.importorskip("numba")
    monkeypatch.setenv("TORCHPF_FUSED", "1" if fused else "0")
    human = request.getfixturevalue(name)
    g = torch.Generator().manual_seed(2)
    theta = _interior_poses(human, 4, seed=2)
    J, D, B = len(human.joint_names), len(human.dof_names), 4
    ap, x = jacobian.dof_frames(human, theta)
    rel = x - x[:1]
    tree = human.tree
    tw = jacobian.twists(tree, ap, x[0])
    r = 0.01 * torch.randn(J, 3, B, generator=g, dtype=torch.float64)
    w = torch.rand(J, B, generator=g, dtype=torch.float64)
    tau = 1e-3 * torch.randn(D, B, generator=g, dtype=torch.float64)
    arm = torch.full((D, B), 1e-3, dtype=torch.float64)
    free = torch.rand(D, B, generator=g) > 0.2
    ours = aba.aba_solve(tree, tw, rel, w, r, tau, arm, free)
    Jac = jacobian.autograd_jacobian(human, theta)
    ref = aba.dense_solve(Jac, w.t(), r.permute(2, 0, 1), tau.t(), arm.t(), free.t()).t()
    torch.testing.assert_close(ours, ref, atol=1e-9, rtol=1e-7)
    assert torch.all(ours[~free] == 0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_exact_targets_recovered_below_a_millimetre(human, dtype):
    truth = _interior_poses(human, 24, seed=3, dtype=dtype)
    g = torch.Generator().manual_seed(4)
    init = human.clamp(truth + 0.05 * torch.randn(truth.shape, generator=g, dtype=torch.float64).to(dtype))
    res = ik.project(human, human.fk(truth), init, return_result=True)
    assert res.theta.dtype == dtype
    assert res.residual.max() < 1e-3  # metres, RMS over the 38 joints
    assert res.errors.max() < 2e-3
    assert human.within_limits(res.theta).all()


def _scipy_reference(skel, targets, theta_init, reg, weights):
    """Float64 bound-constrained least squares of the same objective (scipy trust-region reflective).

    The Jacobian is the tree Jacobian, itself checked against autograd above (the autograd one would make
    this ~30 s a pose on the 96-DOF skeleton).
    """
    D = len(skel.dof_names)
    lo, hi = skel.lower.numpy(), skel.upper.numpy()
    g, t0 = targets.numpy(), theta_init.numpy()
    sw = np.repeat(np.sqrt(weights.numpy()), 3)

    def fun(t):
        x = skel.fk(torch.from_numpy(t)).numpy()
        return np.concatenate([sw * (x - g).ravel(), np.sqrt(reg) * (t - t0)])

    def jac(t):
        Jm = jacobian.tree_jacobian(skel, torch.from_numpy(t)).reshape(-1, D).numpy()
        return np.concatenate([sw[:, None] * Jm, np.sqrt(reg) * np.eye(D)])

    sol = least_squares(
        fun, np.clip(t0, lo, hi), jac=jac, bounds=(lo, hi), method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-12
    )
    return torch.from_numpy(sol.x), 2 * sol.cost


def _kkt_violation(skel, theta, targets, theta_init, reg, weights):
    """Largest violation of the first-order (KKT) conditions, with the *autograd* Jacobian.

    Descent direction ``g = JᵀW r - μ (θ - θ_init)``: zero inside the limits, ``<= 0`` at a lower bound,
    ``>= 0`` at an upper bound.
    """
    Jm = jacobian.autograd_jacobian(skel, theta)  # (J, 3, D)
    r = targets - skel.fk(theta)
    g = torch.einsum("jkd,jk->d", Jm, weights[:, None] * r) - reg * (theta - theta_init)
    at_lo, at_hi = theta <= skel.lower + 1e-12, theta >= skel.upper - 1e-12
    viol = torch.where(at_lo, g.clamp(min=0), torch.where(at_hi, (-g).clamp(min=0), g.abs()))
    return viol.max().item()


@pytest.mark.parametrize("name", ["human", "f22"])
def test_noisy_targets_give_the_least_squares_pose(name, request):
    skel = request.getfixturevalue(name)
    g = torch.Generator().manual_seed(5)
    truth = _interior_poses(skel, 3, seed=6)
    # one pose pushed onto its limits so that bound constraints are active at the optimum
    truth[0] = torch.where(torch.rand(truth.shape[1], generator=g) < 0.3, skel.upper.clamp(max=1.0), truth[0])
    init = skel.clamp(truth + 0.03 * torch.randn(truth.shape, generator=g, dtype=torch.float64))
    J = len(skel.joint_names)
    targets = skel.fk(truth) + 0.01 * torch.randn(3, J, 3, generator=g, dtype=torch.float64)
    weights = 0.5 + torch.rand(J, generator=g, dtype=torch.float64)
    reg = 1e-4
    res = ik.project(
        skel, targets, init, weights, reg=reg, tol=1e-12, ftol=1e-15, iters=200, return_result=True
    )
    assert res.converged.all() and skel.within_limits(res.theta).all()
    for i in range(3):
        # a stationary point of the bound-constrained problem ...
        assert _kkt_violation(skel, res.theta[i], targets[i], init[i], reg, weights) < 1e-8
        # ... and the one the reference finds from the same start: same joints, no higher cost (scipy's
        # trust region can stop a little short near active bounds, so ours may be lower)
        ref_theta, ref_cost = _scipy_reference(skel, targets[i], init[i], reg, weights)
        assert res.cost[i] <= ref_cost * (1 + 1e-8)
        assert res.cost[i] >= ref_cost * (1 - 1e-3)
        torch.testing.assert_close(skel.fk(res.theta[i]), skel.fk(ref_theta), atol=1e-3, rtol=0)


def test_autograd_method_matches_tree_method(f22):
    truth = _interior_poses(f22, 4, seed=7)
    g = torch.Generator().manual_seed(8)
    targets = f22.fk(truth) + 0.01 * torch.randn(4, len(f22.joint_names), 3, generator=g, dtype=torch.float64)
    kw = {"tol": 1e-12, "ftol": 1e-15, "iters": 100}
    a = ik.project(f22, targets, truth, method="tree", **kw)
    b = ik.project(f22, targets, truth, method="autograd", **kw)
    torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


def test_gradients_do_not_leak_across_particles(human):
    truth = _interior_poses(human, 5, seed=9)
    g = torch.Generator().manual_seed(10)
    targets = human.fk(truth) + 0.01 * torch.randn(
        5, len(human.joint_names), 3, generator=g, dtype=torch.float64
    )
    targets.requires_grad_(True)
    init = truth.clone().requires_grad_(True)
    theta = ik.project(human, targets, init)
    theta[2].sum().backward()
    others = [0, 1, 3, 4]
    assert torch.all(targets.grad[others] == 0) and torch.all(init.grad[others] == 0)
    assert targets.grad[2].abs().sum() > 0


def test_implicit_derivative_matches_finite_differences_at_zero_residual(f22):
    # With targets on the manifold the Gauss-Newton implicit derivative is the exact one.
    theta0 = _interior_poses(f22, 1, seed=11, spread=0.5)
    targets = f22.fk(theta0).requires_grad_(True)
    kw = {"tol": 1e-13, "ftol": 0.0, "iters": 80}
    out = ik.project(f22, targets, theta0, **kw)
    v = torch.randn(targets.shape, generator=torch.Generator().manual_seed(12), dtype=torch.float64)
    (out * torch.linspace(-1, 1, out.shape[-1], dtype=torch.float64)).sum().backward()
    ad = (targets.grad * v).sum()
    eps = 1e-6
    with torch.no_grad():
        hi = ik.project(f22, targets + eps * v, theta0, **kw)
        lo = ik.project(f22, targets - eps * v, theta0, **kw)
    fd = ((hi - lo) / (2 * eps) * torch.linspace(-1, 1, out.shape[-1], dtype=torch.float64)).sum()
    torch.testing.assert_close(ad, fd, rtol=1e-4, atol=1e-6)


def test_frozen_dofs_and_zero_weights(human):
    truth = _interior_poses(human, 4, seed=13)
    init = human.clamp(truth + 0.05)
    free = ik.frozen_mask(human, ["Finger", "Thumb", "HandIndex"])
    targets = human.fk(truth)
    out = ik.project(human, targets, init, free=free)
    assert torch.equal(out[:, ~free], human.clamp(init)[:, ~free])
    # a joint with weight 0 does not pull: moving its target changes nothing
    w = torch.ones(len(human.joint_names), dtype=torch.float64)
    head = human.joint_names.index("Head_end")
    w[head] = 0
    moved = targets.clone()
    moved[:, head] += 0.5
    a = ik.project(human, targets, init, w, tol=1e-12, ftol=0.0, iters=60)
    b = ik.project(human, moved, init, w, tol=1e-12, ftol=0.0, iters=60)
    torch.testing.assert_close(a, b, atol=1e-9, rtol=0)


def test_broadcasting_limits_and_shapes(f22):
    D, J = len(f22.dof_names), len(f22.joint_names)
    theta = _interior_poses(f22, 1, seed=14, dtype=torch.float32)[0]
    far = f22.fk(theta) + torch.randn(2, 3, J, 3, generator=torch.Generator().manual_seed(15))
    res = ik.project(f22, far, theta, return_result=True)
    assert res.theta.shape == (2, 3, D) and res.converged.shape == (2, 3) and res.errors.shape == (2, 3, J)
    assert res.theta.dtype == torch.float32
    assert f22.within_limits(res.theta).all()  # far-off goals: the projection stays feasible
    with pytest.raises(ValueError):
        ik.project(f22, far[..., :2], theta)
    with pytest.raises(ValueError):
        ik.project(f22, far, theta[:-1])
    with pytest.raises(ValueError):
        ik.project(f22, far, theta, method="newton")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(human):
    truth = _interior_poses(human, 8, seed=16, dtype=torch.float32)
    targets = human.fk(truth) + 0.01
    cpu = ik.project(human, targets, truth)
    on_gpu = Skeleton.from_urdf(path("human.urdf")).to("cuda")  # own copy: the fixture stays on the CPU
    gpu = ik.project(on_gpu, targets.cuda(), truth.cuda())
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-3, rtol=0)
