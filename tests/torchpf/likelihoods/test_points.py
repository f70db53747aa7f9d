"""Point-cloud cue against Hauberg eq. 15 computed directly."""

import torch

from torchpf.geometry import capsule_distance
from torchpf.likelihoods import (
    PointCloudLikelihood,
)
from torchpf.observations import PointCloud

from .cases import sweep


def test_pointcloud_matches_equation_15(skel, truth, frame):
    lik = PointCloudLikelihood(skel, sigma=0.03, tau=0.01)
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=5)
    ends, radii = skel.capsules(thetas)
    D = capsule_distance(frame.points.points.double(), ends[..., 0, :], ends[..., 1, :], radii)
    expected = -(D.square().clamp_max(0.01)).sum(-1) / (2 * 0.03**2)
    torch.testing.assert_close(lik(thetas, frame), expected)
    # Outliers cost at most tau each: adding 100 far points lowers every pose by exactly 100 tau / 2 sigma^2.
    far = torch.cat([frame.points.points, torch.full((100, 3), 50.0)])
    torch.testing.assert_close(lik(thetas, PointCloud(far)), expected - 100 * 0.01 / (2 * 0.03**2))
