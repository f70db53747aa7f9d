"""Generator of the shipped skeleton URDFs (``python -m torchpf.assets.build`` rewrites them).

Numbers are ours, not copied from any mocap file: segment lengths of an adult of about 1.75 m (close to the
proportions of Winter's anthropometric table), capsule radii from typical limb girths, and joint limits that
combine textbook ranges of motion with what real walking/running mocap reaches in the CMU channel
conventions (checked by a test against the clips in ``../shared/mocap/cmu``).

Axis conventions of ``human.urdf`` are those a converted CMU BVH has: BVH (x left, y up, z forward) maps to
world (x, -z, y), so the BVH channel ``Xrotation`` turns about world +x, ``Yrotation`` about world +z and
``Zrotation`` about world -y. For the left leg, positive ``Xrotation`` of the hip extends it and positive
``Xrotation`` of the knee flexes it; right-side limits mirror the left ones (``Yrotation`` and ``Zrotation``
change sign, ``Xrotation`` does not).
"""

from __future__ import annotations

import math
from pathlib import Path

from torchpf.io import write_text_atomic
from torchpf.kinematics.urdf import ROOT_TRANSLATION_LIMIT, BodyJoint, Dof, build_urdf, floating_root_dofs

_BVH_AXIS = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 0.0, 1.0), "Z": (0.0, -1.0, 0.0)}
_ORDER = ("Z", "Y", "X")  # CMU channel order of every joint

# (parent, offset in metres, world z-up, left side; limits in degrees for Z, Y, X); None = fixed end site.
_LEFT = [
    ("LHipJoint", "Hips", (0.0, 0.0, 0.0), (10, 10, 10)),
    ("LeftUpLeg", "LHipJoint", (0.095, -0.01, -0.085), ((-60, 30), (-45, 45), (-125, 45))),
    ("LeftLeg", "LeftUpLeg", (0.0, 0.0, -0.43), ((-10, 45), (-10, 40), (-5, 150))),
    ("LeftFoot", "LeftLeg", (0.0, 0.0, -0.42), ((-30, 30), (-45, 45), (-50, 60))),
    ("LeftToeBase", "LeftFoot", (0.0, -0.13, -0.06), ((-20, 20), (-30, 30), (-60, 45))),
    ("LeftToeBase_end", "LeftToeBase", (0.0, -0.06, 0.0), None),
    ("LeftShoulder", "Spine1", (0.0, 0.0, 0.0), (20, 20, 20)),
    ("LeftArm", "LeftShoulder", (0.175, 0.0, 0.05), ((-110, 90), (-95, 70), (-90, 90))),
    ("LeftForeArm", "LeftArm", (0.285, 0.0, 0.0), ((-10, 165), (-90, 10), (-150, 10))),
    ("LeftHand", "LeftForeArm", (0.25, 0.0, 0.0), ((-30, 30), (-30, 30), (-70, 70))),
    ("LeftFingerBase", "LeftHand", (0.0, 0.0, 0.0), (60, 60, 60)),
    ("LeftHandIndex1", "LeftFingerBase", (0.05, 0.0, 0.0), (30, 30, 30)),
    ("LeftHandIndex1_end", "LeftHandIndex1", (0.04, 0.0, 0.0), None),
    ("LThumb", "LeftHand", (0.0, 0.0, 0.0), (90, 90, 90)),
    ("LThumb_end", "LThumb", (0.035, -0.035, 0.0), None),
]
_CENTRE = [
    ("LowerBack", "Hips", (0.0, 0.0, 0.0), ((-30, 30), (-30, 30), (-30, 60))),
    ("Spine", "LowerBack", (0.0, 0.0, 0.13), ((-30, 30), (-30, 30), (-30, 60))),
    ("Spine1", "Spine", (0.0, 0.0, 0.13), ((-30, 30), (-30, 30), (-30, 60))),
    ("Neck", "Spine1", (0.0, 0.0, 0.0), ((-40, 40), (-45, 45), (-50, 50))),
    ("Neck1", "Neck", (0.0, 0.01, 0.09), ((-40, 40), (-45, 45), (-50, 50))),
    ("Head", "Neck1", (0.0, 0.0, 0.09), ((-40, 40), (-45, 45), (-50, 50))),
    ("Head_end", "Head", (0.0, -0.01, 0.13), None),
]
_RADII = {
    "LeftUpLeg": 0.08,
    "LeftLeg": 0.075,
    "LeftFoot": 0.055,
    "LeftToeBase": 0.045,
    "LeftToeBase_end": 0.03,
    "LeftArm": 0.05,
    "LeftForeArm": 0.045,
    "LeftHand": 0.038,
    "LeftHandIndex1": 0.03,
    "LeftHandIndex1_end": 0.022,
    "LThumb_end": 0.015,
    "Spine": 0.12,
    "Spine1": 0.125,
    "Neck1": 0.05,
    "Head": 0.055,
    "Head_end": 0.095,
}


def _mirror_name(name: str) -> str:
    for a, b in (("Left", "Right"), ("LHip", "RHip"), ("LThumb", "RThumb")):
        if name.startswith(a):
            return b + name[len(a) :]
    return name


def _ball(name: str, limits_deg) -> list[Dof]:
    dofs = []
    for axis, lim in zip(_ORDER, limits_deg, strict=True):
        lo, hi = (-lim, lim) if isinstance(lim, int | float) else lim
        dofs.append(
            Dof(f"{name}_{axis}rotation", "revolute", _BVH_AXIS[axis], math.radians(lo), math.radians(hi))
        )
    return dofs


