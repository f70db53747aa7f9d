"""Synthetic sequences: rendered masks against the projected model, depth points on the visible skin, noise
options."""

import numpy as np
import pytest
import torch

from torchpf.geometry import capsule_distance, capsule_masks, project_capsules
from torchpf.observations import Frame
from torchpf.sensors import depth_to_points
from torchpf.synth import SynthOptions, render_depth, render_silhouette, synthesize

W, H = 160, 120


@pytest.fixture(scope="module")
def skel(human):
    return human


@pytest.fixture(scope="module")
def motion(skel):
    names = skel.dof_names
    T = 4
    m = torch.zeros(T, len(names), dtype=torch.float64)
    m[:, names.index("Hips_Yposition")] = 1.0
    m[:, names.index("Hips_Xposition")] = torch.linspace(0, 0.3, T, dtype=torch.float64)
    m[:, names.index("LeftArm_Yrotation")] = torch.linspace(0.2, 0.8, T, dtype=torch.float64)
    m[:, names.index("RightUpLeg_Xrotation")] = torch.linspace(0.0, -0.4, T, dtype=torch.float64)
    return m


@pytest.fixture(scope="module")
def clean(skel, motion, rig, depth_cam):
    return synthesize(skel, motion, rig, depth_camera=depth_cam, seed=0)


def test_masks_match_projected_capsules(skel, motion, rig, clean):
    ends, radii = skel.capsules(motion)
    for t in range(len(motion)):
        for v, cam in enumerate(rig.values()):
            mask = clean.masks[t][v] > 0
            model = capsule_masks(project_capsules(cam, ends[t, :, 0], ends[t, :, 1], radii), H, W).numpy()
            # Ray casting is exact perspective; the projected-disc model differs by a few boundary pixels.
            assert (mask ^ model).sum() <= 0.02 * mask.sum()
            assert mask.sum() > 300


def test_depth_points_are_visible_skin(skel, motion, depth_cam, clean):
    ends, radii = skel.capsules(motion)
    for t in range(len(motion)):
        pts = torch.from_numpy(clean.points[t]).double()
        a, b = ends[t, :, 0], ends[t, :, 1]
        assert len(pts) > 300
        d = capsule_distance(pts, a, b, radii)
        np.testing.assert_allclose(d.numpy(), 0.0, atol=1e-5)
        # Self-occlusion: the segment from the sensor to each point stays outside the body until the point.
        c = depth_cam.center
        s = torch.linspace(0.0, 0.98, 50, dtype=torch.float64)
        seg = c + s[:, None, None] * (pts - c)  # (S, K, 3)
        inside = capsule_distance(seg.reshape(-1, 3), a, b, radii).reshape(50, -1)
        far = (1 - s)[:, None] * (pts - c).norm(dim=-1) > 2e-3
        assert bool((inside[far] > -1e-6).all())


def test_render_depth_agrees_with_points(skel, motion, depth_cam, clean):
    depth = render_depth(skel, motion[0], depth_cam).numpy()
    pts = depth_to_points(depth, depth_cam, min_depth=0.1)
    assert len(pts) == len(clean.points[0])
    order = lambda p: p[np.lexsort(p.T)]  # noqa: E731
    np.testing.assert_allclose(order(pts.numpy()), order(clean.points[0]), atol=1e-4)
    sil = render_silhouette(skel, motion[0], depth_cam)
    assert int(sil.sum()) == len(pts)


def test_keypoints_project_joints(skel, motion, rig, clean):
    assert clean.keypoints.shape == (len(motion), 3, len(skel.joint_names), 2)
    joints = skel.fk(motion[2])
    for v, cam in enumerate(rig.values()):
        np.testing.assert_allclose(clean.keypoints[2, v], cam.project(joints).numpy(), atol=1e-4)


def test_noise_options(skel, motion, rig, depth_cam, clean):
    opts = SynthOptions(
        speckle=0.02,
        morph_px=1,
        missing_frames=0.3,
        occluders=1,
        occluder_size=0.3,
        depth_noise=0.01,
        outliers=0.1,
        n_points=500,
        keypoint_noise=1.0,
        keypoint_dropout=0.2,
    )
    noisy = synthesize(skel, motion, rig, depth_camera=depth_cam, options=opts, seed=1)
    again = synthesize(skel, motion, rig, depth_camera=depth_cam, options=opts, seed=1)
    missing = [m is None for row in noisy.masks for m in row]
    assert any(missing) and not all(missing)
    for row_n, row_a in zip(noisy.masks, again.masks, strict=True):
        for m, n in zip(row_n, row_a, strict=True):
            assert (m is None and n is None) or np.array_equal(m, n)
    flips = []
    for t, row in enumerate(noisy.masks):
        for v, m in enumerate(row):
            if m is None:
                assert np.isnan(noisy.keypoints[t, v]).all()
                continue
            flips.append(((m > 0) != (clean.masks[t][v] > 0)).mean())
    assert 0.015 < np.median(flips) < 0.2
    assert np.isnan(noisy.keypoints).any() and np.isfinite(noisy.keypoints).any()
    for pts in noisy.points:
        assert len(pts) <= 500
    ends, radii = skel.capsules(motion[0])
    d = capsule_distance(torch.from_numpy(noisy.points[0]).double(), ends[:, 0], ends[:, 1], radii).abs()
    assert 0.005 < float(d.median()) < 0.03  # 1 cm depth noise
    assert float((d > 0.1).float().mean()) > 0.03  # outliers
    frame = noisy.frame(0)
    assert isinstance(frame, Frame) and frame.points.points.shape[1] == 3


def test_occluder_hides_body_in_masks(skel, motion, rig):
    seq = synthesize(skel, motion[:1], rig, options=SynthOptions(occluders=1, occluder_size=0.5), seed=3)
    clean = synthesize(skel, motion[:1], rig, seed=3)
    lost = sum(((c > 0) & ~(m > 0)).sum() for c, m in zip(clean.masks[0], seq.masks[0], strict=True))
    gained = sum((~(c > 0) & (m > 0)).sum() for c, m in zip(clean.masks[0], seq.masks[0], strict=True))
    assert lost > 0 and gained == 0


def test_bad_motion_shape(skel, rig):
    with pytest.raises(ValueError, match="motion"):
        synthesize(skel, torch.zeros(3, 5), rig)
