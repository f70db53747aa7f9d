"""Image cues against raster references: dual coverage, overlap IoU, skin markers, random model
points, low-resolution masks."""

import cv2
import numpy as np
import pytest
import torch

from torchpf.geometry import capsule_masks, project_capsules
from torchpf.likelihoods import (
    DualSilhouetteLikelihood,
    OverlapLikelihood,
    SilhouetteLikelihood,
    SkinBlobLikelihood,
)
from torchpf.observations import DistanceMaps, Silhouettes
from torchpf.synth import synthesize

from .cases import H, W, assert_peak, sweep


def test_dual_matches_raster_coverage(skel, truth, rig, frame):
    lik = DualSilhouetteLikelihood(skel, rig, n_samples=64)
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=5)
    D = lik.distances(thetas, frame)
    pts, ok = frame.silhouettes.foreground_samples(64)
    ends, radii = skel.capsules(thetas)
    for v, cam in enumerate(rig.values()):
        caps = project_capsules(cam, ends[..., 0, :], ends[..., 1, :], radii)
        masks = capsule_masks(caps, H, W)  # exact hull raster as reference
        u, vv = pts[v, :, 0].long(), pts[v, :, 1].long()
        ref = 1.0 - masks[:, vv, u].double().mean(-1)
        np.testing.assert_allclose(D[:, v].numpy(), ref.numpy(), atol=2 / 64)


def test_overlap_ratio_matches_raster_iou(skel, truth, rig, frame):
    lik = OverlapLikelihood(skel, rig, n_body=24, n_cap=4)
    thetas, _ = sweep(truth, skel, "Hips_Xposition", half=0.1, n=5)
    ratios = lik.ratios(thetas, frame)
    assert ratios.shape == (5, 3)
    ends, radii = skel.capsules(thetas)
    for v, cam in enumerate(rig.values()):
        model = capsule_masks(project_capsules(cam, ends[..., 0, :], ends[..., 1, :], radii), H, W)
        obs = frame.silhouettes.masks[v] > 0.5
        iou = (model & obs).sum((-1, -2)) / (model | obs).sum((-1, -2))
        # A sampling estimate (union area from 16 points per capsule, nearest look-ups): a few % low.
        np.testing.assert_allclose(ratios[:, v].numpy(), iou.numpy(), atol=0.08)
    assert float(ratios[2].min()) > 0.8


def test_skin_markers(skel, truth, rig):
    lik = SkinBlobLikelihood(skel, rig)
    J = skel.fk(truth)
    idx = {n: skel.joint_names.index(n) for n in ("Head", "Head_end", "LeftHand", "RightHand")}
    expected = torch.stack(
        [(J[idx["Head"]] + J[idx["Head_end"]]) / 2, J[idx["LeftHand"]], J[idx["RightHand"]]]
    )
    torch.testing.assert_close(lik.markers(truth), expected)
    one = SkinBlobLikelihood(skel, rig, markers=["LeftHand"], sigma=2.0)
    dist = DistanceMaps(torch.full((3, H, W), 4.0))
    assert one(truth[None], dist).item() == pytest.approx(-3 * 16 / 8)
    with pytest.raises(ValueError, match="markers"):
        SkinBlobLikelihood(type("S", (), {"joint_names": ["a"]})(), rig)


def test_random_model_points_with_generator(skel, truth, rig, frame):
    thetas, centre = sweep(truth, skel, "LeftArm_Yrotation")
    a = SilhouetteLikelihood(skel, rig, generator=torch.Generator().manual_seed(3))(thetas, frame)
    b = SilhouetteLikelihood(skel, rig, generator=torch.Generator().manual_seed(3))(thetas, frame)
    torch.testing.assert_close(a, b)
    lik = SilhouetteLikelihood(skel, rig, generator=torch.Generator().manual_seed(3), n_body=32)
    assert not torch.equal(lik(thetas, frame), lik(thetas, frame))  # fresh points on each call
    vals = lik(thetas, frame)  # noisy: each particle gets its own points
    assert vals[centre] > vals[0] + 0.2 and vals[centre] > vals[-1] + 0.2


def test_low_resolution_masks(skel, truth, rig):
    # Cameras at 160x120 scored on 80x60 masks: pixel coordinates are rescaled, the peak stays (within one
    # 0.05 rad step: a 1.5 cm hand motion is a third of a mask pixel here).
    small = [
        cv2.resize(m, (80, 60), interpolation=cv2.INTER_AREA)
        for m in synthesize(skel, truth[None], rig).masks[0]
    ]
    obs = Silhouettes(np.stack(small))
    thetas, centre = sweep(truth, skel, "LeftArm_Yrotation")
    for lik in (
        SilhouetteLikelihood(skel, rig),
        DualSilhouetteLikelihood(skel, rig),
        OverlapLikelihood(skel, rig),
    ):
        assert_peak(lik(thetas, obs), centre, steps=1)
