"""Results out: the body model of a track drawn over each camera's mask or video frame, cameras side by side.

``python -m torchpf render TRACK.csv --skeleton S.urdf --sequence SEQ --out overlay.mp4`` runs
:func:`render_track`: for every frame, each camera's image (the sequence's ``video/<camera>.mp4`` frame when
there is one, else its mask shown in grey) gets the skeleton's capsules (Hauberg §5) projected with the
camera model (OpenCV conventions, :meth:`torchpf.camera.Camera.project`, distortion included): a tinted
fill where the model covers the image, its outline, and the bones as lines between the projected joints.
The tiles are put side by side and written as an mp4 video (``cv2.VideoWriter``), or as PNG frames when
``--out`` is a folder.

Example::

    from torchpf.render import overlay_frame
    img = overlay_frame(skel, seq.cameras, theta, seq.masks[0])     # (H, V * W, 3) BGR uint8
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import torch

from torchpf.camera import Camera, CameraRig
from torchpf.geometry import project_capsules

__all__ = ["draw_model", "overlay_frame", "project_joints", "render_track"]

#: BGR colours of the overlay: model fill, model outline, bones, joints.
FILL, OUTLINE, BONE, JOINT = (40, 40, 230), (60, 60, 255), (0, 230, 255), (0, 200, 0)
#: Tiles smaller than this (pixels high) are enlarged by an integer factor, so that thin limbs stay visible.
MIN_TILE_HEIGHT = 240


def project_joints(skeleton, camera: Camera, pose: torch.Tensor) -> torch.Tensor:
    """(D,) or (..., D) pose -> (..., J, 2) pixel positions of the body joints in ``camera`` (OpenCV model,
    the same numbers as ``cv2.projectPoints``), and nothing else: a thin wrapper for the overlay and tests."""
    pose = torch.as_tensor(pose, dtype=torch.float64)
    return camera.project(skeleton.fk(pose))


def _background(image: np.ndarray | None, height: int, width: int) -> np.ndarray:
    """A tile's background as BGR uint8: a frame as is, a mask (H, W) in grey, a missing one black."""
    if image is None:
        return np.zeros((height, width, 3), np.uint8)
    img = np.asarray(image)
    if img.ndim == 2:
        fg = img > (127 if img.dtype == np.uint8 else 0.5)
        return np.repeat(np.where(fg, 110, 25).astype(np.uint8)[..., None], 3, -1)
    return np.ascontiguousarray(img[..., :3].astype(np.uint8))


def _fill_capsules(caps, height: int, width: int) -> np.ndarray:
    """(H, W) bool: the projected capsules (one camera's :class:`~torchpf.geometry.Capsules2D`, (C,)) filled
    with OpenCV primitives: each the convex hull of its two end discs, i.e. the two discs and the
    quadrilateral of their outer tangent points: the shape :func:`torchpf.geometry.capsule_masks` rasterises
    (up to the boundary pixels, which OpenCV fills when an edge touches them) at ~1 % of its cost: a
    display, not a likelihood."""
    import cv2

    shift = 4
    one = 1 << shift
    mask = np.zeros((height, width), np.uint8)
    pa, pb = caps.pa.numpy().reshape(-1, 2), caps.pb.numpy().reshape(-1, 2)
    ra, rb = caps.ra.numpy().reshape(-1), caps.rb.numpy().reshape(-1)
    valid = caps.valid.numpy().reshape(-1)
    d = pb - pa
    length = np.linalg.norm(d, axis=-1)
    e = d / np.maximum(length, 1e-12)[:, None]
    n = np.stack([-e[:, 1], e[:, 0]], -1)
    c = (ra - rb) / np.maximum(length, 1e-12)  # cosine of the tangent direction against e
    hull = length > np.abs(ra - rb)  # else one disc holds the other
    s = np.sqrt(np.clip(1 - c * c, 0, 1))
    far = max(height, width) * 4  # coordinates cv2 can take; what lies beyond is off the image anyway
    for k in np.flatnonzero(valid):
        if not (np.isfinite(pa[k]).all() and np.isfinite(pb[k]).all()):
            continue
        if np.abs(np.concatenate([pa[k], pb[k]])).max() > far or max(ra[k], rb[k]) > far:
            continue
        for p, r in ((pa[k], ra[k]), (pb[k], rb[k])):
            centre = tuple(int(v) for v in np.round(p * one))
            cv2.circle(mask, centre, int(round(r * one)), 255, -1, cv2.LINE_8, shift)
        if hull[k]:
            w1, w2 = c[k] * e[k] + s[k] * n[k], c[k] * e[k] - s[k] * n[k]
            quad = np.stack([pa[k] + ra[k] * w1, pb[k] + rb[k] * w1, pb[k] + rb[k] * w2, pa[k] + ra[k] * w2])
            cv2.fillConvexPoly(mask, np.round(quad * one).astype(np.int32), 255, cv2.LINE_8, shift)
    return mask > 0


