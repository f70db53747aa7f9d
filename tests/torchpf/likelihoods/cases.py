"""Shared helpers of the likelihood tests: pose sweeps, peak checks and one instance of every cue."""

import torch

from torchpf.likelihoods import (
    ChamferLikelihood,
    DualSilhouetteLikelihood,
    Keypoints2DLikelihood,
    OverlapLikelihood,
    PointCloudLikelihood,
    SilhouetteDistanceLikelihood,
    SilhouetteLikelihood,
    SkinBlobLikelihood,
)

W, H = 160, 120


def sweep(truth, skel, dof, half=0.4, n=17):
    j = skel.dof_names.index(dof)
    thetas = truth.repeat(n, 1)
    thetas[:, j] += torch.linspace(-half, half, n, dtype=torch.float64)
    return thetas, n // 2


def assert_peak(values, centre, margin=1e-6, steps=0):
    """The maximum is at the truth (or within ``steps`` sweep steps of it) and both ends are clearly lower."""
    v = values.detach()
    assert torch.isfinite(v).all()
    best = v[max(0, centre - steps) : centre + steps + 1].max()
    assert best >= v.max() - 1e-9, f"peak at {int(v.argmax())}, truth at {centre}: {v.tolist()}"
    assert v[0] < v[centre] - margin and v[-1] < v[centre] - margin


# One-sided, hard-count cues may peak one sweep step (0.05 rad, ~0.5 px of hand motion at 160x120) off:
# the renderer's exact perspective silhouettes exceed the projected-capsule model by 2-3 boundary pixels, and
# the dual cue rewards a pose that covers one of them.
STEP_TOLERANCE = {"dual": 1, "dual_soft": 1}


def make_liks(skel, rig, depth_cam):
    return {
        "pointcloud": PointCloudLikelihood(skel, sigma=0.02),
        "pointcloud_half": PointCloudLikelihood(skel, sigma=0.02, view_point=depth_cam),
        "silhouette": SilhouetteLikelihood(skel, rig),
        "silhouette_union": SilhouetteLikelihood(skel, rig, union=True),
        "dual": DualSilhouetteLikelihood(skel, rig),
        "dual_soft": DualSilhouetteLikelihood(skel, rig, softness=1.0),
        "silhouette_distance": SilhouetteDistanceLikelihood(skel, rig),
        "overlap": OverlapLikelihood(skel, rig),
        "keypoints": Keypoints2DLikelihood(skel, rig),
        "keypoints_t": Keypoints2DLikelihood(skel, rig, noise="student"),
        "skin": SkinBlobLikelihood(skel, rig),
        "chamfer": ChamferLikelihood(skel, rig),
    }
