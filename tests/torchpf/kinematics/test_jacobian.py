"""Tree Jacobian: the DOF axes are the motion of each DOF (finite differences), the tree Jacobian equals the
autograd one."""

import pytest
import torch

from torchpf.kinematics import jacobian


def test_dof_axes_are_the_motion_of_each_dof(telescope):
    # Closed form: moving one DOF by h moves a point below it by h (axis x (y - pivot)) (revolute) or
    # h axis (prismatic), to first order; checked by central differences of FK.
    theta = torch.tensor([[0.3, 0.4, -0.7, 0.25, 0.6]], dtype=torch.float64)
    axes, pivots = telescope.dof_axes(theta)
    x = telescope.fk(theta)[0]
    revolute = telescope.dof_revolute.tolist()
    assert revolute == [False, True, True, False, True]  # px, yaw, shoulder, extend, wrist
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
def test_tree_jacobian_matches_autograd(name, request, interior_poses):
    skel = request.getfixturevalue(name)
    theta = interior_poses(skel, 3, seed=1)
    # the telescope's non-unit axes are normalised in float32 by pytorch-kinematics: 1e-8 relative
    atol = 1e-7 if name == "telescope" else 1e-12
    torch.testing.assert_close(
        jacobian.tree_jacobian(skel, theta), jacobian.autograd_jacobian(skel, theta), atol=atol, rtol=0
    )


@pytest.mark.parametrize("name", ["human", "f22", "telescope"])
def test_pose_gradient_is_the_vector_jacobian_product(name, request, interior_poses):
    skel = request.getfixturevalue(name)
    theta = interior_poses(skel, 3, seed=2)
    g = torch.randn(
        3, len(skel.joint_names), 3, generator=torch.Generator().manual_seed(0), dtype=theta.dtype
    )
    ap, joints = jacobian.dof_frames(skel, theta)
    got = jacobian.pose_gradient(skel.tree, ap, joints, g.permute(1, 2, 0)).t()
    want = torch.einsum("bjk,bjkd->bd", g, jacobian.autograd_jacobian(skel, theta))
    atol = 1e-7 if name == "telescope" else 1e-12
    torch.testing.assert_close(got, want, atol=atol * float(g.abs().sum()), rtol=0)
