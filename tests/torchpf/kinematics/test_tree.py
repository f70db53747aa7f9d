"""KinematicTree: the index tensors against pytorch-kinematics and the URDF, the body partition."""

from torchpf import Skeleton
from torchpf.assets import path
from torchpf.kinematics import body_partition


def test_body_partition_covers_every_dof_once():
    skel = Skeleton.from_urdf(path("human.urdf"))
    groups = body_partition(skel, per_limb=True)
    flat = sorted(d for g in groups for d in g)
    assert flat == list(range(96))
    torso = {skel.dof_names[d] for d in groups[0]}
    assert {"Hips_Xposition", "Spine_Xrotation", "Head_Yrotation"} <= torso
    assert len(groups) == 5  # torso, two legs, two arms
    limbs = [{skel.dof_names[d].split("_")[0] for d in g} for g in groups[1:]]
    assert any("LeftForeArm" in limb for limb in limbs) and any("RightLeg" in limb for limb in limbs)
    two = body_partition(skel)  # Fontmarty's two partitions: torso, then every limb
    assert two[0] == groups[0] and sorted(two[1]) == sorted(d for g in groups[1:] for d in g)
    f22 = Skeleton.from_urdf(path("fontmarty22.urdf"))
    assert [len(g) for g in body_partition(f22, per_limb=True)] == [6, 4, 4, 4, 4]  # ball (3) + hinge (1)
    assert [len(g) for g in body_partition(f22)] == [6, 16]
    assert [f22.joint_names[j] for j in body_partition(f22, joints=True)[0]] == ["pelvis", "neck", "head_top"]
