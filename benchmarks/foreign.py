"""A foreign silhouette renderer: bodies the tracker's model has never seen, for honest evaluation (issue 11).

Why
---
Sequences rendered by :mod:`torchpf.synth` are drawn with the tracker's own capsules: tracking them tests the
search, never the model ("inverse crime"). This module draws silhouettes with a body that shares **no
geometry code** with the tracker: it reads only the joint positions ``skel.fk(theta)`` (the positions are the
truth; the capsules are the tracker's model) and the cameras' parameters ``K, R, t, dist, width, height``, and
projects with ``cv2.projectPoints`` itself. It never calls ``torchpf.geometry``, ``Skeleton.capsules`` /
radii, ``torchpf.synth`` or ``Camera.project``.

The body (per performer, in metres)
-----------------------------------
* **Plan from the structure**, never from joint names (:func:`body_plan`): the torso chain and the limbs
  hanging off it are :func:`torchpf.kinematics.body_partition`'s (tree + rest pose); the limbs attached
  lowest on the torso are legs, the others arms (the largest gap in attachment height splits them). Along a
  limb's main chain (at each joint the child with the longest subtree), zero-length bones are merged; with
  three or more segments the first is the girdle (clavicle / pelvis-to-hip offset), the next two the long
  bones (upper arm + forearm, thigh + shank), what follows the extremity (hand, foot).
* **Solids**: tapered limbs (truncated cones between joints with a radius at each end, a ball at the elbow
  and knee), a torso lofted through elliptical cross-sections (buttocks, hips, waist, chest, shoulder line:
  wider at hips and chest), a neck cone, an ellipsoidal head, ellipsoidal hands and feet.
* **Widths** from an anthropometric table in fractions of stature (:data:`PROPORTIONS`, stature = rest-pose
  height of the skeleton) with a seeded per-performer variation (default +-15 % per entry, left/right tied):
  :func:`body_shape`.

Drawing: each solid's surface is sampled in 3-D (two rings for a cone, Fibonacci points for an ellipsoid),
projected per camera with ``cv2.projectPoints``, and its ``cv2.convexHull`` filled with ``cv2.fillConvexPoly``
(the image of a convex solid under a pinhole is convex; a binary mask needs no painter's order).

Defects (:class:`Defects`, presets :data:`PRESETS`): ``clean`` (none) and ``noisy``: ragged edges (smooth
noise added to a blurred mask before re-thresholding, and a random 1-px erosion or dilation per frame and
camera), salt & pepper speckle (~1 %), holes (random blobs removed inside the body), a limb dropping out of
one camera for a few frames, merged limbs (a morphological closing that bridges nearby parts). All seeded.

Sequences: :func:`build_sequence` converts a CMU clip (as ``python -m training convert`` does), resamples it,
places it in the capture volume, renders 3 cameras and writes a sequence directory
(:func:`torchpf.sequence.write_sequence`: ``masks/``, ``truth.csv``, ``cameras.yaml``) with
``skeleton.urdf`` beside it, so that ``python -m torchpf track SEQ --skeleton SEQ/skeleton.urdf`` runs on it
as a user would. ``render.json`` records the renderer's parameters (the tracker never reads it).

Example::

    from benchmarks.foreign import ForeignRenderer, build_sequence
    seq_dir = build_sequence("../shared/mocap/cmu/07_01.bvh", "out/foreign/07_01-clean", defects="clean")
    renderer = ForeignRenderer(skel, performer_seed=3)
    masks = renderer.render(skel.fk(theta), cameras)          # (V, H, W) uint8 0/255
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from torchpf.kinematics import body_partition
from training.mocap import CMU_SCALE

# Body widths as fractions of stature H (performer means before the +-15 % variation). Sources: breadths,
# depths and circumferences (r = C / 2 pi) of the ANSUR II survey (Gordon et al. 2014, adult means) and
# segment lengths of Winter, "Biomechanics and Motor Control of Human Movement" (4th ed., Fig. 4.1), both
# divided by mean stature (~1.75 m): hip breadth 0.19 H, buttock depth 0.14 H, waist breadth 0.17 H, chest
# breadth 0.20 H, chest depth 0.14 H, neck circ. 0.21 H, head breadth 0.088 H / length 0.11 H / height 0.13 H,
# biceps circ. 0.18 H, elbow 0.13 H, wrist 0.10 H, thigh circ. 0.33 H, knee 0.22 H, ankle 0.13 H, hand length
# 0.108 H / breadth 0.05 H, foot length 0.152 H / breadth 0.055 H.
PROPORTIONS: dict[str, float] = {
    # torso cross-sections (half-width, half-depth), buttocks -> shoulder line
    "buttock_half_width": 0.085,
    "buttock_half_depth": 0.065,
    "hip_half_width": 0.100,
    "hip_half_depth": 0.075,
    "waist_half_width": 0.085,
    "waist_half_depth": 0.060,
    "chest_half_width": 0.100,
    "chest_half_depth": 0.070,
    "shoulder_half_width": 0.090,
    "shoulder_half_depth": 0.050,
    "neck_radius": 0.033,
    "head_half_width": 0.044,
    "head_half_depth": 0.056,
    "head_height": 0.130,
    # arms (radii at the joints)
    "deltoid_radius": 0.040,
    "upper_arm_radius": 0.028,
    "elbow_radius": 0.021,
    "wrist_radius": 0.016,
    "hand_length": 0.108,
    "hand_half_width": 0.025,
    "hand_half_thickness": 0.013,
    # legs
    "thigh_radius": 0.053,
    "knee_radius": 0.035,
    "ankle_radius": 0.021,
    "foot_length": 0.152,
    "foot_half_width": 0.028,
    "foot_half_height": 0.022,
}
VARIATION = 0.15  # per-performer relative variation of each PROPORTIONS entry (uniform +-15 %)
BUTTOCK_DROP = 0.04  # the torso starts this far (x H) below the hip joints


# ================================================================================================ body plan
@dataclass(frozen=True)
class Limb:
    """One limb's main chain as body-joint indices (see :func:`body_plan`).

    ``attach``: the torso joint it hangs off; ``girdle``: the joint ending the girdle segment (clavicle /
    hip offset; equal to ``attach``'s position when there is none); ``top, mid, end``: the long bones
    ``top -> mid -> end`` (shoulder, elbow, wrist / hip, knee, ankle); ``tip``: the last joint of the chain
    past ``end`` (fingertip, toe), -1 when the chain stops at ``end``; ``joints``: every joint of the limb.
    """

    attach: int
    top: int
    mid: int
    end: int
    tip: int
    joints: tuple[int, ...]


@dataclass(frozen=True)
class BodyPlan:
    """Which joints carry which solid, found from the tree and the rest pose (:func:`body_plan`).

    ``torso``: the torso chain from the root up (joint indices); ``neck_base``: the torso joint the arms hang
    off; ``legs``, ``arms``: :class:`Limb` s; ``stature``: rest-pose height (m), top of the torso chain to the
    lowest joint.
    """

    torso: tuple[int, ...]
    neck_base: int
    legs: tuple[Limb, ...]
    arms: tuple[Limb, ...]
    stature: float

    def eval_joints(self) -> list[int]:
        """The Fontmarty-like evaluation joints, found structurally: root, neck base, head top, then per limb
        the long bones' three joints (shoulder/elbow/wrist, hip/knee/ankle); duplicates dropped."""
        out = [self.torso[0], self.neck_base, self.torso[-1]]
        for limb in (*self.legs, *self.arms):
            out += [limb.top, limb.mid, limb.end]
        return list(dict.fromkeys(out))


def _rest_positions(skeleton) -> np.ndarray:
    with torch.no_grad():
        zero = torch.zeros(len(skeleton.dof_names), dtype=torch.float64)
        return skeleton.fk(zero).numpy()


def body_plan(skeleton) -> BodyPlan:
    """The body plan of ``skeleton`` from its structure (tree + rest pose), never from joint names.

    Torso and limbs are :func:`torchpf.kinematics.body_partition`'s groups (the chain from the root towards
    the highest joint, and the subtrees hanging off it). Raises ValueError for a skeleton without two limbs.
    """
    rest = _rest_positions(skeleton)
    parents = list(skeleton.parents)
    groups = body_partition(skeleton, per_limb=True, joints=True)
    part = skeleton.tree.joint_part.tolist()
    torso = tuple(j for j in range(len(parents)) if part[j] == 0)
    limbs_joints = [g for g in groups if part[g[0]] > 0]
    if len(limbs_joints) < 2:
        raise ValueError(f"the skeleton has {len(limbs_joints)} limb(s) off its torso chain; need >= 2")
    children: dict[int, list[int]] = {j: [] for j in range(len(parents))}
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)

    def reach(j: int) -> float:
        """Longest rest-pose path length from joint j down its subtree (m)."""
        return max((np.linalg.norm(rest[c] - rest[j]) + reach(c) for c in children[j]), default=0.0)

    limbs = []
    for joints in limbs_joints:
        first = min(
            joints, key=lambda j: (parents[j] in joints, j)
        )  # the joint whose parent is a torso joint
        attach = parents[first]
        chain, j = [first], first
        while children[j]:
            j = max(children[j], key=lambda c: np.linalg.norm(rest[c] - rest[j]) + reach(c))
            chain.append(j)
        # distinct points along the chain (zero-length bones merged into the joint that starts them)
        points = [attach]
        for j in chain:
            if np.linalg.norm(rest[j] - rest[points[-1]]) > 1e-3:
                points.append(j)
        if len(points) < 3:
            raise ValueError(f"limb at joint {first} has fewer than two bones")
        k = 1 if len(points) >= 4 else 0  # with a girdle segment, the long bones start at points[1]
        top, mid, end = points[k], points[k + 1], points[k + 2]
        tip = points[-1] if len(points) > k + 3 else -1
        limbs.append((attach, Limb(attach, top, mid, end, tip, tuple(sorted(joints)))))
    # legs hang off the torso lowest: split the limbs at the largest gap in attachment height
    heights = sorted(float(rest[a, 2]) for a, _ in limbs)
    gaps = np.diff(heights)
    if len(gaps) and gaps.max() > 1e-3:
        cut = heights[int(gaps.argmax())]
        legs = [limb for a, limb in limbs if rest[a, 2] <= cut]
        arms = [limb for a, limb in limbs if rest[a, 2] > cut]
    else:  # all attached at one height: the limbs reaching lowest are the legs
        order = sorted(limbs, key=lambda al: float(rest[list(al[1].joints), 2].min()))
        half = len(order) // 2
        legs, arms = [limb for _, limb in order[:half]], [limb for _, limb in order[half:]]
    neck_base = max((limb.attach for limb in arms), key=lambda j: rest[j, 2], default=torso[-1])
    stature = float(rest[list(torso), 2].max() - rest[:, 2].min())
    return BodyPlan(torso, neck_base, tuple(legs), tuple(arms), stature)


