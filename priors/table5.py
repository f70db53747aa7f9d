"""Fontmarty Table 5: the random-walk stds per joint group, and their mapping onto a skeleton's DOFs.

Fontmarty, Danès & Lerasle, "Evaluations of particle filter based human motion visual trackers", §3.3.2,
Table 5 ("Standard deviation of the random walk dynamics applied on each DOF of the human body
configuration"), given at an acquisition rate of 5 Hz:

================================  ==========
base translations                 0.07 m
base rotations                    0.05 rad
shoulder ball joints              0.1 rad
elbow hinge joints                0.3 rad
hip ball joints                   0.1 rad
knee hinge joints                 0.1 rad
================================  ==========

* :data:`TABLE5` -- the table verbatim (group -> std at :data:`TABLE5_FPS`).
* :func:`rescale` -- a random walk's variance grows linearly in time, so a 5 Hz std becomes
  ``std * sqrt(5 / fps)`` per frame at ``fps``.
* :func:`dof_groups` -- the group of each DOF of a skeleton. The base is the root joint (the one whose parent
  is ``-1``), its prismatic DOFs are translations and its revolute ones rotations (``skeleton.dof_revolute``).
  Limb joints are recognised by name (the 22-DOF model's ``l_shoulder``/``l_elbow``/``l_hip``/``l_knee``, the
  CMU joint tree's ``LeftArm``/``LeftForeArm``/``LeftUpLeg``/``LeftLeg``). The table covers the 22 DOFs of
  Fontmarty's model only; the other joints of a richer skeleton (the CMU tree of ``human.urdf``) get the
  groups of :data:`EXTENSION`, which are ours, not the paper's.
* :func:`table5_sigma` -- the ``(D,)`` per-DOF std at ``fps``: the ``stds="table5"`` option of the
  ``random_walk``, ``constant_velocity`` and ``damped`` factories (:func:`priors.diffusion.diffusion_sigma`,
  which refines it so that no DOF that moves the body is held still), and the ``--dynamics table5`` walk of
  ``benchmarks/evaluate.py``. The factories' default reads no names: :mod:`priors.diffusion`.

Example::

    from priors.table5 import table5_sigma
    sigma = table5_sigma(skel, fps=15.0)          # (D,) float64, rad or m per frame
"""

from __future__ import annotations

import re

import torch

#: Fontmarty Table 5 verbatim: random-walk std per joint group at :data:`TABLE5_FPS` (rad; m for the base
#: translations).
TABLE5 = {
    "base_translation": 0.07,
    "base_rotation": 0.05,
    "shoulder": 0.1,
    "elbow": 0.3,
    "hip": 0.1,
    "knee": 0.1,
}
#: Acquisition rate (Hz) at which Table 5 is given.
TABLE5_FPS = 5.0

#: Groups beyond the paper's 22-DOF model (std at :data:`TABLE5_FPS`, rad), for the other joints of the CMU
#: joint tree: ``frozen`` joints that real CMU data keeps at zero and silhouettes cannot see (clavicles, the
#: pelvis-to-hip links, fingers, thumbs) are held still; ``extremity`` (hands, feet, toes) and ``spine``
#: (back, neck, head) move; ``other`` is any joint not recognised.
EXTENSION = {"frozen": 0.0, "extremity": 0.1, "spine": 0.05, "other": 0.05}

# Non-root joint name -> group, first match wins (so a frozen "LeftShoulder" clavicle is not an arm).
_JOINT_GROUPS = (
    (r"HipJoint$|^(Left|Right)Shoulder$|Finger|Thumb|HandIndex", "frozen"),
    (r"ForeArm$|elbow", "elbow"),
    (r"UpLeg$|_hip$", "hip"),
    (r"(Left|Right)Leg$|knee", "knee"),
    (r"(Left|Right)Arm$|shoulder", "shoulder"),
    (r"Foot$|Toe|ankle|Hand$|wrist", "extremity"),
    (r"Back|Spine|Neck|Head|torso|neck|head", "spine"),
)


def rescale(std, fps: float, *, from_fps: float = TABLE5_FPS, exponent: float = 0.5):
    """Per-frame stds at ``from_fps`` (default Table 5's 5 Hz) as per-frame stds at ``fps`` (Hz), any shape:
    ``std * (from_fps / fps) ** exponent``. ``exponent=0.5`` is a random walk's (variance linear in time, the
    Table 5 rule: ``std * sqrt(5 / fps)``); ``exponent=1`` a speed's (the steps of real motion, see
    :data:`priors.diffusion.SPEEDS`)."""
    if not fps > 0 or not from_fps > 0:
        raise ValueError(f"fps must be > 0, got {fps} (from {from_fps})")
    return std * (from_fps / fps) ** exponent


def dof_groups(skeleton) -> list[str]:
    """``(D,)`` the Table 5 group (a key of :data:`TABLE5` or :data:`EXTENSION`) of each of ``skeleton``'s
    DOFs, in ``dof_names`` order.

    DOFs of the root joint (parent ``-1``) are ``base_translation`` (prismatic) or ``base_rotation``
    (revolute), from ``skeleton.dof_revolute``; the others are grouped by the name of the joint they move
    (``skeleton.dof_joints``).
    """
    names, owner, parents = skeleton.joint_names, skeleton.dof_joints, skeleton.parents
    revolute = skeleton.dof_revolute.tolist()
    groups = []
    for d, j in enumerate(owner):
        if j >= 0 and parents[j] < 0:
            groups.append("base_rotation" if revolute[d] else "base_translation")
            continue
        joint = names[j] if j >= 0 else ""
        groups.append(next((g for pattern, g in _JOINT_GROUPS if re.search(pattern, joint)), "other"))
    return groups


def table5_sigma(skeleton, fps: float = TABLE5_FPS, scale: float = 1.0) -> torch.Tensor:
    """(D,) float64 per-DOF random-walk std of Fontmarty Table 5 for ``skeleton`` at ``fps`` (rad or m per
    frame): the std of each DOF's group (:func:`dof_groups`), rescaled from 5 Hz (:func:`rescale`), times
    ``scale``."""
    stds = {**TABLE5, **EXTENSION}
    sigma = torch.tensor([stds[g] for g in dof_groups(skeleton)], dtype=torch.float64)
    return rescale(sigma, fps) * scale
