"""Structural random-walk stds: from the tree and the capsules, never from names (priors.diffusion)."""

import logging
import math
import re
import warnings

import pytest
import torch

from priors.diffusion import (
    ANGULAR_SPEEDS,
    SPEEDS,
    diffusion_sigma,
    dof_classes,
    lever_arms,
    rest_pose,
    sigma_summary,
    structural_sigma,
)
from priors.factories import random_walk
from priors.table5 import table5_sigma
from torchpf import Skeleton
from torchpf.assets import path
from torchpf.kinematics.urdf import BodyJoint, Dof, build_urdf, floating_root_dofs

FPS = 30.0

# 3ds Max / MotionBuilder naming of the CMU tree: the ball joint of the shoulder is "Shoulder", the
# clavicle "Collar", the hip "UpLeg" becomes "Hip" and the knee "Knee".
RENAME = {
    f"{side}{old}": f"{side}{new}"
    for side in ("Left", "Right")
    for old, new in (
        ("Shoulder", "Collar"),
        ("Arm", "Shoulder"),
        ("ForeArm", "Elbow"),
        ("Hand", "Wrist"),
        ("UpLeg", "Hip"),
        ("Leg", "Knee"),
        ("Foot", "Ankle"),
    )
}


@pytest.fixture(scope="module")
def human():
    return Skeleton.from_urdf(path("human.urdf"))


@pytest.fixture(scope="module")
def f22():
    return Skeleton.from_urdf(path("fontmarty22.urdf"))


@pytest.fixture(scope="module")
def renamed():
    text = path("human.urdf").read_text()
    pattern = re.compile(
        r"(?<![A-Za-z])(" + "|".join(sorted(RENAME, key=len, reverse=True)) + r")(?![A-Za-z])"
    )
    return Skeleton.from_urdf(pattern.sub(lambda m: RENAME[m.group(1)], text))


@pytest.fixture(scope="module")
def handless():
    """A torso with one arm whose wrist and two fingers have DOFs but no geometry (zero-length bones)."""
    rz = (Dof("chest_rz", "revolute", (0.0, 0.0, 1.0)), Dof("chest_rx", "revolute", (1.0, 0.0, 0.0)))
    joints = [
        BodyJoint("pelvis", None, (0.0, 0.0, 1.0), floating_root_dofs("pelvis")),
        BodyJoint("chest", "pelvis", (0.0, 0.0, 0.5), rz),
        BodyJoint("hand", "chest", (0.6, 0.0, 0.0), (Dof("wrist_rx", "revolute", (1.0, 0.0, 0.0)),)),
        BodyJoint("finger", "hand", (0.0, 0.0, 0.0), (Dof("finger_ry", "revolute", (0.0, 1.0, 0.0)),)),
        BodyJoint("thumb", "hand", (0.0, 0.0, 0.0), (Dof("thumb_ry", "revolute", (0.0, 1.0, 0.0)),)),
    ]
    return Skeleton.from_urdf(build_urdf("handless", joints))


def _max_capsule_displacement(skel, d, step):
    """Largest displacement (m) of a capsule surface point when DOF ``d`` moves by ``step`` from the rest
    pose, from FK alone: a moved end sphere of radius r moves by its centre's displacement plus the chord
    ``2 r sin(step / 2)`` of a rotation (0 for a translation)."""
    x0 = rest_pose(skel)
    x1 = x0.clone()
    x1[d] += step
    (e0, r), (e1, _) = skel.capsules(x0), skel.capsules(x1)
    moved = (e1 - e0).norm(dim=-1)  # (C, 2)
    spin = 2 * math.sin(step / 2) if bool(skel.dof_revolute[d]) else 0.0
    return float(torch.where(moved > 1e-12, moved + r[:, None] * spin, torch.zeros_like(moved)).max())


def test_renamed_joints_get_identical_stds(human, renamed):
    assert "LeftShoulder_Zrotation" in renamed.dof_names and "LeftCollar_Zrotation" in renamed.dof_names
    assert renamed.dof_names != human.dof_names
    assert torch.equal(structural_sigma(renamed, FPS), structural_sigma(human, FPS))
    assert torch.equal(random_walk(renamed, fps=FPS).sigma, random_walk(human, fps=FPS).sigma)
    # what the name table did to this skeleton: the shoulder ball joints held still
    sigma = dict(zip(renamed.dof_names, table5_sigma(renamed, FPS).tolist(), strict=True))
    assert sigma["LeftShoulder_Zrotation"] == 0.0
    # ... and what table5 does now: the DOFs it would hold still or does not know take structural stds
    with pytest.warns(UserWarning, match="Table 5 holds still or does not recognise"):
        refined = random_walk(renamed, fps=FPS, stds="table5").sigma
    assert (refined[structural_sigma(renamed, FPS) > 0] > 0).all()


