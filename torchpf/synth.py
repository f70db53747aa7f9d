"""Synthetic observations of a capsule body: the sequences that ``python -m torchpf track`` reads.

:func:`synthesize` renders, for every frame of a motion (angles (T, D) in ``skeleton.dof_names`` order):

* silhouettes per camera, by casting a ray through every pixel centre against the capsules (exact
  perspective, :func:`torchpf.geometry.raycast_capsules`), optionally corrupted by segmentation noise
  (random erosion/dilation, speckle), static occluders (image rectangles that hide the body) and missing
  frames;
* a point cloud from a virtual depth camera: first ray hits (self-occlusion respected), Gaussian noise
  along the ray, a share of outliers spread over the body's bounding box;
* 2D joint detections per camera with Gaussian pixel noise, dropped detections and occluded joints as NaN;
* the ground truth angles.

The result is a :class:`~torchpf.sequence.SequenceData`; :func:`torchpf.sequence.write_sequence` stores
it as a sequence directory.

Example::

    from torchpf.sequence import write_sequence
    from torchpf.synth import synthesize
    seq = synthesize(skel, angles, camera_ring(3), depth_camera=look_at((0, -3, 1.5), name="depth"),
                     options=SynthOptions(speckle=0.01), seed=0)
    write_sequence("out/seq", seq)
    frame = seq.frame(0)             # torchpf.observations.Frame for the likelihoods
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchpf.camera import Camera, CameraRig
from torchpf.geometry import raycast_capsules
from torchpf.sequence import SequenceData

__all__ = [
    "SynthOptions",
    "render_depth",
    "render_silhouette",
    "synthesize",
]


# ---------------------------------------------------------------------- rendering
def _bone_ends(skeleton, theta):
    ends, radii = skeleton.capsules(theta)
    return ends[..., 0, :], ends[..., 1, :], radii


def _ray_hits(camera: Camera, a, b, r, height: int, width: int) -> torch.Tensor:
    rays = camera.pixel_rays(height, width).to(a)
    origin = camera.center.to(a)
    return raycast_capsules(origin, rays.reshape(-1, 3), a, b, r).reshape(height, width)


def render_silhouette(skeleton, theta, camera: Camera, height: int | None = None, width: int | None = None):
    """Exact silhouette of the capsule body in ``theta`` (D,) seen by ``camera``: (H, W) bool, a pixel is
    foreground when the ray through its centre hits a capsule. Default size: the camera's."""
    a, b, r = _bone_ends(skeleton, torch.as_tensor(theta, dtype=torch.float64))
    H, W = height or camera.height, width or camera.width
    return torch.isfinite(_ray_hits(camera, a, b, r, H, W))


def render_depth(skeleton, theta, camera: Camera, height: int | None = None, width: int | None = None):
    """Depth image of the body: (H, W) z-depth (m) along ``camera``'s optical axis, 0 where no capsule is hit.
    Matches the input convention of :func:`torchpf.sensors.depth_to_points`."""
    a, b, r = _bone_ends(skeleton, torch.as_tensor(theta, dtype=torch.float64))
    H, W = height or camera.height, width or camera.width
    t = _ray_hits(camera, a, b, r, H, W)
    rays_c = camera.pixel_rays(H, W) @ camera.R.T
    z = t * rays_c[..., 2]
    return torch.where(torch.isfinite(z), z, torch.zeros_like(z))


