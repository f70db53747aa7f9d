"""Guesses from a skeleton's structure: joint limits for the joints it leaves unlimited, and which limbs are
its arms.

A skeleton converted from BVH has no joint limits (the format has none), so every rotation may turn by a
full circle. Most rotations cannot be limited without knowing what the person does (an arm raised, a leg
kicked), but the torso's cannot turn far whatever the action: a back or a neck bends about a radian either
way in all, spread over the three or more joints a rig splits it into (the shipped ``human.urdf`` gives each
spine joint +-0.52 rad about two of its axes and -0.52 to 1.05 about the third). :func:`torso_limits`
holds each unlimited rotation of the torso chain (the chain from the root towards the highest joint of the
rest pose, :func:`~torchpf.kinematics.tree.partition_labels`: pelvis, spine, neck, head; the root's own DOFs
excluded) within ``+-limit`` rad of the rest pose. No joint name is read.

Measured (BENCHMARKS.md, "Which joint limits carry the gain"): the torso rotations of the 11 CMU walks and
runs, converted, stay within 0.54 rad of the rest pose (0.5 clamps the neck of 07_01 by < 0.04 rad, its
head by < 1 cm). On noisy foreign renders of those clips, joint limits learned from other performers' mocap
took ``track`` from 67 to 51 mm; those of the torso alone to 60 mm (two draws of the defects), of the arms
alone to 57, of the hips and knees to 65. This module's action-free guess, +-0.5 rad on the torso, tracked
ten draws at 66.6 mm against 67.5 (paired -0.9, standard error 1.4) with more frames failed (21.5 % against
19.7), so :class:`~torchpf.tracker.Tracker` applies it only when asked (``torso_limit=0.5``, ``track
--torso-limit 0.5``).

The arms (:func:`arm_bones`) are the limbs that hang off the torso chain above the root in the rest pose
(the legs hang off the root or the pelvis): ``Tracker.hold_thin_arms`` keeps their capsules' widths as the
skeleton has them where the masks are too coarse and noisy to measure them.

Example::

    from torchpf.kinematics.anatomy import arm_bones, torso_limits
    limited, names = torso_limits(skeleton)        # a Skeleton, and the DOFs it limited
    arms = arm_bones(skeleton)                     # indices into skeleton.bones
"""

from __future__ import annotations

import math

import torch

#: Half-range (rad) of a torso rotation around the rest pose, measured (:func:`torso_limits`' default).
TORSO_LIMIT = 0.5


def torso_rotations(skeleton) -> list[int]:
    """Indices of the revolute DOFs of the torso chain's joints below the root (``tree.joint_part == 0``,
    a parent): the spine, neck and head of a humanoid, from the tree and the rest pose only."""
    tree = skeleton.tree
    part, parents = tree.joint_part.tolist(), tree.parents.tolist()
    revolute = tree.dof_revolute.tolist()
    return [
        d
        for d, j in enumerate(tree.dof_joint.tolist())
        if j >= 0 and part[j] == 0 and parents[j] >= 0 and revolute[d]
    ]


def torso_limits(skeleton, limit: float = TORSO_LIMIT, *, full_turn: float = 1.9 * math.pi):
    """``skeleton`` with each *unlimited* torso rotation (:func:`torso_rotations` among
    :meth:`~torchpf.skeleton.Skeleton.free_rotations`: limits spanning ``full_turn`` rad) held within
    ``[-limit, limit]`` rad of the rest pose; limits the skeleton has are kept.

    Args:
        skeleton: a :class:`~torchpf.skeleton.Skeleton`.
        limit: the half-range (rad, > 0).
        full_turn: the span (rad) from which a DOF counts as unlimited.

    Returns:
        ``(limited, names)``: the skeleton (the same object when nothing was unlimited) and the names of the
        DOFs it limited.
    """
    if not limit > 0:
        raise ValueError(f"torso_limits: limit must be > 0 rad, got {limit}")
    unlimited = set(skeleton.free_rotations(full_turn))  # the torso's rotations are posture DOFs
    free = [d for d in torso_rotations(skeleton) if skeleton.dof_names[d] in unlimited]
    if not free:
        return skeleton, []
    D = len(skeleton.dof_names)
    lower = torch.full((D,), -math.inf, dtype=torch.float64)
    upper = torch.full((D,), math.inf, dtype=torch.float64)
    lower[free], upper[free] = -float(limit), float(limit)
    return skeleton.with_limits(lower, upper), [skeleton.dof_names[d] for d in free]


def arm_bones(skeleton) -> list[int]:
    """Indices into ``skeleton.bones`` of the capsules of the arms: the limbs (``tree.joint_part > 0``) whose
    attachment joint on the torso chain lies above the root in the rest pose (z up), where the legs hang
    off the root itself or off a pelvis joint at its height. From the tree and the rest pose only; empty
    for a skeleton without such limbs."""
    tree = skeleton.tree
    part, parents = tree.joint_part.tolist(), tree.parents.tolist()
    rest = skeleton.rest_joints()
    roots = [j for j, p in enumerate(parents) if p < 0]
    if not roots:
        return []
    root_z = float(rest[roots[0], 2])
    arms = set()
    for j, p in enumerate(parents):
        if part[j] > 0 and p >= 0 and part[p] == 0 and float(rest[p, 2]) > root_z + 1e-6:
            arms.add(part[j])
    return [k for k, (_, c) in enumerate(skeleton.bones) if part[c] in arms]
