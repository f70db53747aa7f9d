"""Likelihoods: peaks at the truth along 1-DOF sweeps (Fontmarty Fig. 4), values against direct formulas,
gradients, batching, determinism and the product combinator."""

import math

import cv2
import numpy as np
import pytest
import torch

from torchpf.camera import camera_ring, look_at
from torchpf.geometry import capsule_distance, capsule_masks, project_capsules
from torchpf.likelihoods import (
    ChamferLikelihood,
    DualSilhouetteLikelihood,
    Keypoints2DLikelihood,
    OverlapLikelihood,
    PointCloudLikelihood,
    ProductLikelihood,
    SilhouetteLikelihood,
    SkinBlobLikelihood,
)
from torchpf.observations import DistanceMaps, Frame, Keypoints2D, PointCloud, Silhouettes
from torchpf.synth import synthesize

W, H = 160, 120


@pytest.fixture(scope="module")
def skel(human):
    return human


@pytest.fixture(scope="module")
def truth(skel):
    names = skel.dof_names
    th = torch.zeros(len(names), dtype=torch.float64)
    for k, v in {
        "Hips_Yposition": 1.0,
        "LeftArm_Yrotation": 0.6,
        "RightArm_Yrotation": -0.5,
        "LeftForeArm_Zrotation": 0.5,
        "RightUpLeg_Xrotation": -0.3,
    }.items():
        th[names.index(k)] = v
    return th


@pytest.fixture(scope="module")
def rig():
    return camera_ring(3, radius=4.0, height=1.5, target=(0, 0, 0.8), width=W, height_px=H)


@pytest.fixture(scope="module")
def depth_cam():
    return look_at((0.6, -3.0, 1.4), (0, 0, 0.8), width=W, height=H, name="depth")


@pytest.fixture(scope="module")
def frame(skel, truth, rig, depth_cam):
    seq = synthesize(skel, truth[None], rig, depth_camera=depth_cam, seed=0)
    fr = seq.frame(0)
    # Skin blobs: discs at the projected head and hands; edges: Canny on the rendered silhouettes.
    markers = SkinBlobLikelihood(skel, rig).markers(truth)
    blobs = []
    for cam in rig.values():
        m = np.zeros((H, W), np.uint8)
        for u, v in cam.project(markers).numpy():
            cv2.circle(m, (round(u), round(v)), 3, 255, -1)
        blobs.append(m)
    fr.skin = DistanceMaps.from_features(blobs)
    fr.edges = DistanceMaps.from_features([cv2.Canny(m, 50, 150) for m in seq.masks[0]])
    return fr


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
        "overlap": OverlapLikelihood(skel, rig),
        "keypoints": Keypoints2DLikelihood(skel, rig),
        "keypoints_t": Keypoints2DLikelihood(skel, rig, noise="student"),
        "skin": SkinBlobLikelihood(skel, rig),
        "chamfer": ChamferLikelihood(skel, rig),
    }


@pytest.mark.parametrize(
    "dof", ["LeftArm_Yrotation", "LeftForeArm_Zrotation", "Hips_Xposition", "RightUpLeg_Xrotation"]
)
def test_every_likelihood_peaks_at_truth(skel, truth, rig, depth_cam, frame, dof):
    thetas, centre = sweep(truth, skel, dof, half=0.3 if "position" in dof else 0.4)
    for name, lik in make_liks(skel, rig, depth_cam).items():
        if name == "skin" and dof == "RightUpLeg_Xrotation":
            continue  # the skin markers (head, hands) do not move with the leg
        vals = lik(thetas.float(), frame)
        assert vals.shape == (len(thetas),), name
        try:
            assert_peak(vals, centre, steps=STEP_TOLERANCE.get(name, 0))
        except AssertionError as e:
            raise AssertionError(f"{name}: {e}") from None


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
    def __init__(self, skel):
        super().__init__()
        self.skel, self.calls = skel, 0
        self.joint_names, self.dof_names = skel.joint_names, skel.dof_names
        self.bones, self.radii = skel.bones, skel.radii

    def capsules(self, theta):
        self.calls += 1
        return self.skel.capsules(theta)

    def fk(self, theta):
        self.calls += 1
        return self.skel.fk(theta)


