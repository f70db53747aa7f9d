"""ProductLikelihood: the weighted sum of its terms on one body (one FK), and make_likelihood."""

import pytest
import torch

from torchpf.likelihoods import (
    ChamferLikelihood,
    DualSilhouetteLikelihood,
    Keypoints2DLikelihood,
    PointCloudLikelihood,
    ProductLikelihood,
    SilhouetteLikelihood,
    SkinBlobLikelihood,
    make_likelihood,
)
from torchpf.observations import Frame

from .cases import assert_peak, make_liks, sweep


def test_combined_likelihood_peaks_and_equals_weighted_sum(skel, truth, rig, depth_cam, frame):
    liks = make_liks(skel, rig, depth_cam)
    terms = {k: liks[k] for k in ("silhouette", "dual", "skin", "pointcloud")}
    weights = {"silhouette": 1.0, "dual": 0.5, "skin": 2.0, "pointcloud": 0.1}
    prod = ProductLikelihood(terms, weights)
    thetas, centre = sweep(truth, skel, "LeftArm_Yrotation")
    vals = prod(thetas, frame)
    assert_peak(vals, centre)
    expected = sum(w * terms[k](thetas, frame) for k, w in weights.items())
    torch.testing.assert_close(vals, expected)
    comps = prod.components(thetas, frame)
    assert set(comps) == set(terms)
    # An annealing exponent scales the whole log-likelihood, and a weight of 0 removes a term.
    torch.testing.assert_close(
        ProductLikelihood(terms, {**weights, "dual": 0.0})(thetas, frame), expected - 0.5 * comps["dual"]
    )


class CountingSkeleton(torch.nn.Module):
    """The shipped skeleton with its forward kinematics and capsule calls counted."""

    def __init__(self, skel):
        super().__init__()
        self.skel, self.fk_calls, self.capsule_calls = skel, 0, 0
        self.joint_names, self.dof_names = skel.joint_names, skel.dof_names
        self.bones, self.radii = skel.bones, skel.radii

    def capsules(self, theta):
        self.capsule_calls += 1
        return self.skel.capsules(theta)

    def fk(self, theta):
        self.fk_calls += 1
        return self.skel.fk(theta)


def test_product_computes_forward_kinematics_once(skel, truth, rig, depth_cam, frame):
    counting = CountingSkeleton(skel)
    terms = {
        "silhouette": SilhouetteLikelihood(counting, rig),
        "dual": DualSilhouetteLikelihood(counting, rig),
        "pointcloud": PointCloudLikelihood(counting, view_point=depth_cam),
        "keypoints": Keypoints2DLikelihood(counting, rig),
        "skin": SkinBlobLikelihood(counting, rig),
        "chamfer": ChamferLikelihood(counting, rig),
    }
    weights = {
        "silhouette": 1.0,
        "dual": 0.5,
        "pointcloud": 0.1,
        "keypoints": 0.2,
        "skin": 2.0,
        "chamfer": 0.3,
    }
    prod = ProductLikelihood(terms, weights)
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=5)
    vals = prod(thetas, frame)
    assert counting.fk_calls == 1 and counting.capsule_calls == 0
    comps = prod.components(thetas, frame)
    assert counting.fk_calls == 2
    # Equal to the weighted sum of the terms, each scoring its own FK.
    alone = {k: t(thetas, frame) for k, t in terms.items()}
    assert counting.fk_calls == 2 + len(terms)
    for k in terms:
        torch.testing.assert_close(comps[k], alone[k], rtol=0, atol=0)
    torch.testing.assert_close(vals, sum(w * alone[k] for k, w in weights.items()), rtol=1e-12, atol=1e-9)
    # A frame without data for any term computes no FK at all.
    assert torch.equal(prod(thetas, Frame()), torch.zeros(5, dtype=torch.float64))
    assert counting.fk_calls == 2 + len(terms)


def test_make_likelihood_by_name(skel, rig):
    assert isinstance(make_likelihood(skel, rig, "silhouette"), SilhouetteLikelihood)
    pc = make_likelihood(skel, None, "pointcloud", {"pointcloud": {"sigma": 0.05}})
    assert isinstance(pc, PointCloudLikelihood) and pc.sigma == 0.05
    prod = make_likelihood(skel, rig, {"silhouette": 1.0, "pointcloud": 0.5})
    assert isinstance(prod, ProductLikelihood) and prod.weights == {"silhouette": 1.0, "pointcloud": 0.5}
    assert isinstance(make_likelihood(skel, rig, ["overlap", "skin"]), ProductLikelihood)
    with pytest.raises(ValueError, match="unknown likelihood"):
        make_likelihood(skel, rig, "nope")
    with pytest.raises(ValueError, match="needs cameras"):
        make_likelihood(skel, None, "chamfer")