def body_shape(stature: float, *, seed: int | None = 0, variation: float = VARIATION) -> dict[str, float]:
    """One performer's body dimensions (m): :data:`PROPORTIONS` x ``stature``, each entry scaled by an
    independent uniform factor in ``[1 - variation, 1 + variation]`` drawn from ``seed`` (left and right
    share the table). ``seed=None`` or ``variation=0`` gives the table means."""
    rng = np.random.default_rng(seed)
    factors = rng.uniform(1.0 - variation, 1.0 + variation, len(PROPORTIONS))
    if seed is None or variation == 0:
        factors = np.ones(len(PROPORTIONS))
    return {k: float(v * stature * f) for (k, v), f in zip(PROPORTIONS.items(), factors, strict=True)}


# ================================================================================================ solids
def _unit(v: np.ndarray, fallback=(0.0, 0.0, 1.0)) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.asarray(fallback, dtype=np.float64)


def _perpendicular(axis: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (u, w) completing ``axis`` to an orthonormal frame, ``u`` as close to ``hint`` as
    possible."""
    u = hint - axis * float(hint @ axis)
    if np.linalg.norm(u) < 1e-6:
        other = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = other - axis * float(other @ axis)
    u = _unit(u)
    return u, np.cross(axis, u)


_RING = np.linspace(0.0, 2.0 * math.pi, 32, endpoint=False)
_COS, _SIN = np.cos(_RING), np.sin(_RING)


def _fibonacci_sphere(n: int = 96) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


_SPHERE = _fibonacci_sphere()


def ring(center, axis, hint, half_u: float, half_w: float) -> np.ndarray:
    """(32, 3) points of an ellipse of half-axes ``half_u`` (along ``hint`` made perpendicular to ``axis``)
    and ``half_w``, in the plane through ``center`` perpendicular to ``axis``."""
    u, w = _perpendicular(_unit(np.asarray(axis, np.float64)), np.asarray(hint, np.float64))
    return np.asarray(center)[None] + half_u * _COS[:, None] * u + half_w * _SIN[:, None] * w


def frustum(a, b, radius_a: float, radius_b: float) -> np.ndarray:
    """(64, 3) surface points of a truncated cone from ``a`` (radius ``radius_a``) to ``b`` (``radius_b``)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    axis = _unit(b - a)
    return np.concatenate([ring(a, axis, axis, radius_a, radius_a), ring(b, axis, axis, radius_b, radius_b)])


def ellipsoid(center, axes: np.ndarray, semi: Sequence[float]) -> np.ndarray:
    """(96, 3) surface points of an ellipsoid: ``axes`` (3, 3) orthonormal rows, ``semi`` half-lengths."""
    return np.asarray(center)[None] + (_SPHERE * np.asarray(semi)[None]) @ np.asarray(axes)


def _frame(axis, hint) -> np.ndarray:
    """(3, 3) rows (axis, u, w): ``axis`` normalised, ``u`` the part of ``hint`` perpendicular to it."""
    axis = _unit(np.asarray(axis, np.float64))
    u, w = _perpendicular(axis, np.asarray(hint, np.float64))
    return np.stack([axis, u, w])


def _polyline_point(points: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """The point at arc length ``s`` along ``points`` (P, 3) and the unit tangent there (clamped)."""
    seg = np.diff(points, axis=0)
    lengths = np.linalg.norm(seg, axis=-1)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    s = float(np.clip(s, 0.0, cum[-1]))
    i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
    f = (s - cum[i]) / max(lengths[i], 1e-12)
    return points[i] + f * seg[i], _unit(seg[i])


def _dedupe(points: Sequence[np.ndarray], tol: float = 1e-3) -> np.ndarray:
    out = [np.asarray(points[0], np.float64)]
    for p in points[1:]:
        if np.linalg.norm(p - out[-1]) > tol:
            out.append(np.asarray(p, np.float64))
    return np.stack(out)


# Torso cross-sections along the torso axis from the buttocks (0) to the shoulder line (1): the fraction of
# the way and the PROPORTIONS entries of the half-width and half-depth.
_TORSO_SECTIONS = (
    (0.0, "buttock"),
    (0.2, "hip"),
    (0.5, "waist"),
    (0.8, "chest"),
    (1.0, "shoulder"),
)


def body_solids(
    plan: BodyPlan, shape: Mapping[str, float], joints: np.ndarray
) -> list[tuple[str, np.ndarray]]:
    """The convex solids of one pose as ``(part, (P, 3) surface points)``; ``part`` is ``torso``, ``neck``,
    ``head``, ``leg<i>`` or ``arm<i>`` (what a limb drop-out removes). ``joints`` (J, 3) positions (m)."""
    P = np.asarray(joints, np.float64)
    s = shape
    solids: list[tuple[str, np.ndarray]] = []

    def pair_axis(limbs) -> np.ndarray | None:
        return P[limbs[-1].top] - P[limbs[0].top] if len(limbs) >= 2 else None

    hips_mid = np.mean([P[limb.top] for limb in plan.legs], 0) if plan.legs else P[plan.torso[0]]
    neck = P[plan.neck_base]
    up = _unit(neck - hips_mid)
    shoulders_mid = np.mean([P[limb.top] for limb in plan.arms], 0) if plan.arms else neck
    top = neck + up * max(0.0, float((shoulders_mid - neck) @ up))
    pelvis_lat = pair_axis(plan.legs)
    chest_lat = pair_axis(plan.arms)
    pelvis_lat = chest_lat if pelvis_lat is None else pelvis_lat
    chest_lat = pelvis_lat if chest_lat is None else chest_lat
    if pelvis_lat is None:
        pelvis_lat = chest_lat = np.array([1.0, 0.0, 0.0])

    # torso: elliptical sections lofted pairwise along buttocks -> hips -> torso chain -> shoulder line
    k_neck = plan.torso.index(plan.neck_base)
    spine = [hips_mid - up * BUTTOCK_DROP * plan.stature, hips_mid]
    spine += [P[j] for j in plan.torso[: k_neck + 1] if float((P[j] - hips_mid) @ up) > 0.0] + [top]
    spine = _dedupe(spine)
    length = float(np.linalg.norm(np.diff(spine, axis=0), axis=-1).sum())
    rings = []
    for frac, name in _TORSO_SECTIONS:
        c, tangent = _polyline_point(spine, frac * length)
        lat = (1.0 - frac) * _unit(pelvis_lat) + frac * _unit(chest_lat)
        rings.append(ring(c, tangent, lat, s[f"{name}_half_width"], s[f"{name}_half_depth"]))
    solids += [("torso", np.concatenate([r0, r1])) for r0, r1 in zip(rings[:-1], rings[1:], strict=True)]

    # neck and head along the top of the torso chain
    head_chain = _dedupe([neck] + [P[j] for j in plan.torso[k_neck + 1 :]])
    if len(head_chain) >= 2:
        seg = np.linalg.norm(np.diff(head_chain, axis=0), axis=-1).sum()
        head_top = head_chain[-1]
        base, _ = _polyline_point(head_chain, seg - min(s["head_height"], 0.8 * seg))
    else:  # no joint above the neck base: a head of the table's height on top of it
        base, head_top = neck, neck + up * s["head_height"]
    head_axis = _unit(head_top - base, up)
    solids.append(("neck", frustum(neck, base + 0.3 * (head_top - base), s["neck_radius"], s["neck_radius"])))
    head_h = 0.5 * max(float(np.linalg.norm(head_top - base)), 0.5 * s["head_height"])
    axes = _frame(head_axis, chest_lat)
    solids.append(
        (
            "head",
            ellipsoid(
                head_top - head_axis * head_h, axes, (head_h, s["head_half_width"], s["head_half_depth"])
            ),
        )
    )

    for i, limb in enumerate(plan.arms):
        a, b, c = P[limb.top], P[limb.mid], P[limb.end]
        r_top, r_mid, r_end = s["upper_arm_radius"], s["elbow_radius"], s["wrist_radius"]
        parts = [
            frustum(P[limb.attach], a, 0.8 * s["deltoid_radius"], s["deltoid_radius"]),
            ellipsoid(a, np.eye(3), (s["deltoid_radius"],) * 3),
            frustum(a, b, r_top, r_mid),
            ellipsoid(b, np.eye(3), (r_mid,) * 3),
            frustum(b, c, r_mid, r_end),
        ]
        along = _unit(P[limb.tip] - c if limb.tip >= 0 else c - b, c - b)
        half = 0.5 * s["hand_length"]
        hand = ellipsoid(
            c + along * half, _frame(along, chest_lat), (half, s["hand_half_width"], s["hand_half_thickness"])
        )
        solids += [(f"arm{i}", p) for p in [*parts, hand]]

    forward = np.cross(_unit(pelvis_lat), up)
    for i, limb in enumerate(plan.legs):
        a, b, c = P[limb.top], P[limb.mid], P[limb.end]
        parts = [
            frustum(P[limb.attach], a, s["thigh_radius"], s["thigh_radius"]),
            frustum(a, b, s["thigh_radius"], s["knee_radius"]),
            ellipsoid(b, np.eye(3), (s["knee_radius"],) * 3),
            frustum(b, c, s["knee_radius"], s["ankle_radius"]),
        ]
        shank = _unit(c - b, -up)
        foot_len = s["foot_length"]
        if limb.tip >= 0:  # heel a quarter of the foot behind the ankle, toes along the chain
            along = _unit(P[limb.tip] - c, forward)
            centre = c + along * 0.25 * foot_len + shank * s["foot_half_height"]
        else:  # no toe joint: which way is forward is unknown, centre the foot under the ankle
            along = _unit(forward - shank * float(forward @ shank), forward)
            centre = c + shank * s["foot_half_height"]
        foot = ellipsoid(
            centre, _frame(along, pelvis_lat), (0.5 * foot_len, s["foot_half_width"], s["foot_half_height"])
        )
        solids += [(f"leg{i}", p) for p in [*parts, foot]]
    return solids


# ================================================================================================ drawing
@dataclass(frozen=True)
class CameraParams:
    """A pinhole camera as plain numpy (OpenCV conventions): ``K`` (3, 3), ``R`` (3, 3) world -> camera,
    ``t`` (3,) (m), ``dist`` (5,) ``k1 k2 p1 p2 k3``, image ``width`` x ``height`` pixels."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dist: np.ndarray
    width: int
    height: int

    @classmethod
    def from_camera(cls, cam) -> CameraParams:
        """From a :class:`torchpf.camera.Camera` (its fields only: no torchpf projection code is used)."""
        dist = np.zeros(5) if cam.dist is None else np.asarray(cam.dist, np.float64)
        return cls(
            np.asarray(cam.K, np.float64),
            np.asarray(cam.R, np.float64),
            np.asarray(cam.t, np.float64),
            dist,
            int(cam.width),
            int(cam.height),
        )


def camera_params(cameras) -> list[CameraParams]:
    """A rig (``rig[v]`` Cameras), a list of Cameras or of :class:`CameraParams` -> list of CameraParams."""
    if hasattr(cameras, "names") and hasattr(cameras, "sizes"):  # a CameraRig
        cameras = [cameras[v] for v in range(len(cameras))]
    return [c if isinstance(c, CameraParams) else CameraParams.from_camera(c) for c in cameras]


_SHIFT = 4  # fillConvexPoly fixed-point bits: vertices at 1/16 px
SUPERSAMPLE = 4  # draw at 4x the resolution, then keep the pixels at least half covered


def draw_solids(
    solids: Sequence[tuple[str, np.ndarray]],
    camera: CameraParams,
    drop: set[str] = frozenset(),
    supersample: int = SUPERSAMPLE,
) -> np.ndarray:
    """(H, W) uint8 0/255 mask: the union of the solids' projected convex hulls (parts in ``drop`` left out).

    ``cv2.fillConvexPoly`` fills every pixel an edge touches, which widens a 4-px limb by about a pixel; the
    hulls are therefore drawn ``supersample`` times finer and a pixel is foreground when at least half of it
    is covered. Points behind the camera are left out of a hull (a solid wholly behind draws nothing).
    """
    s = max(1, int(supersample))
    mask = np.zeros((camera.height * s, camera.width * s), np.uint8)
    kept = [p for part, p in solids if part not in drop]
    if not kept:
        return np.zeros((camera.height, camera.width), np.uint8)
    sizes = [len(p) for p in kept]
    pts = np.concatenate(kept)
    depth = pts @ camera.R[2] + camera.t[2]
    rvec, _ = cv2.Rodrigues(camera.R)
    uv, _ = cv2.projectPoints(pts, rvec, camera.t, camera.K, camera.dist)
    uv = (uv.reshape(-1, 2) + 0.5) * s - 0.5  # the same pixel centres on the finer grid
    start = 0
    for n in sizes:
        sel = slice(start, start + n)
        start += n
        front = depth[sel] > 1e-3
        if front.sum() < 3:
            continue
        fixed = np.round(uv[sel][front] * (1 << _SHIFT)).astype(np.int32)
        hull = cv2.convexHull(fixed)
        cv2.fillConvexPoly(mask, hull, 255, lineType=cv2.LINE_8, shift=_SHIFT)
    if s > 1:
        mask = cv2.resize(mask, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return np.where(mask >= 128, 255, 0).astype(np.uint8)


# ================================================================================================ defects
@dataclass(frozen=True)
class Defects:
    """Real-mask defects (pixel sizes for 160x120 masks). All zero: clean masks.

    ``ragged``: std of a smooth noise field added to the blurred mask before re-thresholding at 0.5 (ragged
    edges); ``morph_px``: radius of a random erosion or dilation (or none) per frame and camera; ``speckle``:
    fraction of pixels set to salt or pepper; ``holes``: up to this many blobs of radius ``hole_px`` removed
    inside the body per mask; ``dropout``: probability per frame that one limb vanishes from one camera for
    ``dropout_frames`` (min, max) frames; ``merge``: probability per frame and camera of a closing with a
    ``merge_px`` disk (bridges limbs closer than about ``2 merge_px``).
    """

    ragged: float = 0.0
    morph_px: int = 0
    speckle: float = 0.0
    holes: int = 0
    hole_px: float = 2.5
    dropout: float = 0.0
    dropout_frames: tuple[int, int] = (2, 6)
    merge: float = 0.0
    merge_px: int = 3


PRESETS: dict[str, Defects] = {
    "clean": Defects(),
    "noisy": Defects(ragged=0.25, morph_px=1, speckle=0.01, holes=3, dropout=0.08, merge=0.3),
}


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def degrade(mask: np.ndarray, defects: Defects, rng: np.random.Generator) -> np.ndarray:
    """Apply the per-mask defects of ``defects`` (all but the limb drop-out) to a (H, W) 0/255 mask."""
    m = mask.copy()
    H, W = m.shape
    if defects.merge > 0 and rng.random() < defects.merge:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(defects.merge_px))
    if defects.morph_px > 0:
        op = rng.integers(3)  # erode, dilate or neither
        if op < 2:
            fn = cv2.erode if op == 0 else cv2.dilate
            m = fn(m, _disk(defects.morph_px))
    if defects.ragged > 0:
        noise = cv2.GaussianBlur(rng.standard_normal((H, W)).astype(np.float32), (0, 0), 1.5)
        noise *= defects.ragged / max(float(noise.std()), 1e-6)
        soft = cv2.GaussianBlur(m.astype(np.float32) / 255.0, (0, 0), 1.0)
        band = cv2.dilate(m, _disk(2)) != cv2.erode(m, _disk(2))  # only the edges turn ragged
        m = np.where(band, np.where(soft + noise > 0.5, 255, 0), m).astype(np.uint8)
    if defects.holes > 0:
        inside = np.argwhere(cv2.erode(m, _disk(2)) > 0)
        for _ in range(int(rng.integers(defects.holes + 1))):
            if len(inside) == 0:
                break
            y, x = inside[rng.integers(len(inside))]
            r = max(1, int(round(rng.uniform(0.5, 1.0) * defects.hole_px)))
            cv2.circle(m, (int(x), int(y)), r, 0, -1)
    if defects.speckle > 0:
        flip = rng.random((H, W)) < defects.speckle
        m[flip] = np.where(rng.random(int(flip.sum())) < 0.5, 0, 255).astype(np.uint8)
    return m


def dropout_schedule(
    n_frames: int, n_cameras: int, parts: Sequence[str], defects: Defects, rng: np.random.Generator
) -> list[list[set[str]]]:
    """``drop[t][v]``: the limbs missing from camera ``v`` at frame ``t`` (events of :class:`Defects`)."""
    drop = [[set() for _ in range(n_cameras)] for _ in range(n_frames)]
    if defects.dropout <= 0 or not parts:
        return drop
    for t in range(n_frames):
        if rng.random() < defects.dropout:
            part, v = parts[rng.integers(len(parts))], int(rng.integers(n_cameras))
            lo, hi = defects.dropout_frames
            for k in range(t, min(n_frames, t + int(rng.integers(lo, hi + 1)))):
                drop[k][v].add(part)
    return drop


# ================================================================================================ renderer
class ForeignRenderer:
    """Silhouettes of one performer on ``skeleton``'s motion (module docstring).

    Args:
        skeleton: a :class:`torchpf.Skeleton` (only its tree, rest pose and ``fk`` positions are read).
        performer_seed: draws the body's widths (:func:`body_shape`); ``None`` gives the table means.
        variation: relative spread of the widths (default +-15 %).
        stature: override of the rest-pose height (m) the widths scale with.

    Attributes: ``plan`` (:class:`BodyPlan`), ``shape`` (dimension name -> metres).
    """

    def __init__(
        self, skeleton, *, performer_seed: int | None = 0, variation: float = VARIATION, stature=None
    ):
        self.skeleton = skeleton
        self.plan = body_plan(skeleton)
        self.stature = float(stature if stature is not None else self.plan.stature)
        self.shape = body_shape(self.stature, seed=performer_seed, variation=variation)
        self.limb_parts = [f"leg{i}" for i in range(len(self.plan.legs))] + [
            f"arm{i}" for i in range(len(self.plan.arms))
        ]

    def joints(self, angles: torch.Tensor) -> np.ndarray:
        """(..., D) angles -> (..., J, 3) float64 joint positions (the truth the body is drawn on)."""
        with torch.no_grad():
            return self.skeleton.fk(torch.as_tensor(angles, dtype=torch.float64)).numpy()

    def render(self, joints: np.ndarray, cameras, drop: Sequence[set[str]] | None = None) -> np.ndarray:
        """(V, H, W) uint8 0/255 clean masks of one pose ``joints`` (J, 3); ``drop[v]`` parts to leave out."""
        cams = camera_params(cameras)
        solids = body_solids(self.plan, self.shape, np.asarray(joints, np.float64))
        drop = drop or [frozenset()] * len(cams)
        return np.stack([draw_solids(solids, c, d) for c, d in zip(cams, drop, strict=True)])

    def render_sequence(
        self, angles: torch.Tensor, cameras, *, defects: str | Defects = "clean", seed: int = 0
    ) -> np.ndarray:
        """(T, V, H, W) uint8 0/255 masks of the poses ``angles`` (T, D) with the ``defects`` (a preset name
        or :class:`Defects`), reproducible from ``seed``."""
        d = PRESETS[defects] if isinstance(defects, str) else defects
        cams = camera_params(cameras)
        P = self.joints(angles)
        rng = np.random.default_rng(seed)
        drop = dropout_schedule(len(P), len(cams), self.limb_parts, d, rng)
        out = np.stack([self.render(P[t], cams, drop[t]) for t in range(len(P))])
        if d != Defects():
            for t in range(len(P)):
                for v in range(len(cams)):
                    out[t, v] = degrade(out[t, v], d, rng)
        return out


# ================================================================================================ video
def textured_background(height: int, width: int, seed: int = 0) -> np.ndarray:
    """(H, W, 3) BGR uint8 scene behind the performer: smooth colour blotches, a striped and a checkered
    poster and a floor-to-wall brightness ramp, so that background subtraction has texture to model."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(30, 226, (max(2, height // 20), max(2, width // 20), 3)).astype(np.uint8)
    img = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC).astype(np.float64)
    img *= np.linspace(0.8, 1.1, height)[:, None, None]
    for _ in range(2):
        x0, y0 = int(rng.integers(0, width * 3 // 4)), int(rng.integers(0, height // 2))
        w, h = int(rng.integers(width // 8, width // 3)), int(rng.integers(height // 6, height // 2))
        ys, xs = np.mgrid[y0 : min(y0 + h, height), x0 : min(x0 + w, width)]
        period = int(rng.integers(3, 7))
        pattern = (xs // period + (ys // period) * int(rng.integers(0, 2))) % 2
        img[ys, xs] = np.where(pattern[..., None] > 0, rng.uniform(20, 90, 3), rng.uniform(160, 240, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def composite_video(
    masks: np.ndarray,
    background: np.ndarray,
    *,
    shadows: np.ndarray | None = None,
    seed: int = 0,
    noise: float = 2.0,
    clothing: Sequence[float] = (175.0, 120.0, 60.0),
) -> np.ndarray:
    """(T, H, W) 0/255 silhouettes of one camera over ``background`` (H, W, 3) -> (T, H, W, 3) BGR frames:
    the performer in a textured ``clothing`` colour, darker towards the outline (a rounded body), the
    optional ``shadows`` (T, H, W) in [0, 1] darkening the scene by up to 30 %, and Gaussian sensor noise of
    ``noise`` grey levels per frame."""
    rng = np.random.default_rng(seed)
    T, H, W = masks.shape
    weave = cv2.GaussianBlur(rng.standard_normal((H, W)).astype(np.float32), (0, 0), 1.2)
    weave = 1.0 + 0.12 * weave / max(float(weave.std()), 1e-6)
    frames = np.empty((T, H, W, 3), np.uint8)
    base = background.astype(np.float32)
    for t in range(T):
        img = base.copy()
        if shadows is not None:
            img *= 1.0 - 0.3 * shadows[t][..., None]
        fg = masks[t] > 0
        if fg.any():
            depth = cv2.distanceTransform(fg.astype(np.uint8), cv2.DIST_L2, 3)
            shade = 0.65 + 0.35 * np.clip(depth / 4.0, 0, 1)
            body = np.asarray(clothing, np.float32) * (shade * weave)[..., None]
            img[fg] = body[fg]
        img += rng.normal(0.0, noise, img.shape).astype(np.float32)
        frames[t] = np.clip(img, 0, 255).astype(np.uint8)
    return frames


def shadow_masks(joints: np.ndarray, camera, root: int, radius: float = 0.35) -> np.ndarray:
    """(T, H, W) float32 soft shadow of a performer on the floor (z = 0): a disc of ``radius`` m under the
    root joint ``root`` of ``joints`` (T, J, 3), projected with ``cv2.projectPoints`` and blurred."""
    cam = camera_params([camera])[0] if not isinstance(camera, CameraParams) else camera
    rvec, _ = cv2.Rodrigues(cam.R)
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    out = np.zeros((len(joints), cam.height, cam.width), np.float32)
    for t, P in enumerate(joints):
        ring_pts = np.stack(
            [P[root, 0] + radius * np.cos(phi), P[root, 1] + 0.6 * radius * np.sin(phi), np.zeros_like(phi)],
            -1,
        )
        uv, _ = cv2.projectPoints(ring_pts, rvec, cam.t, cam.K, cam.dist)
        cv2.fillConvexPoly(out[t], np.round(uv.reshape(-1, 2)).astype(np.int32), 1.0)
        out[t] = cv2.GaussianBlur(out[t], (0, 0), 2.0)
    return out


def write_videos(
    out_dir, masks: np.ndarray, cameras, joints: np.ndarray, root: int, fps: float, seed: int = 0
):
    """Render ``out_dir/video/<camera>.mp4`` (the performer over a textured scene, with a floor shadow and
    sensor noise) and ``out_dir/background/<camera>.png`` (the clean plate, one noisy frame of the empty
    scene) for masks (T, V, H, W) 0/255 seen by ``cameras`` (a rig). Returns the video paths."""
    from torchpf.io import write_atomic

    out = Path(out_dir)
    (out / "video").mkdir(parents=True, exist_ok=True)
    rig_cams = [cameras[v] for v in range(len(cameras))]
    paths = []
    for v, cam in enumerate(rig_cams):
        T, _, H, W = masks.shape
        bg = textured_background(H, W, seed=seed * 101 + v)
        frames = composite_video(masks[:, v], bg, shadows=shadow_masks(joints, cam, root), seed=seed + v)
        path = out / "video" / f"{cam.name}.mp4"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (W, H))
        if not writer.isOpened():
            raise OSError(f"{path}: OpenCV cannot write mp4 video")
        for f in frames:
            writer.write(f)
        writer.release()
        plate = composite_video(np.zeros((1, H, W), np.uint8), bg, seed=seed + 1000 + v)[0]
        ok, buf = cv2.imencode(".png", plate)
        write_atomic(out / "background" / f"{cam.name}.png", buf.tobytes())
        paths.append(path)
    return paths


# ================================================================================================ sequences
def resample(angles: torch.Tensor, fps_in: float, fps_out: float, revolute: torch.Tensor) -> torch.Tensor:
    """(T, D) angles at ``fps_in`` -> (T', D) at ``fps_out``: linear interpolation in time, revolute DOFs
    unwrapped before and wrapped to [-pi, pi) after (an integer ratio gives exact subsampling)."""
    a = angles.numpy().astype(np.float64).copy()
    rev = revolute.numpy().astype(bool)
    a[:, rev] = np.unwrap(a[:, rev], axis=0)
    t_in = np.arange(len(a)) / fps_in
    t_out = np.arange(0.0, t_in[-1] + 1e-9, 1.0 / fps_out)
    out = np.stack([np.interp(t_out, t_in, a[:, d]) for d in range(a.shape[1])], -1)
    out[:, rev] = (out[:, rev] + math.pi) % (2 * math.pi) - math.pi
    return torch.from_numpy(out)


def centre_root(skeleton, angles: torch.Tensor) -> torch.Tensor:
    """Shift the root's translation DOFs so that the root's mean horizontal position is the origin (the
    motion itself, drift included, is kept: the performer walks through the capture volume)."""
    root = skeleton.parents.index(-1)
    D = angles.shape[-1]
    trans = [
        d for d in range(D) if not bool(skeleton.dof_revolute[d]) and int(skeleton.dof_joints[d]) == root
    ]
    if not trans:
        return angles
    with torch.no_grad():
        zero = torch.zeros(D, dtype=torch.float64)
        axes = torch.stack([skeleton.fk(zero + torch.eye(D, dtype=torch.float64)[d])[root] for d in trans])
        axes = axes - skeleton.fk(zero)[root]  # (P, 3) root displacement per metre of each DOF
        mean = skeleton.fk(angles.to(torch.float64))[:, root].mean(0)
    target = -mean.clone()
    target[2] = 0.0
    # least-squares DOF offsets moving the root horizontally by -mean (height untouched)
    coef = torch.linalg.pinv(axes.T[:2]) @ target[:2]  # (lstsq's default CPU driver fails here)
    out = angles.clone().to(torch.float64)
    out[:, trans] += coef
    return out


def place_cameras(joints: np.ndarray, *, n: int = 3, size=(160, 120), radius: float = 4.0, margin_px=2.0):
    """A ring of ``n`` cameras (:func:`torchpf.camera.camera_ring`, used for placement only) around the
    motion's centre, moved out in 0.5 m steps from ``radius`` until every joint of every frame (plus a body
    half-width) is in every image. Returns ``(rig, radius)``."""
    from torchpf.camera import camera_ring

    centre = joints.reshape(-1, 3).mean(0)
    target = (float(centre[0]), float(centre[1]), float(centre[2]))
    pts = joints.reshape(-1, 3)
    for r in np.arange(radius, radius + 8.01, 0.5):
        rig = camera_ring(n, radius=float(r), height=1.5, target=target, width=size[0], height_px=size[1])
        ok = True
        for cam in camera_params(rig):
            rvec, _ = cv2.Rodrigues(cam.R)
            uv, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, cam.dist)
            uv = uv.reshape(-1, 2)
            m = margin_px + 0.15 * cam.K[0, 0] / max(float(r), 1e-6)  # ~0.15 m of body around a joint
            ok &= bool((uv[:, 0] >= m).all() and (uv[:, 0] <= cam.width - 1 - m).all())
            ok &= bool((uv[:, 1] >= m).all() and (uv[:, 1] <= cam.height - 1 - m).all())
        if ok:
            return rig, float(r)
    return rig, float(r)


@dataclass
class ForeignSequence:
    """What :func:`build_sequence` wrote: ``path`` (the sequence directory), ``skeleton_path``
    (``path/skeleton.urdf``), the skeleton, the ``angles`` (T, D) truth, ``fps``, ``cameras`` and
    ``info`` (the contents of ``render.json``)."""

    path: Path
    skeleton_path: Path
    skeleton: object
    angles: torch.Tensor
    fps: float
    cameras: object
    info: dict = field(default_factory=dict)


def build_sequence(
    clip: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    defects: str | Defects = "clean",
    fps: float = 30.0,
    frames: int | None = 60,
    size: tuple[int, int] = (160, 120),
    n_cameras: int = 3,
    radius: float = 4.0,
    performer_seed: int | None = None,
    seed: int = 0,
    scale: float = CMU_SCALE,
    in_place: bool = False,
    video: bool = False,
    video_scale: int = 2,
) -> ForeignSequence:
    """Render a BVH clip with the foreign body and write it as a sequence directory ``out_dir``.

    The clip is converted as ``python -m training convert`` does (``skeleton.urdf`` written beside the
    masks), its frame 0 (a rest pose in CMU files) dropped, resampled to ``fps`` and cut to ``frames``, its
    root centred horizontally (:func:`centre_root`), and seen by ``n_cameras`` cameras of ``size`` pixels
    (:func:`place_cameras`). ``performer_seed`` draws the body (default: from the clip's name, so each
    performer gets a body of their own); ``seed`` drives the defects. ``in_place`` removes the root's straight
    horizontal drift instead (:func:`benchmarks.evaluate.treadmill`, for diagnosis: a walk at 1.5 m/s moves
    the root 5 cm per frame at 30 fps, a run twice that). ``video`` also writes what cameras would film
    (:func:`write_videos`): ``video/<camera>.mp4``, the clean (defect-free) body over a textured scene with a
    floor shadow and sensor noise, and ``background/<camera>.png`` clean plates, the input of
    ``python -m torchpf masks`` (``masks/`` keeps the renderer's own silhouettes, to score it against), at
    ``video_scale`` times the masks' size (a 160x120 mp4 loses the background texture to compression).
    """
    from torchpf.camera import CameraRig
    from torchpf.io import write_text_atomic
    from torchpf.sequence import SequenceData, write_sequence
    from training.mocap import convert_bvh

    clip, out = Path(clip), Path(out_dir)
    urdf, skel, motion, _ = convert_bvh(clip, scale)
    angles = resample(motion.angles[1:], motion.fps, fps, skel.dof_revolute)
    if frames is not None:
        angles = angles[:frames]
    if in_place:
        from benchmarks.evaluate import treadmill

        angles = treadmill(skel, angles)
    angles = centre_root(skel, angles)
    if performer_seed is None:
        performer_seed = sum(ord(ch) for ch in clip.stem.split("_")[0])  # one body per CMU subject
    renderer = ForeignRenderer(skel, performer_seed=performer_seed)
    joints = renderer.joints(angles)
    rig, used_radius = place_cameras(joints, n=n_cameras, size=size, radius=radius)
    masks = renderer.render_sequence(angles, rig, defects=defects, seed=seed)
    seq = SequenceData(
        cameras=CameraRig(rig),
        masks=[list(m) for m in masks],
        truth=angles,
        dof_names=list(skel.dof_names),
        times=np.arange(len(angles)) / fps,
    )
    write_sequence(out, seq)
    skel_path = out / "skeleton.urdf"
    write_text_atomic(skel_path, urdf)
    d = PRESETS[defects] if isinstance(defects, str) else defects
    info = {
        "clip": clip.name,
        "frames": len(angles),
        "fps": fps,
        "size": list(size),
        "camera_radius": used_radius,
        "defects": defects if isinstance(defects, str) else "custom",
        "defect_parameters": asdict(d),
        "seed": seed,
        "in_place": in_place,
        "performer_seed": performer_seed,
        "stature": renderer.stature,
        "body": renderer.shape,
        "foreground_fraction": float((masks > 0).mean()),
    }
    if video:
        film = CameraRig(rig).resized(size[0] * video_scale, size[1] * video_scale)
        clean = renderer.render_sequence(angles, film, defects="clean")
        write_videos(out, clean, film, joints, skel.parents.index(-1), fps, seed=seed)
        info["video"] = {"size": [size[0] * video_scale, size[1] * video_scale], "noise": 2.0, "shadow": 0.3}
    write_text_atomic(out / "render.json", json.dumps(info, indent=2))
    return ForeignSequence(out, skel_path, skel, angles, fps, rig, info)
