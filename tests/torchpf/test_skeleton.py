"""Skeleton: fused FK against pytorch-kinematics, joint detection, limits, capsules, gradients, errors."""

import math

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import build, path
from torchpf.kinematics.urdf import BodyJoint, Dof, build_urdf, floating_root_dofs

# A URDF exercising what the shipped models do not: prismatic root joints with a rotated origin, fixed
# joints in the middle of a chain, non-unit and non-principal axes, rpy origins, a continuous joint, a link
# with several children on the same intermediate frame.
ODD_URDF = """<?xml version="1.0"?>
<robot name="odd">
  <link name="base"/>
  <link name="slider_x"/>
  <link name="slider_y"/>
  <link name="torso"><collision name="arm"><geometry><cylinder radius="0.07" length="0.3"/></geometry>
    </collision><collision name="leg"><geometry><capsule radius="0.09" length="0.4"/></geometry></collision>
  </link>
  <link name="mount"/>
  <link name="arm"><visual><geometry><cylinder radius="0.04" length="0.2"/></geometry></visual></link>
  <link name="arm_roll"/>
  <link name="hand"/>
  <link name="leg"/>
  <link name="foot"/>
  <joint name="px" type="prismatic"><parent link="base"/><child link="slider_x"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.3 -0.2 0.5"/><axis xyz="1 0 0"/>
    <limit lower="-5" upper="5" effort="1" velocity="1"/></joint>
  <joint name="py" type="prismatic"><parent link="slider_x"/><child link="slider_y"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 2 0"/><limit lower="-5" upper="5" effort="1" velocity="1"/>
  </joint>
  <joint name="yaw" type="continuous"><parent link="slider_y"/><child link="torso"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/></joint>
  <joint name="mount_fixed" type="fixed"><parent link="torso"/><child link="mount"/>
    <origin xyz="0 0.1 0.4" rpy="0.1 0.2 0.3"/></joint>
  <joint name="shoulder" type="revolute"><parent link="mount"/><child link="arm"/>
    <origin xyz="0.2 0 0" rpy="0 0.4 0"/><axis xyz="1 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="roll" type="revolute"><parent link="arm"/><child link="arm_roll"/>
    <origin xyz="0.3 0 0" rpy="0 0 0"/><axis xyz="0.2 -0.5 0.8"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="wrist" type="revolute"><parent link="arm_roll"/><child link="hand"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="hip" type="revolute"><parent link="torso"/><child link="leg"/>
    <origin xyz="0 0 -0.1" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="ankle" type="fixed"><parent link="leg"/><child link="foot"/>
    <origin xyz="0 0 -0.4" rpy="0 0 0"/></joint>
</robot>
"""

MODELS = {
    "human": lambda: path("human.urdf"),
    "fontmarty22": lambda: path("fontmarty22.urdf"),
    "odd": lambda: ODD_URDF,
}


def random_poses(skel, shape, dtype, seed=0):
    gen = torch.Generator().manual_seed(seed)
    lo = skel.lower.clamp(min=-math.pi)
    hi = skel.upper.clamp(max=math.pi)
    u = torch.rand(*shape, len(skel.dof_names), generator=gen, dtype=torch.float64)
    return (lo + u * (hi - lo)).to(dtype)


def pk_reference(skel, theta):
    """(B, J, 4, 4) body-joint transforms from pytorch-kinematics' own forward_kinematics."""
    chain = skel.chain.to(dtype=theta.dtype)
    frames = chain.forward_kinematics(theta)
    return torch.stack([frames[name].get_matrix() for name in skel.joint_names], 1)


@pytest.fixture(scope="module", params=list(MODELS))
def skel(request):
    return Skeleton.from_urdf(MODELS[request.param]())


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-10)])
def test_fk_matches_pytorch_kinematics(skel, dtype, tol):
    theta = random_poses(skel, (64,), dtype)
    ref = pk_reference(skel, theta)
    joints = skel.fk(theta)
    assert joints.dtype == dtype and joints.shape == (64, len(skel.joint_names), 3)
    assert (joints - ref[..., :3, 3]).abs().max().item() < tol
    assert (skel.transforms(theta) - ref).abs().max().item() < tol


def test_leading_batch_dims_and_single_pose(skel):
    theta = random_poses(skel, (2, 3, 5), torch.float64)
    out = skel.fk(theta)
    assert out.shape == (2, 3, 5, len(skel.joint_names), 3)
    flat = skel.fk(theta.reshape(-1, theta.shape[-1])).reshape(out.shape)
    assert torch.equal(out, flat)
    one = skel.fk(theta[1, 2, 4])
    assert one.shape == (len(skel.joint_names), 3)
    torch.testing.assert_close(one, out[1, 2, 4], rtol=0, atol=1e-12)
    assert skel.transforms(theta).shape == (2, 3, 5, len(skel.joint_names), 4, 4)


def test_fk_gradient_matches_finite_differences(skel):
    theta = random_poses(skel, (3,), torch.float64, seed=1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: skel.fk(t), (theta,), eps=1e-6, atol=1e-6)


