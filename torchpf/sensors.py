"""Sensor preprocessing with OpenCV: from raw images and depth maps to the data the observation containers
hold (:mod:`torchpf.observations`). Run once per frame, outside the particle loop.

* :class:`BackgroundSubtractor` - video frames -> silhouettes (Brubaker et al. §3.2 / Fig. 3): an adaptive
  per-pixel background model (MOG2 or KNN), shadows removed (pixels the model labels as shadow are
  background), then morphological opening/closing, small blobs dropped and holes filled (:func:`clean_mask`).
  :func:`silhouettes_from_video` runs it over a file or an iterable of frames.
* :func:`depth_to_points` - a depth image and the depth camera -> world point cloud (m), with foreground
  selection by a depth range (Hauberg et al. §5 use the points of a stereo/depth sensor).
* :func:`edge_map`, :func:`skin_mask` and :func:`distance_image` - Canny edges (Brubaker eq. 9), a simple
  skin-colour segmentation and ``cv2.distanceTransform`` images (Fontmarty et al. §3.2.3, Fig. 3(d)).

Example::

    from torchpf.observations import Silhouettes
    from torchpf.sensors import BackgroundSubtractor
    sub = BackgroundSubtractor("mog2")
    masks = [sub.apply(frame) for frame in frames]          # uint8 0/255, (H, W) each
    obs = Silhouettes(np.stack(masks_of_one_frame))         # (V, H, W)
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator

import numpy as np
import torch

__all__ = [
    "BackgroundSubtractor",
    "clean_mask",
    "depth_to_points",
    "distance_image",
    "edge_map",
    "silhouettes_from_video",
    "skin_mask",
]


class BackgroundSubtractor:
    """Video frames -> binary silhouettes (Brubaker et al. §3.2, Fig. 3 (d)-(e)).

    Args:
        method: "mog2" (Gaussian mixture per pixel) or "knn" (K nearest neighbours per pixel).
        history: frames the background model remembers.
        threshold: the model's decision threshold (MOG2: squared Mahalanobis distance, default 16;
            KNN: squared distance, default 400).
        detect_shadows: label shadows (darker, same chromaticity) and drop them from the foreground.
        open_px, close_px: sizes (pixels) of the elliptic structuring elements of the opening (removes
            speckle) and closing (bridges gaps) applied to the raw foreground; 0 disables.
        min_area: connected components smaller than this fraction of the image are dropped.
        fill_holes: fill background regions not connected to the image border.
    """

    def __init__(
        self,
        method: str = "mog2",
        *,
        history: int = 200,
        threshold: float | None = None,
        detect_shadows: bool = True,
        open_px: int = 3,
        close_px: int = 7,
        min_area: float = 0.002,
        fill_holes: bool = True,
    ):
        import cv2

        if method == "mog2":
            self.model = cv2.createBackgroundSubtractorMOG2(history, threshold or 16.0, detect_shadows)
        elif method == "knn":
            self.model = cv2.createBackgroundSubtractorKNN(history, threshold or 400.0, detect_shadows)
        else:
            raise ValueError(f"method must be 'mog2' or 'knn', got {method!r}")
        self.open_px, self.close_px = int(open_px), int(close_px)
        self.min_area, self.fill_holes = float(min_area), bool(fill_holes)

    def learn(self, frames: Iterable[np.ndarray]) -> BackgroundSubtractor:
        """Feed background-only frames (or the first frames of a video) to the model."""
        for f in frames:
            self.model.apply(f)
        return self

    def apply(self, frame: np.ndarray, learning_rate: float = -1) -> np.ndarray:
        """One (H, W, 3) BGR or (H, W) grey uint8 frame -> (H, W) uint8 mask, 255 = foreground.

        ``learning_rate`` in [0, 1] (-1: automatic from ``history``; 0: freeze the background model).
        """
        raw = self.model.apply(frame, learningRate=learning_rate)
        return clean_mask(raw == 255, self.open_px, self.close_px, self.min_area, self.fill_holes)


def clean_mask(
    mask: np.ndarray, open_px: int = 3, close_px: int = 7, min_area: float = 0.002, fill_holes: bool = True
) -> np.ndarray:
    """Morphological clean-up of a raw foreground mask (bool or 0/255) -> uint8 0/255 (Brubaker Fig. 3e)."""
    import cv2

    m = (np.asarray(mask) > 0).astype(np.uint8) * 255
    if open_px > 0:
        m = cv2.morphologyEx(
            m, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (open_px, open_px))
        )
    if close_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (close_px, close_px))
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, k)
    if min_area > 0:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        keep = np.zeros(n, dtype=bool)
        keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area * m.size
        m = np.where(keep[labels], 255, 0).astype(np.uint8)
    if fill_holes:
        # Background reachable from the border stays background; everything else is a hole.
        padded = np.pad(m, 1)
        flood = padded.copy()
        cv2.floodFill(flood, None, (0, 0), 255)
        holes = flood[1:-1, 1:-1] == 0
        m[holes] = 255
    return m


def silhouettes_from_video(
    source: str | os.PathLike | Iterable[np.ndarray],
    *,
    warmup: int = 0,
    **kwargs,
) -> Iterator[np.ndarray]:
    """Yield one uint8 0/255 silhouette per frame of a video file (any format OpenCV reads) or an iterable
    of frames. ``warmup`` first frames only train the background model (nothing is yielded for them);
    ``kwargs`` go to :class:`BackgroundSubtractor`. Several synchronised cameras into a sequence directory:
    :func:`torchpf.video.segment_videos`."""
    from torchpf.video import FrameReader

    sub = BackgroundSubtractor(**kwargs)
    it = iter(FrameReader(source)) if isinstance(source, (str, os.PathLike)) else iter(source)
    for i, f in enumerate(it):
        mask = sub.apply(f)
        if i >= warmup:
            yield mask


def depth_to_points(
    depth,
    camera,
    *,
    min_depth: float = 0.1,
    max_depth: float = math.inf,
    stride: int = 1,
    mask=None,
) -> torch.Tensor:
    """Depth image -> world point cloud, keeping pixels within a depth range (foreground selection).

    Args:
        depth: (H, W) z-depth along the optical axis (m; Kinect/OpenCV convention, not ray length); 0 or
            NaN marks no measurement. May be smaller than the camera's image (a resampled image).
        camera: :class:`torchpf.camera.Camera` of the depth sensor (distortion is undone per pixel).
        min_depth, max_depth: keep ``min_depth < z < max_depth`` (m).
        stride: use every ``stride``-th row and column.
        mask: optional (H, W) foreground mask; only nonzero pixels are kept.

    Returns:
        (K, 3) float32 world points (m).
    """
    d = np.asarray(depth, dtype=np.float64)
    H, W = d.shape
    rays_w = camera.pixel_rays(H, W, stride)  # unit world directions
    d = d[::stride, ::stride]
    keep = np.isfinite(d) & (d > min_depth) & (d < max_depth)
    if mask is not None:
        keep &= np.asarray(mask)[::stride, ::stride] > 0
    # A unit ray's z-component in the camera frame converts z-depth to ray length.
    rays_c = rays_w.numpy() @ camera.R.numpy().T
    length = d / rays_c[..., 2]
    pts = camera.center.numpy() + rays_w.numpy() * length[..., None]
    return torch.from_numpy(pts[keep].astype(np.float32))


def edge_map(image, low: float = 50, high: float = 150) -> np.ndarray:
    """(H, W) grey or (H, W, 3) BGR uint8 image -> (H, W) uint8 Canny edge map (255 = edge)."""
    import cv2

    im = np.asarray(image)
    if im.ndim == 3:
        im = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)
    return cv2.Canny(im.astype(np.uint8), low, high)


def skin_mask(image, *, open_px: int = 3, min_area: float = 0.0005) -> np.ndarray:
    """(H, W, 3) BGR uint8 -> (H, W) uint8 skin blobs (255), by the classic YCrCb box
    (133 <= Cr <= 173, 77 <= Cb <= 127). Fontmarty et al. use a learnt colour histogram back-projection;
    this fixed box is the usual stand-in. Clean-up as in :func:`clean_mask` without hole filling."""
    import cv2

    ycrcb = cv2.cvtColor(np.asarray(image, dtype=np.uint8), cv2.COLOR_BGR2YCrCb)
    raw = cv2.inRange(ycrcb, (0, 133, 77), (255, 173, 127))
    return clean_mask(raw, open_px, 0, min_area, False)


def distance_image(features) -> np.ndarray:
    """(H, W) binary features (nonzero = feature) -> (H, W) float32 Euclidean distance (pixels) from each
    pixel to the nearest feature pixel (``cv2.distanceTransform``, exact L2 mask). With no feature at all
    every distance is the image diagonal, a finite "far away"."""
    import cv2

    f = np.asarray(features) > 0
    if not f.any():
        return np.full(f.shape, float(np.hypot(*f.shape)), dtype=np.float32)
    d = cv2.distanceTransform((~f).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # The exact transform's squared distances are integers (pixel offsets), but OpenCV's square roots vary
    # in the last bits with the buffer's alignment (the same mask read twice gave 39.4249 +- 4e-6): rounded
    # back to the integer they are exact and the same on every call, so a track is reproducible bit for bit.
    return np.sqrt(np.rint(np.square(d, dtype=np.float64))).astype(np.float32)