def draw_model(image: np.ndarray, skeleton, camera: Camera, pose, *, alpha: float = 0.45) -> np.ndarray:
    """Draw the capsule body in ``pose`` (D,) over ``image`` (H, W, 3) BGR uint8 seen by ``camera`` (whose
    size must be the image's: use :meth:`Camera.resized`). Returns a new image."""
    import cv2

    pose = torch.as_tensor(pose, dtype=torch.float64)
    H, W = image.shape[:2]
    out = image.copy()
    with torch.no_grad():
        ends, radii = skeleton.capsules(pose)
        caps = project_capsules(camera, ends[..., 0, :], ends[..., 1, :], radii)
        model = _fill_capsules(caps, H, W)
        joints = project_joints(skeleton, camera, pose).numpy()
        in_front = (camera.depth(skeleton.fk(pose)) > 1e-2).numpy()
    if model.any():
        tint = np.empty_like(out)
        tint[:] = FILL
        out[model] = (alpha * tint[model] + (1 - alpha) * out[model]).astype(np.uint8)
        contours, _ = cv2.findContours(model.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, OUTLINE, 1, cv2.LINE_AA)
    shift = 4  # sub-pixel line ends
    pts = np.round(joints * (1 << shift)).astype(np.int64)
    limit = 1 << 28  # far off-image points (a joint near the camera plane) would overflow cv2
    ok = in_front & (np.abs(pts) < limit).all(-1)
    for a, b in skeleton.tree.bones.tolist():
        if ok[a] and ok[b]:
            cv2.line(out, tuple(map(int, pts[a])), tuple(map(int, pts[b])), BONE, 1, cv2.LINE_AA, shift)
    for j in np.flatnonzero(ok):
        cv2.circle(out, tuple(map(int, pts[j])), 2 << shift, JOINT, -1, cv2.LINE_AA, shift)
    return out


def overlay_frame(
    skeleton,
    cameras: CameraRig,
    pose,
    images: Sequence[np.ndarray | None],
    *,
    min_height: int = MIN_TILE_HEIGHT,
    labels: bool = True,
) -> np.ndarray:
    """One frame of the overlay: for each camera ``v`` the model in ``pose`` (D,) drawn over ``images[v]``
    (a BGR frame (H, W, 3), a mask (H, W) shown in grey, or None: black at the camera's size), tiles side
    by side -> (H', sum W', 3) BGR uint8. Each camera is projected at its image's size
    (:meth:`Camera.resized`); tiles lower than ``min_height`` are enlarged by an integer factor first."""
    import cv2

    tiles = []
    for v, name in enumerate(cameras.names):
        cam = cameras[v]
        img = images[v] if v < len(images) else None
        h, w = np.asarray(img).shape[:2] if img is not None else (cam.height, cam.width)
        bg = _background(img, h, w)
        k = max(1, -(-min_height // h))
        if k > 1:
            bg = cv2.resize(bg, (w * k, h * k), interpolation=cv2.INTER_NEAREST)
        # the camera at the image's size, then at the enlarged size (pixel centres kept consistent)
        tile = draw_model(bg, skeleton, cam.resized(w, h).resized(w * k, h * k), pose)
        if labels:
            cv2.putText(tile, name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 220, 0), 1, cv2.LINE_AA)
        tiles.append(tile)
    height = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, height - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
    return np.concatenate(tiles, 1)


def render_track(
    skeleton,
    angles: torch.Tensor,
    sequence,
    out: str | os.PathLike,
    *,
    fps: float = 30.0,
    background: str = "auto",
    min_height: int = MIN_TILE_HEIGHT,
    progress: bool = True,
) -> int:
    """Write the overlay of a track on a sequence: an mp4 video, or PNG frames ``<out>/<t:06d>.png`` when
    ``out`` is an existing folder or has no file extension.

    Args:
        skeleton: the tracked :class:`~torchpf.skeleton.Skeleton`.
        angles: (T, D) poses in ``skeleton.dof_names`` order.
        sequence: a sequence directory (path) or a :class:`~torchpf.sequence.SequenceData` (masks only).
        fps: frame rate of the video.
        background: "video" (``SEQ/video/<camera>.mp4``), "masks", or "auto" (video when every camera has
            one).
        min_height: tiles lower than this are enlarged (:func:`overlay_frame`).

    Returns:
        The number of frames written: ``min(T, frames of the sequence)``.
    """
    import cv2
    from tqdm.auto import tqdm

    from torchpf.io import write_atomic
    from torchpf.sequence import SequenceData, read_sequence
    from torchpf.video import FrameReader

    if background not in ("auto", "video", "masks"):
        raise ValueError(f"background must be auto, video or masks, got {background!r}")
    seq_dir = None if isinstance(sequence, SequenceData) else os.fspath(sequence)
    seq = sequence if seq_dir is None else read_sequence(seq_dir)
    names = list(seq.cameras.names)
    videos = []
    if seq_dir is not None and background != "masks":
        paths = [os.path.join(seq_dir, "video", f"{n}.mp4") for n in names]
        if all(os.path.isfile(p) for p in paths):
            videos = [iter(FrameReader(p)) for p in paths]
        elif background == "video":
            missing = [p for p in paths if not os.path.isfile(p)]
            raise FileNotFoundError(f"no video for camera(s): {', '.join(missing)}")
    angles = torch.as_tensor(angles, dtype=torch.float64)
    n = min(len(angles), len(seq)) if len(seq) else len(angles)
    path = os.fspath(out)
    as_frames = os.path.isdir(path) or not os.path.splitext(path)[1]
    writer = None
    written = 0
    try:
        for t in tqdm(range(n), desc="render", unit="frame", disable=not progress):
            if videos:
                images = [next(it, None) for it in videos]
                if any(im is None for im in images):
                    break
            else:
                images = seq.masks[t] if t < len(seq.masks) else [None] * len(names)
            frame = overlay_frame(skeleton, seq.cameras, angles[t], images, min_height=min_height)
            if as_frames:
                ok, buf = cv2.imencode(".png", frame)
                if not ok:
                    raise OSError(f"cannot encode frame {t}")
                write_atomic(os.path.join(path, f"{t:06d}.png"), buf.tobytes())
            else:
                if writer is None:
                    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
                    h, w = frame.shape[:2]
                    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
                    if not writer.isOpened():
                        raise OSError(f"{path}: OpenCV cannot write a video here (try a .mp4 or .avi name)")
                writer.write(frame)
            written += 1
    finally:
        if writer is not None:
            writer.release()
    return written
