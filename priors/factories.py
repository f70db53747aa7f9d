"""Motion priors by name, for ``torchpf.Tracker(dynamics="...")`` and ``python -m torchpf track``.

torchpf never imports this package; it finds these factories through the ``torchpf.dynamics`` entry-point
group declared in ``pyproject.toml``. Each factory is ``factory(skeleton, **options) -> dynamics``.

* ``random_walk``: angular random walk (Hauberg eq. 3, Fontmarty §3.1) with the per-joint-group stds of
  Fontmarty Table 5 (:func:`table5_sigma`), restricted to the joint limits.
* ``constant_velocity``: Rius eq. 3 (:class:`priors.motion.ConstantVelocity`), diffusion from Table 5.
* ``damped``: Brubaker eq. 13 (:class:`priors.motion.DampedSecondOrder`).
* ``action``: the action-constrained dynamics of Rius eq. 3 + 6 from a saved action model (``model=path``).

Example::

    from torchpf import Tracker
    tracker = Tracker(skel, cams, dynamics="random_walk", dynamics_options={"fps": 15.0, "scale": 0.5})
"""

from __future__ import annotations

import math
import re

import torch

#: Fontmarty Table 5: random-walk std per joint group at a 5 Hz acquisition rate (rad, or m for the base).
TABLE5 = {
    "base_translation": 0.07,
    "base_rotation": 0.05,
    "shoulder": 0.1,
    "elbow": 0.3,
    "hip": 0.1,
    "knee": 0.1,
}
TABLE5_FPS = 5.0

# Joint name -> group, first match wins. Table 5 covers the 22-DOF model; for the CMU joint tree of
# human.urdf the other joints get a spine/extremity std, and the joints that real CMU data keeps at zero and
# silhouettes cannot see (clavicles, the pelvis-to-hip links, fingers, thumbs) are held still.
_GROUPS = [
    (r"HipJoint$|^(Left|Right)Shoulder$|Finger|Thumb|HandIndex", 0.0),
    (r"ForeArm$|elbow", TABLE5["elbow"]),
    (r"UpLeg$|_hip$", TABLE5["hip"]),
    (r"(Left|Right)Leg$|knee", TABLE5["knee"]),
    (r"(Left|Right)Arm$|shoulder", TABLE5["shoulder"]),
    (r"Foot$|Toe|ankle|Hand$|wrist", 0.1),
    (r"Back|Spine|Neck|Head|torso|neck|head", 0.05),
]


def table5_sigma(skeleton, fps: float = TABLE5_FPS, scale: float = 1.0) -> torch.Tensor:
    """(D,) per-DOF random-walk std of Fontmarty Table 5 for ``skeleton``, at ``fps``.

    The table is given at 5 Hz; a random walk's std grows with the square root of the time step, so the
    std per frame at ``fps`` is ``sigma_5Hz * sqrt(5 / fps)``, times ``scale``. The root's prismatic DOFs
    get the base translation std (m), its revolute DOFs the base rotation std; other DOFs are grouped by
    the name of the joint they move (``skeleton.dof_joints``).
    """
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    names, owner, parents = skeleton.joint_names, skeleton.dof_joints, skeleton.parents
    sigma = []
    for d, j in enumerate(owner):
        if j >= 0 and parents[j] < 0:
            kind = skeleton.chain.find_joint(skeleton.dof_names[d]).joint_type
            s = TABLE5["base_translation"] if kind == "prismatic" else TABLE5["base_rotation"]
        else:
            joint = names[j] if j >= 0 else ""
            s = next((v for pattern, v in _GROUPS if re.search(pattern, joint)), 0.05)
        sigma.append(s)
    return torch.tensor(sigma, dtype=torch.float64) * math.sqrt(TABLE5_FPS / fps) * scale


def random_walk(skeleton, *, fps: float = TABLE5_FPS, scale: float = 1.0, **options):
    """Angular random walk with Table 5 stds, restricted to the joint limits (Hauberg eq. 3)."""
    from priors.random_walk import AngularRandomWalk

    return AngularRandomWalk(
        table5_sigma(skeleton, fps, scale), lower=skeleton.lower, upper=skeleton.upper, **options
    )


def constant_velocity(
    skeleton, *, fps: float = TABLE5_FPS, scale: float = 1.0, alpha: float = 0.5, **options
):
    """Rius eq. 3 with Table 5 diffusion stds."""
    from priors.motion import ConstantVelocity

    return ConstantVelocity(table5_sigma(skeleton, fps, scale), alpha=alpha, **options)


def damped(skeleton, *, fps: float = TABLE5_FPS, scale: float = 1.0, kappa: float = 0.8, **options):
    """Brubaker eq. 13 with Table 5 diffusion stds."""
    from priors.motion import DampedSecondOrder

    return DampedSecondOrder(table5_sigma(skeleton, fps, scale), kappa=kappa, **options)


def action(skeleton, *, model, **options):
    """Action-constrained dynamics (Rius eq. 3 + 6) from an action model file (``.npz``) or object."""
    from priors.action import ActionConstrained, ActionModel

    if not isinstance(model, ActionModel):
        model = ActionModel.load(model, dof_names=skeleton.dof_names)
    return ActionConstrained(model, **options)