def test_gradients_do_not_mix_poses():
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
    odd = Skeleton.from_urdf(ODD_URDF)
    assert odd.joint_names == ["torso", "mount", "arm", "hand", "leg", "foot"]
    assert odd.dof_names == ["px", "py", "yaw", "shoulder", "roll", "wrist", "hip"]


def test_explicit_joint_names_expose_intermediate_links():
    skel = Skeleton.from_urdf(ODD_URDF, joint_names=["slider_x", "torso", "arm_roll", "hand", "foot"])
    theta = random_poses(skel, (16,), torch.float64)
    ref = pk_reference(skel, theta)
    torch.testing.assert_close(skel.fk(theta), ref[..., :3, 3], rtol=0, atol=1e-10)
    assert skel.parents == [-1, 0, 1, 2, 1]
    with pytest.raises(ValueError, match="not among the URDF links"):
        Skeleton.from_urdf(ODD_URDF, joint_names=["torso", "elbow"])


def test_rest_pose_of_human_is_upright_t_pose():
    skel = Skeleton.from_urdf(path("human.urdf"))
    j = dict(zip(skel.joint_names, skel.fk(torch.zeros(96, dtype=torch.float64)), strict=True))
    assert j["Head_end"][2] > j["Spine1"][2] > j["Hips"][2] > j["LeftLeg"][2] > j["LeftFoot"][2]
    assert j["LeftHand"][0] > 0.5 and j["RightHand"][0] < -0.5  # arms out, left is +x
    assert j["LeftToeBase_end"][1] < j["LeftFoot"][1]  # facing -y
    height = (j["Head_end"][2] - j["LeftToeBase_end"][2]).item()
    assert 1.45 < height < 1.75


def test_limits_and_clamp(skel):
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


def test_capsules_follow_fk_and_read_radii():
    skel = Skeleton.from_urdf(ODD_URDF, radii={"foot": 0.05})
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


def test_shipped_assets_match_generator():
    for name, text in build.render().items():
        assert path(name).read_text() == text, f"{name} is stale: run python -m torchpf.assets.build"


def test_urdf_builder_round_trip():
    joints = [
        BodyJoint("pelvis", None, (0.0, 0.0, 1.0), floating_root_dofs("pelvis")),
        BodyJoint(
            "knee", "pelvis", (0.0, 0.0, -0.45), [Dof("knee_rx", "revolute", (1.0, 0.0, 0.0), 0.0, 2.6)]
        ),
        BodyJoint("ankle", "knee", (0.0, 0.0, -0.4)),
    ]
    skel = Skeleton.from_urdf(build_urdf("toy", joints, radii={"knee": 0.07}))
    assert skel.joint_names == ["pelvis", "knee", "ankle"]
    assert skel.dof_names[:3] == ["pelvis_tx", "pelvis_ty", "pelvis_tz"]
    theta = torch.zeros(7, dtype=torch.float64)
    theta[:3] = torch.tensor([1.0, 2.0, 3.0])
    theta[6] = math.pi / 2
    torch.testing.assert_close(skel.fk(theta)[2], torch.tensor([1.0, 2.4, 3.55], dtype=torch.float64))
    assert skel.radii.tolist() == pytest.approx([0.07, 0.03])
    with pytest.raises(ValueError, match="not listed before"):
        build_urdf("bad", [joints[0], joints[2]])
    with pytest.raises(ValueError, match="lower limit"):
        Dof("x", "revolute", (1.0, 0.0, 0.0), 1.0, 0.0)


def test_errors_name_the_source(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.urdf"):
        Skeleton.from_urdf(tmp_path / "nowhere.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'></robot>")
    with pytest.raises(ValueError, match="bad.urdf"):
        Skeleton.from_urdf(bad)
    skel = Skeleton.from_urdf(path("fontmarty22.urdf"))
    with pytest.raises(ValueError, match=r"\(\.\.\., 22\)"):
        skel.fk(torch.zeros(5, 21))


def test_integer_and_module_call():
    skel = Skeleton.from_urdf(path("fontmarty22.urdf"))
    out = skel(torch.zeros(2, 22, dtype=torch.long))
    assert out.dtype == torch.get_default_dtype()
    torch.testing.assert_close(out, skel.fk(torch.zeros(2, 22)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    skel = Skeleton.from_urdf(path("human.urdf"))
    theta = random_poses(skel, (128,), torch.float32)
    gpu = skel.to("cuda").fk(theta.cuda())
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), skel.fk(theta), rtol=0, atol=1e-5)
    ends, radii = skel.capsules(theta.cuda())
    assert ends.device.type == "cuda" and radii.device.type == "cuda"


def test_dof_joints_name_the_moved_joint():
    human = Skeleton.from_urdf(path("human.urdf"))
    for d, j in zip(human.dof_names, human.dof_joints, strict=True):
        assert d.rsplit("_", 1)[0] == human.joint_names[j]  # "LeftLeg_Xrotation" moves "LeftLeg"
    odd = Skeleton.from_urdf(ODD_URDF)
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
