"""IK projection (Hauberg eq. 7): recovery of exact targets, least-squares optimum against scipy's
bound-constrained solver in float64, the autograd method, gradients, frozen DOFs, shapes and limits."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares

from torchpf import Skeleton, ik
from torchpf.assets import path
from torchpf.kinematics import jacobian


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_exact_targets_recovered_below_a_millimetre(human, dtype, interior_poses):
    truth = interior_poses(human, 24, seed=3, dtype=dtype)
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
def test_noisy_targets_give_the_least_squares_pose(name, request, interior_poses):
    skel = request.getfixturevalue(name)
    g = torch.Generator().manual_seed(5)
    truth = interior_poses(skel, 3, seed=6)
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


def test_autograd_method_matches_tree_method(f22, interior_poses):
    truth = interior_poses(f22, 4, seed=7)
    g = torch.Generator().manual_seed(8)
    targets = f22.fk(truth) + 0.01 * torch.randn(4, len(f22.joint_names), 3, generator=g, dtype=torch.float64)
    kw = {"tol": 1e-12, "ftol": 1e-15, "iters": 100}
    a = ik.project(f22, targets, truth, method="tree", **kw)
    b = ik.project(f22, targets, truth, method="autograd", **kw)
    torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


def test_gradients_do_not_leak_across_particles(human, interior_poses):
    truth = interior_poses(human, 5, seed=9)
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


def test_implicit_derivative_matches_finite_differences_at_zero_residual(f22, interior_poses):
    # With targets on the manifold the Gauss-Newton implicit derivative is the exact one.
    theta0 = interior_poses(f22, 1, seed=11, spread=0.5)
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


def test_frozen_dofs_and_zero_weights(human, interior_poses):
    truth = interior_poses(human, 4, seed=13)
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


def test_broadcasting_limits_and_shapes(f22, interior_poses):
    D, J = len(f22.dof_names), len(f22.joint_names)
    theta = interior_poses(f22, 1, seed=14, dtype=torch.float32)[0]
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


def test_device_and_dtype_match_the_cpu(human, interior_poses, device, dtype):
    truth = interior_poses(human, 8, seed=16, dtype=torch.float64)
    targets = human.fk(truth) + 0.01
    cpu = ik.project(human, targets, truth)
    moved = Skeleton.from_urdf(path("human.urdf")).to(device)  # own copy: the fixture stays on the CPU
    out = ik.project(moved, targets.to(device, dtype), truth.to(device, dtype))
    assert out.device.type == device.type and out.dtype == dtype
    torch.testing.assert_close(out.cpu().double(), cpu, atol=1e-3, rtol=0)