def test_product_shares_forward_kinematics(skel, truth, rig, frame):
    counting = CountingSkeleton(skel)
    prod = ProductLikelihood([SilhouetteLikelihood(counting, rig), DualSilhouetteLikelihood(counting, rig)])
    prod(truth.repeat(4, 1), frame)
    assert counting.calls == 1


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


@pytest.mark.parametrize(
    "name",
    ["pointcloud", "pointcloud_half", "silhouette", "dual_soft", "overlap", "keypoints", "skin", "chamfer"],
)
def test_gradients_exist(skel, truth, rig, depth_cam, frame, name):
    lik = make_liks(skel, rig, depth_cam)[name]
    thetas, _ = sweep(truth, skel, "LeftForeArm_Zrotation", half=0.2, n=3)
    thetas = thetas.clone().requires_grad_()
    lik(thetas, frame).sum().backward()
    g = thetas.grad
    j = skel.dof_names.index("LeftForeArm_Zrotation")
    assert torch.isfinite(g).all()
    assert float(g[:, j].abs().max()) > 0


def test_batch_dims_dtype_and_determinism(skel, truth, rig, depth_cam, frame):
    g = torch.Generator().manual_seed(0)
    thetas = truth + 0.05 * torch.randn(2, 3, len(truth), generator=g, dtype=torch.float64)
    for name, lik in make_liks(skel, rig, depth_cam).items():
        batched = lik(thetas, frame)
        assert batched.shape == (2, 3) and batched.dtype == torch.float64, name
        flat = lik(thetas.reshape(6, -1), frame)
        torch.testing.assert_close(batched.reshape(6), flat, msg=name)
        torch.testing.assert_close(lik(thetas, frame), batched, msg=name)  # fixed sample patterns
        f32 = lik(thetas.float(), frame)
        assert f32.dtype == torch.float32
        torch.testing.assert_close(f32.double(), batched, rtol=1e-3, atol=1e-2, msg=name)


def test_random_model_points_with_generator(skel, truth, rig, frame):
    thetas, centre = sweep(truth, skel, "LeftArm_Yrotation")
    a = SilhouetteLikelihood(skel, rig, generator=torch.Generator().manual_seed(3))(thetas, frame)
    b = SilhouetteLikelihood(skel, rig, generator=torch.Generator().manual_seed(3))(thetas, frame)
    torch.testing.assert_close(a, b)
    lik = SilhouetteLikelihood(skel, rig, generator=torch.Generator().manual_seed(3), n_body=32)
    assert not torch.equal(lik(thetas, frame), lik(thetas, frame))  # fresh points on each call
    vals = lik(thetas, frame)  # noisy: each particle gets its own points
    assert vals[centre] > vals[0] + 0.2 and vals[centre] > vals[-1] + 0.2


def test_missing_data_contributes_nothing(skel, truth, rig, frame):
    thetas, centre = sweep(truth, skel, "LeftArm_Yrotation")
    sil = SilhouetteLikelihood(skel, rig)
    assert torch.equal(sil(thetas, Frame()), torch.zeros(len(thetas), dtype=torch.float64))
    assert torch.equal(
        PointCloudLikelihood(skel)(thetas, PointCloud(torch.zeros(0, 3))), torch.zeros(len(thetas))
    )
    # Dropping camera 1 equals scoring with cameras 0 and 2 only.
    masks = frame.silhouettes.masks
    dropped = Silhouettes(masks, valid=torch.tensor([True, False, True]))
    two = SilhouetteLikelihood(skel, [rig["cam0"], rig["cam2"]])
    torch.testing.assert_close(sil(thetas, dropped), two(thetas, Silhouettes(masks[[0, 2]])))
    dual = DualSilhouetteLikelihood(skel, rig)
    dual_two = DualSilhouetteLikelihood(skel, [rig["cam0"], rig["cam2"]])
    torch.testing.assert_close(dual(thetas, dropped), dual_two(thetas, Silhouettes(masks[[0, 2]])))
    with pytest.raises(ValueError, match="cameras"):
        two(thetas, frame)
    with pytest.raises(TypeError, match="Silhouettes"):
        sil(thetas, 3.0)


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


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_likelihoods_cuda(skel, truth, rig, depth_cam, frame):
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=5)
    for name, lik in make_liks(skel, rig, depth_cam).items():
        cpu = lik(thetas, frame)
        gpu = lik.to("cuda")(thetas.cuda(), frame)
        torch.testing.assert_close(gpu.cpu(), cpu, msg=name)
