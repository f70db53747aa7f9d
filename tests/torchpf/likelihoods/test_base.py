"""Every cue through the base class: peaks at the truth along 1-DOF sweeps (Fontmarty Fig. 4),
gradients, batch dims, dtypes and determinism, missing data, the body computed once, the registry."""

import pytest
import torch

from torchpf.likelihoods import (
    LIKELIHOODS,
    Body,
    DualSilhouetteLikelihood,
    PointCloudLikelihood,
    SilhouetteLikelihood,
)
from torchpf.observations import Frame, PointCloud, Silhouettes

from .cases import STEP_TOLERANCE, assert_peak, make_liks, sweep


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


@pytest.mark.parametrize(
    "name",
    [
        "pointcloud",
        "pointcloud_half",
        "silhouette",
        "dual_soft",
        "silhouette_distance",
        "overlap",
        "keypoints",
        "skin",
        "chamfer",
    ],
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


@pytest.mark.parametrize(
    "name", ["pointcloud", "silhouette", "dual_soft", "silhouette_distance", "keypoints"]
)
def test_log_likelihood_and_grad_equals_autograd(skel, truth, rig, depth_cam, frame, name):
    """The pose gradient through the tree's vector-Jacobian product equals autograd through FK."""
    lik = make_liks(skel, rig, depth_cam)[name].double()
    thetas, _ = sweep(truth, skel, "LeftForeArm_Zrotation", half=0.2, n=3)
    thetas = thetas.reshape(1, 3, -1).double()
    x = thetas.clone().requires_grad_()
    want = lik(x, frame)
    (g,) = torch.autograd.grad(want.sum(), x)
    got, grad = lik.log_likelihood_and_grad(thetas, frame)
    assert got.shape == (1, 3) and grad.shape == thetas.shape and not grad.requires_grad
    torch.testing.assert_close(got, want.detach(), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grad, g, rtol=1e-9, atol=1e-9 * float(g.abs().max()))


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


def test_likelihoods_follow_the_particles_device_and_dtype(skel, truth, rig, depth_cam, frame, device, dtype):
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=5)
    for name, lik in make_liks(skel, rig, depth_cam).items():
        cpu = lik(thetas.to(dtype), frame)
        out = lik.to(device)(thetas.to(device, dtype), frame)  # the frame stays on the CPU: cues move it
        assert out.device.type == device.type and out.dtype == dtype, name
        tol = {"rtol": 1e-3, "atol": 1e-3} if dtype == torch.float32 else {}
        torch.testing.assert_close(out.cpu(), cpu, msg=name, **tol)
        lik.to("cpu")


def test_body_is_one_forward_kinematics(skel, truth):
    g = torch.Generator().manual_seed(0)
    thetas = truth + 0.05 * torch.randn(2, 3, len(truth), generator=g, dtype=torch.float64)
    body = Body.of(skel, thetas)
    assert body.batch == (2, 3) and body.theta.shape == (6, len(truth))
    torch.testing.assert_close(body.joints, skel.fk(thetas).reshape(6, -1, 3), rtol=0, atol=0)
    ends, radii = skel.capsules(thetas)
    torch.testing.assert_close(body.ends, ends.reshape(6, -1, 2, 3), rtol=0, atol=0)
    a, b, r = body.capsules([0, 2])
    torch.testing.assert_close(a, ends.reshape(6, -1, 2, 3)[:, [0, 2], 0], rtol=0, atol=0)
    torch.testing.assert_close(r, radii[[0, 2]], rtol=0, atol=0)


def test_forward_is_the_body_score(skel, truth, rig, depth_cam, frame):
    thetas, _ = sweep(truth, skel, "LeftArm_Yrotation", n=4)
    thetas = thetas.reshape(2, 2, -1)
    body = Body.of(skel, thetas)
    for name, lik in make_liks(skel, rig, depth_cam).items():
        torch.testing.assert_close(lik.log_likelihood_body(body, frame), lik(thetas, frame), msg=name)


def test_registry_names_every_cue():
    assert LIKELIHOODS.names() == sorted(
        [
            "silhouette",
            "dual_silhouette",
            "silhouette_distance",
            "overlap",
            "pointcloud",
            "keypoints",
            "chamfer",
            "skin",
            "self_collision",
        ]
    )
    assert LIKELIHOODS.get("pointcloud") is PointCloudLikelihood and not PointCloudLikelihood.needs_cameras
    with pytest.raises(ValueError, match="unknown likelihood 'nope'; choose from"):
        LIKELIHOODS.get("nope")


def test_a_batch_of_sequences_scores_each_against_its_own_frame(skel, truth, rig, depth_cam, frame):
    """(S, V, H, W) images (and (S, V, J, 2) keypoints, (S, K, 3) clouds) with (S, N, D) poses: sequence s
    is scored against its own frame, as S separate calls would."""
    from torchpf.observations import DistanceMaps, Keypoints2D

    g = torch.Generator().manual_seed(0)
    thetas = truth + 0.05 * torch.randn(2, 3, len(truth), generator=g, dtype=torch.float64)
    other = Frame(  # a second frame: everything shifted by 2 pixels / 3 cm, camera 1 missing
        silhouettes=Silhouettes(frame.silhouettes.masks.roll(2, -1), valid=torch.tensor([True, False, True])),
        points=PointCloud(frame.points.points + 0.03),
        keypoints=Keypoints2D(frame.keypoints.uv + 2.0),
        skin=DistanceMaps(frame.skin.distance.roll(2, -1)),
        edges=DistanceMaps(frame.edges.distance.roll(2, -2), valid=torch.tensor([True, True, False])),
    )
    frames = (frame, other)
    batched = Frame(
        silhouettes=Silhouettes(
            torch.stack([f.silhouettes.masks for f in frames]),
            torch.stack([f.silhouettes.valid for f in frames]),
        ),
        points=PointCloud(torch.stack([f.points.points for f in frames])),
        keypoints=Keypoints2D(torch.stack([f.keypoints.uv for f in frames])),
        skin=DistanceMaps(torch.stack([f.skin.distance for f in frames])),
        edges=DistanceMaps(
            torch.stack([f.edges.distance for f in frames]), torch.stack([f.edges.valid for f in frames])
        ),
    )
    for name, lik in make_liks(skel, rig, depth_cam).items():
        expected = torch.stack([lik(thetas[s], frames[s]) for s in range(2)])
        torch.testing.assert_close(lik(thetas, batched), expected, msg=name)
        assert not torch.allclose(expected[0], lik(thetas[0], frames[1])), name
    with pytest.raises(ValueError, match="leading dims"):
        SilhouetteLikelihood(skel, rig)(thetas[:1], batched)
