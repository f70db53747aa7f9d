"""URDF in and out: the writer's round trip and shipped assets, reading (text, frames, radii), errors."""

import math

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import build, path
from torchpf.kinematics.urdf import (
    BodyJoint,
    Dof,
    build_chain,
    build_urdf,
    flatten_chain,
    floating_root_dofs,
    link_geometry,
    parse_urdf_xml,
    read_urdf_text,
)


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


def test_reading_gives_depth_first_frames_and_radii(data_dir):
    xml, source = read_urdf_text(data_dir / "odd.urdf")
    assert source.endswith("odd.urdf") and read_urdf_text(xml) == (xml, "<urdf string>")
    frames = flatten_chain(build_chain(xml, source))
    names = [f.name for f in frames]
    assert names[0] == "base" and len(names) == 10
    for i, f in enumerate(frames):
        assert f.parent < i and all(c > i for c in f.children)  # parents before children
        assert (f.dof >= 0) == (f.joint_type != "fixed")
        assert f.static.shape == (4, 4) and f.static.dtype == torch.float64
    assert {f.joint_type for f in frames} == {"fixed", "prismatic", "revolute"}  # continuous is revolute
    geometry = link_geometry(parse_urdf_xml(xml, source))
    assert geometry["torso"] == [("arm", 0.07), ("leg", 0.09)] and geometry["arm"] == [(None, 0.04)]
    assert geometry["hand"] == []


def test_errors_name_the_source(tmp_path, data_dir):
    with pytest.raises(FileNotFoundError, match="nowhere.urdf"):
        Skeleton.from_urdf(tmp_path / "nowhere.urdf")
    with pytest.raises(ValueError, match="malformed.urdf"):
        Skeleton.from_urdf(data_dir / "malformed.urdf")
    with pytest.raises(ValueError, match="<urdf string>: invalid URDF XML"):
        parse_urdf_xml("<robot>", "<urdf string>")


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            '<parent link="torso"/><child link="leg"/>',
            '<parent link="torsoo"/><child link="leg"/>',
            "joint 'hip': parent link 'torsoo' is not a <link>",
        ),
        ('<child link="leg"/>', '<child link="legg"/>', "joint 'hip': child link 'legg'"),
        ('<axis xyz="0 1 0"/>', '<axis xyz="0 0 0"/>', "joint 'hip': the axis is zero"),
        ('<axis xyz="0 1 0"/>', '<axis xyz="0 nan 0"/>', "joint 'hip'.*finite"),
        ('xyz="0 0 -0.1"', 'xyz="0 inf -0.1"', "joint 'hip'.*finite"),
        ('xyz="0 0 -0.1"', 'xyz="0 1e200 -0.1"', "joint 'hip'.*within"),
        ('xyz="0 0 -0.1"', 'xyz="0 1_000 -0.1"', "joint 'hip'.*not 3 number"),
        ('xyz="0 0 -0.1"', 'xyz="0 \u0661 -0.1"', "joint 'hip'.*not 3 number"),
        (
            'lower="-2" upper="2" effort="1" velocity="1"/></joint>\n  <joint name="ankle"',
            'lower="2" upper="-2" effort="1" velocity="1"/></joint>\n  <joint name="ankle"',
            "joint 'hip': lower limit 2 > upper limit -2",
        ),
        (
            'lower="-2" upper="2" effort="1" velocity="1"/></joint>\n  <joint name="ankle"',
            'lower="nan" upper="2" effort="1" velocity="1"/></joint>\n  <joint name="ankle"',
            "joint 'hip'",
        ),
        ('<cylinder radius="0.07"', '<cylinder radius="-0.07"', "link 'torso' <collision name='arm'>.*> 0"),
        ('<cylinder radius="0.07"', '<cylinder radius="0"', "> 0"),
        ('<capsule radius="0.09"', '<capsule radius="nan"', "link 'torso'"),
        ('<joint name="wrist"', '<joint name="roll"', "duplicate joint name 'roll'"),
        ('<link name="foot"/>', '<link name="foot"/><link name="stray"/>', "links \\['base', 'stray'\\]"),
    ],
)
def test_validation_names_the_element(tmp_path, data_dir, old, new, message):
    text = (data_dir / "odd.urdf").read_text()
    assert old in text
    bad = tmp_path / "bad.urdf"
    bad.write_text(text.replace(old, new, 1))
    with pytest.raises(ValueError, match=message) as info:
        Skeleton.from_urdf(bad)
    assert "bad.urdf" in str(info.value)


