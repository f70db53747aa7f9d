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
