"""Fontmarty Table 5: the paper's groups, their 5 Hz -> fps rescaling and their mapping onto skeletons."""

import math
from types import SimpleNamespace

import pytest
import torch

from priors.table5 import EXTENSION, TABLE5, TABLE5_FPS, dof_groups, rescale, table5_sigma
from torchpf import Skeleton
from torchpf.assets import path

# Fontmarty et al. Table 5 (§3.3.2), at 5 Hz: the only numbers the paper gives.
PAPER = dict(base_translation=0.07, base_rotation=0.05, shoulder=0.1, elbow=0.3, hip=0.1, knee=0.1)

# Group of every joint's DOFs, pinned: these are the stds the random_walk prior (and every benchmark number
# made with it) used before the table got its own module.
F22_JOINTS = {
    "l_shoulder": "shoulder",
    "r_shoulder": "shoulder",
    "l_elbow": "elbow",
    "r_elbow": "elbow",
    "l_hip": "hip",
    "r_hip": "hip",
    "l_knee": "knee",
    "r_knee": "knee",
}
CMU_JOINTS = {
    **{j: "frozen" for j in ("LHipJoint", "RHipJoint", "LeftShoulder", "RightShoulder")},
    **{f"{s}{j}": "frozen" for s in ("Left", "Right") for j in ("FingerBase", "HandIndex1")},
    **{j: "frozen" for j in ("LThumb", "RThumb")},
    **{f"{s}{j}": "extremity" for s in ("Left", "Right") for j in ("Foot", "ToeBase", "Hand")},
    **{j: "spine" for j in ("LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head")},
    **{f"{s}Arm": "shoulder" for s in ("Left", "Right")},
    **{f"{s}ForeArm": "elbow" for s in ("Left", "Right")},
    **{f"{s}UpLeg": "hip" for s in ("Left", "Right")},
    **{f"{s}Leg": "knee" for s in ("Left", "Right")},
}


@pytest.fixture(scope="module")
def f22():
    return Skeleton.from_urdf(path("fontmarty22.urdf"))


@pytest.fixture(scope="module")
def human():
    return Skeleton.from_urdf(path("human.urdf"))


def _expected(skel, root, joints):
    """(D,) the pinned std of each DOF at 5 Hz."""
    out = []
    for d, j in enumerate(skel.dof_joints):
        name = skel.joint_names[j]
        if name == root:
            group = "base_rotation" if bool(skel.dof_revolute[d]) else "base_translation"
        else:
            group = joints[name]
        out.append({**PAPER, **EXTENSION}[group])
    return torch.tensor(out, dtype=torch.float64)


def test_the_table_is_the_papers():
    assert TABLE5 == PAPER and TABLE5_FPS == 5.0
    assert set(EXTENSION).isdisjoint(TABLE5)


def test_every_dof_of_the_22_dof_model_gets_its_paper_group(f22):
    assert set(dof_groups(f22)) == set(PAPER)  # the paper's model: no extension group needed
    torch.testing.assert_close(table5_sigma(f22), _expected(f22, "pelvis", F22_JOINTS), rtol=0, atol=0)
    sigma = dict(zip(f22.dof_names, table5_sigma(f22).tolist(), strict=True))
    assert sigma["pelvis_tx"] == 0.07 and sigma["pelvis_rz"] == 0.05
    assert (
        sigma["l_shoulder_ry"] == sigma["r_hip_rz"] == sigma["r_knee_rx"] == 0.1
        and sigma["l_elbow_rx"] == 0.3
    )


def test_every_dof_of_the_cmu_joint_tree_is_pinned(human):
    torch.testing.assert_close(table5_sigma(human), _expected(human, "Hips", CMU_JOINTS), rtol=0, atol=0)
    sigma = dict(zip(human.dof_names, table5_sigma(human, scale=2.0).tolist(), strict=True))
    assert sigma["Hips_Xposition"] == pytest.approx(0.14) and sigma["Hips_Yrotation"] == pytest.approx(0.1)
    assert sigma["LeftForeArm_Zrotation"] == pytest.approx(0.6)
    assert sigma["RightUpLeg_Xrotation"] == sigma["LeftArm_Yrotation"] == pytest.approx(0.2)
    assert sigma["RightLeg_Xrotation"] == pytest.approx(0.2)
    # unobservable and, in CMU data, constant joints are held still
    for dof in (
        "LeftShoulder_Zrotation",
        "LHipJoint_Xrotation",
        "RThumb_Yrotation",
        "LeftFingerBase_Xrotation",
    ):
        assert sigma[dof] == 0.0
    assert math.isclose(sigma["Spine1_Xrotation"], 0.1)


def test_the_base_is_found_from_structure_not_names():
    # the root is the joint with parent -1 and its kind comes from dof_revolute, whatever the DOFs are called
    skel = SimpleNamespace(
        joint_names=["torso", "LeftForeArm"],
        parents=[-1, 0],
        dof_joints=[0, 0, 0, 1],
        dof_names=["a_rotation", "b_position", "c", "d"],
        dof_revolute=torch.tensor([False, True, False, True]),
    )
    assert dof_groups(skel) == ["base_translation", "base_rotation", "base_translation", "elbow"]


def test_fps_rescaling(f22):
    # a random walk's variance grows linearly with time: 20 Hz steps have half the 5 Hz std
    torch.testing.assert_close(table5_sigma(f22, fps=20.0), table5_sigma(f22) / 2)
    assert rescale(0.3, 45.0) == pytest.approx(0.1)
    with pytest.raises(ValueError, match="fps"):
        table5_sigma(f22, fps=0)
