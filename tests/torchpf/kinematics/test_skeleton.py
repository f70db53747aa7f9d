"""Skeleton: fused FK against pytorch-kinematics, joint detection, limits, capsules, gradients, errors."""

from pathlib import Path

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import path

ODD = Path(__file__).resolve().parents[2] / "data" / "odd.urdf"
MODELS = {"human": path("human.urdf"), "fontmarty22": path("fontmarty22.urdf"), "odd": ODD}


def pk_reference(skel, theta):
    """(B, J, 4, 4) body-joint transforms from pytorch-kinematics' own forward_kinematics."""
    chain = skel.chain.to(dtype=theta.dtype)
    frames = chain.forward_kinematics(theta)
    return torch.stack([frames[name].get_matrix() for name in skel.joint_names], 1)


@pytest.fixture(scope="module", params=list(MODELS))
def skel(request):
    return Skeleton.from_urdf(MODELS[request.param])


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-10)])
def test_fk_matches_pytorch_kinematics(skel, dtype, tol, random_poses):
    theta = random_poses(skel, (64,), dtype)
    ref = pk_reference(skel, theta)
    joints = skel.fk(theta)
    assert joints.dtype == dtype and joints.shape == (64, len(skel.joint_names), 3)
    assert (joints - ref[..., :3, 3]).abs().max().item() < tol
    assert (skel.transforms(theta) - ref).abs().max().item() < tol


def test_rest_joints_are_pytorch_kinematics_at_zero(skel):
    """The rest pose the structure-derived code reads: pytorch-kinematics' joints at every DOF 0, float64,
    without a graph; a body with other widths and a longer stature (``with_body``) has its own."""
    rest = skel.rest_joints()
    ref = pk_reference(skel, torch.zeros(1, len(skel.dof_names), dtype=torch.float64))[0, :, :3, 3]
    assert rest.dtype == torch.float64 and not rest.requires_grad
    assert (rest - ref).abs().max().item() < 1e-10
    taller = skel.with_body(scale=1.1).rest_joints()
    root = skel.parents.index(-1)
    assert torch.allclose(taller - taller[root], 1.1 * (rest - rest[root]), atol=1e-9)


def test_leading_batch_dims_and_single_pose(skel, random_poses):
    theta = random_poses(skel, (2, 3, 5), torch.float64)
    out = skel.fk(theta)
    assert out.shape == (2, 3, 5, len(skel.joint_names), 3)
    flat = skel.fk(theta.reshape(-1, theta.shape[-1])).reshape(out.shape)
    assert torch.equal(out, flat)
    one = skel.fk(theta[1, 2, 4])
    assert one.shape == (len(skel.joint_names), 3)
    torch.testing.assert_close(one, out[1, 2, 4], rtol=0, atol=1e-12)
    assert skel.transforms(theta).shape == (2, 3, 5, len(skel.joint_names), 4, 4)


def test_empty_batch(skel):
    D, J = len(skel.dof_names), len(skel.joint_names)
    assert skel.fk(torch.zeros(0, D)).shape == (0, J, 3)
    assert skel.fk(torch.zeros(2, 0, D)).shape == (2, 0, J, 3)
    assert skel.transforms(torch.zeros(0, D)).shape == (0, J, 4, 4)
    axes, pivots = skel.dof_axes(torch.zeros(0, D))
    assert axes.shape == pivots.shape == (0, D, 3)
    assert skel.capsules(torch.zeros(0, D))[0].shape == (0, len(skel.bones), 2, 3)


def test_fk_gradient_matches_finite_differences(skel, random_poses):
    theta = random_poses(skel, (3,), torch.float64, seed=1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: skel.fk(t), (theta,), eps=1e-6, atol=1e-6)


def test_gradients_do_not_mix_poses(random_poses):
    skel = Skeleton.from_urdf(path("human.urdf"))
    theta = random_poses(skel, (4,), torch.float64).requires_grad_(True)
    skel.fk(theta)[1].sum().backward()
    grad = theta.grad
    assert grad[1].abs().sum() > 0
    assert torch.all(grad[[0, 2, 3]] == 0)


