"""Articulated-body solve: the fused numba kernel and the eager tensor recursion against a dense Cholesky
solve of the same Gauss-Newton system."""

import pytest
import torch

from torchpf.kinematics import aba, jacobian


@pytest.mark.parametrize("fused", [True, False], ids=["fused-kernel", "eager"])
@pytest.mark.parametrize("name", ["human", "f22", "telescope"])
def test_articulated_body_solve_matches_dense_cholesky(name, fused, request, monkeypatch, interior_poses):
    # (JᵀWJ + diag(arm)) δ = JᵀW r + tau with random weights, frozen DOFs and right-hand side, by the fused
    # CPU kernel and by the eager tensor code
    if fused:
        pytest.importorskip("numba")
    monkeypatch.setenv("TORCHPF_FUSED", "1" if fused else "0")
    human = request.getfixturevalue(name)
    g = torch.Generator().manual_seed(2)
    theta = interior_poses(human, 4, seed=2)
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
