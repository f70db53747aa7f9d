"""Likelihoods and cameras that learn: scale parameters as buffers or ``nn.Parameter`` s, cameras shared by
reference, and a sigma and a focal length fitted by maximising the log-evidence (``run(..., grad=True)``)."""

import pytest
import torch
from torch import nn

from torchpf.camera import CameraRig, camera_ring
from torchpf.filters import ParticleFilter
from torchpf.likelihoods import (
    Keypoints2DLikelihood,
    OverlapLikelihood,
    ProductLikelihood,
    SilhouetteLikelihood,
)
from torchpf.observations import Keypoints2D
from torchpf.proposals import GaussianRandomWalk
from torchpf.tracker import Tracker

from .cases import make_liks, sweep


def test_scales_are_buffers_unless_learnable(skel, truth, rig, depth_cam, frame):
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=3)
    for name, lik in make_liks(skel, rig, depth_cam).items():
        assert list(lik.parameters()) == [], name
        scale = lik.scales[0]
        assert isinstance(getattr(lik, scale), torch.Tensor) and scale in dict(lik.named_buffers()), name
        learnable = type(lik)(skel, *([rig] if lik.needs_cameras else []), learnable=True)
        assert [n for n, _ in learnable.named_parameters()] == [scale], name
    sil = SilhouetteLikelihood(skel, rig, sigma=0.1, learnable=["sigma"])
    sil(thetas, frame).sum().backward()
    assert float(sil.sigma.grad) != 0
    with pytest.raises(ValueError, match="learnable"):
        SilhouetteLikelihood(skel, rig, learnable=["beta"])
    assert [n for n, _ in OverlapLikelihood(skel, rig, learnable=True).named_parameters()] == ["beta"]
    prod = ProductLikelihood(
        {"a": sil, "b": SilhouetteLikelihood(skel, rig)}, {"a": 1.0, "b": 0.0}, learnable=True
    )
    prod(thetas, frame).sum().backward()
    assert prod.term_weights.grad.shape == (2,) and float(prod.weights["b"].detach()) == 0.0


def test_a_rig_is_shared_and_its_edits_take_effect(skel, truth, frame):
    rig = camera_ring(3, radius=4.0, height=1.5, target=(0, 0, 0.8), width=160, height_px=120)
    lik = SilhouetteLikelihood(skel, rig)
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=3)
    before = lik(thetas, frame)
    assert lik.cameras is rig
    rig["cam1"].K[0, 0] *= 1.5  # a Camera from a rig views the rig's tensors
    assert not torch.allclose(lik(thetas, frame), before)
    tracker = Tracker(
        skel, CameraRig(rig, learnable=["K", "R"]), likelihood="silhouette", fps=15.0, progress=False
    )
    assert {n.split(".")[-1] for n, _ in tracker.named_parameters()} == {"K", "rotation_update"}


def test_learns_a_sigma_and_a_focal_length_from_the_log_evidence(skel, truth, rig):
    """Keypoints of a sequence drawn from the filter's own random walk, seen by three cameras with 2 px of
    noise; the likelihood starts at sigma = 4 px and the cameras at 0.8 times their focal length. Adam on
    ``-log p_hat(z_{1:T})`` (fixed random numbers each step) recovers both within 10 %."""
    g = torch.Generator().manual_seed(1)
    D = len(skel.dof_names)
    moving = [
        i
        for i, n in enumerate(skel.dof_names)
        if n.split("_")[0] in ("LeftArm", "LeftForeArm", "RightArm", "RightForeArm", "LeftUpLeg", "LeftLeg")
    ]
    std = torch.zeros(D, dtype=torch.float64)
    std[moving] = 0.03
    start = truth
    walk = GaussianRandomWalk(std)
    angles = [start[None]]
    for _ in range(11):
        angles.append(walk.sample(angles[-1], g))
    angles = torch.cat(angles)  # (T, D)
    joints = ["Head", "LeftHand", "RightHand", "LeftFoot", "RightFoot", "LeftForeArm", "RightForeArm"]
    joints += ["LeftLeg", "RightLeg", "Hips", "LeftArm", "RightArm", "LeftUpLeg", "RightUpLeg"]
    cams = rig
    noise = 2.0
    uv = cams.project(skel.fk(angles)[:, [skel.joint_names.index(j) for j in joints]]).transpose(1, 2)
    observations = [Keypoints2D(u) for u in uv + noise * torch.randn(uv.shape, generator=g, dtype=uv.dtype)]

    fitted = CameraRig(cams, learnable=["K"])
    with torch.no_grad():
        fitted.K[:, :2, :2] *= 0.8
    focal = torch.zeros(3, 3, dtype=torch.float64)
    focal[0, 0] = focal[1, 1] = 1.0
    fitted.K.register_hook(lambda grad: grad * focal)  # fit the focal lengths only
    lik = Keypoints2DLikelihood(skel, fitted, joints=joints, sigma=2 * noise, learnable=True)
    pf = ParticleFilter(walk, lik, n_particles=100, progress=False)
    assert isinstance(lik.sigma, nn.Parameter)
    opt = torch.optim.Adam([{"params": [fitted.K], "lr": 2.0}, {"params": [lik.sigma], "lr": 0.1}])
    sched = torch.optim.lr_scheduler.StepLR(opt, 20, 0.3)
    for _ in range(45):
        opt.zero_grad()
        track = pf.run(observations, start[None].expand(100, D), generator=0, grad=True)
        (-track.log_evidence).backward()
        opt.step()
        sched.step()
    torch.testing.assert_close(fitted.K.detach()[:, :2, :2], cams.K[:, :2, :2], rtol=0.1, atol=0)
    sigma = float(lik.sigma.detach())
    assert abs(sigma / noise - 1) < 0.1, sigma
    assert pf.run(observations, start[None].expand(100, D), generator=0).log_evidence.grad_fn is None
