"""Procedural motion generator: the embedded default data of torchpf.

Real mocap (``../shared/mocap``) is never shipped; notebooks, ``make demo`` and quick tests train and track on
performances generated here for the shipped ``human.urdf`` (CMU joint tree and channel conventions, see
:mod:`torchpf.assets.build`). Three actions:

* ``walk``: a gait cycle (hip, knee, ankle flexion curves shaped like textbook gait kinematics, opposite arm
  swing, pelvis rotation and vertical bob), the root travelling along its heading, optionally on an arc.
* ``wave``: standing, the right arm raised and waving side to side with the forearm flexing.
* ``bend``: repeated forward bends (trunk pitch, hip flexion keeping the legs upright, spine curl).

Each performer differs in tempo, stride/amplitude, phase, posture offsets (a few degrees on the spine, arms,
head), bone-length scale (a scaled copy of the skeleton, :func:`performer_urdf`) and a small smooth noise.
Everything is drawn from one seed, so the same seed gives the same performances.

Example::

    from training.synthetic import generate_dataset
    paths = generate_dataset("data/walk", action="walk", n_performers=6, seconds=4.0, seed=0)
    # data/walk/walk_00.csv ... + data/walk/walk_00.urdf (that performer's skeleton)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchpf import Skeleton
from torchpf.assets import build
from torchpf.distributions import as_generator
from torchpf.io import write_text_atomic
from torchpf.kinematics.urdf import BodyJoint, build_urdf
from training.mocap import Motion, save_csv

ACTIONS = ("walk", "wave", "bend")


@dataclass(frozen=True)
class PerformerStyle:
    """What makes one performer's performance differ from another's.

    Attributes:
        tempo: cycles per second (a gait cycle is two steps; a wave cycle one side-to-side sweep).
        amplitude: scale (about 1) of the joint excursions.
        stride: scale (about 1) of the step length (walk) or of the bend depth (bend).
        phase: initial phase of the cycle, in cycles [0, 1).
        posture: constant offsets (degrees) added to named DOFs.
        bone_scale: scale of every bone length of the performer's skeleton.
        noise_deg: standard deviation (degrees) of a smooth noise added to every animated DOF.
        turn_rate: heading change (degrees per second) of a walk.
    """

    tempo: float = 0.9
    amplitude: float = 1.0
    stride: float = 1.0
    phase: float = 0.0
    posture: dict[str, float] = field(default_factory=dict)
    bone_scale: float = 1.0
    noise_deg: float = 0.5
    turn_rate: float = 0.0


_POSTURE_DOFS = (
    "LowerBack_Xrotation",
    "Spine1_Xrotation",
    "Neck1_Xrotation",
    "Head_Yrotation",
    "LeftArm_Zrotation",
    "RightArm_Zrotation",
    "LeftForeArm_Yrotation",
    "RightForeArm_Yrotation",
    "LeftUpLeg_Zrotation",
    "RightUpLeg_Zrotation",
)


def sample_style(action: str, generator: torch.Generator) -> PerformerStyle:
    """A random performer for ``action`` (uniform/normal ranges typical of healthy adults)."""
    _check_action(action)

    def u(lo, hi):
        return lo + (hi - lo) * float(torch.rand((), generator=generator, dtype=torch.float64))

    tempo = {"walk": (0.8, 1.05), "wave": (1.2, 2.0), "bend": (0.2, 0.3)}[action]
    posture = {
        name: 3.0 * float(torch.randn((), generator=generator, dtype=torch.float64)) for name in _POSTURE_DOFS
    }
    return PerformerStyle(
        tempo=u(*tempo),
        amplitude=u(0.85, 1.15),
        stride=u(0.85, 1.15),
        phase=u(0.0, 1.0),
        posture=posture,
        bone_scale=u(0.92, 1.08),
        noise_deg=u(0.3, 0.8),
        turn_rate=u(-8.0, 8.0) if action == "walk" else 0.0,
    )


def _check_action(action: str) -> None:
    if action not in ACTIONS:
        raise ValueError(f"unknown action {action!r}; choose one of {ACTIONS}")


def _bump(p: torch.Tensor, centre: float, width: float) -> torch.Tensor:
    """Periodic Gaussian bump on the cycle phase p (cycles)."""
    d = torch.remainder(p - centre + 0.5, 1.0) - 0.5
    return torch.exp(-0.5 * (d / width) ** 2)


def _smooth_noise(shape, fps: float, generator: torch.Generator) -> torch.Tensor:
    """Unit-variance noise low-passed to about 1 Hz (a random walk would drift out of the limits)."""
    T = shape[0]
    raw = torch.randn(shape, generator=generator, dtype=torch.float64)
    k = max(1, int(round(0.25 * fps)))
    t = torch.arange(-2 * k, 2 * k + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (t / k) ** 2)
    w = w / w.norm()
    pad = torch.nn.functional.pad(raw.t()[:, None], (2 * k, 2 * k), mode="replicate" if T > 1 else "constant")
    return torch.nn.functional.conv1d(pad, w[None, None]).squeeze(1).t()


def _walk(t: torch.Tensor, s: PerformerStyle) -> dict[str, torch.Tensor]:
    p = s.tempo * t + s.phase  # gait phase in cycles, left heel strike at integer values
    a = s.amplitude
    out = {}
    for side, shift, sign in (("Left", 0.0, 1.0), ("Right", 0.5, -1.0)):
        q = p + shift
        hip_flex = 10.0 + 20.0 * s.stride * torch.cos(2 * math.pi * (q - 0.9))
        out[f"{side}UpLeg_Xrotation"] = -a * hip_flex  # flexion is negative Xrotation
        out[f"{side}UpLeg_Zrotation"] = sign * (-3.0 - 3.0 * a * torch.sin(2 * math.pi * q))
        out[f"{side}Leg_Xrotation"] = a * (5.0 + 12.0 * _bump(q, 0.15, 0.07) + 55.0 * _bump(q, 0.72, 0.1))
        # push-off plantarflexion, then toes up (negative Xrotation) to clear the floor in swing
        out[f"{side}Foot_Xrotation"] = a * (12.0 * _bump(q, 0.55, 0.06) - 18.0 * _bump(q, 0.8, 0.1))
        out[f"{side}ToeBase_Xrotation"] = -a * 15.0 * _bump(q, 0.55, 0.06)
        # the arm swings forward (negative left Yrotation) while the same-side leg is back
        out[f"{side}Arm_Zrotation"] = torch.full_like(t, -sign * 78.0)
        out[f"{side}Arm_Yrotation"] = -sign * a * 15.0 * s.stride * torch.cos(2 * math.pi * (q - 0.4))
        out[f"{side}ForeArm_Yrotation"] = -sign * (20.0 + a * 10.0 * (1 + torch.cos(2 * math.pi * (q - 0.4))))
    out["Hips_Yrotation"] = 5.0 * a * torch.sin(2 * math.pi * p)
    out["Hips_Zrotation"] = 3.0 * a * torch.sin(2 * math.pi * p)
    out["Hips_Xrotation"] = torch.full_like(t, 4.0)
    out["Spine_Yrotation"] = -4.0 * a * torch.sin(2 * math.pi * p)
    out["LowerBack_Xrotation"] = torch.full_like(t, -3.0)
    # stance is the first 60% of each leg's cycle: the left foot supports the body while in stance and
    # the right one is not yet (double support goes to the foot that landed last)
    out[_SUPPORT_LEFT] = (torch.remainder(p, 1.0) < 0.5) | (torch.remainder(p + 0.5, 1.0) >= 0.6)
    # the root's travel and height follow from planting the feet (_plant_feet); the heading turns
    out["Hips_Yrotation"] = out["Hips_Yrotation"] + s.turn_rate * t
    return out


def _wave(t: torch.Tensor, s: PerformerStyle) -> dict[str, torch.Tensor]:
    p = s.tempo * t + s.phase
    raise_ = torch.clamp(t / 0.8, max=1.0)  # the arm goes up during the first 0.8 s
    raise_ = raise_ * raise_ * (3 - 2 * raise_)
    a = s.amplitude
    sweep = torch.sin(2 * math.pi * p)
    out = {
        "RightArm_Zrotation": 78.0 + raise_ * (-78.0 - 45.0 + 15.0 * a * sweep),
        "RightArm_Yrotation": raise_ * 20.0,
        "RightArm_Xrotation": raise_ * -70.0,
        "RightForeArm_Yrotation": 15.0 + raise_ * (45.0 + 25.0 * a * sweep),
        "RightHand_Xrotation": raise_ * 15.0 * a * torch.sin(2 * math.pi * p - 0.5),
        "LeftArm_Zrotation": torch.full_like(t, -80.0),
        "LeftForeArm_Yrotation": torch.full_like(t, -15.0),
        "Head_Zrotation": -4.0 * raise_,
        "Spine1_Zrotation": 3.0 * raise_ * sweep,
        "Hips_Zrotation": 1.5 * torch.sin(2 * math.pi * 0.2 * t),
    }
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        out[f"{side}UpLeg_Zrotation"] = torch.full_like(t, sign * -4.0)
        out[f"{side}Leg_Xrotation"] = torch.full_like(t, 4.0)
    return out


def _bend(t: torch.Tensor, s: PerformerStyle) -> dict[str, torch.Tensor]:
    p = s.tempo * t + s.phase
    # smooth 0 -> 1 -> 0 per cycle with a short hold at the bottom
    depth = 0.5 - 0.5 * torch.cos(2 * math.pi * p)
    depth = torch.clamp(1.15 * depth, max=1.0)
    pitch = 55.0 * s.stride * depth  # trunk pitch carried by the pelvis
    curl = 12.0 * s.amplitude * depth  # per spine joint
    out = {
        "Hips_Xrotation": pitch,
        "LowerBack_Xrotation": curl,
        "Spine_Xrotation": curl,
        "Spine1_Xrotation": curl,
        "Neck1_Xrotation": -0.6 * curl,
    }
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        out[f"{side}UpLeg_Xrotation"] = -pitch - 4.0 * depth  # flex the hips to keep the legs upright
        out[f"{side}Leg_Xrotation"] = 8.0 * depth
        out[f"{side}Foot_Xrotation"] = -4.0 * depth
        out[f"{side}Arm_Zrotation"] = torch.full_like(t, -sign * 80.0)
        # arms hang toward the floor while the trunk pitches forward
        out[f"{side}Arm_Yrotation"] = -sign * (pitch + 3 * curl) * 0.9
        out[f"{side}ForeArm_Yrotation"] = -sign * (10.0 + 10.0 * depth)
    return out


_SUPPORT_LEFT = "support_left"  # (T,) bool track: which foot carries the body (walk only)

_ACTION_FN = {"walk": _walk, "wave": _wave, "bend": _bend}


def generate(
    action: str,
    n_frames: int = 120,
    fps: float = 30.0,
    style: PerformerStyle | None = None,
    seed: int = 0,
    name: str | None = None,
) -> Motion:
    """One performance of ``action`` for ``human.urdf`` (or a performer's scaled copy of it).

    Args:
        action: ``"walk"``, ``"wave"`` or ``"bend"``.
        n_frames: T, number of frames.
        fps: frame rate (Hz).
        style: the performer; drawn from ``seed`` when None.
        seed: seeds the style (when drawn) and the noise.

    Returns:
        A :class:`~training.mocap.Motion` with the 96 DOFs of ``human.urdf`` (radians, metres), float64,
        every frame within the model's joint limits.
    """
    _check_action(action)
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    gen = as_generator(int(seed))
    if style is None:
        style = sample_style(action, gen)
    joints, _ = build.human_joints()
    names = [d.name for j in joints for d in j.dofs]
    prismatic = {d.name for j in joints for d in j.dofs if d.type == "prismatic"}  # tracks in metres
    lower = torch.tensor([d.lower for j in joints for d in j.dofs], dtype=torch.float64)
    upper = torch.tensor([d.upper for j in joints for d in j.dofs], dtype=torch.float64)
    t = torch.arange(n_frames, dtype=torch.float64) / fps
    tracks = _ACTION_FN[action](t, style)
    support_left = tracks.pop(_SUPPORT_LEFT, None)

    angles = torch.zeros(n_frames, len(names), dtype=torch.float64)
    noise = _smooth_noise((n_frames, len(names)), fps, gen) * style.noise_deg
    index = {n: i for i, n in enumerate(names)}
    for dof, track in tracks.items():
        i = index[dof]
        if dof in prismatic:
            angles[:, i] = track
        else:
            angles[:, i] = torch.deg2rad(track + style.posture.get(dof, 0.0) + noise[:, i])
    for dof, offset in style.posture.items():
        if dof not in tracks:
            angles[:, index[dof]] += math.radians(offset)
    angles = torch.maximum(torch.minimum(angles, upper), lower)
    _plant_feet(angles, names, style.bone_scale, support_left)
    return Motion(names, fps, angles, name=name or f"{action}_{seed}")


def _plant_feet(
    angles: torch.Tensor, names: list[str], bone_scale: float, support_left: torch.Tensor | None
) -> None:
    """Place the root so that the feet neither sink nor skate (in place, on the performer's skeleton).

    Foot points: the toe joints and a heel one foot-depth (the ankle's height above the sole at rest) below
    each ankle. Per frame the support is the lowest point of the supporting foot (``support_left``, (T,)
    bool; None: both feet). The root's horizontal motion cancels the support's motion relative to the
    body and the root height puts the lowest foot point on the floor z=0, so walking speed is what the leg
    angles produce (stride length x cadence) and a standing performer stays put.
    """
    skel = Skeleton.from_urdf(performer_urdf(bone_scale))
    ix, iy, iz = (names.index(f"Hips_{a}position") for a in "XYZ")
    body = angles.clone()
    body[:, [ix, iy, iz]] = 0.0
    pos = skel.fk(body)
    j = skel.joint_names
    offsets = {b.name: b.offset for b in build.human_joints()[0]}
    heel = torch.tensor([0.0, 0.0, offsets["LeftToeBase"][2] * bone_scale], dtype=pos.dtype)
    toes = ("LeftToeBase", "LeftToeBase_end", "RightToeBase", "RightToeBase_end")
    points = torch.stack(
        [pos[:, j.index(n)] for n in toes] + [pos[:, j.index(n)] + heel for n in ("LeftFoot", "RightFoot")], 1
    )  # (T, 6, 3)
    height = points[..., 2]
    if support_left is not None:
        left = torch.tensor([True, True, False, False, True, False])
        off_foot = left[None, :] != support_left[:, None]
        height = height.masked_fill(off_foot, float("inf"))
    support = height.argmin(1)  # (T,)
    frames = torch.arange(len(angles))
    now = points[frames, support]
    before = points[(frames - 1).clamp(min=0), support]
    slide = (now - before)[:, :2]  # support motion relative to the root, zero at frame 0
    root_xy = -torch.cumsum(slide, 0)
    # world x is Hips_Xposition; world y is -Hips_Zposition (BVH z maps to world -y)
    angles[:, ix] = root_xy[:, 0]
    angles[:, iz] = -root_xy[:, 1]
    angles[:, iy] = -points[..., 2].min(1).values  # no foot below the floor, the lowest one on it


def performer_urdf(bone_scale: float) -> str:
    """URDF text of ``human.urdf`` with every bone length and capsule radius scaled by ``bone_scale``."""
    if not bone_scale > 0:
        raise ValueError(f"bone_scale must be > 0, got {bone_scale}")
    joints, radii = build.human_joints()
    scaled = [BodyJoint(j.name, j.parent, tuple(bone_scale * v for v in j.offset), j.dofs) for j in joints]
    return build_urdf("torchpf_human", scaled, {k: bone_scale * r for k, r in radii.items()})


def generate_dataset(
    out_dir: str | os.PathLike,
    action: str = "walk",
    n_performers: int = 5,
    seconds: float = 4.0,
    fps: float = 30.0,
    seed: int = 0,
) -> list[Path]:
    """Write ``n_performers`` performances of ``action`` as mocap CSV plus each performer's URDF.

    Files: ``out_dir/<action>_<k:02d>.csv`` and ``out_dir/<action>_<k:02d>.urdf``, written atomically.
    Performer ``k`` uses seed ``seed * 1000 + k`` so datasets with different seeds do not share performers.

    Returns:
        The CSV paths, in performer order.
    """
    _check_action(action)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_frames = max(1, int(round(seconds * fps)))
    paths = []
    for k in range(n_performers):
        perf_seed = seed * 1000 + k
        style = sample_style(action, as_generator(perf_seed))
        motion = generate(action, n_frames, fps, style=style, seed=perf_seed, name=f"{action}_{k:02d}")
        csv = out / f"{action}_{k:02d}.csv"
        save_csv(csv, motion)
        write_text_atomic(out / f"{action}_{k:02d}.urdf", performer_urdf(style.bone_scale))
        paths.append(csv)
    return paths
