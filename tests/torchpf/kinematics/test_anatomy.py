"""torchpf.kinematics.anatomy: the torso's rotations found from the tree, and limited where a skeleton has no
limits (a converted BVH); the arms found from the tree and the rest pose."""

import math
import re
import warnings
from pathlib import Path

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import path
from torchpf.kinematics.anatomy import TORSO_LIMIT, arm_bones, torso_limits, torso_rotations

CMU = Path(__file__).resolve().parents[3].parent / "shared" / "mocap" / "cmu"


def _unlimited(skel: Skeleton, keep=()) -> Skeleton:
    """``skel`` with every revolute DOF but those in ``keep`` turning a full circle (as BVH gives them)."""
    revolute = skel.tree.dof_revolute.cpu()
    lower, upper = skel.lower.clone().cpu(), skel.upper.clone().cpu()
    free = revolute.clone()
    free[list(keep)] = False
    lower[free], upper[free] = -math.pi, math.pi
    return skel.with_limits(lower, upper)


def _renamed(skel: Skeleton, tmp_path) -> Skeleton:
    """The same URDF with every joint and link called by a number: nothing left to read in the names."""
    xml = skel.urdf_xml
    names = sorted(set(re.findall(r'name="([^"]+)"', xml)), key=len, reverse=True)
    for i, name in enumerate(names):
        xml = xml.replace(f'"{name}"', f'"n{i}"')
    f = tmp_path / "renamed.urdf"
    f.write_text(xml)
    return Skeleton.from_urdf(str(f))


def _chain_to_the_top(skel: Skeleton) -> list[int]:
    """Reference: the revolute DOFs of the ancestors of the highest joint at rest (itself included), the
    root excepted: the pelvis-to-head chain, found another way than ``partition_labels``' greedy walk."""
    rest = skel.fk(torch.zeros(len(skel.dof_names), dtype=torch.float64))
    parents = skel.tree.parents.tolist()
    j, chain = int(rest[:, 2].argmax()), set()
    while parents[j] >= 0:
        chain.add(j)
        j = parents[j]
    revolute = skel.tree.dof_revolute.tolist()
    return [d for d, k in enumerate(skel.tree.dof_joint.tolist()) if k in chain and revolute[d]]


def test_the_torso_is_the_chain_from_the_root_to_the_top_whatever_the_names(tmp_path):
    human = Skeleton.from_urdf(path("human.urdf"))
    found = torso_rotations(human)
    assert found == _chain_to_the_top(human)
    assert {human.dof_names[d].split("_")[0] for d in found} == {
        "LowerBack",
        "Spine",
        "Spine1",
        "Neck",
        "Neck1",
        "Head",
    }
    assert torso_rotations(_renamed(human, tmp_path)) == found
    # the 22-DOF Fontmarty model: its torso chain (pelvis, neck, head top) turns only at the root
    f22 = Skeleton.from_urdf(path("fontmarty22.urdf"))
    assert torso_rotations(f22) == _chain_to_the_top(f22) == []


def test_only_the_unlimited_torso_rotations_get_the_limit():
    human = Skeleton.from_urdf(path("human.urdf"))
    torso = torso_rotations(human)
    kept = torso[4]  # one torso DOF that has a limit of its own
    skel = _unlimited(human, keep=[kept])
    limited, names = torso_limits(skel, 0.4)
    assert names == [skel.dof_names[d] for d in torso if d != kept]
    others = [d for d in range(len(skel.dof_names)) if d not in torso]
    for d in torso:
        if d == kept:
            assert (float(limited.lower[d]), float(limited.upper[d])) == (
                float(human.lower[d]),
                float(human.upper[d]),
            )
        else:
            assert (float(limited.lower[d]), float(limited.upper[d])) == pytest.approx((-0.4, 0.4))
    assert torch.equal(limited.lower[others], skel.lower[others])
    assert torch.equal(limited.upper[others], skel.upper[others])
    # the body is the same; limited once, there is nothing left to guess
    theta = torch.zeros(len(skel.dof_names), dtype=torch.float64)
    assert torch.equal(limited.fk(theta), skel.fk(theta))
    again, none = torso_limits(limited, 0.4)
    assert again is limited and none == []
    # a skeleton with limits everywhere (the shipped model) is left as it is
    assert torso_limits(human)[1] == []
    for bad in (0.0, -0.5, float("nan")):
        with pytest.raises(ValueError, match="limit must be > 0"):
            torso_limits(skel, bad)