def test_joint_detection_hides_intermediate_links():
    human = Skeleton.from_urdf(path("human.urdf"))
    assert len(human.dof_names) == 96
    # 31 CMU joints + 7 end sites; no "__" intermediate links, no base link
    assert len(human.joint_names) == 38
    assert not any("__" in n for n in human.joint_names) and "world" not in human.joint_names
    assert human.joint_names[0] == "Hips" and human.parents[0] == -1
    parent_of = {
        n: human.joint_names[p] for n, p in zip(human.joint_names, human.parents, strict=True) if p >= 0
    }
    assert parent_of["LeftForeArm"] == "LeftArm" and parent_of["Spine"] == "LowerBack"
    assert parent_of["LowerBack"] == "Hips" and parent_of["LThumb_end"] == "LThumb"
    odd = Skeleton.from_urdf(ODD)
    assert odd.joint_names == ["torso", "mount", "arm", "hand", "leg", "foot"]
    assert odd.dof_names == ["px", "py", "yaw", "shoulder", "roll", "wrist", "hip"]


def test_explicit_joint_names_expose_intermediate_links(random_poses):
    skel = Skeleton.from_urdf(ODD, joint_names=["slider_x", "torso", "arm_roll", "hand", "foot"])
    theta = random_poses(skel, (16,), torch.float64)
    ref = pk_reference(skel, theta)
    torch.testing.assert_close(skel.fk(theta), ref[..., :3, 3], rtol=0, atol=1e-10)
    assert skel.parents == [-1, 0, 1, 2, 1]
    with pytest.raises(ValueError, match="not among the URDF links"):
        Skeleton.from_urdf(ODD, joint_names=["torso", "elbow"])


def test_rest_pose_of_human_is_upright_t_pose():
    skel = Skeleton.from_urdf(path("human.urdf"))
    j = dict(zip(skel.joint_names, skel.fk(torch.zeros(96, dtype=torch.float64)), strict=True))
    assert j["Head_end"][2] > j["Spine1"][2] > j["Hips"][2] > j["LeftLeg"][2] > j["LeftFoot"][2]
    assert j["LeftHand"][0] > 0.5 and j["RightHand"][0] < -0.5  # arms out, left is +x
    assert j["LeftToeBase_end"][1] < j["LeftFoot"][1]  # facing -y
    height = (j["Head_end"][2] - j["LeftToeBase_end"][2]).item()
    assert 1.45 < height < 1.75


def test_limits_and_clamp(skel, random_poses):
    assert skel.lower.shape == skel.upper.shape == (len(skel.dof_names),)
    assert torch.all(skel.lower <= skel.upper)
    theta = random_poses(skel, (10,), torch.float32) * 4
    clamped = skel.clamp(theta)
    assert clamped.dtype == torch.float32
    assert torch.all(skel.within_limits(clamped))
    inside = skel.within_limits(theta)
    assert torch.equal(clamped[inside], theta[inside])


def test_knee_and_elbow_limits_follow_anatomy():
    skel = Skeleton.from_urdf(path("fontmarty22.urdf"))
    knee = skel.dof_names.index("l_knee_rx")
    assert skel.lower[knee] == 0 and skel.upper[knee] > 2
    bent = torch.zeros(22, dtype=torch.float64)
    bent[knee] = 1.5
    j = dict(zip(skel.joint_names, skel.fk(bent), strict=True))
    assert j["l_ankle"][1] > j["l_knee"][1] + 0.3  # a flexed knee sends the shank backward (+y)


def test_capsules_follow_fk_and_read_radii(random_poses):
    skel = Skeleton.from_urdf(ODD, radii={"foot": 0.05})
    theta = random_poses(skel, (7,), torch.float64)
    ends, radii = skel.capsules(theta)
    joints = skel.fk(theta)
    names = skel.joint_names
    bones = [(names[p], names[c]) for p, c in skel.bones]
    # mount is a fixed child of torso with an offset: torso->mount, torso->leg; arm->hand; leg->foot
    assert ("torso", "leg") in bones and ("arm", "hand") in bones and ("leg", "foot") in bones
    assert ends.shape == (7, len(bones), 2, 3)
    for k, (p, c) in enumerate(skel.bones):
        torch.testing.assert_close(ends[:, k, 0], joints[:, p])
        torch.testing.assert_close(ends[:, k, 1], joints[:, c])
    r = dict(zip([c for _, c in bones], radii.tolist(), strict=True))
    assert r["leg"] == pytest.approx(0.09)  # named <collision> capsule on the parent link
    assert r["hand"] == pytest.approx(0.04)  # the single unnamed <visual> cylinder of a one-bone link
    assert r["foot"] == pytest.approx(0.05)  # radii table overrides
    rest = skel.fk(torch.zeros(len(skel.dof_names), dtype=torch.float64))
    mount_len = (rest[names.index("mount")] - rest[names.index("torso")]).norm().item()
    assert r["mount"] == pytest.approx(0.15 * mount_len)  # default proportional to bone length


