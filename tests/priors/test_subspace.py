"""Refinement on an action's manifold: the aSpace as the refiner's coordinates
(`priors.action.ActionSubspace`), the choice of which poses move in it (`manifold_choice`), and the hybrid
filter that uses it.

References are independent of the code under test: autograd's vector-Jacobian product of `decode` for the
pullback, and the closed-form least-squares point of an affine subspace for the refined optimum.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from priors.action import ActionConstrained, ActionProposal, ActionSubspace, manifold_choice
from priors.bank import ActionBank
from priors.motion import AngularRandomWalk
from torchpf.filters import HybridParticleFilter
from torchpf.refine import Refiner, RefineSpace

from .test_action import NAMES, near_mean_poses, tiny_model

D = len(NAMES)


def fake_skeleton(limit: float = 10.0):
    """What the refiner reads of a skeleton: limits, joint types, clamp. Limits wide enough never to bind."""
    lower = torch.full((D,), -limit, dtype=torch.float64)
    upper = torch.full((D,), limit, dtype=torch.float64)
    revolute = torch.tensor([False, True, True, True, True])

    def clamp(x):
        return torch.maximum(torch.minimum(x, upper.to(x)), lower.to(x))

    return SimpleNamespace(lower=lower, upper=upper, dof_revolute=revolute, clamp=clamp, dof_names=NAMES)


class QuadraticCue(torch.nn.Module):
    """``log p = -½ Σ_d w_d (x_d - target_d)²`` with a closed-form optimum on any affine subspace."""

    def __init__(self, target: torch.Tensor, weight: torch.Tensor | None = None):
        super().__init__()
        self.target = target
        self.weight = torch.ones(D, dtype=torch.float64) if weight is None else weight

    def forward(self, x, obs=None):
        return -0.5 * (self.weight * (x - self.target).square()).sum(-1)


def test_log_soft_prior_is_the_log_of_the_soft_prior_and_stays_finite_far_away():
    model = tiny_model()
    near = near_mean_poses(model, 50, spread=0.1)
    torch.testing.assert_close(
        model.log_soft_accept_probability(near), model.soft_accept_probability(near).log()
    )
    # float32, where exp() underflows below about -100: postures a quarter turn off the mean performance
    far = near.float()
    far[:, 2] += 1.5
    far[:, 3] -= 1.5
    far.requires_grad_(True)
    log_soft = model.log_soft_accept_probability(far)
    (grad,) = torch.autograd.grad(log_soft.sum(), far)
    assert torch.isfinite(log_soft).all() and torch.isfinite(grad).all()
    assert (grad.abs().sum(-1) > 0).all()  # still pointing back to the action
    assert (model.soft_accept_probability(far.detach()) == 0).all()
    assert (log_soft < -100).all()


def test_decode_puts_the_pca_reconstruction_on_the_posture_and_keeps_the_rest():
    model = tiny_model()
    g = torch.Generator().manual_seed(0)
    x = near_mean_poses(model, 6, spread=0.3) + 0.2 * torch.randn(6, D, generator=g, dtype=torch.float64)
    choice = torch.tensor([0, 0, -1, 0, -1, 0])
    space = ActionSubspace([model], choice)
    assert isinstance(space, RefineSpace)
    y = space.encode(x)
    assert y.shape == (6, D + model.n_components)
    out = space.decode(y)
    posture = model.posture_index
    on = choice >= 0
    torch.testing.assert_close(out[~on], x[~on], rtol=0, atol=0)  # not chosen: the pose as it was
    rest = [i for i in range(D) if i not in posture.tolist()]
    torch.testing.assert_close(out[:, rest], x[:, rest], rtol=0, atol=0)
    # on the manifold: the posture is mu + c U (Brubaker eq. 14) up to 2 pi, on the branch nearest x's own
    recon = model.pca_mean + model.project(x[on]) @ model.components
    diff = out[on][:, posture] - recon
    torch.testing.assert_close(torch.remainder(diff + math.pi, 2 * math.pi) - math.pi, torch.zeros_like(diff))
    assert ((out[on][:, posture] - x[on][:, posture]).abs() <= math.pi + 1e-12).all()
    # and decoding is idempotent: a decoded pose encodes to itself
    torch.testing.assert_close(space.decode(space.encode(out)), out)


def test_pullback_is_the_vector_jacobian_product_of_decode():
    walk = tiny_model()
    other = tiny_model(
        components=torch.eye(3, dtype=torch.float64)[[0, 2]], action="other", std=walk.std, delta=walk.delta
    )
    x = near_mean_poses(walk, 5, spread=0.2)
    space = ActionSubspace([walk, other], torch.tensor([0, 1, -1, 1, 0]))
    y = space.encode(x)
    grad_x = torch.randn(5, D, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    _, reference = torch.autograd.functional.vjp(space.decode, y, grad_x)
    torch.testing.assert_close(space.pullback(y, grad_x), reference)
    lr = torch.tensor([0.01, 0.03, 0.03, 0.02, 0.0], dtype=torch.float64)
    steps = space.step_sizes(lr)
    torch.testing.assert_close(steps, torch.cat([lr, torch.full((4,), 0.03, dtype=torch.float64)]))


def test_manifold_choice_picks_the_best_model_within_the_radius():
    walk = tiny_model()
    shifted = tiny_model(pca_mean=[1.2, 0.9, 3.0], center=[1.2, 0.9, 3.0], action="shifted")
    near_walk = near_mean_poses(walk, 20, spread=0.05, seed=1)
    near_shifted = near_mean_poses(shifted, 20, spread=0.05, seed=2)
    far = near_walk.clone()
    far[:, 2] += 1.5  # a quarter turn off: far from both actions' mean postures
    far[:, 3] -= 1.5
    x = torch.cat([near_walk, near_shifted, far])
    choice = manifold_choice([walk, shifted], x, radius=4.0)
    assert (choice[:20] == 0).all() and (choice[20:40] == 1).all() and (choice[40:] == -1).all()
    assert (manifold_choice([walk, shifted], x, radius=None) == -1).all()
    # the threshold is -r^2 / 2 on the log soft prior
    score = walk.log_soft_accept_probability(near_walk)
    r = float((-2 * score.min()).sqrt()) * 0.99
    assert (manifold_choice([walk], near_walk, radius=r) == -1).any()


def test_refining_in_the_aspace_reaches_the_least_squares_point_of_the_subspace():
    """A quadratic cue's optimum restricted to ``{x : x_p = mu + c U}`` is the projection of its target:
    ``c* = U (t_p - mu)``, the other DOFs at the target. Without a space the refiner reaches the target."""
    model = tiny_model()
    skel = fake_skeleton()
    g = torch.Generator().manual_seed(2)
    target = near_mean_poses(model, 1, spread=0.1, seed=3)[0]
    target[model.posture_index] += 0.1 * torch.randn(3, generator=g, dtype=torch.float64)  # off the subspace
    start = target + 0.2 * torch.randn(4, D, generator=g, dtype=torch.float64)
    refiner = Refiner(
        skel, cue=QuadraticCue(target), steps=400, lr_rotation=0.02, lr_translation=0.02
    ).double()
    space = ActionSubspace([model], torch.zeros(4, dtype=torch.long))
    on = refiner(start, None, space=space).x
    c_star = (target[model.posture_index] - model.pca_mean) @ model.components.T
    expected = target.clone()
    expected[model.posture_index] = model.pca_mean + c_star @ model.components
    torch.testing.assert_close(on, expected.expand_as(on), atol=2e-3, rtol=0)
    free = refiner(start, None).x
    torch.testing.assert_close(free, target.expand_as(free), atol=2e-3, rtol=0)
    # a space that chooses no model for any pose is the plain refinement (the limits never bind here)
    none = refiner(start, None, space=ActionSubspace([model], torch.full((4,), -1)))
    torch.testing.assert_close(none.x, refiner(start, None).x)


@pytest.mark.parametrize("prior", ["constrained", "bank", "proposal"])
def test_the_hybrid_refines_on_the_manifold_of_its_action_prior(prior):
    """In "recentre" mode the estimate of a frame whose particles perform the action is a posture of the
    action's subspace, and the set follows it; ``refine_space=False`` leaves it off the subspace."""
    model = tiny_model()
    skel = fake_skeleton()
    g = torch.Generator().manual_seed(4)
    target = near_mean_poses(model, 1, spread=0.05, seed=5)[0]
    target[model.posture_index] += 0.03 * torch.randn(3, generator=g, dtype=torch.float64)
    walk = AngularRandomWalk(torch.full((D,), 0.01, dtype=torch.float64))
    proposal = None
    if prior == "bank":
        other = tiny_model(pca_mean=[2.2, 1.9, 3.0], center=[2.2, 1.9, 3.0], action="other")
        dynamics = ActionBank([model, other], walk, mode="soft")
    elif prior == "proposal":
        dynamics, proposal = walk, ActionProposal(model, walk)
    else:
        dynamics = ActionConstrained(model, walk, mode="soft")
    cue = QuadraticCue(target, weight=torch.full((D,), 400.0, dtype=torch.float64))
    x0 = near_mean_poses(model, 64, spread=0.02, seed=6)

    def run(**kw):
        refiner = Refiner(skel, cue=cue, steps=60, lr_rotation=0.01, lr_translation=0.01).double()
        f = HybridParticleFilter(
            dynamics,
            cue,
            proposal,
            refiner=refiner,
            n_particles=64,
            betas=(0.5, 1.0),
            diffusion_std=0.01,
            **kw,
        )
        return f.step(f.init(x0), None, torch.Generator().manual_seed(7))

    out = run()
    est = out.info["estimate"]
    assert float(out.info["refine_on_manifold"]) == 1.0
    recon = model.pca_mean + model.project(est) @ model.components
    torch.testing.assert_close(est[model.posture_index], recon, atol=1e-9, rtol=0)
    torch.testing.assert_close(out.mean(), est)  # the set followed its estimate
    free = run(refine_space=False)
    assert "refine_on_manifold" not in free.info
    off = free.info["estimate"][model.posture_index] - (
        model.pca_mean + model.project(free.info["estimate"]) @ model.components
    )
    assert off.abs().max() > 1e-3  # the free refinement goes after the target's off-subspace part


def test_the_space_follows_the_poses_device(device):
    """One device rule: the model's buffers stay where they are; coordinates, poses and gradients live on
    the poses' device and agree with the CPU's."""
    model = tiny_model()
    x = near_mean_poses(model, 4, spread=0.2)
    grad = torch.randn(4, D, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    lr = torch.full((D,), 0.02, dtype=torch.float64)
    cpu = ActionSubspace.around([model], x, 4.0)
    dev = ActionSubspace.around([model], x.to(device), 4.0)
    y = dev.encode(x.to(device))
    for name, got, want in [
        ("choice", dev.choice, cpu.choice),
        ("encode", y, cpu.encode(x)),
        ("decode", dev.decode(y), cpu.decode(cpu.encode(x))),
        ("pullback", dev.pullback(y, grad.to(device)), cpu.pullback(cpu.encode(x), grad)),
        ("step_sizes", dev.step_sizes(lr.to(device)), cpu.step_sizes(lr)),
    ]:
        assert got.device.type == device.type, name
        torch.testing.assert_close(got.cpu(), want, msg=name)
