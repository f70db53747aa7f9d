"""Body calibration: fit the capsule radii, a global scale and optionally bone lengths to silhouettes.

A converted mocap skeleton gets capsule radii of ``0.15 x`` bone length: a stick figure that fits anywhere
inside a silhouette. :func:`fit_body` fits the body's shape to the masks of a few frames (default the first
8) while refining their poses, so an approximate initial pose (the first rows of ``truth.csv``, a pose
within ~10 cm per joint) is enough:

* **Parameters** (all log-parametrised, so they stay positive): one radius per *group* of bones, a global
  scale on every bone length (and, with ``fit_lengths``, one length factor per group), and the poses of the
  used frames, projected onto the joint limits after every step (``skel.clamp``).
* **Groups** (:func:`bone_groups`) come from the structure, never from names: each bone of the torso chain
  is its own group; a limb hanging off the torso (:func:`~torchpf.kinematics.body_partition`) is tied to its
  mirror image, a limb with the same tree shape, the same bone lengths and a rest pose that is its
  reflection across the plane between them; matching bones of the pair share one radius.
* **Objective**: soft rasterisation of the projected capsules (:func:`torchpf.geometry.project_capsules`,
  :func:`torchpf.geometry.capsule_coverage`: a linear ramp of ``softness`` pixels across each capsule
  boundary, union by max) against the mask, squared error over the pixels around the silhouette, which
  penalises both directions (model outside the mask, mask not covered); plus, while the ramp is wide, the
  distance of the model's area samples (:func:`torchpf.geometry.sample_in_capsules`) to the mask
  (``cv2.distanceTransform``), whose gradient reaches limbs lying wholly outside the silhouette. The ramp
  narrows stage by stage (coarse to fine, each stage with a smaller Adam step and early stopping), and the
  last stage is the pixel-accurate area match alone. A weak penalty keeps the joints near the initial poses
  (silhouettes leave some rotations free).
* **Outline offsets** (``view_offset_sigma``): a segmenter's masks are often thinner or fatter in one
  camera or frame than in the next (a threshold, a 1-px erosion or dilation: at 160x120 a third of a limb).
  Fitted as they are, the shared radii follow whichever masks pull hardest. With the option each mask gets
  its own outline offset, pixels added to every projected radius in it, centred to mean 0 over the masks
  and weakly held at 0: the radii explain what the masks share, the offsets what one mask has alone. On 30
  noisy foreign-rendered frames at the true poses the fitted body's IoU against the *clean* masks rose
  from 0.74-0.85 to 0.82-0.87 on the 11 CMU clips (clean-mask fits: 0.85-0.89).

Masks larger than ``max_size`` pixels are fitted at a reduced resolution (area-averaged, so the targets
keep sub-pixel edge information); the reported IoU is at that resolution.

Shapes: ``F`` frames, ``V`` cameras, ``H x W`` masks, ``D`` DOFs, ``J`` joints, ``C`` bones, ``G`` groups.
Units: metres, radians, pixels.

Example::

    from torchpf.calibrate import fit_body
    fitted, report = fit_body(skel, seq.cameras, seq.masks[:8], seq.truth[:8])
    print(report.table())
    fitted.save_urdf("fitted.urdf")
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from torchpf.camera import CameraRig
from torchpf.devices import on_cpu
from torchpf.geometry import Capsules2D, project_capsules, sample_in_capsules
from torchpf.kinematics.symmetry import mirror_limbs
from torchpf.observations import Silhouettes

__all__ = [
    "CalibrationReport",
    "bone_groups",
    "fit_body",
    "outline_disagreement",
    "overlay_image",
    "projected_radii",
]


# ---------------------------------------------------------------------------------------------- groups
def bone_groups(skeleton, *, tol: float = 0.1) -> list[list[int]]:
    """Bones that share a radius (and a length factor): torso bones alone, mirror limbs tied bone by bone.

    From the structure only (module docstring): the torso/limb partition of ``skeleton.tree.joint_part``,
    the limbs' tree shapes, and the rest pose, in which a limb reflected across the plane half-way between
    its centroid and its mirror's must land on the mirror's joints within ``tol`` x the limb's size.

    Returns:
        Lists of bone indices (into ``skeleton.bones``), every bone exactly once, in order of first bone.
    """
    tree = skeleton.tree
    bone_of = {int(c): k for k, (_, c) in enumerate(tree.bones.tolist())}
    group_of: dict[int, int] = {}
    groups: list[list[int]] = []
    for joints, mirror, _ in mirror_limbs(skeleton, tol=tol):
        for pos, j in enumerate(joints):
            if j not in bone_of:
                continue
            members = [bone_of[j]]
            if mirror is not None and mirror[pos] in bone_of:
                members.append(bone_of[mirror[pos]])
            for m in members:
                group_of[m] = len(groups)
            groups.append(members)
    for k in range(len(tree.bones)):
        if k not in group_of:  # torso chain (and any other root's tree): one bone per group
            group_of[k] = len(groups)
            groups.append([k])
    return sorted(groups, key=min)


# ---------------------------------------------------------------------------------------------- model
def _posed(skeleton, cameras: CameraRig, pose, size: tuple[int, int] | None = None):
    """CPU copies of ``skeleton`` and of the rig (resized to the masks' grid ``size`` (W, H) when given),
    and the joints (J, 3) at ``pose`` (D,), without a graph."""
    skeleton, rig = on_cpu(skeleton), on_cpu(cameras)
    rig = rig.resized(*size) if size is not None else rig
    with torch.no_grad():
        joints = skeleton.fk(torch.as_tensor(pose, dtype=torch.float64).cpu().to(skeleton.radii.dtype))
    return skeleton, rig, joints


def projected_radii(skeleton, cameras: CameraRig, pose, size: tuple[int, int] | None = None) -> torch.Tensor:
    """(C,) each capsule's radius in pixels at ``pose`` (D,): the mean over its two ends and over the cameras
    that see it in front (pinhole: ``f r / z`` at each end), with the rig resized to ``size`` (W, H), the
    masks' grid, when given. NaN for a capsule no camera sees."""
    skeleton, rig, joints = _posed(skeleton, cameras, pose, size)
    with torch.no_grad():
        bones = skeleton.tree.bones
        caps = project_capsules(rig, joints[None, bones[:, 0]], joints[None, bones[:, 1]], skeleton.radii)
        seen = caps.valid[0].to(caps.ra.dtype)  # (V, C)
        radius = 0.5 * (caps.ra[0] + caps.rb[0])
        return ((radius * seen).sum(0) / seen.sum(0)).double()


def outline_disagreement(skeleton, cameras: CameraRig, masks, pose) -> torch.Tensor:
    """(V,) how far each mask's outline strays from the body's silhouette at ``pose`` (D,), in pixels: the
    pixels where the body's rasterised silhouette and the mask disagree (symmetric difference) per pixel of
    the mask's outline (its foreground pixels with a background pixel among their 8 neighbours). Every
    disagreeing pixel lying along the outline, it is the outline's mean displacement; speckle, holes and
    ragged edges add to it too. NaN for a camera whose mask is empty or missing.

    With a body fitted to the masks (:func:`fit_body`) it says how well the masks can measure widths: on
    the foreign renders of 11 CMU clips (160x120, frame 0 fitted at the true pose, mean over 3 cameras)
    0.15-0.26 px for clean masks, 0.59-0.85 for the noisy preset's (``Tracker.hold_thin_arms``); a mask
    grown or shrunk by one pixel strays one pixel more.

    ``masks``: a (V, H, W) array or a list of V masks (None for a missing one), foreground ``> 0.5``
    (``> 127`` as uint8); the rig is resized to their grid."""
    masks = [m.detach().cpu() if isinstance(m, torch.Tensor) else m for m in masks]  # masks on any device
    arr, valid = _as_masks([masks], 1)
    target, valid = torch.from_numpy(arr[0] > 0.5), torch.from_numpy(valid[0])
    V, H, W = target.shape
    skeleton, rig, joints = _posed(skeleton, cameras, pose, (W, H))
    model = torch.from_numpy(_model_masks(skeleton, rig, joints[None], skeleton.radii, H, W)[0])
    inner = -torch.nn.functional.max_pool2d(-target[:, None].float(), 3, stride=1, padding=1)[:, 0] > 0.5
    outline = (target & ~inner).sum((1, 2)).double()
    wrong = (model ^ target).sum((1, 2)).double()
    return torch.where(valid & (outline > 0), wrong / outline.clamp_min(1), torch.nan)


def _ancestors(parents: Sequence[int]) -> torch.Tensor:
    """(J, J) float: ``A[j, a] = 1`` when ``a`` is ``j`` or one of its ancestors."""
    J = len(parents)
    A = torch.zeros(J, J, dtype=torch.float64)
    for j in range(J):
        a = j
        while a >= 0:
            A[j, a] = 1.0
            a = parents[a]
    return A


def scaled_joints(skeleton, theta, log_scale, log_lengths=None, ancestors=None) -> torch.Tensor:
    """Joint positions (..., J, 3) m of ``skeleton.with_body(scale=exp(log_scale), lengths=exp(log_lengths))``
    at poses ``theta`` (..., D), differentiable in all three.

    A global scale ``s`` is ``s * fk(theta')`` with the prismatic DOFs divided by ``s`` (every length, the
    root translation included, scaled, then the translation restored); a bone-length factor ``l_c`` scales
    the world bone vector ``x_c - x_parent`` (rotations do not depend on lengths), summed down the tree
    (``ancestors``, :func:`_ancestors`). ``log_lengths`` (J,) or None.
    """
    s = log_scale.exp()
    prismatic = ~skeleton.tree.dof_revolute.to(theta.device)
    joints = skeleton.fk(torch.where(prismatic, theta / s, theta))
    if log_lengths is not None:
        parents = skeleton.tree.parents.to(theta.device)
        has_parent = (parents >= 0)[:, None]
        parent_pos = joints[..., parents.clamp(min=0), :]
        vectors = torch.where(has_parent, (joints - parent_pos) * log_lengths.exp()[:, None], joints)
        joints = ancestors.to(joints) @ vectors
    return s * joints


# ---------------------------------------------------------------------------------------------- data
def _as_masks(frames, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(F, V, H, W) float32 in [0, 1] and (F, V) bool valid, from an array or nested lists (None missing)."""
    if isinstance(frames, torch.Tensor):
        frames = frames.detach().cpu().numpy()
    if isinstance(frames, np.ndarray):
        arr = frames.astype(np.float32)
        if arr.ndim != 4:
            raise ValueError(f"frames must have shape (F, V, H, W), got {arr.shape}")
        if frames.dtype == np.uint8:
            arr = arr / 255.0
        return arr[:n_frames], np.ones(arr.shape[:2], dtype=bool)[:n_frames]
    rows = list(frames)[:n_frames]
    shape = next((np.asarray(m).shape for row in rows for m in row if m is not None), None)
    if shape is None:
        raise ValueError("frames: no mask in the frames used")
    out = np.zeros((len(rows), len(rows[0]), *shape), dtype=np.float32)
    valid = np.zeros(out.shape[:2], dtype=bool)
    for f, row in enumerate(rows):
        for v, m in enumerate(row):
            if m is None:
                continue
            m = np.asarray(m)
            if m.shape != shape:
                raise ValueError(f"frames: mask ({f}, {v}) is {m.shape}, others are {shape}")
            out[f, v] = m / 255.0 if m.dtype == np.uint8 else m.astype(np.float32)
            valid[f, v] = True
    return out, valid


def _downsample(masks: np.ndarray, max_size: int) -> np.ndarray:
    import cv2

    F, V, H, W = masks.shape
    k = max(H, W) / max_size
    if k <= 1:
        return masks
    w, h = max(1, round(W / k)), max(1, round(H / k))
    out = np.stack([cv2.resize(m, (w, h), interpolation=cv2.INTER_AREA) for m in masks.reshape(-1, H, W)])
    return out.reshape(F, V, h, w)


def _flat_caps(caps):
    """(B * C, ...) fields of :class:`~torchpf.geometry.Capsules2D` (..., C), batch dims flattened."""
    return (
        caps.pa.reshape(-1, 2),
        caps.pb.reshape(-1, 2),
        caps.ra.reshape(-1),
        caps.rb.reshape(-1),
        caps.valid.reshape(-1),
    )


def _capsule_pairs(caps, uv: torch.Tensor, view: torch.Tensor, C: int, reach: float):
    """The (pixel, capsule) pairs whose capsule's box, grown by ``reach`` px, holds the pixel: the only
    pairs whose coverage can be non-zero. ``uv`` (N, 2) pixels of views ``view`` (N,) (rows of the
    flattened batch of ``caps`` (B, C)). Returns pixel rows (K,) and flat capsule rows (K,) into
    ``B * C``."""
    pa, pb, ra, rb, _ = (x.detach() for x in _flat_caps(caps))
    lo = torch.minimum(pa - ra[:, None], pb - rb[:, None]) - reach
    hi = torch.maximum(pa + ra[:, None], pb + rb[:, None]) + reach
    pix, cap = [], []
    starts = torch.searchsorted(view, torch.arange(len(lo) // C + 1))  # ``view`` is sorted
    for b in range(len(lo) // C):
        rows = torch.arange(int(starts[b]), int(starts[b + 1]))
        if not len(rows):
            continue
        p = uv[rows]  # (n, 2)
        box_lo, box_hi = lo[b * C : (b + 1) * C, None], hi[b * C : (b + 1) * C, None]
        pu, pv = p[:, 0], p[:, 1]
        inside = (
            (pu >= box_lo[..., 0]) & (pu <= box_hi[..., 0]) & (pv >= box_lo[..., 1]) & (pv <= box_hi[..., 1])
        )
        c, k = torch.nonzero(inside, as_tuple=True)
        pix.append(rows[k])
        cap.append(b * C + c)
    return torch.cat(pix), torch.cat(cap)


def _coverage(caps, uv: torch.Tensor, pix: torch.Tensor, cap: torch.Tensor, width: float) -> torch.Tensor:
    """(N,) soft coverage of pixels ``uv`` (N, 2) by the projected capsules: per pair a linear ramp of
    ``width`` px across the tapered capsule's outline (``clamp(1/2 + (r(t) - d) / width)``, ``d`` the
    distance to the axis, ``r(t)`` the radius interpolated at the nearest axis point), united over the
    capsules by a probabilistic OR ``1 - prod(1 - c)``. Differentiable in the capsules."""
    pa, pb, ra, rb, valid = _flat_caps(caps)
    pa, pb, ra, rb = pa[cap], pb[cap], ra[cap], rb[cap]
    q = uv[pix].to(pa)
    e = pb - pa
    t = (((q - pa) * e).sum(-1) / (e * e).sum(-1).clamp_min(1e-9)).clamp(0.0, 1.0)
    d = (q - pa - t[:, None] * e).square().sum(-1).clamp_min(1e-12).sqrt()
    c = (0.5 + (ra + t * (rb - ra) - d) / width).clamp(0.0, 1.0 - 1e-6) * valid[cap]
    miss = uv.new_zeros(len(uv), dtype=pa.dtype).index_add(0, pix, torch.log1p(-c))
    return 1.0 - miss.exp()


def _active_pixels(target: np.ndarray, model: np.ndarray, band: int) -> np.ndarray:
    """(F, V, H, W) bool: the pixels whose term can change while the model moves by less than ``band`` px:
    within ``band`` of the model's outline, of a pixel where model and mask disagree, or on the mask's
    (fractional) edge; elsewhere model and mask agree and the ramp is flat. ``target`` in [0, 1],
    ``model`` bool, both (F, V, H, W)."""
    import cv2

    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))
    out = np.zeros(target.shape, dtype=bool)
    for f, v in np.ndindex(*target.shape[:2]):
        m = model[f, v].astype(np.uint8)
        t = target[f, v]
        disagree = ((m > 0) != (t > 0.5)).astype(np.uint8)
        out[f, v] = (cv2.dilate(m, kernel) > cv2.erode(m, kernel)) | (cv2.dilate(disagree, kernel) > 0)
        out[f, v] |= (t > 0.01) & (t < 0.99)
    return out


# ---------------------------------------------------------------------------------------------- report
@dataclass
class CalibrationReport:
    """What :func:`fit_body` found and how well it fits.

    Fields: ``groups`` (G) lists of bone indices and ``labels`` (G) their child joint names joined by
    ``/`` (display only); ``radii_before``, ``radii_after`` (G,) m (a group's geometric mean before);
    ``scale`` the global length factor; ``lengths`` (G,) bone-length factors (ones unless
    ``fit_lengths``); ``iou_before``, ``iou_after`` camera name -> silhouette IoU over the frames used (the
    body alone, without the outline offsets: what a tracker draws);
    ``poses`` (F, D) the refined poses; ``loss`` the objective per iteration; ``iterations``; ``seconds``;
    ``offsets`` (F, V) the masks' fitted outline offsets (px of the working grid, NaN for a missing mask)
    with ``view_offset_sigma``, else None.
    """

    groups: list[list[int]]
    labels: list[str]
    radii_before: torch.Tensor
    radii_after: torch.Tensor
    scale: float
    lengths: torch.Tensor
    iou_before: dict[str, float]
    iou_after: dict[str, float]
    poses: torch.Tensor
    loss: list[float] = field(default_factory=list)
    iterations: int = 0
    seconds: float = 0.0
    offsets: torch.Tensor | None = None

    def table(self) -> str:
        """The fitted radii per group and the IoU per camera, as Markdown tables."""
        lines = ["| bones | radius before (cm) | radius after (cm) | length factor |", "|---|---:|---:|---:|"]
        for label, r0, r1, ln in zip(
            self.labels,
            self.radii_before.tolist(),
            self.radii_after.tolist(),
            self.lengths.tolist(),
            strict=True,
        ):
            lines.append(f"| {label} | {r0 * 100:.1f} | {r1 * 100:.1f} | {ln:.3f} |")
        lines += [
            "",
            f"global scale {self.scale:.4f}",
            "",
            "| camera | IoU before | IoU after |"
            + (" outline offset (px) |" if self.offsets is not None else ""),
            "|---|---:|---:|" + ("---:|" if self.offsets is not None else ""),
        ]
        for v, name in enumerate(self.iou_before):
            row = f"| {name} | {self.iou_before[name]:.3f} | {self.iou_after[name]:.3f} |"
            if self.offsets is not None:  # mean and spread over the frames with a mask
                off = self.offsets[:, v][torch.isfinite(self.offsets[:, v])]
                row += f" {float(off.mean()):+.2f} +- {float(off.std(unbiased=False)):.2f} |"
            lines.append(row)
        lines.append(
            f"\n{self.iterations} iterations in {self.seconds:.1f} s, "
            f"loss {self.loss[0]:.4g} -> {self.loss[-1]:.4g}"
        )
        return "\n".join(lines)


def _model_masks(
    skeleton, rig: CameraRig, joints: torch.Tensor, radii: torch.Tensor, h: int, w: int
) -> np.ndarray:
    """(F, V, h, w) bool silhouettes of the capsules of joints (F, J, 3) m with radii (C,) m (the tapered
    capsules of :func:`_coverage`, rasterised at pixel centres)."""
    bones = skeleton.tree.bones
    with torch.no_grad():
        caps = project_capsules(rig, joints[:, bones[:, 0]], joints[:, bones[:, 1]], radii.to(joints))
        pa, pb, ra, rb, _ = _flat_caps(caps)
        lo = torch.minimum(pa - ra[:, None], pb - rb[:, None]).floor().clamp_min(0).long()
        hi = torch.maximum(pa + ra[:, None], pb + rb[:, None]).ceil().long()
        hi = torch.minimum(hi, torch.tensor([w - 1, h - 1]))
        C = caps.pa.shape[-2]
        pix, cap = [], []
        # each capsule's box of pixels (rows of the flattened (B, h, w) grid)
        for k, ((x0, y0), (x1, y1)) in enumerate(zip(lo.tolist(), hi.tolist(), strict=True)):
            if x1 < x0 or y1 < y0:
                continue
            ys, xs = torch.meshgrid(torch.arange(y0, y1 + 1), torch.arange(x0, x1 + 1), indexing="ij")
            pix.append(((k // C) * h + ys.reshape(-1)) * w + xs.reshape(-1))
            cap.append(torch.full((xs.numel(),), k))
        B = len(pa) // C
        v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        uv = torch.stack([u, v], -1).reshape(-1, 2).to(joints.dtype).repeat(B, 1)
        if not pix:
            return np.zeros((*caps.pa.shape[:2], h, w), dtype=bool)
        covered = _coverage(caps, uv, torch.cat(pix), torch.cat(cap), 1e-3) > 0.5
    return covered.reshape(*caps.pa.shape[:2], h, w).numpy()


def _iou(model: np.ndarray, target: np.ndarray, valid: np.ndarray, names: list[str]) -> dict[str, float]:
    inter = ((model & target) * valid[..., None, None]).sum((0, 2, 3))
    union = ((model | target) * valid[..., None, None]).sum((0, 2, 3))
    return {n: float(i / u) if u else float("nan") for n, i, u in zip(names, inter, union, strict=True)}


# ---------------------------------------------------------------------------------------------- fitting
def fit_body(
    skeleton,
    cameras: CameraRig,
    frames,
    poses,
    *,
    frames_used: int | Sequence[int] = 8,
    fit_lengths: bool = False,
    iterations: int = 400,
    softness: Sequence[float] = (6.0, 3.0, 1.5, 0.75),
    lr: float = 0.05,
    pose_lr: float = 0.02,
    pose_sigma: float = 0.1,
    length_sigma: float = 0.1,
    scale_sigma: float | None = None,
    radius_sigma: float | None = None,
    distance_weight: float = 0.05,
    view_offset_sigma: float | None = None,
    max_size: int = 200,
    groups: list[list[int]] | None = None,
    fixed: Sequence[int] = (),
    tol: float = 1e-4,
    patience: int = 20,
    refresh_every: int = 10,
    progress: bool = False,
):
    """Fit capsule radii (per :func:`bone_groups` group), a global scale and optionally bone lengths to
    silhouettes, refining the poses of the frames used (module docstring).

    Args:
        skeleton: the :class:`~torchpf.skeleton.Skeleton` to fit (its radii are the starting point).
        cameras: :class:`~torchpf.camera.CameraRig` of the ``V`` mask cameras, in mask order (any image
            size: it is resized to the mask grid).
        frames: masks (F, V, H, W) (bool, 0/1 float or 0/255 uint8; array or tensor), or F lists of V (H, W)
            arrays with None for a missing mask (``SequenceData.masks``).
        poses: (F, D) approximate poses of those frames (rad / m, ``dof_names`` order).
        frames_used: the first ``k`` frames, or a list of frame indices.
        fit_lengths: also fit one bone-length factor per group (weakly held at 1 by ``length_sigma``).
        scale_sigma: ``None`` fits the global scale freely; a number holds it near 1 by the same kind of
            weak penalty (``1e-3 log(s)^2 / scale_sigma^2``): a MAP scale for a skeleton whose bone lengths
            are already roughly right (one noisy frame moves a free scale by up to 13 %, see
            :func:`torchpf.detect.fit_body_to_frame`).
        radius_sigma: ``None`` fits each group's radius freely; a number holds the groups' log radii near
            their mean by ``1e-3 mean_g (log r_g - mean log r)^2 / radius_sigma^2``, a shrinkage prior on the
            spread of the body's widths. Masks with defects seen at poses that are off (a tracker's first
            poses) are explained as well by absurd bodies: a 1-4 mm torso with 80-100 mm balls for hands or
            hips, which then carry the torso's width (noisy foreign renders of the runs; BENCHMARKS.md,
            "Round 10"); at 0.25 such fits keep a torso of 35-60 mm and their IoU against the clean masks
            at the true poses rises 0.72 -> 0.75 and 0.68 -> 0.71.
        iterations: the most Adam steps over all stages; each of the ``len(softness)`` stages gets an equal
            share and stops early when the loss improves by less than ``tol`` (relative) in ``patience``
            steps.
        softness: the ramp width (pixels of the working grid) of each stage, coarse to fine.
        lr: Adam step of the log-radii, log-scale and log-lengths in the first stage (halved each stage);
            ``pose_lr`` that of the poses (rad / m).
        pose_sigma: std (m) of the joints around the initial poses' joints (the weak pose penalty).
        distance_weight: weight of the model-to-mask distance term in all stages but the last.
        view_offset_sigma: ``None`` fits the body to every mask as it is; a number (px of the working
            grid) also fits each mask's outline offset, pixels added to every projected radius in that mask
            (an erosion or dilation of one camera's mask, a segmenter's bias), held near 0 by
            ``1e-3 (d / view_offset_sigma)^2`` and centred to mean 0 over the masks, so that the shared
            radii explain what the masks have in common and the offsets what one mask has on its own.
        max_size: masks whose larger side exceeds this many pixels are fitted at reduced resolution.
        groups: bone groups overriding :func:`bone_groups`.
        fixed: bones (indices into ``skeleton.bones``) whose radii are held as the skeleton has them: their
            groups' radii are not fitted (a group's bones share one radius, so holding one bone holds its
            mirror image too). For capsules the masks cannot measure, e.g. limbs a pixel or two across in
            masks whose outlines move by a pixel (``Tracker.hold_thin_arms`` puts such arms back after the
            fit instead: on noisy foreign renders that tracked closer than holding them in it).
        refresh_every: steps between two choices of the pixels scored (:func:`_active_pixels`).
        progress: a tqdm progress bar over the iterations.

    Returns:
        ``(fitted, report)``: ``skeleton.with_body(...)`` with the fitted radii, scale and lengths (the
        refined poses are valid poses of it), and a :class:`CalibrationReport`. The fit runs on the CPU
        (OpenCV rasterises the masks' active pixels): ``fitted`` is on the CPU whatever the device of
        ``skeleton``, which is not moved.
    """
    t_start = time.perf_counter()
    skeleton, cameras = on_cpu(skeleton), on_cpu(cameras)  # OpenCV rasterises on the CPU
    D = len(skeleton.dof_names)
    poses = torch.as_tensor(poses, dtype=torch.float64).cpu()
    if poses.ndim != 2 or poses.shape[1] != D:
        raise ValueError(f"poses must have shape (F, {D}), got {tuple(poses.shape)}")
    idx = (
        list(range(min(int(frames_used), len(poses)))) if isinstance(frames_used, int) else list(frames_used)
    )
    if not idx:
        raise ValueError("fit_body: no frame to fit")
    if radius_sigma is not None and not radius_sigma > 0:
        raise ValueError(f"fit_body: radius_sigma must be > 0 or None, got {radius_sigma}")
    if view_offset_sigma is not None and not view_offset_sigma > 0:
        raise ValueError(f"fit_body: view_offset_sigma must be > 0 px or None, got {view_offset_sigma}")
    raw = list(frames) if not isinstance(frames, (np.ndarray, torch.Tensor)) else frames
    if max(idx) >= min(len(raw), len(poses)) or min(idx) < 0:
        raise ValueError(f"fit_body: frames {idx} out of range ({len(raw)} frames, {len(poses)} poses)")
    masks, valid = _as_masks([raw[i] for i in idx] if isinstance(raw, list) else raw[idx], len(idx))
    if masks.shape[1] != len(cameras):
        raise ValueError(f"frames have {masks.shape[1]} cameras, the rig has {len(cameras)}")
    target = torch.from_numpy(_downsample(masks, max_size))
    F, V, H, W = target.shape
    rig = cameras.resized(W, H)
    dtype = torch.float32

    groups = bone_groups(skeleton) if groups is None else [list(g) for g in groups]
    C, G = len(skeleton.bones), len(groups)
    member = torch.zeros(C, G, dtype=dtype)
    for g, bones in enumerate(groups):
        member[bones, g] = 1.0
    if not bool((member.sum(1) == 1).all()):
        raise ValueError("groups must hold every bone exactly once")
    fixed = sorted({int(k) for k in fixed})
    if fixed and not 0 <= fixed[0] <= fixed[-1] < C:
        raise ValueError(f"fit_body: fixed bones {fixed} out of range (the skeleton has {C} bones)")
    held = (member[fixed].sum(0) > 0) if fixed else torch.zeros(G, dtype=torch.bool)
    is_fixed = torch.zeros(C, dtype=torch.bool)
    is_fixed[fixed] = True
    given_r = skeleton.radii.to(dtype)

    def bone_radii(log_r):
        """(C,) radii: the groups' fitted ones, the fixed bones' as given."""
        return torch.where(is_fixed, given_r, (member @ log_r).exp())

    log_r0 = (member.t() @ skeleton.radii.to(dtype).clamp_min(1e-4).log()) / member.sum(0)
    joint_group = torch.full((len(skeleton.joint_names),), -1, dtype=torch.long)
    for k, (_, c) in enumerate(skeleton.bones):
        joint_group[c] = int(member[k].argmax())
    ancestors = _ancestors(skeleton.parents) if fit_lengths else None

    log_r = log_r0.clone().requires_grad_(True)
    log_s = torch.zeros((), dtype=dtype, requires_grad=True)
    fit_offsets = view_offset_sigma is not None
    raw_offset = torch.zeros(F, V, dtype=dtype, requires_grad=fit_offsets)
    log_l = torch.zeros(G, dtype=dtype, requires_grad=fit_lengths)
    theta0 = skeleton.clamp(poses[idx].to(dtype))
    theta = theta0.clone().requires_grad_(True)
    bones = skeleton.tree.bones

    def per_joint(log_l):
        return torch.where(
            joint_group >= 0, log_l[joint_group.clamp(min=0)], torch.zeros_like(joint_group, dtype=dtype)
        )

    def joints_of(theta, log_s, log_l):
        return scaled_joints(skeleton, theta, log_s, per_joint(log_l) if fit_lengths else None, ancestors)

    with torch.no_grad():
        joints0 = joints_of(theta0, log_s, log_l)
        model0 = _model_masks(skeleton, rig, joints0, bone_radii(log_r0), H, W)
    hard = target.numpy() > 0.5
    iou_before = _iou(model0, hard, valid, rig.names)
    area = (target * torch.from_numpy(valid)[..., None, None]).sum((-2, -1)).clamp_min(1.0)  # (F, V)
    pixels: dict = {}
    grid_v, grid_u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    grid = torch.stack([grid_u, grid_v], -1).reshape(-1, 2).to(dtype)
    from torchpf.geometry.chamfer import distance_lookup

    view_valid = torch.from_numpy(valid).to(dtype)

    def offsets():
        """(F, V) outline offsets (px), mean 0 over the masks present."""
        if not fit_offsets:
            return raw_offset.detach()
        mean = (raw_offset * view_valid).sum() / view_valid.sum().clamp_min(1.0)
        return (raw_offset - mean) * view_valid

    def capsules(joints, radii, offset):
        caps = project_capsules(rig, joints[:, bones[:, 0]], joints[:, bones[:, 1]], radii)
        grow = offset[..., None]  # (F, V, 1): the same pixels added to every capsule of a mask
        return Capsules2D(caps.pa, caps.pb, caps.ra + grow, caps.rb + grow, caps.valid)

    def refresh(width: float) -> None:
        """The pixels scored for the next steps (:func:`_active_pixels`) and their capsule pairs."""
        with torch.no_grad():
            joints, radii = joints_of(theta, log_s, log_l), bone_radii(log_r)
            model = _model_masks(skeleton, rig, joints, radii, H, W)
            off = offsets()
            caps = capsules(joints, radii, off)
        band = int(math.ceil(width / 2 + 3))
        active = torch.from_numpy(_active_pixels(target.numpy(), model, band) & valid[..., None, None])
        rows = torch.nonzero(active.reshape(-1)).reshape(-1)
        uv, view = grid[rows % (H * W)], rows // (H * W)
        reach = width / 2 + 2 + float(off.abs().max())
        pix, cap = _capsule_pairs(caps, uv, view, C, reach)
        pixels.update(uv=uv, view=view, pix=pix, cap=cap, target=target.reshape(-1)[rows].to(dtype))

    # distance (px) from each pixel to the silhouette, 0 inside; its zero level is the pixel edge
    outside = Silhouettes(torch.from_numpy(hard)).outside_distance().to(dtype).reshape(F * V, H, W)
    has_mask = torch.from_numpy(hard.any((2, 3)) & valid).to(dtype)
    n_views = max(1.0, float(valid.sum()))

    def objective(width: float, dist_w: float):
        joints = joints_of(theta, log_s, log_l)
        caps = capsules(joints, bone_radii(log_r), offsets())
        cov = _coverage(caps, pixels["uv"], pixels["pix"], pixels["cap"], width)
        sq = (cov - pixels["target"]) ** 2
        per_view = sq.new_zeros(F * V).index_add(0, pixels["view"], sq)
        loss = (per_view / area.reshape(-1)).sum() / n_views
        if dist_w > 0:
            grown = Capsules2D(caps.pa, caps.pb, caps.ra.clamp_min(0.0), caps.rb.clamp_min(0.0), caps.valid)
            pts, w_area = sample_in_capsules(grown, n_body=8, n_cap=1)  # (F, V, Q, 2), (F, V, Q)
            d = torch.stack(
                [distance_lookup(outside[k], p) for k, p in enumerate(pts.reshape(F * V, -1, 2))]
            ).reshape(w_area.shape)
            far = (d * w_area).sum(-1) / area * has_mask
            loss = loss + dist_w * far.sum() / max(1.0, float(has_mask.sum()))
        drift = ((joints - joints0) ** 2).sum(-1).mean() / pose_sigma**2
        loss = loss + 1e-3 * drift
        if fit_lengths:
            loss = loss + 1e-3 * (log_l**2).sum() / length_sigma**2
        if scale_sigma is not None:
            loss = loss + 1e-3 * log_s**2 / scale_sigma**2
        if radius_sigma is not None:
            spread = log_r - log_r.mean()
            loss = loss + 1e-3 * spread.square().mean() / radius_sigma**2
        if fit_offsets:
            loss = loss + 1e-3 * (offsets() ** 2).sum() / n_views / view_offset_sigma**2
        return loss

    params = [
        {"params": [log_r], "lr": lr},
        {"params": [log_s], "lr": 0.2 * lr},
        {"params": [theta], "lr": pose_lr},
    ]
    if fit_lengths:
        params.append({"params": [log_l], "lr": 0.2 * lr})
    if fit_offsets:  # px: a 1-2 px erosion or dilation is reached within the first stage's steps
        params.append({"params": [raw_offset], "lr": 0.5})
    opt = torch.optim.Adam(params)
    base_lrs = [g["lr"] for g in opt.param_groups]
    per_stage = max(1, iterations // len(softness))
    losses: list[float] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=per_stage * len(softness), desc="calibrate", unit="it")
    for stage, width in enumerate(softness):
        last = stage == len(softness) - 1
        for g, base in zip(opt.param_groups, base_lrs, strict=True):
            g["lr"] = base * 0.5**stage
        best, since = math.inf, 0
        for step in range(per_stage):
            if step % refresh_every == 0:
                refresh(width)
            opt.zero_grad()
            loss = objective(width, 0.0 if last else distance_weight)
            loss.backward()
            if fixed:  # zero gradients leave Adam's moments, and so the held radii, at rest
                log_r.grad[held] = 0.0
            opt.step()
            with torch.no_grad():
                theta.copy_(skeleton.clamp(theta))
            value = float(loss.detach())
            losses.append(value)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{value:.4g}", softness=width, refresh=False)
            if value < best * (1 - tol):
                best, since = value, 0
            else:
                since += 1
                if since >= patience:
                    break
    if bar is not None:
        bar.close()

    with torch.no_grad():
        scale = float(log_s.exp())
        radii = torch.where(is_fixed, skeleton.radii.double(), (member @ log_r).exp().double())
        lengths = per_joint(log_l).exp().double() if fit_lengths else None
        fitted = skeleton.with_body(radii=radii / scale, scale=scale, lengths=lengths)
        poses_after = theta.detach().double()
        model1 = _model_masks(fitted, rig, fitted.fk(poses_after), fitted.radii, H, W)
    labels = ["/".join(skeleton.joint_names[skeleton.bones[k][1]] for k in g) for g in groups]
    report = CalibrationReport(
        groups=groups,
        labels=labels,
        radii_before=log_r0.exp().double(),
        radii_after=log_r.detach().exp().double(),
        scale=scale,
        lengths=log_l.detach().exp().double(),
        iou_before=iou_before,
        iou_after=_iou(model1, hard, valid, rig.names),
        poses=poses_after,
        loss=losses,
        iterations=len(losses),
        seconds=time.perf_counter() - t_start,
        # NaN where a mask is missing: no offset was fitted there
        offsets=torch.where(view_valid > 0, offsets().detach(), math.nan).double() if fit_offsets else None,
    )
    return fitted, report


def overlay_image(skeleton, cameras: CameraRig, masks, pose) -> np.ndarray:
    """Masks against the model, one tile per camera side by side: BGR uint8 (H, V * W, 3).

    Grey: mask only; red: model only; white: both. ``masks`` (V, H, W) (None for a missing one), ``pose``
    (D,) of that frame.
    """
    import cv2

    shape = next(np.asarray(m).shape for m in masks if m is not None)
    H, W = shape
    rig = cameras.resized(W, H)
    pose = torch.as_tensor(pose, dtype=torch.float64)
    model = _model_masks(skeleton, rig, skeleton.fk(pose)[None], skeleton.radii, H, W)[0]
    tiles = []
    for v, name in enumerate(rig.names):
        m = (
            np.zeros(shape, bool)
            if masks[v] is None
            else np.asarray(masks[v]) > (127 if np.asarray(masks[v]).dtype == np.uint8 else 0.5)
        )
        tile = np.zeros((H, W, 3), np.uint8)
        tile[m & ~model[v]] = (110, 110, 110)
        tile[model[v] & ~m] = (40, 40, 230)
        tile[model[v] & m] = (235, 235, 235)
        cv2.putText(tile, name, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 220, 0), 1, cv2.LINE_AA)
        tiles.append(tile)
    return np.concatenate(tiles, 1)