def human_joints() -> tuple[list[BodyJoint], dict[str, float]]:
    """Body joints and capsule radii of ``human.urdf`` (CMU joint tree, 96 DOFs)."""
    root_dofs = [
        Dof(f"Hips_{a}position", "prismatic", _BVH_AXIS[a], -ROOT_TRANSLATION_LIMIT, ROOT_TRANSLATION_LIMIT)
        for a in ("X", "Y", "Z")
    ]
    # Heading (BVH Yrotation) may wind up over a long performance: allow two turns.
    root_limits = ((-180, 180), (-360, 360), (-180, 180))
    joints = [BodyJoint("Hips", None, (0.0, 0.0, 0.0), root_dofs + _ball("Hips", root_limits))]
    radii = dict(_RADII)

    def add(spec, mirror: bool):
        name, parent, offset, limits = spec
        if mirror:
            name, parent = _mirror_name(name), _mirror_name(parent)
            offset = (-offset[0], offset[1], offset[2])
            if limits is not None:
                z, y, x = (lim if isinstance(lim, tuple) else (-lim, lim) for lim in limits)
                limits = ((-z[1], -z[0]), (-y[1], -y[0]), x)
        dofs = [] if limits is None else _ball(name, limits)
        joints.append(BodyJoint(name, parent, offset, dofs))

    legs = [s for s in _LEFT if "Leg" in s[0] or "Foot" in s[0] or "Toe" in s[0] or "HipJoint" in s[0]]
    arms = [s for s in _LEFT if s not in legs]
    for spec in legs:
        add(spec, False)
    for spec in legs:
        add(spec, True)
    for spec in _CENTRE:
        add(spec, False)
    for spec in arms:
        add(spec, False)
    for spec in arms:
        add(spec, True)
    radii.update({_mirror_name(k): v for k, v in _RADII.items()})
    return joints, radii


def fontmarty22_joints() -> tuple[list[BodyJoint], dict[str, float]]:
    """Body joints and radii of the 22-DOF model of Fontmarty et al. (Fig. 1), arms hanging, facing -y.

    6 root DOFs; shoulders and hips are ball joints (``_rx``, ``_ry``, ``_rz``: flexion about the lateral
    axis, abduction about the antero-posterior axis, twist about the limb); elbows and knees are hinges whose
    positive angle is flexion. Torso, neck and head are rigid with the pelvis.
    """

    def ball(name, lims):
        return [
            Dof(f"{name}_r{a}", "revolute", ax, math.radians(lo), math.radians(hi))
            for a, ax, (lo, hi) in zip("xyz", ((1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0)), lims, strict=True)
        ]

    j = [BodyJoint("pelvis", None, (0.0, 0.0, 0.0), floating_root_dofs("pelvis", "zyx"))]
    j.append(BodyJoint("neck", "pelvis", (0.0, 0.0, 0.5), []))
    j.append(BodyJoint("head_top", "neck", (0.0, 0.0, 0.25), []))
    for side, s in (("l", 1.0), ("r", -1.0)):
        # abduction moves a left limb toward +x, i.e. a negative rotation about +y
        abd_arm = (-170, 20) if s > 0 else (-20, 170)
        abd_leg = (-45, 20) if s > 0 else (-20, 45)
        j.append(
            BodyJoint(
                f"{side}_shoulder",
                "neck",
                (s * 0.19, 0.0, -0.03),
                ball(f"{side}_shoulder", ((-180, 60), abd_arm, (-90, 90))),
            )
        )
        j.append(
            BodyJoint(
                f"{side}_elbow",
                f"{side}_shoulder",
                (0.0, 0.0, -0.29),
                [Dof(f"{side}_elbow_rx", "revolute", (-1.0, 0.0, 0.0), 0.0, math.radians(150))],
            )
        )
        j.append(BodyJoint(f"{side}_wrist", f"{side}_elbow", (0.0, 0.0, -0.26), []))
        j.append(
            BodyJoint(
                f"{side}_hip",
                "pelvis",
                (s * 0.095, 0.0, -0.06),
                ball(f"{side}_hip", ((-125, 30), abd_leg, (-45, 45))),
            )
        )
        j.append(
            BodyJoint(
                f"{side}_knee",
                f"{side}_hip",
                (0.0, 0.0, -0.43),
                [Dof(f"{side}_knee_rx", "revolute", (1.0, 0.0, 0.0), 0.0, math.radians(150))],
            )
        )
        j.append(BodyJoint(f"{side}_ankle", f"{side}_knee", (0.0, 0.0, -0.42), []))
    radii = {"neck": 0.14, "head_top": 0.1}
    for side in "lr":
        radii.update(
            {
                f"{side}_elbow": 0.045,
                f"{side}_wrist": 0.038,
                f"{side}_knee": 0.07,
                f"{side}_ankle": 0.055,
                f"{side}_shoulder": 0.05,
                f"{side}_hip": 0.08,
            }
        )
    return j, radii


def render() -> dict[str, str]:
    """File name -> URDF text of every shipped model."""
    return {
        "human.urdf": build_urdf("torchpf_human", *human_joints()),
        "fontmarty22.urdf": build_urdf("fontmarty22", *fontmarty22_joints()),
    }


def main() -> None:
    here = Path(__file__).resolve().parent
    for name, text in render().items():
        write_text_atomic(here / name, text)
        print(f"wrote {here / name}")


if __name__ == "__main__":
    main()