def test_human_capsules_skip_zero_length_bones():
    skel = Skeleton.from_urdf(path("human.urdf"))
    _, radii = skel.capsules(torch.zeros(96))
    names = skel.joint_names
    children = {names[c] for _, c in skel.bones}
    assert "LowerBack" not in children and "LHipJoint" not in children  # zero offset from Hips
    assert len(skel.bones) == 27 and radii.dtype == torch.float32
    assert dict(zip([names[c] for _, c in skel.bones], radii.tolist(), strict=True))[
        "LeftLeg"
    ] == pytest.approx(0.075)


def test_wrong_pose_shape_is_named():
    skel = Skeleton.from_urdf(path("fontmarty22.urdf"))
    with pytest.raises(ValueError, match=r"\(\.\.\., 22\)"):
        skel.fk(torch.zeros(5, 21))


def test_integer_and_module_call():
    skel = Skeleton.from_urdf(path("fontmarty22.urdf"))
    out = skel(torch.zeros(2, 22, dtype=torch.long))
    assert out.dtype == torch.get_default_dtype()
    torch.testing.assert_close(out, skel.fk(torch.zeros(2, 22)))


def test_device_and_dtype_match_the_cpu(random_poses, device, dtype):
    skel = Skeleton.from_urdf(path("human.urdf"))
    theta = random_poses(skel, (128,), torch.float64)
    reference = skel.fk(theta)
    out = skel.to(device).fk(theta.to(device, dtype))
    assert out.device.type == device.type and out.dtype == dtype
    assert skel.tree.parents.device.type == device.type  # buffers moved
    torch.testing.assert_close(out.cpu().double(), reference, rtol=0, atol=1e-5)
    ends, radii = skel.capsules(theta.to(device, dtype))
    assert ends.device.type == device.type and radii.device.type == device.type and ends.dtype == dtype


def test_dof_joints_name_the_moved_joint():
    human = Skeleton.from_urdf(path("human.urdf"))
    for d, j in zip(human.dof_names, human.dof_joints, strict=True):
        assert d.rsplit("_", 1)[0] == human.joint_names[j]  # "LeftLeg_Xrotation" moves "LeftLeg"
    odd = Skeleton.from_urdf(ODD)
    owner = {d: odd.joint_names[j] for d, j in zip(odd.dof_names, odd.dof_joints, strict=True)}
    assert owner == {
        "px": "torso",
        "py": "torso",
        "yaw": "torso",
        "shoulder": "arm",
        "roll": "hand",
        "wrist": "hand",
        "hip": "leg",
    }


