"""BVH export (:func:`training.mocap.save_bvh`, ``python -m training export``): round trips, Blender's
conventions checked with the independent BVH reference of ``test_mocap`` (its own parser and FK), skeletons
that need Euler re-decomposition, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.training.test_mocap import CMU_DIR, CMU_PARAMS, needs_cmu, ref_parse, ref_positions
from torchpf.kinematics.urdf import BodyJoint, Dof, build_urdf
from torchpf.skeleton import Skeleton
from training.__main__ import main
from training.mocap import (
    CMU_SCALE,
    Motion,
    _euler_from_matrix,
    load_bvh,
    read_bvh,
    save_bvh,
    save_csv,
)


def _reference_fk(path, scale, names) -> np.ndarray:
    """(T, J, 3) world positions of ``names`` by the reference BVH semantics of ``test_mocap``."""
    joints, _, values = ref_parse(path.read_text())
    ref = ref_positions(joints, values, scale)
    return np.stack([ref[n] for n in names], 1)


# ------------------------------------------------------------------------------------------ CMU round trip
@needs_cmu
@pytest.mark.parametrize("clip", CMU_PARAMS)
def test_cmu_round_trip_is_exact(clip, tmp_path):
    skel, motion = load_bvh(CMU_DIR / clip, CMU_SCALE)
    out = tmp_path / "rt.bvh"
    save_bvh(out, skel, motion, scale=CMU_SCALE)
    skel2, motion2 = load_bvh(out, CMU_SCALE)
    assert skel2.joint_names == skel.joint_names and skel2.dof_names == skel.dof_names
    assert motion2.fps == pytest.approx(motion.fps, rel=1e-9)
    assert torch.allclose(motion2.angles, motion.angles, atol=1e-6, rtol=0)
    assert torch.allclose(skel2.fk(motion2.angles), skel.fk(motion.angles), atol=1e-6, rtol=0)
    # the file itself: same hierarchy, channels in the declared order, values in the file's units
    a, b = read_bvh(CMU_DIR / clip), read_bvh(out)
    assert [(j.name, j.parent, j.channels) for j in a.joints] == [
        (j.name, j.parent, j.channels) for j in b.joints
    ]
    assert np.allclose([j.offset for j in a.joints], [j.offset for j in b.joints], atol=1e-5, rtol=0)
    assert np.allclose(a.values, b.values, atol=1e-6, rtol=0)
    assert b.frame_time == pytest.approx(a.frame_time, rel=1e-9)


# ------------------------------------------------------------------------------------ Blender conventions
def test_human_urdf_exports_exactly_with_blender_conventions(human, tmp_path):
    g = torch.Generator().manual_seed(0)
    theta = human.clamp(0.4 * torch.randn(12, len(human.dof_names), generator=g, dtype=torch.float64))
    theta[:, :3] = torch.tensor([0.5, -1.0, 0.95], dtype=torch.float64)  # root position (m)
    out = tmp_path / "human.bvh"
    save_bvh(out, human, Motion(human.dof_names, 25.0, theta), scale=0.01)  # file in centimetres
    text = out.read_text()
    lines = text.splitlines()
    assert lines[0] == "HIERARCHY" and lines[1] == "ROOT Hips"
    root_channels = lines[4].split()
    assert root_channels[:5] == ["CHANNELS", "6", "Xposition", "Yposition", "Zposition"]
    assert "Frames: 12" in lines and "Frame Time: 0.04" in lines
    # y up, in file units: LeftLeg hangs 0.43 m below LeftUpLeg along world -z, i.e. BVH -y, 43 cm
    i = lines.index("      JOINT LeftLeg")
    assert lines[i + 2].split() == ["OFFSET", "0", "-43", "0"]
    # every channel one DOF with its name kept: load_bvh gives back the skeleton and the angles
    skel2, motion2 = load_bvh(out, 0.01)
    assert skel2.joint_names == human.joint_names and skel2.dof_names == human.dof_names
    assert torch.allclose(motion2.angles, theta, atol=1e-6, rtol=0)
    # and an independent BVH reader agrees with the skeleton's FK
    ref = _reference_fk(out, 0.01, human.joint_names)
    assert np.abs(ref - human.fk(theta).numpy()).max() < 1e-6


def _oblique_skeleton() -> Skeleton:
    """A body a BVH cannot take channel by channel: an oblique hinge, two rotations about one axis, a
    prismatic DOF off the root, a DOF-less joint with a child and a root with rotations only."""
    s = math.sqrt(0.5)
    root = [Dof(f"pelvis_r{a}", "revolute", ax, -3.0, 3.0) for a, ax in (("z", (0, 0, 1)), ("x", (1, 0, 0)))]
    joints = [
        BodyJoint("pelvis", None, (0.0, 0.0, 0.0), root),
        BodyJoint("hip", "pelvis", (0.1, 0.0, -0.1), [Dof("hip_oblique", "revolute", (s, 0.0, s), -2, 2)]),
        BodyJoint(
            "knee",
            "hip",
            (0.0, 0.0, -0.4),
            [Dof("knee_a", "revolute", (1, 0, 0), -2, 2), Dof("knee_b", "revolute", (1, 0, 0), -2, 2)],
        ),
        BodyJoint("ankle", "knee", (0.0, 0.0, -0.4), [Dof("ankle_slide", "prismatic", (0, 1, 0), -1, 1)]),
        BodyJoint("toe", "ankle", (0.0, -0.1, 0.0)),
        BodyJoint("neck", "pelvis", (0.0, 0.0, 0.5)),  # fixed, with a child
        BodyJoint("head", "neck", (0.0, 0.0, 0.1), [Dof("head_ry", "revolute", (0, 1, 0), -1, 1)]),
        BodyJoint("head_end", "head", (0.0, 0.0, 0.2)),
    ]
    return Skeleton.from_urdf(build_urdf("oblique", joints))


@pytest.mark.parametrize("order", ["ZXY", "XYZ", "ZYX", "YZX", "XZY", "YXZ"])
def test_skeletons_without_channel_map_are_re_decomposed_exactly(order, tmp_path):
    skel = _oblique_skeleton()
    g = torch.Generator().manual_seed(1)
    theta = skel.clamp(torch.randn(30, len(skel.dof_names), generator=g, dtype=torch.float64))
    out = tmp_path / "oblique.bvh"
    save_bvh(out, skel, Motion(skel.dof_names, 30.0, theta), euler_order=order)
    joints, _, values = ref_parse(out.read_text())
    by_name = {j[0]: j[3] for j in joints}
    assert by_name["pelvis"] == ["Xposition", "Yposition", "Zposition"] + [f"{c}rotation" for c in order]
    assert by_name["hip"] == [f"{c}rotation" for c in order]  # the oblique hinge, re-decomposed
    assert by_name["knee"] == [f"{c}rotation" for c in order]  # two turns about one axis
    assert by_name["ankle"] == ["Zposition"]  # a prismatic DOF off the root, along world y = BVH -z
    assert by_name["head"] == ["Zrotation"]  # y (z up) is -z (y up): one channel, sign in the value
    names = [n if n != "toe" else "ankle_end" for n in skel.joint_names]  # a DOF-less leaf is an End Site
    ref = _reference_fk(out, 1.0, names)
    assert np.abs(ref - skel.fk(theta).numpy()).max() < 1e-6
    skel2, motion2 = load_bvh(out)
    fk2 = skel2.fk(motion2.angles)[:, [skel2.joint_names.index(n) for n in names]]
    assert torch.allclose(fk2, skel.fk(theta), atol=1e-6, rtol=0)


def _compose(order: str, angles: np.ndarray) -> np.ndarray:
    """R_order[0](a0) @ R_order[1](a1) @ R_order[2](a2), built element by element."""
    m = np.eye(3)
    for axis, v in zip(order, angles, strict=True):
        i = "XYZ".index(axis)
        j, k = (i + 1) % 3, (i + 2) % 3
        e = np.eye(3)
        e[j, j], e[j, k], e[k, j], e[k, k] = math.cos(v), -math.sin(v), math.sin(v), math.cos(v)
        m = m @ e
    return m


@pytest.mark.parametrize("order", ["XYZ", "ZYX", "ZXY", "YXZ", "XZY", "YZX"])
def test_euler_decomposition_reproduces_rotations_at_gimbal_lock(order):
    angles = np.random.default_rng(0).uniform(-3, 3, (60, 3))
    angles[:5, 1] = math.pi / 2  # gimbal lock
    angles[5:10, 1] = -math.pi / 2
    angles[10:15, 1] = math.pi / 2 - 1e-7  # near it
    R = np.stack([_compose(order, a) for a in angles])
    back = _euler_from_matrix(R, order)
    assert np.abs(np.stack([_compose(order, a) for a in back]) - R).max() < 1e-9


# ------------------------------------------------------------------------------------------------ errors
def test_unexportable_skeletons_and_motions_fail_clearly(human, tmp_path):
    theta = torch.zeros(2, len(human.dof_names), dtype=torch.float64)
    partial = Motion(human.dof_names[:-1], 30.0, theta[:, :-1])
    with pytest.raises(ValueError, match="lacks DOF"):
        save_bvh(tmp_path / "x.bvh", human, partial)
    with pytest.raises(ValueError, match="permutation of XYZ"):
        save_bvh(tmp_path / "x.bvh", human, Motion(human.dof_names, 30.0, theta), euler_order="XXY")
    # two trees side by side: no single ROOT
    two = Skeleton.from_urdf(human.urdf_xml, joint_names=["LeftUpLeg", "LeftLeg", "RightUpLeg", "RightLeg"])
    with pytest.raises(ValueError, match="one ROOT"):
        save_bvh(tmp_path / "x.bvh", two, Motion(two.dof_names, 30.0, torch.zeros(2, len(two.dof_names))))
    assert not (tmp_path / "x.bvh").exists()


# ------------------------------------------------------------------------------------------------ CLI
def test_export_cli(human, tmp_path, capsys):
    theta = 0.1 * torch.ones(5, len(human.dof_names), dtype=torch.float64)
    track = tmp_path / "track.csv"
    save_csv(track, Motion(human.dof_names, 30.0, theta))
    urdf = tmp_path / "human.urdf"
    human.save_urdf(urdf)
    out = tmp_path / "track.bvh"
    assert (
        main(["export", str(track), "--skeleton", str(urdf), "--out", str(out), "--scale", "0.056444"]) == 0
    )
    assert "wrote" in capsys.readouterr().out
    skel2, motion2 = load_bvh(out, CMU_SCALE)
    assert torch.allclose(motion2.angles, theta, atol=1e-6, rtol=0) and motion2.fps == pytest.approx(30.0)
    # a CSV of another skeleton: one line, exit status 2
    save_csv(track, Motion(["a", "b"], 30.0, torch.zeros(3, 2)))
    assert main(["export", str(track), "--skeleton", str(urdf), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("python -m training export: error:") and err.count("\n") == 1
