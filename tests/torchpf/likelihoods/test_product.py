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


def test_product_projects_the_capsules_once_per_rig_and_bones(skel, truth, rig, frame, monkeypatch):
    """The silhouette and dual-silhouette terms project the same capsules into the same rig: once per body
    (Body.shared); a term scoring a subset of the bones projects its own."""
    import torchpf.likelihoods.images as images

    calls = []
    project = images.project_capsules
    monkeypatch.setattr(images, "project_capsules", lambda *a, **k: calls.append(1) or project(*a, **k))
    terms = {
        "silhouette": SilhouetteLikelihood(skel, rig),
        "dual": DualSilhouetteLikelihood(skel, rig),
        "limbs": DualSilhouetteLikelihood(skel, rig, bones=[0, 1, 2]),
    }
    prod = ProductLikelihood(terms)
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=5)
    vals = prod(thetas, frame)
    assert len(calls) == 2
    alone = {k: t(thetas, frame) for k, t in terms.items()}
    torch.testing.assert_close(vals, sum(alone.values()), rtol=1e-12, atol=1e-9)


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


def test_tempered_likelihood_scales_and_keeps_impossible_poses():
    import math

    from torchpf.likelihoods import TemperedLikelihood

    def base(x, obs):
        return torch.where(x[..., 0] > 0, -x.square().sum(-1), torch.full_like(x[..., 0], -math.inf))  # noqa: E731

    x = torch.tensor([[[1.0, 2.0], [-1.0, 0.0]]])
    out = TemperedLikelihood(base, 0.5)(x, None)
    assert out[0, 0] == -2.5 and out[0, 1] == -math.inf
    assert TemperedLikelihood(base, 0.0)(x, None)[0, 1] == -math.inf  # 0 * -inf is not a probability


def test_calibrated_temperature_matches_the_closed_form_survival_rate():
    """Gaussian particles x ~ N(0, I_2) weighted by exp(-a |x|^2): ESS/N -> (1 + 4a) / (1 + 2a)^2, which is
    0.2 at a = 2 + sqrt(5); the calibrated beta for log-likelihood -c |x|^2 is then (2 + sqrt(5)) / c."""
    from torchpf.filters.weights import survival_fraction
    from torchpf.likelihoods import calibrate_temperature

    x = torch.randn(4, 200_000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for c in (0.01, 1.0, 100.0):
        lik = lambda theta, obs, c=c: -c * theta.square().sum(-1)  # noqa: E731
        beta = calibrate_temperature(lik, x, None, survival_rate=0.2)
        torch.testing.assert_close(
            beta, torch.full((4,), (2 + 5**0.5) / c, dtype=torch.float64), rtol=0.05, atol=0
        )
        torch.testing.assert_close(
            survival_fraction(-c * beta[:, None] * x.square().sum(-1)),
            torch.full((4,), 0.2, dtype=torch.float64),
            rtol=1e-3,
            atol=0,
        )
    dead = lambda theta, obs: torch.full(theta.shape[:-1], float("-inf"))  # noqa: E731
    assert torch.equal(calibrate_temperature(dead, x[:, :10], None), torch.ones(4, dtype=torch.float64))