def test_validation_refuses_cycles_deep_trees_and_bad_radii(data_dir):
    links = "".join(f'<link name="l{i}"/>' for i in range(3))
    joints = "".join(
        f'<joint name="j{i}" type="fixed"><parent link="l{i}"/><child link="l{(i + 1) % 3}"/></joint>'
        for i in range(3)
    )
    with pytest.raises(ValueError, match="no link is without a parent joint"):
        Skeleton.from_urdf(f"<robot name='c'>{links}{joints}</robot>")
    n = 300
    links = "".join(f'<link name="l{i}"/>' for i in range(n + 1))
    joints = "".join(
        f'<joint name="j{i}" type="fixed"><parent link="l{i}"/><child link="l{i + 1}"/></joint>'
        for i in range(n)
    )
    with pytest.raises(ValueError, match="more than 256 joints below the root"):
        Skeleton.from_urdf(f"<robot name='deep'>{links}{joints}</robot>")
    with pytest.raises(ValueError, match="radii must be finite and > 0"):
        Skeleton.from_urdf(data_dir / "odd.urdf", radii={"arm": float("nan")})


def test_non_utf8_urdf_names_the_file(tmp_path):
    bad = tmp_path / "latin.urdf"
    bad.write_bytes(b"<robot name='\xe9'><link name='a'/></robot>")
    with pytest.raises(ValueError, match="latin.urdf: not a UTF-8"):
        Skeleton.from_urdf(bad)


FLOATING = """<robot name="f">
  <link name="world"/>
  <link name="pelvis"><collision><geometry><sphere radius="0.1"/></geometry></collision></link>
  <link name="thigh"/>
  <joint name="root" type="floating">
    <parent link="world"/><child link="pelvis"/><origin xyz="0.2 0 1" rpy="0 0 0.3"/>
  </joint>
  <joint name="hip" type="revolute">
    <parent link="pelvis"/><child link="thigh"/><origin xyz="0 0 -0.4"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
</robot>
"""


def test_floating_joint_becomes_three_prismatic_and_three_revolute_joints(tmp_path):
    file = tmp_path / "floating.urdf"
    file.write_text(FLOATING)
    skel = Skeleton.from_urdf(file)
    assert skel.dof_names == ["root_tx", "root_ty", "root_tz", "root_rz", "root_ry", "root_rx", "hip"]
    assert skel.joint_names == ["pelvis", "thigh"]
    assert skel.dof_revolute.tolist() == [False] * 3 + [True] * 4
    # the same body written by build_urdf (whose floating root has no rotated origin: turn it by 0.3 rad)
    ref = Skeleton.from_urdf(
        build_urdf(
            "ref",
            [
                BodyJoint("pelvis", None, (0.2, 0.0, 1.0), floating_root_dofs("root")),
                BodyJoint("thigh", "pelvis", (0.0, 0.0, -0.4), [Dof("hip", "revolute", (1, 0, 0), -1, 1)]),
            ],
        )
    )
    theta = torch.rand(5, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) - 0.5
    c, s = math.cos(0.3), math.sin(0.3)
    turn = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    origin = torch.tensor([0.2, 0.0, 1.0], dtype=torch.float64)
    expected = (ref.fk(theta) - origin) @ turn.T + origin  # the origin's rpy turns everything below it
    torch.testing.assert_close(skel.fk(theta), expected)
    saved = tmp_path / "saved.urdf"  # written back in the expanded form, which reads the same
    skel.save_urdf(saved)
    torch.testing.assert_close(Skeleton.from_urdf(saved).fk(theta), expected)


def test_planar_joint_is_refused_with_advice():
    with pytest.raises(ValueError, match="'planar' is not supported; write it as prismatic and revolute"):
        Skeleton.from_urdf(FLOATING.replace('type="floating"', 'type="planar"'))