@dataclass(kw_only=True)
class SynthOptions:
    """Corruptions applied by :func:`synthesize` (all off by default: clean data).

    Masks: ``morph_px`` - each (frame, camera) mask is eroded or dilated by a random radius in
    ``[-morph_px, morph_px]`` pixels; ``speckle`` - share of pixels flipped; ``missing_frames`` -
    probability that a camera's frame is dropped (mask None, its detections NaN); ``occluders`` - number of
    static rectangles per camera, each ``occluder_size`` (share of the image side) wide, that hide the body
    (mask 0, detections NaN, depth pixels dropped when the depth camera is occluded).
    Depth: ``depth_noise`` (m, along the ray), ``outliers`` (share of extra points uniform in the body's
    bounding box enlarged by ``outlier_margin`` m), ``n_points`` (keep at most this many, random subset).
    2D points: ``keypoint_noise`` (pixels), ``keypoint_dropout`` (probability a detection is missing).
    """

    morph_px: int = 0
    speckle: float = 0.0
    missing_frames: float = 0.0
    occluders: int = 0
    occluder_size: float = 0.2
    depth_noise: float = 0.0
    outliers: float = 0.0
    outlier_margin: float = 0.3
    n_points: int | None = None
    keypoint_noise: float = 0.0
    keypoint_dropout: float = 0.0


def _perturb_mask(mask: np.ndarray, opts: SynthOptions, rng: np.random.Generator) -> np.ndarray:
    import cv2

    m = mask.astype(np.uint8) * 255
    if opts.morph_px > 0:
        k = int(rng.integers(-opts.morph_px, opts.morph_px + 1))
        if k != 0:
            se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * abs(k) + 1, 2 * abs(k) + 1))
            m = cv2.dilate(m, se) if k > 0 else cv2.erode(m, se)
    if opts.speckle > 0:
        flip = rng.random(m.shape) < opts.speckle
        m = np.where(flip, 255 - m, m).astype(np.uint8)
    return m


def _occluder_boxes(opts: SynthOptions, width: int, height: int, rng: np.random.Generator):
    boxes = []
    for _ in range(opts.occluders):
        bw, bh = max(1, int(opts.occluder_size * width)), max(1, int(opts.occluder_size * height))
        x0, y0 = int(rng.integers(0, max(1, width - bw))), int(rng.integers(0, max(1, height - bh)))
        boxes.append((x0, y0, x0 + bw, y0 + bh))
    return boxes


def _in_boxes(u, v, boxes) -> np.ndarray:
    hit = np.zeros(np.shape(u), dtype=bool)
    for x0, y0, x1, y1 in boxes:
        hit |= (u >= x0 - 0.5) & (u < x1 - 0.5) & (v >= y0 - 0.5) & (v < y1 - 0.5)
    return hit


