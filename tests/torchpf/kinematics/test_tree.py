"""KinematicTree: the index tensors against pytorch-kinematics' chain and the URDF joint types, buffers and
freezing, and the body partition (Fontmarty Table 2)."""

import xml.etree.ElementTree as ET

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import path
from torchpf.kinematics import KinematicTree, body_partition
from torchpf.kinematics.urdf import flatten_chain, read_urdf_text


@pytest.fixture(params=["human", "f22", "odd", "telescope"])
def skel(request):
    return request.getfixturevalue(request.param)


def _ancestors(chain) -> list[set[int]]:
    """pytorch-kinematics frame index -> its ancestors' indices, itself included."""
    return [set(p.tolist()) for p in chain.parents_indices]


def test_parents_follow_the_chain(skel):
    chain, tree = skel.chain, skel.tree
    idx = [chain.frame_to_idx[n] for n in skel.joint_names]
    for j, p in enumerate(tree.parents.tolist()):
        above = chain.parents_indices[idx[j]].tolist()[:-1]  # strict ancestors, root first
        body_above = [a for a in above if a in idx]
        assert p == (idx.index(body_above[-1]) if body_above else -1)
        assert p < j  # parents before children
    assert skel.parents == tree.parents.tolist()


def test_levels_and_runs_follow_the_chain(skel):
    chain, tree = skel.chain, skel.tree
    anc = _ancestors(chain)
    names = [f.name for f in flatten_chain(chain)]
    node_pk = [chain.frame_to_idx[names[i]] for i in tree.node_frame.tolist()]
    parent = tree.node_parent.tolist()
    starts = tree.level_starts.tolist()
    assert starts[0] == 0 and starts[-1] == tree.n_nodes and starts == sorted(set(starts))
    for level, (s, e) in enumerate(tree.levels()):
        for r in range(s, e):
            if level == 0:
                assert parent[r] == -1
            else:  # every parent in the level above: one batched product per level
                assert starts[level - 1] <= parent[r] < s
    # a node's run: the DOFs above its frame and below its parent node's frame, root side first
    dof_frame = {d: i for i, d in enumerate(chain.joint_indices.tolist()) if d >= 0}
    for r, run in enumerate(tree.node_runs()):
        above = anc[node_pk[r]] - (anc[node_pk[parent[r]]] if parent[r] >= 0 else set())
        expected = sorted(
            (d for d, f in dof_frame.items() if f in above), key=lambda d: len(anc[dof_frame[d]])
        )
        assert run == expected
        assert all(tree.dof_node[d] == r for d in run)
    assert (tree.node_dofs >= 0).sum() == sum(len(r) for r in tree.node_runs())
    assert torch.equal(
        tree.joint_node, torch.tensor([node_pk.index(chain.frame_to_idx[n]) for n in skel.joint_names])
    )


def test_moves_and_owners_follow_the_chain(skel):
    chain, tree = skel.chain, skel.tree
    anc = _ancestors(chain)
    dof_frame = {d: i for i, d in enumerate(chain.joint_indices.tolist()) if d >= 0}
    joint_pk = [chain.frame_to_idx[n] for n in skel.joint_names]
    expected = torch.tensor([[dof_frame[d] in anc[f] for f in joint_pk] for d in range(tree.n_dofs)])
    assert torch.equal(tree.dof_moves, expected)
    parents = tree.parents.tolist()
    for d, j in enumerate(tree.dof_joint.tolist()):
        # the owner is the first body joint below the DOF: moved by it, its parent joint not
        assert tree.dof_moves[d, j] and (parents[j] < 0 or not tree.dof_moves[d, parents[j]])
    assert skel.dof_joints == tree.dof_joint.tolist()


def test_revolute_mask_is_the_urdf_joint_types(skel):
    xml, _ = read_urdf_text(skel.source)
    types = {j.get("name"): j.get("type") for j in ET.fromstring(xml).iter("joint")}
    expected = [types[n] in ("revolute", "continuous") for n in skel.dof_names]
    assert skel.tree.dof_revolute.tolist() == expected and skel.dof_revolute.tolist() == expected
    assert all(types[n] == "prismatic" for n, rev in zip(skel.dof_names, expected, strict=True) if not rev)
    kinds = skel.chain.joint_type_indices[[skel.chain.frame_to_idx[f] for f in _dof_child_links(skel)]]
    assert torch.equal(kinds == 1, skel.tree.dof_revolute)  # pytorch-kinematics: 1 revolute, 2 prismatic


def _dof_child_links(skel) -> list[str]:
    xml, _ = read_urdf_text(skel.source)
    child = {j.get("name"): j.find("child").get("link") for j in ET.fromstring(xml).iter("joint")}
    return [child[n] for n in skel.dof_names]


def test_bones_and_partition_fields(skel):
    tree = skel.tree
    assert torch.equal(tree.bones, torch.tensor(skel.bones, dtype=torch.long).reshape(-1, 2))
    assert all(tree.parents[c] == p for p, c in tree.bones.tolist())
    assert tree.joint_part[tree.parents.tolist().index(-1)] == 0  # the root is torso


def test_fields_are_buffers_and_frozen(f22):
    tree = f22.tree
    buffers = dict(f22.named_buffers())
    assert all(buffers[f"tree.{name}"] is getattr(tree, name) for name in KinematicTree.FIELDS)
    assert f22.state_dict().keys().isdisjoint(f"tree.{name}" for name in KinematicTree.FIELDS)
    with pytest.raises(AttributeError, match="frozen"):
        tree.parents = torch.zeros(15, dtype=torch.long)
    tree.eval()  # nn.Module bookkeeping still works
    copy = tree.replace(joint_part=torch.zeros(15, dtype=torch.long))
    assert copy.joint_part.tolist() == [0] * 15 and copy.parents is tree.parents
    assert tree.joint_part.tolist() != [0] * 15
    calls = []
    for _ in range(2):
        value = tree.cached(("test", torch.float32), lambda: calls.append(1) or len(calls))
    assert value == 1 and calls == [1]
    with pytest.raises(TypeError, match="missing"):
        KinematicTree(parents=tree.parents)


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


@pytest.mark.parametrize("per_limb", [False, True])
def test_partition_covers_every_dof_and_joint_once(skel, per_limb):
    D, J = len(skel.dof_names), len(skel.joint_names)
    groups = body_partition(skel, per_limb=per_limb)
    assert sorted(d for g in groups for d in g) == list(range(D))
    assert all(g == sorted(g) for g in groups)
    joints = body_partition(skel.tree, per_limb=per_limb, joints=True)
    assert sorted(j for g in joints for j in g) == list(range(J))
    # a DOF sits in the group of the joint it moves first
    for g, js in zip(groups, joints, strict=True):
        assert all(skel.dof_joints[d] in js for d in g)
