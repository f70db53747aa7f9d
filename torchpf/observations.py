"""Observations: from raw sensor data to what the likelihoods consume.

Image processing (OpenCV, run once per frame, outside the particle loop):

* :class:`BackgroundSubtractor` - video frames -> silhouettes (Brubaker et al. §3.2 / Fig. 3): an adaptive
  per-pixel background model (MOG2 or KNN), shadows removed (pixels the model labels as shadow are
  background), then morphological opening/closing, small blobs dropped and holes filled.
  :func:`silhouettes_from_video` runs it over a file or an iterable of frames.
* :func:`depth_to_points` - a depth image and the depth camera -> world point cloud (m), with foreground
  selection by a depth range (Hauberg et al. §5 use the points of a stereo/depth sensor).
* :func:`edge_map`, :func:`skin_mask` and :func:`distance_image` - Canny edges (Brubaker eq. 9), a simple
  skin-colour segmentation and ``cv2.distanceTransform`` images (Fontmarty et al. §3.2.3, Fig. 3(d)).

Observation containers (one frame; ``V`` cameras in the camera-rig order, ``H x W`` mask size). Each
likelihood in :mod:`torchpf.likelihoods` takes its own container, or a :class:`Frame` holding several:

=====================  ====================================================  ============================
container              content                                               used by
=====================  ====================================================  ============================
:class:`PointCloud`    ``points`` (K, 3) world points (m)                    ``PointCloudLikelihood``
:class:`Silhouettes`   ``masks`` (V, H, W) foreground in [0, 1]              silhouette, dual, overlap
:class:`Keypoints2D`   ``uv`` (V, J, 2) pixels, NaN where missing            ``Keypoints2DLikelihood``
:class:`DistanceMaps`  ``distance`` (V, H, W) pixels to the nearest feature  skin blobs, Chamfer edges
=====================  ====================================================  ============================

Containers cache what the likelihoods derive from them (blurred masks, foreground sample points), so build
one per frame and reuse it across particles, annealing layers and likelihood terms.

Example::

    sub = BackgroundSubtractor("mog2")
    masks = [sub.apply(frame) for frame in frames]          # uint8 0/255
    obs = Silhouettes(np.stack(per_camera_masks))           # (V, H, W)
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np
import torch

__all__ = [
    "BackgroundSubtractor",
    "DistanceMaps",
    "Frame",
    "Keypoints2D",
    "PointCloud",
    "Silhouettes",
    "depth_to_points",
    "distance_image",
    "edge_map",
    "silhouettes_from_video",
    "skin_mask",
]


def _to_tensor(x, dtype=torch.float32) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x if x.is_floating_point() else x.to(dtype)
    arr = np.asarray(x)
    if arr.dtype == np.bool_:
        arr = arr.astype(np.float32)
    return torch.as_tensor(arr, dtype=dtype)


# ---------------------------------------------------------------------- containers
@dataclass(eq=False)
class PointCloud:
    """World points of one frame from a depth sensor.

    Fields: ``points`` (K, 3) metres (or (..., K, 3) with batch dims matching the particles' leading dims).
    """

    points: torch.Tensor

    def __post_init__(self):
        self.points = _to_tensor(self.points)
        if self.points.ndim < 2 or self.points.shape[-1] != 3:
            raise ValueError(f"points must have shape (K, 3), got {tuple(self.points.shape)}")


@dataclass(eq=False)
class Silhouettes:
    """Foreground masks of one frame, one per camera.

    Fields:
        masks: (V, H, W) foreground in [0, 1] (bool, 0/1 or 0/255 uint8 accepted; 255 is rescaled).
        valid: (V,) bool, False for a camera whose frame is missing (its terms are skipped).

    Derived (cached): :meth:`blurred` soft masks for smooth look-ups, :meth:`foreground_samples` fixed
    stratified points on the foreground (dual silhouette cue), :meth:`area` foreground pixel counts.
    """

    masks: torch.Tensor
    valid: torch.Tensor | None = None
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        m = self.masks
        m = _to_tensor(m)
        if m.numel() and float(m.max()) > 1.0 + 1e-6:  # 0/255 images
            m = m / 255.0
        if m.ndim == 2:
            m = m[None]
        if m.ndim != 3:
            raise ValueError(f"masks must have shape (V, H, W), got {tuple(m.shape)}")
        self.masks = m
        V = m.shape[0]
        self.valid = (
            torch.ones(V, dtype=torch.bool)
            if self.valid is None
            else torch.as_tensor(self.valid, dtype=torch.bool)
        )
        if self.valid.shape != (V,):
            raise ValueError(f"valid must have shape ({V},), got {tuple(self.valid.shape)}")

    @property
    def height(self) -> int:
        return self.masks.shape[-2]

    @property
    def width(self) -> int:
        return self.masks.shape[-1]

    def blurred(self, sigma: float) -> torch.Tensor:
        """(V, H, W) masks smoothed by a Gaussian of ``sigma`` pixels (0: the masks themselves). A bilinear
        look-up in it is a smooth function of the point, which gives the silhouette cue a gradient."""
        key = ("blur", float(sigma))
        if key not in self._cache:
            if sigma <= 0:
                out = self.masks
            else:
                import cv2

                k = 2 * int(math.ceil(3 * sigma)) + 1
                out = torch.stack(
                    [torch.from_numpy(cv2.GaussianBlur(m.numpy(), (k, k), sigma)) for m in self.masks.float()]
                ).to(self.masks.dtype)
            self._cache[key] = out
        return self._cache[key]

    def area(self) -> torch.Tensor:
        """(V,) foreground area in pixels (sum of the mask)."""
        if "area" not in self._cache:
            self._cache["area"] = self.masks.sum((-1, -2))
        return self._cache["area"]

    def foreground_samples(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` fixed points on each camera's foreground (Fontmarty's N_s points of the dual cue, §3.2.2).

        Pixels with mask > 0.5 are enumerated in raster order and picked at the indices of the golden-ratio
        sequence ``frac(0.5 + i / phi)``, a deterministic low-discrepancy subsample that covers the
        silhouette evenly without aliasing with the row length.

        Returns:
            points (V, n, 2) pixel coordinates (u, v); ok (V,) bool, False for an empty or invalid mask.
        """
        key = ("samples", int(n))
        if key not in self._cache:
            V = self.masks.shape[0]
            pts = torch.zeros(V, n, 2)
            ok = torch.zeros(V, dtype=torch.bool)
            golden = torch.frac(0.5 + torch.arange(n, dtype=torch.float64) * (math.sqrt(5) - 1) / 2)
            for v in range(V):
                ys, xs = torch.nonzero(self.masks[v] > 0.5, as_tuple=True)
                if len(xs) == 0 or not bool(self.valid[v]):
                    continue
                idx = (golden * len(xs)).long().clamp_max(len(xs) - 1)
                pts[v] = torch.stack([xs[idx], ys[idx]], -1).float()
                ok[v] = True
            self._cache[key] = (pts, ok)
        return self._cache[key]


@dataclass(eq=False)
class Keypoints2D:
    """Detected 2D body points of one frame (Brubaker et al. §3.1).

    Fields:
        uv: (V, J, 2) pixel coordinates per camera, in the order of the likelihood's ``joints``; NaN marks
            a missing detection.
        visible: optional (V, J) bool; False also marks a missing detection.
    """

    uv: torch.Tensor
    visible: torch.Tensor | None = None

    def __post_init__(self):
        self.uv = _to_tensor(self.uv)
        if self.uv.ndim == 2:
            self.uv = self.uv[None]
        if self.uv.ndim != 3 or self.uv.shape[-1] != 2:
            raise ValueError(f"uv must have shape (V, J, 2), got {tuple(self.uv.shape)}")
        vis = ~torch.isnan(self.uv).any(-1)
        if self.visible is not None:
            vis = vis & torch.as_tensor(self.visible, dtype=torch.bool).reshape(vis.shape)
        self.visible = vis
        self.uv = torch.nan_to_num(self.uv, nan=0.0)


@dataclass(eq=False)
class DistanceMaps:
    """Per-camera distance images (pixels): distance to the nearest skin blob (Fontmarty §3.2.3) or to the
    nearest edge (Chamfer matching, Brubaker eq. 9).

    Fields: ``distance`` (V, H, W) float pixels; ``valid`` (V,) bool. Build with :meth:`from_features`
    (binary feature masks: skin blobs, edges) or :meth:`from_edges_of` (grey or colour images, Canny).
    """

    distance: torch.Tensor
    valid: torch.Tensor | None = None

    def __post_init__(self):
        self.distance = _to_tensor(self.distance)
        if self.distance.ndim == 2:
            self.distance = self.distance[None]
        V = self.distance.shape[0]
        self.valid = (
            torch.ones(V, dtype=torch.bool)
            if self.valid is None
            else torch.as_tensor(self.valid, dtype=torch.bool)
        )

    @classmethod
    def from_features(cls, features, valid=None) -> DistanceMaps:
        """(V, H, W) binary feature masks (nonzero = feature) -> distance to the nearest feature pixel."""
        feats = [np.asarray(f) for f in features]
        return cls(torch.stack([torch.from_numpy(distance_image(f)) for f in feats]), valid)

    @classmethod
    def from_edges_of(cls, images, low: float = 50, high: float = 150, valid=None) -> DistanceMaps:
        """Images (V of (H, W) grey or (H, W, 3) BGR uint8) -> Canny edges -> distance images."""
        return cls.from_features([edge_map(im, low, high) for im in images], valid)


@dataclass(eq=False)
class Frame:
    """Everything observed at one time step; each likelihood picks its field (None: no information, the
    term contributes 0). ``skin`` and ``edges`` are :class:`DistanceMaps`."""

    silhouettes: Silhouettes | None = None
    points: PointCloud | None = None
    keypoints: Keypoints2D | None = None
    skin: DistanceMaps | None = None
    edges: DistanceMaps | None = None


# ---------------------------------------------------------------------- image processing
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
    ``kwargs`` go to :class:`BackgroundSubtractor`."""
    import cv2

    sub = BackgroundSubtractor(**kwargs)
    if isinstance(source, (str, os.PathLike)):
        cap = cv2.VideoCapture(os.fspath(source))
        if not cap.isOpened():
            raise OSError(f"{os.fspath(source)}: OpenCV cannot open this video")

        def frames():
            try:
                while True:
                    ok, f = cap.read()
                    if not ok:
                        return
                    yield f
            finally:
                cap.release()

        it = frames()
    else:
        it = iter(source)
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
    return cv2.distanceTransform((~f).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
