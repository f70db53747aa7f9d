"""Bottom-up person detection from silhouettes: automatic initialisation and track recovery.

The papers initialise their trackers by hand. This module finds the person from the masks alone, so that
``Tracker.track(seq, init="auto")`` needs no ground truth, and re-acquires a lost track (Brubaker §6: a
bottom-up detector mixed into the proposal, as I-CONDENSATION does):

* **Where** (:func:`visual_hull`): the rays through each camera's silhouette centroid are triangulated
  (least squares), a voxel grid around that point is carved by every mask (a voxel survives when it projects
  inside the silhouette in every valid camera: the visual hull, Laurentini 1994), and the hull gives the
  person's horizontal centre (the median of the torso slice), the floor (its lowest voxels) and the
  stature (its vertical extent).
* **How** (:class:`PersonDetector`): candidate poses are built from the skeleton's *structure* and rest pose,
  never from joint names: a few canonical postures (standing with the arms down, two walking strides, arms
  half down, the rest pose, two running strides with bent knee and elbows), made by inverse kinematics from
  the rest pose with limbs found by :func:`~torchpf.kinematics.body_partition` (a limb reaching far below
  the root is a leg, the others are arms; a limb rotates about the joint that ends its girdle segment, which
  stays at rest, and bends at its middle joint); a grid of headings about the vertical
  (root DOFs solved by IK, so any Euler order works); the root placed at the hull's centre, its height the
  floor plus the rest pose's root height.
* **Which heading**: the torso slice's principal axis gives the shoulder line up to its sign; the hull's
  motion over the first frames picks the sign whose feet point forwards, and above ``lead_speed`` (0.5 m/s)
  the direction of motion gives the heading itself (:meth:`~PersonDetector.heading_choices`).
* **Initial pose** (:meth:`PersonDetector.fit`): each kept heading x {standing, each stride} is refined
  by :func:`torchpf.calibrate.fit_body` on frame 0 (a soft area match: it tells the strides apart where a
  thin model's likelihood does not), and the lowest silhouette loss wins; the fitted body comes with it.
* **Re-acquisition** (:meth:`PersonDetector.search`, :class:`Recovery`): the candidates, the lost
  track's own particles and its last good estimate moved over the hull are scored by the tracker's
  likelihood (with a weak prior: each body part near standing or near that estimate) and refined by
  partitioned annealing (Deutscher's adaptive annealing, survival rate 0.3; torso then each limb: resample,
  diffuse with shrinking noise); the population replaces the filter's particles.
* **Body**: :func:`looks_uncalibrated` tells a stick-figure body (a converted skeleton's ``0.15 x`` length
  capsules) from a fitted one by its torso's thickness relative to the stature.

Conventions: z up, metres, radians. Shapes: ``V`` cameras, ``H x W`` masks, ``D`` DOFs, ``J`` joints,
``N`` particles.

Example::

    detector = PersonDetector(skel, seq.cameras)
    det = detector.detect(seq.frame(0))                    # Detection: centre, floor, stature
    pose, fitted, report = detector.fit(seq.frame(0))      # (D,) pose, fitted body
    particles, log_lik = detector.search(likelihood, seq.frame(0), n=500)   # (500, D), (500,)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchpf.devices import on_cpu
from torchpf.distributions import as_generator, wrap_angle
from torchpf.filters.annealed import anneal_beta
from torchpf.filters.weights import temper
from torchpf.kinematics.tree import body_partition, children_of, subtree_of
from torchpf.resampling import RESAMPLERS

__all__ = [
    "Detection",
    "PersonDetector",
    "fit_body_to_frame",
    "looks_uncalibrated",
    "silhouette_masks",
    "visual_hull",
]


# ---------------------------------------------------------------------------------------------- hull
@dataclass
class Detection:
    """A person found by :func:`visual_hull`.

    Attributes:
        centre: (3,) float64 horizontal centre of the hull's torso slice, at mid-height (m).
        floor: z of the hull's lowest voxels (m): the soles.
        top: z of its highest voxels (m): the top of the head.
        voxels: number of occupied voxels; ``voxel`` their edge (m).
        area: (V,) silhouette area (pixels) per camera, 0 for a missing one.
        axis: (2,) unit horizontal major axis of the torso slice (the shoulder / hip line; its sign is
            arbitrary); ``elongation`` the ratio of its two principal spreads (1 = round: no axis).
    """

    centre: Tensor
    floor: float
    top: float
    voxels: int
    voxel: float
    area: Tensor
    axis: Tensor | None = None
    elongation: float = 1.0

    @property
    def stature(self) -> float:
        """Vertical extent of the hull (m)."""
        return self.top - self.floor


def silhouette_masks(obs) -> tuple[Tensor, Tensor] | None:
    """``(masks (V, H, W) bool, valid (V,) bool)`` from a :class:`~torchpf.observations.Frame`, a
    :class:`~torchpf.observations.Silhouettes` or a (V, H, W) array; None when there are no masks."""
    sil = getattr(obs, "silhouettes", obs)
    if sil is None:
        return None
    masks = getattr(sil, "masks", sil)
    masks = torch.as_tensor(np.asarray(masks) if not isinstance(masks, Tensor) else masks)
    if masks.ndim == 2:
        masks = masks[None]
    valid = getattr(sil, "valid", None)
    valid = torch.ones(masks.shape[0], dtype=torch.bool) if valid is None else valid.bool().cpu()
    return masks.cpu().float() > 0.5 * float(masks.max().clamp_min(1e-9)), valid


def fit_body_to_frame(
    skeleton,
    cameras,
    obs,
    pose: Tensor,
    *,
    iterations: int = 200,
    scale_sigma: float | None = 0.03,
    radius_sigma: float | None = None,
    **options,
):
    """:func:`torchpf.calibrate.fit_body` on one frame's silhouettes (a :class:`Frame`, :class:`Silhouettes`
    or (V, H, W) masks) from an approximate ``pose (D,)``: capsule radii, global scale and the pose refined
    together. Returns ``(fitted skeleton, CalibrationReport)``; ``report.poses[0]`` is the refined pose.

    ``obs`` may also be a list of such frames (consecutive ones, e.g. a sequence's first few): the body is
    fitted to all of them, every frame's pose starting at ``pose`` (or at its own row of a ``(F, D)``
    ``pose``: with ``Tracker.auto_refit_frames``, ``init="auto"`` refits at the poses it tracked) and
    refined on its own (``report.poses[k]``). ``init="auto"`` fits one frame: with its body fitted so to
    the first 5, the 11 noisy foreign clips tracked at 127 mm against 155, but notebook 05's
    video-segmented walk at 7.7 cm against 5.3 (6 seeds; BENCHMARKS.md).

    ``scale_sigma`` holds the global scale near 1 (:func:`~torchpf.calibrate.fit_body`): one frame's masks
    are weak evidence of it. On frames 0 and 1 of the foreign renders of the 11 CMU clips (true scale 1), a
    free scale came out at 0.98-1.02 on clean masks but 0.87-1.03 on noisy ones (a body 13 % too small is
    44 mm off at the true pose); held at 0.03, 1.00-1.02 on clean and 1.00-1.04 on noisy masks. ``None``
    fits it freely. ``radius_sigma`` holds the spread of the log radii (``fit_body``; ``None``, the default,
    fits each radius freely): the fits ``Tracker`` makes (frame 0, then the refit at the first tracked
    poses) see defects at poses that are off, and freely fitted they came out absurd on the noisy runs (a
    1-8 mm torso, 100 mm hands); at 0.25 the bodies stay sane, but tracks on them were no closer to the
    truth (four noisy draws: 66.4 mm both) and a 5-frame fit's refined poses drifted further (BENCHMARKS.md,
    "Round 10"). ``options`` go to ``fit_body``."""
    from torchpf.calibrate import fit_body

    frames = []
    for k, one in enumerate(obs if isinstance(obs, (list, tuple)) else [obs]):
        got = silhouette_masks(one)
        if got is None:
            raise ValueError(f"fitting the body needs silhouettes (frame {k} has none)")
        masks, valid = got
        frames.append(
            [
                m.numpy().astype(np.uint8) * 255 if ok else None
                for m, ok in zip(masks, valid.tolist(), strict=True)
            ]
        )
    pose = torch.as_tensor(pose, dtype=torch.float64).cpu()
    poses = pose[None].expand(len(frames), -1) if pose.ndim == 1 else pose
    if poses.shape != (len(frames), len(skeleton.dof_names)):
        raise ValueError(
            f"pose must be ({len(skeleton.dof_names)},) or one per frame ({len(frames)}, "
            f"{len(skeleton.dof_names)}), got {tuple(pose.shape)}"
        )
    return fit_body(
        skeleton,
        cameras,
        frames,
        poses,
        frames_used=len(frames),
        iterations=iterations,
        scale_sigma=scale_sigma,
        radius_sigma=radius_sigma,
        **options,
    )


def _triangulate_centroids(rig, masks: Tensor, valid: Tensor) -> Tensor | None:
    """Least-squares point (3,) closest to the rays through the silhouette centroids, or None."""
    import cv2

    V, H, W = masks.shape
    A, b, used = torch.zeros(3, 3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 0
    for v, cam in enumerate(rig.cameras):
        if not bool(valid[v]) or not bool(masks[v].any()):
            continue
        ii, jj = torch.nonzero(masks[v], as_tuple=True)
        u = (float(jj.double().mean()) + 0.5) * cam.width / W - 0.5
        w = (float(ii.double().mean()) + 0.5) * cam.height / H - 0.5
        dist = None if cam.dist is None else cam.dist.double().numpy()
        xy = cv2.undistortPoints(np.array([[[u, w]]]), cam.K.double().numpy(), dist).reshape(2)
        d = torch.from_numpy(np.array([xy[0], xy[1], 1.0])) @ cam.R.double()  # R^T d: world direction
        d = d / d.norm()
        P = torch.eye(3, dtype=torch.float64) - torch.outer(d, d)
        A += P
        b += P @ cam.center.double()
        used += 1
    if used < 2:
        return None
    return torch.linalg.solve(A, b)


def _carve_cells(rig, masks: Tensor, seen: list[int], pts: Tensor, radius: float = 0.0) -> Tensor:
    """Indices (K',) of the points (K, 3) whose projection lies on every seen camera's mask, carved one
    camera at a time (each projects only the points the previous ones kept). With ``radius`` > 0 (m) a
    point stands for a cell of that half-diagonal: it is kept where any point of the cell could project on
    the mask (the mask dilated by the cell's largest projected radius, also beyond the image's edges)."""
    import cv2

    H, W = masks.shape[-2:]
    idx = torch.arange(len(pts))
    for v in seen:
        cam = rig[v]
        uv, depth = cam.project(pts[idx], return_depth=True)  # (K', 2), (K',)
        uv = uv.round().long()
        if radius > 0.0:
            near = float(depth.min()) - radius if len(depth) else 1.0
            if near <= 1e-3:  # a cell reaches the camera plane: no bound on its image, nothing carved
                continue
            # a cell's image lies within f r / z' of its centre's, times the lens's largest magnification
            # (at a normalised radius <= 1: 1 + 3|k1| + 5|k2| + 7|k3| + 6(|p1| + |p2|), and at least 2);
            # rounding both moves up to 1.5 px
            grow = 1.0
            if cam.dist is not None and bool(cam.dist.abs().gt(0).any()):
                k1, k2, p1, p2, k3 = cam.dist.abs().tolist()
                grow = max(2.0, 1 + 3 * k1 + 5 * k2 + 7 * k3 + 6 * (p1 + p2))
            pad = math.ceil(grow * float(cam.K[:2, :2].abs().max()) * radius / near + 1.5)
            mask = cv2.copyMakeBorder(
                masks[v].to(torch.uint8).numpy(), pad, pad, pad, pad, cv2.BORDER_CONSTANT
            )
            grown = torch.from_numpy(cv2.dilate(mask, np.ones((2 * pad + 1, 2 * pad + 1), np.uint8))).bool()
            uv, bounds = uv + pad, (W + 2 * pad, H + 2 * pad)
        else:
            grown, bounds = masks[v], (W, H)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < bounds[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < bounds[1])
        inside &= depth > 1e-3 - radius
        on_mask = grown[uv[:, 1].clamp(0, bounds[1] - 1), uv[:, 0].clamp(0, bounds[0] - 1)] & inside
        idx = idx[on_mask]
    return idx


def _carve(rig, masks: Tensor, seen: list[int], axes: list[Tensor], voxel: float) -> Tensor:
    """The voxel centres (K, 3) of the grid ``axes`` that every seen camera's mask keeps: first the cells of
    2 x 2 x 2 voxels, by the conservative test of :func:`_carve_cells`, then the voxels of the cells left.
    The same set as carving every voxel, for about 1/8 of the projections where the person fills little of
    the box (the tracker's lost-track check carves a hull every few frames)."""
    sizes = torch.tensor([len(a) for a in axes])
    first = [torch.arange(0, len(a), 2) for a in axes]  # each cell's first voxel, per axis
    # an odd axis ends in a one-voxel cell
    mid = [(a[f] + a[(f + 1).clamp(max=len(a) - 1)]) / 2 for a, f in zip(axes, first, strict=True)]
    centres = torch.stack(torch.meshgrid(*mid, indexing="ij"), -1).reshape(-1, 3)  # (C, 3)
    first = torch.stack(torch.meshgrid(*first, indexing="ij"), -1).reshape(-1, 3)  # (C, 3)
    cells = first[_carve_cells(rig, masks, seen, centres, math.sqrt(3) * voxel / 2)]
    offsets = torch.stack(torch.meshgrid(*[torch.arange(2)] * 3, indexing="ij"), -1).reshape(1, 8, 3)
    ijk = (cells[:, None] + offsets).reshape(-1, 3)
    ijk = ijk[(ijk < sizes).all(-1)]
    pts = torch.stack([a[i] for a, i in zip(axes, ijk.T, strict=True)], -1)  # (K, 3)
    return pts[_carve_cells(rig, masks, seen, pts)]


def visual_hull(
    cameras,
    obs,
    *,
    voxel: float = 0.04,
    half_extent: tuple[float, float, float] = (1.2, 1.2, 1.4),
) -> Detection | None:
    """Carve the visual hull of one frame's silhouettes and summarise it (module docstring).

    Args:
        cameras: :class:`~torchpf.camera.CameraRig` of the masks (any image size: resized to the masks; any
            device: the hull is carved on the CPU).
        obs: a Frame / Silhouettes / (V, H, W) masks.
        voxel: voxel edge (m).
        half_extent: half-size (m) of the carved box around the triangulated silhouette centroids.

    Returns:
        a :class:`Detection`, or None when fewer than two cameras see a silhouette or the hull is empty.
    """
    got = silhouette_masks(obs)
    if got is None:
        return None
    masks, valid = got
    V, H, W = masks.shape
    area = masks.flatten(1).sum(1).double() * valid
    rig = on_cpu(cameras).resized(W, H)  # carved on the CPU, as the masks are
    centre = _triangulate_centroids(rig, masks, valid & (area > 0))
    if centre is None:
        return None
    axes = [
        torch.arange(-e, e + 1e-9, voxel, dtype=torch.float64) + float(c)
        for e, c in zip(half_extent, centre, strict=True)
    ]
    # a camera without a silhouette carves nothing
    seen = torch.nonzero(valid & (area > 0)).reshape(-1).tolist()
    pts = _carve(rig, masks, seen, axes, voxel)
    if not len(pts):
        return None
    z = pts[:, 2]
    floor = float(torch.quantile(z, 0.005)) - 0.5 * voxel
    top = float(torch.quantile(z, 0.995)) + 0.5 * voxel
    # the torso slice (40-70 % of the height) locates the body without the swing of arms and legs
    h = top - floor
    torso = pts[(z > floor + 0.4 * h) & (z < floor + 0.7 * h)]
    torso = torso if len(torso) else pts
    xy = torso[:, :2].median(0).values
    centre = torch.stack([xy[0], xy[1], torch.tensor(floor + 0.5 * h, dtype=torch.float64)])
    # a torso is wider than deep: the slice's principal axis is the shoulder line (up to its sign)
    spread = torch.linalg.eigh(torch.cov(torso[:, :2].T) if len(torso) > 2 else torch.eye(2, dtype=xy.dtype))
    axis = spread.eigenvectors[:, 1]
    elongation = math.sqrt(float(spread.eigenvalues[1]) / max(float(spread.eigenvalues[0]), 1e-12))
    return Detection(
        centre=centre,
        floor=floor,
        top=top,
        voxels=int(len(pts)),
        voxel=voxel,
        area=area,
        axis=axis,
        elongation=elongation,
    )


# ---------------------------------------------------------------------------------------------- body
def _rest(skeleton) -> Tensor:
    zero = skeleton.clamp(torch.zeros(len(skeleton.dof_names), dtype=torch.float64))
    with torch.no_grad():
        return skeleton.fk(zero)


def looks_uncalibrated(skeleton, *, ratio: float = 0.04) -> bool:
    """True when the body is a stick figure: the thickest capsule of the torso chain
    (:func:`~torchpf.kinematics.body_partition`) has a radius below ``ratio`` x the rest-pose stature. A
    human torso is ~0.07 x stature deep and wide (ANSUR II); a converted mocap skeleton's ``0.15 x`` bone
    length capsules are ~0.015 x. A guess from the structure, not a certainty."""
    rest = _rest(skeleton)
    stature = float(rest[:, 2].max() - rest[:, 2].min())
    torso = set(body_partition(skeleton, joints=True)[0])
    radii = [float(r) for (p, c), r in zip(skeleton.bones, skeleton.radii, strict=True) if c in torso]
    return stature > 0 and (not radii or max(radii) < ratio * stature)


def _rotation_between(a: Tensor, b: Tensor) -> Tensor:
    """(3, 3) rotation taking unit vector ``a`` to unit vector ``b`` (Rodrigues)."""
    v, c = torch.linalg.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:  # opposite: a half turn about any axis perpendicular to a
        axis = torch.linalg.cross(a, torch.tensor([1.0, 0, 0], dtype=a.dtype))
        if axis.norm() < 1e-6:
            axis = torch.linalg.cross(a, torch.tensor([0, 1.0, 0], dtype=a.dtype))
        return _axis_angle(axis / axis.norm(), math.pi)
    K = torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=a.dtype)
    return torch.eye(3, dtype=a.dtype) + K + K @ K / (1 + c)


def _axis_angle(axis: Tensor, angle: float) -> Tensor:
    K = torch.tensor(
        [[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=axis.dtype
    )
    return torch.eye(3, dtype=axis.dtype) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


@dataclass
class _Limb:
    joints: list[int]  # the limb's joints
    pivot: int  # the joint it swings about (end of the girdle segment)
    moved: list[int]  # joints below the pivot
    extremity: int  # farthest joint of the main chain
    leg: bool
    bend: int | None = None  # the main chain's middle joint (knee, elbow), None for a short limb
    lower: list[int] | None = None  # joints below ``bend``


class PersonDetector:
    """Bottom-up detector of one person in multi-camera silhouettes (module docstring).

    Args:
        skeleton: the tracked :class:`~torchpf.skeleton.Skeleton` (its root must carry the global DOFs).
        cameras: :class:`~torchpf.camera.CameraRig` of the masks.
        headings: number of headings about the vertical in the global search (evenly spaced).
        voxel: voxel edge (m) of :func:`visual_hull`.
        posture_sigma: std (rad) of the posture prior of :meth:`search`.
        scale_sigma: the weak prior on the global scale in :meth:`fit`'s body fit
            (:func:`~torchpf.calibrate.fit_body`; ``None``: free).
        lead_speed: hull speed (m/s) above which the direction of motion gives the heading
            (:meth:`heading_choices`); ``inf`` leaves it to the torso's shoulder line.

    Attributes: ``postures`` (P, D) canonical postures (root at rest), ``heading_dofs`` (headings, R) the
    root's revolute DOF values per heading, ``root_height`` (m) of the root above the rest pose's lowest
    joint.
    """

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        headings: int = 24,
        voxel: float = 0.04,
        posture_sigma: float = 0.5,
        scale_sigma: float | None = 0.1,
        lead_speed: float = 0.5,
    ):
        # the detector's search is CPU-side geometry in float64 (OpenCV, the visual hull, IK); a tracker on a
        # GPU keeps its own skeleton and rig there and gets its particles back on its device (`search`)
        skeleton, cameras = on_cpu(skeleton), on_cpu(cameras)
        self.skeleton = skeleton
        self.posture_sigma = float(posture_sigma)
        self.scale_sigma = scale_sigma
        self.lead_speed = float(lead_speed)
        self.cameras = cameras
        self.voxel = float(voxel)
        parents = list(skeleton.parents)
        self.root = parents.index(-1)
        owner = (
            skeleton.dof_joints.tolist() if hasattr(skeleton.dof_joints, "tolist") else skeleton.dof_joints
        )
        revolute = skeleton.dof_revolute.tolist()
        D = len(skeleton.dof_names)
        self.trans = [d for d in range(D) if owner[d] == self.root and not revolute[d]]
        self.rot = [d for d in range(D) if owner[d] == self.root and revolute[d]]
        self.zero = skeleton.clamp(torch.zeros(D, dtype=torch.float64))
        rest = _rest(skeleton)
        self.rest = rest
        self.root_height = float(rest[self.root, 2] - rest[:, 2].min())
        self.stature = float(rest[:, 2].max() - rest[:, 2].min())
        with torch.no_grad():  # root displacement per unit of each translation DOF
            eye = torch.eye(D, dtype=torch.float64)[self.trans]
            self._trans_axes = (skeleton.fk(self.zero + eye)[:, self.root] - rest[self.root]).T  # (3, P)
        self.limbs = self._limbs(parents, rest)
        self.groups = body_partition(skeleton, per_limb=True)  # DOF indices: torso with the root, each limb
        self.lateral = self._lateral(rest)
        self.forward = self._forward(rest)
        self.headings = torch.arange(headings, dtype=torch.float64) * (2 * math.pi / headings)
        # the postures and headings' root rotations (IK, ~0.2 s) are built on first use: the tracker's
        # lost-track check only carves visual hulls, and most tracks never search

    @functools.cached_property
    def postures(self) -> Tensor:
        """(P, D) canonical postures, root at rest (standing, arms half down, rest, strides)."""
        return self._postures(self.rest)

    @property
    def posture_strata(self) -> list[list[int]]:
        """Posture indices searched apart (:meth:`search`): standing / arms half down / rest, then each
        stride."""
        return [[0, 3, 4], [1], [2]] + [[k] for k in range(5, len(self.postures))]

    @property
    def fit_postures(self) -> list[int]:
        """Posture indices fitted by :meth:`fit`: standing and every stride (walking and running)."""
        return [0, 1, 2, *range(5, len(self.postures))]

    @functools.cached_property
    def heading_dofs(self) -> Tensor:
        """(headings, R) the root's rotation DOFs that turn the body to each of :attr:`headings`."""
        return self._heading_dofs(self.rest)

    # ------------------------------------------------------------------ structure
    def _limbs(self, parents: list[int], rest: Tensor) -> list[_Limb]:
        kids = children_of(parents)

        def subtree(j):
            return subtree_of(kids, j)

        root_z, out = float(rest[self.root, 2]), []
        for joints in body_partition(self.skeleton, per_limb=True, joints=True)[1:]:
            start = next(j for j in joints if parents[j] not in joints)
            base = rest[parents[start]] if parents[start] >= 0 else rest[start]
            chain, j = [start], start
            while kids[j]:  # main chain: the child whose subtree reaches farthest from the limb's base
                j = max(kids[j], key=lambda c: float((rest[subtree(c)] - base).norm(dim=-1).max()))
                chain.append(j)
            points = [base]
            firsts = []
            for j in chain:
                if float((rest[j] - points[-1]).norm()) > 1e-3:
                    points.append(rest[j])
                    firsts.append(j)
            pivot = firsts[0] if len(firsts) >= 3 else start
            moved = [k for k in subtree(pivot) if k != pivot]
            leg = float(rest[joints, 2].min()) < root_z - 0.25 * self.stature
            bend = firsts[1] if len(firsts) >= 3 else None
            lower = [k for k in subtree(bend) if k != bend] if bend is not None else None
            out.append(_Limb(joints, pivot, moved, chain[-1], leg, bend, lower))
        return out

    def _lateral(self, rest: Tensor) -> Tensor:
        """Unit horizontal axis through the hips (between the two first legs' pivots), else world x."""
        legs = [limb for limb in self.limbs if limb.leg]
        if len(legs) >= 2:
            d = rest[legs[0].pivot] - rest[legs[1].pivot]
            d[2] = 0.0
            if float(d.norm()) > 1e-6:
                return d / d.norm()
        return torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)

    def _forward(self, rest: Tensor) -> Tensor | None:
        """Unit horizontal direction the feet point to in the rest pose (the legs' extremities ahead of
        their pivots, across the hip axis), or None when the legs end straight down."""
        legs = [limb for limb in self.limbs if limb.leg]
        if not legs:
            return None
        d = torch.stack([rest[limb.extremity] - rest[limb.pivot] for limb in legs]).mean(0)
        d[2] = 0.0
        d = d - (d @ self.lateral) * self.lateral
        return d / d.norm() if float(d.norm()) > 0.02 * self.stature else None

    def _postures(self, rest: Tensor) -> Tensor:
        """(P, D) canonical postures by IK from the rest pose (root DOFs at rest): arms down; arms down with
        a stride either way (legs +-20 deg about the hip axis, arms swinging against them); arms half down;
        the rest pose itself; and, when the feet give a forward direction, a running stride either way
        (legs +-30 deg, the back knee flexed 70 deg and the front one 20, elbows flexed 80 deg forwards)."""
        from torchpf.ik import project

        lateral = self.lateral
        down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)

        def rotated(points: Tensor, limb: _Limb, R: Tensor) -> Tensor:
            p = rest[limb.pivot]
            points[limb.moved] = (points[limb.moved] - p) @ R.T + p
            return points

        def flexed(points: Tensor, limb: _Limb, angle: float, backwards: bool) -> Tensor:
            # the limb's lower segment turned about the hip axis at its middle joint, its end moving
            # backwards (a knee) or forwards (an elbow) along the feet's direction
            if not angle or limb.bend is None or not limb.lower or self.forward is None:
                return points
            p = points[limb.bend]
            best = None
            for a in (angle, -angle):
                moved = (points[limb.lower] - p) @ _axis_angle(lateral, a).T + p
                ahead = float((moved[-1] - points[limb.lower][-1]) @ self.forward)
                if best is None or (ahead < best[0] if backwards else ahead > best[0]):
                    best = (ahead, moved)
            points[limb.lower] = best[1]
            return points

        def posture(arm_drop: float, stride: float, knees: tuple = (0.0, 0.0), elbows: float = 0.0) -> Tensor:
            pts = rest.clone()
            sign, legs_seen = 1.0, 0
            for limb in self.limbs:
                if limb.leg:
                    s = sign if legs_seen % 2 == 0 else -sign
                    legs_seen += 1
                    # close a splayed rest stance (feet under the hips), then swing about the hip axis
                    a = rest[limb.extremity] - rest[limb.pivot]
                    splay = (a @ lateral) * lateral + a[2] * down.abs()
                    close = _rotation_between(splay / splay.norm(), down)
                    pts = rotated(pts, limb, _axis_angle(lateral, s * stride) @ close)
                    if self.forward is not None and any(knees):
                        back = float((pts[limb.extremity] - pts[limb.pivot]) @ self.forward) < 0
                        pts = flexed(pts, limb, knees[0] if back else knees[1], backwards=True)
                    continue
                a = rest[limb.extremity] - rest[limb.pivot]
                if float(a.norm()) < 1e-6:
                    continue
                a = a / a.norm()
                out = a.clone()
                out[2] = 0.0
                out = out / out.norm() if float(out.norm()) > 1e-6 else torch.zeros(3, dtype=torch.float64)
                # the target direction: ``arm_drop`` of the way from the rest direction to hanging down
                target = math.cos(arm_drop) * out + math.sin(arm_drop) * down
                target = target / target.norm()
                R = _rotation_between(a, target)
                side = float((rest[limb.pivot] - rest[self.root]) @ lateral)
                R = _axis_angle(lateral, -0.75 * stride * math.copysign(1.0, side)) @ R
                pts = flexed(rotated(pts, limb, R), limb, elbows, backwards=False)
            return pts

        hang = math.radians(80.0)
        targets = torch.stack(
            [
                posture(hang, 0.0),
                posture(hang, math.radians(20.0)),
                posture(hang, -math.radians(20.0)),
                posture(math.radians(45.0), 0.0),
                rest,
            ]
            + [
                posture(
                    hang, s * math.radians(30.0), (math.radians(70.0), math.radians(20.0)), math.radians(80)
                )
                for s in ((1.0, -1.0) if self.forward is not None else ())
            ]
        )
        # only the DOFs that swing a limb about its pivot are solved for: with the girdle (clavicle, hip
        # joint) and spine free too, IK found far-off solutions that meet the targets with a twisted girdle
        owner = torch.as_tensor(self.skeleton.dof_joints)
        swung = torch.tensor(sorted({j for limb in self.limbs for j in [limb.pivot, *limb.moved]}))
        free = torch.isin(owner, swung)
        return project(self.skeleton, targets, self.zero.expand(len(targets), -1), free=free, iters=60)

    def _heading_dofs(self, rest: Tensor) -> Tensor:
        """(headings, R) root revolute DOFs turning the rest pose about the vertical through the root; each
        solved by IK from the previous heading's solution (a warm start, so the Euler angles stay
        continuous)."""
        from torchpf.ik import project

        if not self.rot:
            return torch.zeros(len(self.headings), 0, dtype=torch.float64)
        free = torch.zeros(len(self.zero), dtype=torch.bool)
        free[self.rot] = True
        theta, out = self.zero.clone(), []
        p = rest[self.root]
        for psi in self.headings.tolist():
            R = _axis_angle(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), psi)
            target = (rest - p) @ R.T + p
            theta = project(self.skeleton, target, theta, free=free, iters=60, ftol=0.0, tol=1e-7)
            out.append(theta[self.rot])
        return torch.stack(out)

    # ------------------------------------------------------------------ detection and proposals
    def detect(self, obs) -> Detection | None:
        """The person in one frame (:func:`visual_hull`), or None."""
        return visual_hull(self.cameras, obs, voxel=self.voxel)

    def place(self, theta: Tensor, position: Tensor) -> Tensor:
        """``theta`` (..., D) with the root's translation DOFs set so that the root joint is at ``position``
        (..., 3) (least squares when the root cannot reach every direction)."""
        if not self.trans:
            return theta
        theta = theta.clone()
        theta[..., self.trans] = 0.0
        with torch.no_grad():
            root = self.skeleton.fk(theta)[..., self.root, :]
        delta = torch.linalg.pinv(self._trans_axes) @ (position - root).unsqueeze(-1)
        theta[..., self.trans] = delta.squeeze(-1).to(theta.dtype)
        return theta

    def root_target(self, det: Detection) -> Tensor:
        """(3,) root position of a detection: the hull's centre, the floor plus the rest root height."""
        return torch.stack(
            [det.centre[0], det.centre[1], det.centre.new_tensor(det.floor + self.root_height)]
        )

    def heading_choices(self, det: Detection, motion: Tensor | None = None) -> list[list[int]]:
        """Indices into :attr:`headings` worth searching for a detection, in strata searched apart
        (:meth:`search`).

        A torso slice elongated by more than 15 % gives the shoulder line up to its sign: the two headings
        that align the rest pose's hip axis with it, and their neighbours. ``motion`` (2 or 3,) the
        hull's horizontal velocity (m/s) over the first frames: faster than 0.3 m/s, the heading whose
        feet point along it is kept (people walk and run forwards; a guess, so only a tie-break between
        the two). Otherwise every heading, in four quadrants.

        Faster than :attr:`lead_speed` the motion leads: the heading whose feet point along it, and its
        neighbours, come first, and the shoulder line's stratum follows only where it points elsewhere (a
        person walking sideways). On the foreign renders of CMU 16_46 (a run, 4.5 m/s), 07_01 and 35_02
        (walks, 1.1-1.5 m/s) the hull's motion over 5 frames pointed within 1-4 deg of the root's, while the
        shoulder line put the body 26, 15 and 4 deg off (16_46's torso slice is too round to give one, so
        all four quadrants were searched).
        """
        n = len(self.headings)
        step = 2 * math.pi / n

        def stratum(turn: float) -> list[int]:  # the heading nearest a turn (rad), and its neighbours
            k = round(turn / step)
            return [(k + o) % n for o in (-1, 0, 1)]

        lead = None
        speed = float(motion[:2].norm()) if motion is not None else 0.0
        if self.forward is not None and speed > self.lead_speed:
            lead = stratum(
                math.atan2(float(motion[1]), float(motion[0]))
                - math.atan2(float(self.forward[1]), float(self.forward[0]))
            )
        if det.axis is None or det.elongation < 1.15:
            if lead is not None:
                return [lead]
            return [list(range(q * n // 4, (q + 1) * n // 4)) for q in range(4)]
        lat = math.atan2(float(self.lateral[1]), float(self.lateral[0]))
        psi = math.atan2(float(det.axis[1]), float(det.axis[0])) - lat
        keep = [lead] if lead is not None else []
        for base in (psi, psi + math.pi):
            if self.forward is not None and speed > 0.3:
                c, s_ = math.cos(base), math.sin(base)
                fwd = (
                    c * float(self.forward[0]) - s_ * float(self.forward[1]),
                    s_ * float(self.forward[0]) + c * float(self.forward[1]),
                )
                if fwd[0] * float(motion[0]) + fwd[1] * float(motion[1]) < 0:
                    continue
            one = stratum(base)
            if lead is not None and one[1] in lead:
                continue  # the motion's stratum covers it
            keep.append(one)
        return keep

    def candidates(self, det: Detection, headings: list[int] | None = None) -> Tensor:
        """(H' x postures, D): every canonical posture at every heading of ``headings`` (indices into
        :attr:`headings`, default all), rooted at the detection."""
        headings = list(range(len(self.headings))) if headings is None else list(headings)
        P, Hn = len(self.postures), len(headings)
        theta = self.postures[None].expand(Hn, P, -1).clone()
        theta[..., self.rot] = self.heading_dofs[headings][:, None]
        return self.skeleton.clamp(self.place(theta.reshape(Hn * P, -1), self.root_target(det)))

    def propose(
        self,
        det: Detection,
        n: int,
        generator: torch.Generator | None = None,
        *,
        std: Tensor | float = 0.05,
        position_std: float = 0.05,
        headings: list[int] | None = None,
    ) -> Tensor:
        """(n, D) random detector particles: a random heading and posture of :meth:`candidates`, the root
        moved by N(0, position_std^2) per axis, every other DOF by N(0, std^2)."""
        cand = self.candidates(det, headings)
        generator = as_generator(generator, cand.device)
        pick = torch.randint(len(cand), (n,), generator=generator)
        x = cand[pick]
        std = torch.as_tensor(std, dtype=x.dtype).expand(x.shape[-1]).clone()
        std[self.trans] = 0.0
        x = x + torch.randn(x.shape, generator=generator, dtype=x.dtype) * std
        shift = torch.randn(n, 3, generator=generator, dtype=x.dtype) * position_std
        return self.skeleton.clamp(self.place(x, self.root_target(det) + shift))

    def fit(
        self,
        obs,
        *,
        det: Detection | None = None,
        motion: Tensor | None = None,
        quick: int = 60,
        iterations: int = 200,
        keep: int = 2,
    ):
        """Pose (and body) from one frame's masks alone: the central heading of each stratum of
        :meth:`heading_choices` x {standing, each walking and running stride} is refined by
        :func:`torchpf.calibrate.fit_body` for ``quick`` steps, the ``keep`` lowest final silhouette
        losses for ``iterations`` steps, and the best of those is returned. The fit's objective penalises
        both a model outside the mask and mask left uncovered (a soft-rasterised area match), which tells
        the strides and the front from the back far better than a thin model's likelihood does.

        Returns:
            ``(pose (D,), fitted, report)``: the refined pose, the fitted skeleton (radii, scale) and its
            :class:`~torchpf.calibrate.CalibrationReport`; raises ValueError when no person is detected.
        """
        det = det if det is not None else self.detect(obs)
        if det is None:
            raise ValueError("no person found in the silhouettes (fewer than two cameras see one)")
        headings = [h for group in self.heading_choices(det, motion) for h in group[len(group) // 2 :][:1]]
        cand = self.candidates(det, headings).reshape(len(headings), len(self.postures), -1)
        cand = cand[:, self.fit_postures]
        cand = cand.reshape(-1, cand.shape[-1])

        def run(pose, steps):
            # a looser scale prior than the fit at a given pose (0.03): with 0.03 notebook 05's
            # video-segmented walk tracked at 7.1 cm (6 seeds), free at 5.3 but the 11 noisy foreign clips
            # at 155 mm (2 runs); with 0.1, 5.7 cm (5.0-5.3 but one seed 8.3) and 131 mm (BENCHMARKS.md)
            fitted, report = fit_body_to_frame(
                self.skeleton, self.cameras, obs, pose, iterations=steps, scale_sigma=self.scale_sigma
            )
            return report.loss[-1], fitted, report

        quick_fits = sorted((run(p, quick)[0], k) for k, p in enumerate(cand))
        best = None
        for _, k in quick_fits[:keep]:
            loss, fitted, report = run(cand[k], iterations)
            if best is None or loss < best[0]:
                best = (loss, fitted, report)
        _, fitted, report = best
        return report.poses[0].to(torch.float64), fitted, report

    def search(
        self,
        likelihood,
        obs,
        *,
        n: int = 500,
        iterations: int = 4,
        std: Tensor | float = 0.05,
        start: Tensor | None = None,
        survival_rate: float = 0.3,
        generator: torch.Generator | None = None,
        det: Detection | None = None,
        motion: Tensor | None = None,
        strata: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        posture: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Global search of one frame: score every heading x posture (:meth:`candidates`, plus ``start``
        particles if given), then ``iterations`` rounds of partitioned annealing: for the torso (with the
        root) and then each limb (:func:`~torchpf.kinematics.body_partition`), resample by the annealed
        weights (Deutscher's adaptive ``beta`` for ``survival_rate``) and diffuse that part's DOFs, with
        noise shrinking from 3 to 0.5 x ``std`` over the rounds (rad; the root translation gets 3 cm,
        shrinking alike). ``iterations x (limbs + 1) x n`` likelihood evaluations.

        Args:
            likelihood: ``(x (N, D), obs) -> (N,)`` log-likelihood (the tracker's).
            obs: the frame.
            n: population size (the particles returned).
            std: (D,) or scalar per-DOF diffusion scale.
            start: (M, D) extra starting particles (a recovering track's own).
            det: the frame's detection (default: :meth:`detect`); ``motion`` the hull's velocity
                (:meth:`heading_choices`).
            strata: search each heading x stride stratum apart and keep the best (else one population
                from every candidate and ``start``).
            device, dtype: where and in which precision the likelihood runs (the tracker's).
            posture: (D,) pose whose limb DOFs centre the weak posture prior of the search (``N(posture,
                posture_sigma^2)`` per limb DOF); default the canonical standing posture. A recovering
                track passes its last good estimate: a run's bent elbows, hidden in the silhouette of the
                torso at low resolution, are kept instead of being pulled straight.

        Returns:
            ``(particles (n, D), log_likelihood (n,))`` in the likelihood's device and float dtype of
            ``self.zero`` (float64), or raises ValueError when no person is detected.
        """
        det = det if det is not None else self.detect(obs)
        if det is None:
            raise ValueError("no person found in the silhouettes (fewer than two cameras see one)")
        generator = as_generator(generator, torch.device("cpu"))
        scale = torch.as_tensor(std, dtype=torch.float64).expand(len(self.zero)).clone()
        scale[self.trans] = 0.03
        best = None
        choices = self.heading_choices(det, motion)
        if strata:
            groups = [(h, p) for h in choices for p in self.posture_strata]
        else:
            groups = [([h for c in choices for h in c], list(range(len(self.postures))))]
        for headings, postures in groups:
            # each heading x stride stratum is searched on its own: a population collapses on the mode the
            # canonical postures happen to favour, and the front/back modes, or the two strides (which leg
            # is ahead), are far apart in pose space but close in the silhouettes
            x = self.candidates(det, headings)
            x = x.reshape(len(headings), len(self.postures), -1)[:, postures].reshape(-1, x.shape[-1])
            if start is not None:
                x = torch.cat([x, start.detach().to(x)])
            x, ll = self._anneal(
                x,
                likelihood,
                obs,
                det,
                n,
                iterations,
                scale,
                survival_rate,
                generator,
                headings,
                device,
                dtype,
                posture,
            )
            if best is None or float(ll.max()) > float(best[1].max()):
                best = (x, ll)
        return best

    def _anneal(
        self,
        x,
        likelihood,
        obs,
        det,
        n,
        iterations,
        scale,
        survival_rate,
        generator,
        headings,
        device,
        dtype,
        posture=None,
    ) -> tuple[Tensor, Tensor]:
        if len(x) < n:
            x = torch.cat([x, self.propose(det, n - len(x), generator, std=scale, headings=headings)])
        resampler = RESAMPLERS.resolve("systematic")

        limbs = torch.ones(len(self.zero), dtype=torch.bool)
        limbs[self.trans + self.rot] = False
        limbs &= scale > 0
        # a weak prior keeps a thin model from folding its limbs inside the silhouette: each body part
        # (torso, each limb) near standing, or, given ``posture``, near either (a per-part mixture: a run's
        # bent elbows are kept from the last good pose while the legs are free to take the other stride)
        centres = self.postures[:1] if posture is None else torch.stack([self.postures[0], posture.cpu()])
        centres = centres.to(x.dtype)[:, limbs]  # (K, L)
        parts = torch.zeros(len(self.zero), len(self.groups), dtype=x.dtype)
        for g, group in enumerate(self.groups):
            parts[group, g] = 1.0
        parts = parts[limbs]  # (L, G)

        def score(x):
            off = wrap_angle(x[:, None, limbs] - centres) / self.posture_sigma  # (N, K, L)
            per_part = -0.5 * off.square() @ parts  # (N, K, G)
            prior = (torch.logsumexp(per_part, 1) - math.log(len(centres))).sum(-1)
            with torch.no_grad():
                return likelihood(x.to(device=device, dtype=dtype), obs).double().cpu() + prior

        ll = score(x)
        # partitioned annealing (MacCormick & Isard; Fontmarty Table 2): the torso with the root first,
        # then one limb at a time, so each round searches a few DOFs instead of all of them
        groups = self.groups
        for k in range(iterations):
            shrink = 3.0 * (0.5 / 3.0) ** (k / max(1, iterations - 1))
            for group in groups:
                beta = anneal_beta(torch.zeros(()), ll, survival_rate, torch.zeros((), dtype=ll.dtype))
                logw = temper(beta, ll)
                if len(x) != n:  # the first draw also brings the population to n
                    idx = torch.multinomial(torch.softmax(logw, -1), n, replacement=True, generator=generator)
                else:
                    idx = resampler(logw - torch.logsumexp(logw, -1), generator)
                x = x[idx].clone()
                noise = torch.randn(n, len(group), generator=generator, dtype=x.dtype)
                x[:, group] += noise * scale[group] * shrink
                x = self.skeleton.clamp(x)
                ll = score(x)
        return x, ll


# ---------------------------------------------------------------------------------------------- recovery
class Recovery:
    """Track-loss detection and re-acquisition, a filter hook (``filter.run(..., hook=recovery)``).

    Brubaker et al. §6 mix a bottom-up detector into the proposal so that a lost track comes back
    (I-CONDENSATION, :class:`~torchpf.proposals.ICondensationProposal`, with the detector as importance
    function). Here the detector is :class:`PersonDetector` and the mixture is applied when the track is
    judged lost, after the frame's filtering step:

    * **lost** when the silhouettes' total area falls below ``coverage`` x its running median (the person
      is occluded or gone: nothing to re-acquire from, the frame is flagged and the filter coasts; the first
      frame seen again is re-acquired), or the
      estimate's root is more than ``distance`` (m) horizontally from the visual hull's centre. The hull
      is checked when the log-likelihood of the estimate collapses (below the running median of the last
      ``window`` good frames by more than ``max(4 x 1.48 MAD, collapse x |median|)``), on every frame after
      a lost one, and every ``check_every`` frames.
    * **re-acquire**: the particles and the last good estimate are moved so their roots sit over the hull
      (keeping their postures and headings) and, with fresh detector candidates (every heading x posture
      at the hull; the heading chosen by the way the person moved since the last good frame, as for
      ``init="auto"``: :meth:`PersonDetector.heading_choices`), refined by :meth:`PersonDetector.search`
      (``iterations`` rounds of partitioned annealing, about ``iterations x (limbs + 1)`` frames' worth of
      likelihood evaluations; its posture prior is a per-part mixture of standing and the last good
      estimate); the result, weighted by its likelihood, replaces the filter's particles (a
      re-initialisation, not an importance-corrected weight: a lost track has no prior worth keeping).
      With ``strata`` (default) each heading x stride stratum is searched apart (with the track's own
      particles in each) and the best kept, as :meth:`PersonDetector.search` describes: after a 10-frame
      occlusion the foreign-render cases (``python -m benchmarks.auto_init --cases 8 --recovery``, seeds 0
      and 100) came back within 80 mm in 15 frames in 16 of 16 (15 of 16 with one population), at 68 mm
      after the occlusion against 79, for about 3 % more time per case (BENCHMARKS.md).

    After a run, ``lost`` and ``recovered`` (lists of frame flags; recovered: the first good frame after a
    lost run, where the re-acquired track is accepted) describe what happened.
    """

    def __init__(
        self,
        detector: PersonDetector,
        likelihood,
        *,
        std: Tensor | float = 0.05,
        coverage: float = 0.3,
        collapse: float = 0.5,
        distance: float = 0.3,
        window: int = 10,
        check_every: int = 5,
        iterations: int = 2,
        init_extras=None,
        dtype: torch.dtype = torch.float32,
        fps: float = 30.0,
        strata: bool = True,
    ):
        self.detector = detector
        self.strata = bool(strata)
        self.fps = float(fps)
        self.init_extras = init_extras
        self.likelihood = likelihood
        self.std = std
        self.coverage, self.collapse, self.distance = float(coverage), float(collapse), float(distance)
        self.window, self.check_every, self.iterations = int(window), int(check_every), int(iterations)
        self.dtype = dtype
        self.lost: list[bool] = []
        self.recovered: list[bool] = []
        self._areas: list[float] = []
        self._lls: list[float] = []
        self._gap = False
        self._last_good: Tensor | None = None  # (D,) the estimate of the last good frame, and its index
        self._last_t = 0

    @staticmethod
    def _estimate(state) -> Tensor:
        """The frame's estimate (D,): the filter's own where it reports one (the hybrid's refined pose)."""
        return state.info["estimate"] if "estimate" in state.info else state.mean()

    def _estimate_ll(self, state, obs) -> float:
        if "estimate_log_likelihood" in state.info:  # the hybrid scored its estimate already
            return float(state.info["estimate_log_likelihood"])
        with torch.no_grad():
            return float(self.likelihood(self._estimate(state)[None], obs)[0])

    def _root_distance(self, state, det: Detection) -> float:
        with torch.no_grad():
            root = self.detector.skeleton.fk(self._estimate(state).double().cpu())[self.detector.root]
        return float((root[:2] - det.centre[:2]).norm())

    def __call__(self, state, obs, generator=None):
        t = len(self.lost)
        got = silhouette_masks(obs)
        area = 0.0 if got is None else float((got[0].flatten(1).sum(1) * got[1]).sum())
        ref_area = float(np.median(self._areas[-self.window :])) if self._areas else area
        was_lost = bool(self.lost) and self.lost[-1]
        lost, recovered = area <= self.coverage * ref_area, False
        if lost:
            self._gap = True
        else:
            self._areas.append(area)
            ll = self._estimate_ll(state, obs)
            history = np.asarray(self._lls[-self.window :])
            suspicious = False
            if len(history) >= 3:
                med = float(np.median(history))
                mad = 1.4826 * float(np.median(np.abs(history - med)))
                suspicious = ll < med - max(4.0 * mad, self.collapse * abs(med))
            det = None
            if suspicious or was_lost or t % self.check_every == 0:
                det = self.detector.detect(obs)
            dist = self._root_distance(state, det) if det is not None else 0.0
            if det is not None and (dist > self.distance or self._gap):
                # after a gap the particles have coasted blind: the posture is re-searched even when the
                # root is still over the person
                state = self._reacquire(state, obs, det, generator)
                self._gap = False
                # lost when the root was off the person; a re-search after a gap alone is no failure
                lost = dist > self.distance
                recovered = was_lost and not lost
            else:
                recovered = was_lost
                self._lls.append(ll)
                if not suspicious:
                    self._last_good = self._estimate(state).detach().double().cpu()
                    self._last_t = t
        self.lost.append(lost)
        self.recovered.append(recovered)
        return state

    def _motion(self, det: Detection) -> Tensor | None:
        """(2,) horizontal velocity (m/s) from the last good estimate's root to the hull, or None."""
        if self._last_good is None:
            return None
        with torch.no_grad():
            root = self.detector.skeleton.fk(self._last_good)[self.detector.root]
        frames = max(1, len(self.lost) - self._last_t)
        return (det.centre[:2] - root[:2]) * self.fps / frames

    def _reacquire(self, state, obs, det: Detection, generator):
        x = state.particles
        n = x.shape[-2]
        own = x.reshape(-1, x.shape[-1]).double().cpu()
        if self._last_good is not None:
            own = torch.cat([own, self._last_good[None]])
        own = self.detector.place(own, self.detector.root_target(det)[None].expand(len(own), -1))
        g = torch.Generator().manual_seed(
            int(torch.randint(2**31 - 1, (1,), generator=generator, device=x.device))
        )
        new, ll = self.detector.search(
            self.likelihood,
            obs,
            n=n,
            iterations=self.iterations,
            std=self.std,
            start=own,
            generator=g,
            det=det,
            motion=self._motion(det),
            strata=self.strata,
            device=x.device,
            dtype=self.dtype,
            posture=self._last_good,
        )
        new = new.to(x)
        log_w = (ll - torch.logsumexp(ll, -1)).to(state.log_weights)
        new = new.reshape(x.shape)
        extras = dict(self.init_extras(new)) if self.init_extras is not None else dict(state.extras)
        # a filter that reports its own estimate (the hybrid's refined one, ``info["estimate"]``) made it from
        # the lost particles: the frame's estimate is the re-acquired set's mean instead
        info = {k: v for k, v in state.info.items() if k != "estimate"}
        return state.replace(
            particles=new, log_weights=log_w.reshape(state.log_weights.shape), extras=extras, info=info
        )
