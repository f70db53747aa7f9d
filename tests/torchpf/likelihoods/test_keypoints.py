"""2-D point cue (Brubaker eq. 3-4): Gaussian and Student-t values, missing detections."""

import math

import pytest
import torch

from torchpf.likelihoods import (
    Keypoints2DLikelihood,
)
from torchpf.observations import Keypoints2D


def test_keypoints_missing_points_and_student(skel, truth, rig):
    lik = Keypoints2DLikelihood(skel, rig, joints=["Head", "LeftHand", "RightFoot"], sigma=3.0)
    X = skel.fk(truth)[[skel.joint_names.index(j) for j in ("Head", "LeftHand", "RightFoot")]]
    uv = torch.stack([cam.project(X) for cam in rig.values()]).float()
    uv_noisy = uv + torch.tensor([2.0, -1.0])
    full = lik(truth[None], Keypoints2D(uv_noisy))
    expected = 9 * (-(5.0) / (2 * 9.0) - math.log(2 * math.pi * 9.0))
    assert full.item() == pytest.approx(expected, rel=1e-4)
    # A NaN detection and visible=False are both "missing": the term drops that point.
    miss = uv_noisy.clone()
    miss[1, 2] = float("nan")
    vis = torch.ones(3, 3, dtype=torch.bool)
    vis[1, 2] = False
    one_less = expected * 8 / 9
    assert lik(truth[None], Keypoints2D(miss)).item() == pytest.approx(one_less, rel=1e-4)
    assert lik(truth[None], Keypoints2D(uv_noisy, visible=vis)).item() == pytest.approx(one_less, rel=1e-4)
    # Student-t: an outlier 100 px away costs far less than under the Gaussian.
    out = uv.clone()
    out[0, 0, 0] += 100.0
    student = Keypoints2DLikelihood(
        skel, rig, joints=["Head", "LeftHand", "RightFoot"], sigma=3.0, noise="student"
    )
    gauss_drop = lik(truth[None], Keypoints2D(uv)) - lik(truth[None], Keypoints2D(out))
    t_drop = student(truth[None], Keypoints2D(uv)) - student(truth[None], Keypoints2D(out))
    assert 0 < t_drop.item() < 0.05 * gauss_drop.item()
    nu, s2, d2 = 3.0, 9.0, 100.0**2
    assert t_drop.item() == pytest.approx((nu + 2) / 2 * math.log1p(d2 / (nu * s2)), rel=1e-3)