def test_the_tracker_limits_an_unlimited_torso_and_says_so():
    from torchpf.tracker import Tracker

    human = Skeleton.from_urdf(path("human.urdf"))
    skel = _unlimited(human)
    torso = torso_rotations(skel)
    with pytest.warns(UserWarning, match=r"18 rotations of the skeleton's torso chain .* within 0.5 rad"):
        tracker = Tracker(
            skel, None, likelihood="pointcloud", n_particles=20, torso_limit=TORSO_LIMIT, progress=False
        )
    assert torch.equal(tracker.skeleton.upper[torso], torch.full((len(torso),), 0.5, dtype=torch.float64))
    # a bent initial pose starts the particles clamped into the limits
    bent = torch.zeros(len(skel.dof_names))
    bent[torso] = 1.0
    x0 = tracker.initial_particles(bent, torch.Generator().manual_seed(0))
    assert float(x0[:, torso].max()) <= 0.5 and float(x0[:, torso].min()) > 0.4
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        as_given = Tracker(skel, None, likelihood="pointcloud", n_particles=20, progress=False)  # default
        assert torch.equal(as_given.skeleton.upper, skel.upper)
        # rebuilt on its own (limited) skeleton, e.g. a fitted body: nothing more to guess, no warning
        tracker.with_skeleton(tracker.skeleton)
        Tracker(human, None, likelihood="pointcloud", n_particles=20, torso_limit=0.5, progress=False)


@pytest.mark.skipif(not (CMU / "07_01.bvh").is_file(), reason="CMU clips not present")
@pytest.mark.parametrize("clip", ["07_01", "16_46"])
def test_a_converted_cmu_clip_moves_its_torso_within_the_suggested_limit(clip):
    """The premise of the limit, on real mocap: a walk and a run turn each torso joint by < 0.55 rad, and
    the limits move no joint of their poses by 1.5 cm."""
    from training.mocap import CMU_SCALE, convert_bvh

    _, skel, motion, _ = convert_bvh(CMU / f"{clip}.bvh", CMU_SCALE)
    limited, names = torso_limits(skel)
    assert [n.split("_")[0] for n in names[::3]] == ["LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head"]
    torso = torso_rotations(skel)
    angles = motion.angles[1:, torso]  # frame 0 is the CMU rest pose
    assert float(angles.abs().max()) < TORSO_LIMIT + 0.05
    # where the neck reaches beyond the limit (07_01: up to 0.54 rad), the clamped pose is still that pose
    truth = motion.angles[1:].double()
    moved = (limited.fk(limited.clamp(truth)) - skel.fk(truth)).norm(dim=-1).amax()
    assert float(moved) < 0.015


@pytest.mark.parametrize("asset", ["human.urdf", "fontmarty22.urdf"])
def test_the_arms_are_the_limbs_hanging_off_the_torso_above_the_root(asset, tmp_path):
    """Both shipped bodies (a 31-joint CMU-like rig, Fontmarty's 22-DOF model): the arms' bones are every
    bone of the two limbs attached to the torso chain above the root (their hands the highest limb joints
    but the head's, their roots off the chest), whatever the joints are called; the legs are not."""
    skel = Skeleton.from_urdf(path(asset))
    renamed = _renamed(skel, tmp_path)
    arms = arm_bones(skel)
    assert arms == arm_bones(renamed)
    part, parents = skel.tree.joint_part.tolist(), skel.tree.parents.tolist()
    rest = skel.fk(torch.zeros(len(skel.dof_names), dtype=torch.float64))
    limbs = {part[c] for k, (_, c) in enumerate(skel.bones) if k in arms}
    assert len(limbs) == 2  # two arms, every bone of each
    assert sorted(arms) == [k for k, (_, c) in enumerate(skel.bones) if part[c] in limbs]
    root_z = float(rest[0, 2])
    for j, p in enumerate(parents):
        if part[j] > 0 and p >= 0 and part[p] == 0:  # a limb's attachment on the torso chain
            assert (part[j] in limbs) == (float(rest[p, 2]) > root_z + 0.2)  # arms off the chest
    names = {skel.joint_names[skel.bones[k][1]].lower() for k in arms}
    assert not any("leg" in n or "knee" in n or "foot" in n for n in names)