def test_dofs_without_geometry_are_held_still(handless, human, f22):
    sigma = dict(zip(handless.dof_names, structural_sigma(handless, FPS).tolist(), strict=True))
    assert sigma["wrist_rx"] == sigma["finger_ry"] == sigma["thumb_ry"] == 0.0
    assert sigma["chest_rz"] > 0 and sigma["chest_rx"] > 0 and sigma["pelvis_tx"] > 0
    for skel in (handless, human, f22):
        sigma = structural_sigma(skel, FPS)
        for d in range(len(skel.dof_names)):
            if _max_capsule_displacement(skel, d, 0.1) > 1e-9:  # it moves a capsule: it must be free
                assert sigma[d] > 0, skel.dof_names[d]


def test_the_std_moves_the_farthest_capsule_point_by_the_set_distance(human, f22):
    for skel in (human, f22):
        sigma, classes = structural_sigma(skel, FPS), dof_classes(skel)
        cap = torch.tensor([ANGULAR_SPEEDS.get(c, math.inf) / FPS for c in classes], dtype=torch.float64)
        capped = torch.isclose(sigma, cap, rtol=1e-12, atol=0)  # short levers: held to an angular speed
        ratio = torch.zeros(len(sigma), dtype=torch.float64)
        for d in range(len(sigma)):
            if sigma[d] > 0:
                ratio[d] = _max_capsule_displacement(skel, d, float(sigma[d])) / (SPEEDS[classes[d]] / FPS)
        # no capsule point moves farther than the set distance; the lever is the distance to the pivot, so
        # the DOF of each joint whose axis lies square to its farthest point moves that point by it exactly
        assert float(ratio.max()) <= 1 + 1e-6 and (sigma <= cap * (1 + 1e-12)).all()
        for j in set(skel.dof_joints):
            mine = [d for d, k in enumerate(skel.dof_joints) if k == j and sigma[d] > 0]
            if mine and not capped[mine].any():
                assert float(ratio[mine].max()) == pytest.approx(1.0, rel=0.01), skel.joint_names[j]
    # the cap bites on the short levers only: hands, feet, thumbs and the neck, not hips, knees, shoulders
    sigma = dict(zip(human.dof_names, structural_sigma(human, FPS).tolist(), strict=True))
    assert (
        sigma["LThumb_Xrotation"]
        == sigma["LeftHand_Zrotation"]
        == pytest.approx(ANGULAR_SPEEDS["limb"] / FPS)
    )
    assert max(sigma[f"Left{j}_Xrotation"] for j in ("UpLeg", "Leg", "Arm")) < ANGULAR_SPEEDS["limb"] / FPS


def test_structure_decides_classes_and_fps_scales_like_a_speed(human, f22):
    classes = dict(zip(f22.dof_names, dof_classes(f22), strict=True))
    assert classes["pelvis_tx"] == "root_translation" and classes["pelvis_rz"] == "root_rotation"
    assert (
        classes["l_knee_rx"] == "limb"
        and dof_classes(human)[human.dof_names.index("Spine_Xrotation")] == "torso"
    )
    # doubling the rate halves the std (the chord is nearly the arc; 0.4 % off for the fingers at 60 fps)
    torch.testing.assert_close(
        structural_sigma(human, 120.0), structural_sigma(human, 60.0) / 2, rtol=0.01, atol=0
    )
    fast = structural_sigma(
        f22, FPS, speeds={"limb": 2 * SPEEDS["limb"]}, angular_speeds={"limb": 2 * ANGULAR_SPEEDS["limb"]}
    )
    slow = structural_sigma(f22, FPS)
    limb = torch.tensor([c == "limb" for c in dof_classes(f22)])
    assert (fast[limb] > 1.9 * slow[limb]).all() and torch.equal(fast[~limb], slow[~limb])
    assert (lever_arms(f22) > 0).all()
    with pytest.raises(ValueError, match="speed class"):
        structural_sigma(f22, FPS, speeds={"arms": 1.0})
    with pytest.raises(ValueError, match="fps"):
        structural_sigma(f22, 0.0)


def test_factory_logs_a_summary_and_warns_when_it_guesses(f22, human, caplog):
    with caplog.at_level(logging.INFO, logger="priors"), warnings.catch_warnings():
        warnings.simplefilter("error")  # fps given, structural: no guess, no warning
        random_walk(f22, fps=FPS)
    (line,) = [r.getMessage() for r in caplog.records]
    assert line.startswith("random_walk stds (structural, 30 fps, per frame): root ")
    assert all(part in line for part in ("leg1", "leg2", "arm1", "arm2"))
    assert (
        sigma_summary(human, structural_sigma(human, FPS), fps=FPS).count(";") == 5
    )  # root torso 2 legs 2 arms
    with pytest.warns(UserWarning, match="no fps given"):
        random_walk(f22)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the paper's own model: every group recognised, nothing replaced
        torch.testing.assert_close(random_walk(f22, fps=FPS, stds="table5").sigma, table5_sigma(f22, FPS))
    given = torch.full((22,), 0.01, dtype=torch.float64)
    torch.testing.assert_close(diffusion_sigma(f22, given, fps=FPS, scale=2.0), 2 * given)
    with pytest.raises(ValueError, match="stds must"):
        diffusion_sigma(f22, "names", fps=FPS)
    with pytest.raises(ValueError, match="shape"):
        diffusion_sigma(f22, given[:3], fps=FPS)
