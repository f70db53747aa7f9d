"""The shipped human model's joint limits admit real walking and running (CMU clips, same DOF names)."""

from pathlib import Path

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import path
from training.mocap import load_bvh

CMU = Path(__file__).resolve().parents[2].parent / "shared" / "mocap" / "cmu"
CLIPS = sorted(CMU.glob("*.bvh"))
# The hand end effectors of real CMU data carry marker glitches and +-180 degree Euler flips.
GLITCHY = ("FingerBase", "Thumb")


@pytest.mark.skipif(not CLIPS, reason=f"CMU clips not found in {CMU}")
def test_cmu_motions_drive_the_human_model_within_its_limits():
    human = Skeleton.from_urdf(path("human.urdf"))
    keep = torch.tensor([not any(g in n for g in GLITCHY) for n in human.dof_names])
    for clip in CLIPS:
        _, motion = load_bvh(clip, scale=0.056444)
        assert motion.dof_names == human.dof_names, clip.name
        angles = motion.angles[1:]  # frame 0 of a CMU clip is a rest pose
        inside = ((angles >= human.lower) & (angles <= human.upper)).all(0)
        outside = [n for n, ok, k in zip(human.dof_names, inside, keep, strict=True) if k and not ok]
        assert not outside, f"{clip.name}: {outside}"