def synthesize(
    skeleton,
    motion,
    cameras,
    *,
    depth_camera: Camera | str | None = None,
    mask_size: tuple[int, int] | None = None,
    keypoint_joints: list[str] | None = None,
    options: SynthOptions | None = None,
    fps: float = 30.0,
    seed: int | None = 0,
) -> SequenceData:
    """Render a synthetic multi-camera sequence of the capsule body (module docstring).

    Args:
        skeleton: provides ``capsules``, ``fk``, ``dof_names``, ``joint_names``.
        motion: (T, D) angles in ``skeleton.dof_names`` order (tensor or array).
        cameras: :class:`~torchpf.camera.CameraRig` or list of cameras for the silhouettes/2D points.
        depth_camera: a camera (or the name of one in ``cameras``) for point clouds; None for no points
            (default: ``cameras.depth_camera`` when set).
        mask_size: (width, height) of the masks (default: each camera's image size).
        keypoint_joints: joints whose 2D detections are simulated (default: all).
        options: :class:`SynthOptions` corruptions (default: none).
        fps: frame rate for the ``time`` column. seed: seed of the noise (numpy ``Generator``).

    Returns:
        :class:`~torchpf.sequence.SequenceData`.
    """
    opts = options or SynthOptions()
    rng = np.random.default_rng(seed)
    rig = cameras if isinstance(cameras, CameraRig) else CameraRig(cameras)
    if depth_camera is None and rig.depth_camera is not None:
        depth_camera = rig.depth_camera
    if isinstance(depth_camera, str):
        depth_camera = rig[depth_camera]
    angles = (
        torch.as_tensor(np.asarray(motion), dtype=torch.float64)
        if not isinstance(motion, torch.Tensor)
        else motion
    )
    angles = angles.detach().to(torch.float64).cpu()
    if angles.ndim != 2 or angles.shape[1] != len(skeleton.dof_names):
        raise ValueError(f"motion must have shape (T, {len(skeleton.dof_names)}), got {tuple(angles.shape)}")
    T = angles.shape[0]
    cams = rig.cameras
    sizes = [mask_size or (c.width, c.height) for c in cams]
    rays = [c.pixel_rays(h, w).reshape(-1, 3) for c, (w, h) in zip(cams, sizes, strict=True)]
    boxes = [_occluder_boxes(opts, w, h, rng) for (w, h) in sizes]
    joint_names = list(keypoint_joints or skeleton.joint_names)
    jidx = [list(skeleton.joint_names).index(j) for j in joint_names]
    if depth_camera is not None:
        d_rays = depth_camera.pixel_rays().reshape(-1, 3)
        d_boxes = _occluder_boxes(opts, depth_camera.width, depth_camera.height, rng)
        dv, du = np.meshgrid(np.arange(depth_camera.height), np.arange(depth_camera.width), indexing="ij")
        d_keep = ~_in_boxes(du.reshape(-1), dv.reshape(-1), d_boxes)

    masks, points, kps = (
        [],
        [] if depth_camera is not None else None,
        np.full((T, len(cams), len(jidx), 2), np.nan),
    )
    for f in range(T):
        a, b, r = _bone_ends(skeleton, angles[f])
        joints = skeleton.fk(angles[f])[jidx]
        row = []
        for v, cam in enumerate(cams):
            w, h = sizes[v]
            if opts.missing_frames > 0 and rng.random() < opts.missing_frames:
                row.append(None)
                continue
            hit = torch.isfinite(raycast_capsules(cam.center, rays[v], a, b, r)).reshape(h, w).numpy()
            if boxes[v]:
                vv, uu = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
                hit = hit & ~_in_boxes(uu, vv, boxes[v])
            row.append(_perturb_mask(hit, opts, rng))
            uv = cam.resized(w, h).project(joints).numpy()
            uv = uv + rng.normal(0.0, opts.keypoint_noise, uv.shape) if opts.keypoint_noise > 0 else uv
            lost = ~cam.in_front(joints).numpy() | _in_boxes(uv[:, 0], uv[:, 1], boxes[v])
            if opts.keypoint_dropout > 0:
                lost |= rng.random(len(jidx)) < opts.keypoint_dropout
            uv[lost] = np.nan
            kps[f, v] = uv
        masks.append(row)
        if depth_camera is not None:
            t_hit = raycast_capsules(depth_camera.center, d_rays, a, b, r).numpy()
            ok = np.isfinite(t_hit) & d_keep
            t_ok = t_hit[ok]
            if opts.depth_noise > 0:
                # Noise on z-depth, turned into ray length through the ray's obliquity.
                cos = (d_rays[ok].numpy() @ depth_camera.R.numpy().T)[:, 2]
                t_ok = t_ok + rng.normal(0.0, opts.depth_noise, t_ok.shape) / cos
            pts = depth_camera.center.numpy() + d_rays[ok].numpy() * t_ok[:, None]
            if opts.outliers > 0 and len(pts):
                n_out = int(round(opts.outliers * len(pts)))
                lo = torch.minimum(a, b).amin(0).numpy() - opts.outlier_margin
                hi = torch.maximum(a, b).amax(0).numpy() + opts.outlier_margin
                pts = np.concatenate([pts, rng.uniform(lo, hi, (n_out, 3))])
            if opts.n_points is not None and len(pts) > opts.n_points:
                pts = pts[rng.choice(len(pts), opts.n_points, replace=False)]
            points.append(pts.astype(np.float32))
    return SequenceData(
        cameras=CameraRig(cams, depth_camera=None),
        masks=masks,
        points=points,
        depth_camera=depth_camera,
        keypoints=kps,
        keypoint_joints=joint_names,
        truth=angles.clone(),
        dof_names=list(skeleton.dof_names),
        times=np.arange(T) / fps,
        mask_size=mask_size,
    )