@pytest.mark.parametrize("n", [1, 5, 300])
def test_fk_paths_agree_with_pytorch_kinematics(skel, n, random_poses, monkeypatch):
    """The three ways of composing the tree (the tensor version's pointer jumping for few poses and one
    depth level at a time for many, and the fused CPU kernel without autograd) give pytorch-kinematics'
    transforms and the same DOF axes and pivots, whichever the batch size."""
    import torchpf.skeleton as module
    from torchpf.kinematics import _fk_cpu

    theta = random_poses(skel, (n,), torch.float64, seed=3)
    ref = pk_reference(skel, theta)
    out = {}
    paths = [("0", 0), ("0", 10**9)] + ([("1", 0)] if _fk_cpu.AVAILABLE else [])
    for fused, rows in paths:  # the levels, pointer jumping, the kernel
        monkeypatch.setenv("TORCHPF_FUSED", fused)
        monkeypatch.setattr(module, "_JUMP_MAX_ROWS", rows)
        assert _fk_cpu.applies(theta) == (fused == "1")
        assert (skel.transforms(theta) - ref).abs().max().item() < 1e-10
        out[fused, rows] = skel.fk_with_axes(theta)
        torch.testing.assert_close(out[fused, rows][2].permute(2, 0, 1), ref[..., :3, 3], rtol=0, atol=1e-10)
    for other in paths[1:]:
        for a, b in zip(out[paths[0]], out[other], strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_the_fused_kernel_in_float32_and_not_under_autograd(skel, random_poses, monkeypatch):
    """The fused kernel's float32 results are the tensor version's to float32 rounding, and a pose that
    autograd tracks goes through the tensor version (its gradient is finite differences', test above)."""
    from torchpf.kinematics import _fk_cpu

    if not _fk_cpu.AVAILABLE:
        pytest.skip("numba is not installed")
    theta = random_poses(skel, (7,), torch.float32, seed=4)
    monkeypatch.setenv("TORCHPF_FUSED", "0")
    ref = skel.fk_with_axes(theta)
    monkeypatch.setenv("TORCHPF_FUSED", "1")
    assert _fk_cpu.applies(theta)
    for a, b in zip(ref, skel.fk_with_axes(theta), strict=True):
        assert a.dtype == b.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=0, atol=5e-6)
    tracked = theta.clone().requires_grad_(True)
    assert not _fk_cpu.applies(tracked)
    assert skel.fk(tracked).requires_grad
    with torch.no_grad():
        assert _fk_cpu.applies(tracked)


def test_fused_kernels_leave_large_threaded_batches_to_the_tensor_version(monkeypatch):
    """With several torch threads a batch above ``FUSED_MAX_POSES_THREADED`` poses runs the tensor
    operations (they spread over the threads, the kernels run on one); with one thread the kernels run at
    every size; autograd, a non-CPU device or ``TORCHPF_FUSED=0`` always keep the tensor version."""
    from torchpf import devices

    monkeypatch.setattr(devices, "FUSED_MAX_POSES_THREADED", 4)
    monkeypatch.delenv("TORCHPF_FUSED", raising=False)
    t = torch.zeros(10, 3)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert devices.fused_cpu(t, 4) and not devices.fused_cpu(t, 5)
        torch.set_num_threads(1)
        assert devices.fused_cpu(t, 10**6)
    finally:
        torch.set_num_threads(threads)
    assert not devices.fused_cpu(t.requires_grad_(True), 1)
    assert not devices.fused_cpu(torch.zeros(10, 3, dtype=torch.int64), 1)
    assert not devices.fused_cpu(torch.zeros(10, 3, device="meta"), 1)
    monkeypatch.setenv("TORCHPF_FUSED", "0")
    assert not devices.fused_cpu(torch.zeros(10, 3), 1)


def test_a_pickled_skeleton_runs_the_fused_kernel(skel, random_poses, tmp_path):
    """A skeleton saved whole (``torch.save``, as a tracking result keeps it) and loaded again builds the
    fused kernel's arrays from what it carries and gives the same FK."""
    theta = random_poses(skel, (3,), torch.float64, seed=5)
    torch.save(skel, tmp_path / "skel.pt")
    loaded = torch.load(tmp_path / "skel.pt", weights_only=False)
    for a, b in zip(skel.fk_with_axes(theta), loaded.fk_with_axes(theta), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_the_fused_kernel_propagates_nan_as_the_tensor_version(skel, random_poses, monkeypatch):
    """A NaN angle makes the same entries NaN in both versions (0 x NaN is NaN: the kernel skips no zero
    coefficient), so a NaN pose is never half finite on one path only; the finite entries agree."""
    from torchpf.kinematics import _fk_cpu

    if not _fk_cpu.AVAILABLE:
        pytest.skip("numba is not installed")
    D = len(skel.dof_names)
    theta = random_poses(skel, (D,), torch.float64, seed=6)
    theta[torch.arange(D), torch.arange(D)] = float("nan")  # pose d has DOF d undefined
    out = {}
    for fused in ("0", "1"):
        monkeypatch.setenv("TORCHPF_FUSED", fused)
        out[fused] = skel.fk_with_axes(theta)
    for a, b in zip(out["0"], out["1"], strict=True):
        assert torch.equal(a.isnan(), b.isnan())
        torch.testing.assert_close(a.nan_to_num(0.0), b.nan_to_num(0.0), rtol=0, atol=1e-12)
