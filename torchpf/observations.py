"""Observation containers: what the likelihoods consume, one frame at a time.

The containers are built from sensor data prepared by :mod:`torchpf.sensors` (background subtraction, depth
back-projection, edges and distance transforms) or read from a sequence directory
(:mod:`torchpf.sequence`).

One frame per container; ``V`` cameras in the camera-rig order, ``H x W`` mask size. Each
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

    from torchpf.observations import Frame, Silhouettes
    obs = Silhouettes(np.stack(per_camera_masks))           # (V, H, W) uint8 0/255 or bool
    frame = Frame(silhouettes=obs)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from torchpf.sensors import distance_image, edge_map

__all__ = [
    "DistanceMaps",
    "Frame",
    "Keypoints2D",
    "PointCloud",
    "Silhouettes",
    "binary_mask",
    "mask_full_scale",
]


def _to_tensor(x, dtype=torch.float32) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x if x.is_floating_point() else x.to(dtype)
    arr = np.asarray(x)
    if arr.dtype == np.bool_:
        arr = arr.astype(np.float32)
    return torch.as_tensor(arr, dtype=dtype)


def _valid(valid, shape: tuple[int, ...], what: str) -> torch.Tensor:
    """(..., V) bool flags of the cameras: all True by default, a (V,) vector shared by a batch."""
    if valid is None:
        return torch.ones(shape, dtype=torch.bool)
    valid = torch.as_tensor(valid, dtype=torch.bool)
    if valid.shape != shape and valid.shape == shape[-1:]:
        valid = valid.expand(shape)
    if valid.shape != shape:
        raise ValueError(
            f"valid must have shape {shape} (the {what}' leading dims), got {tuple(valid.shape)}"
        )
    return valid


def gaussian_blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """(..., H, W) images smoothed by a Gaussian of ``sigma`` pixels, on their device and in their dtype.

    Separable kernel of ``2 ceil(3 sigma) + 1`` taps normalised to sum 1, borders mirrored without repeating
    the edge pixel (OpenCV's default ``BORDER_REFLECT_101``; an image narrower than the kernel's half
    width repeats its edge instead), i.e. what ``cv2.GaussianBlur(img, (k, k), sigma)`` computes.
    """
    half = int(math.ceil(3 * sigma))
    x = images.float() if not images.is_floating_point() else images
    taps = torch.arange(-half, half + 1, dtype=torch.float64, device=x.device)
    kernel = torch.exp(-0.5 * (taps / sigma) ** 2)
    kernel = (kernel / kernel.sum()).to(x.dtype)
    flat = x.reshape(-1, 1, *x.shape[-2:])
    H, W = flat.shape[-2:]
    mode = "reflect" if half < min(H, W) else "replicate"
    flat = torch.nn.functional.pad(flat, (half, half, half, half), mode=mode)
    flat = torch.nn.functional.conv2d(flat, kernel.reshape(1, 1, 1, -1))
    flat = torch.nn.functional.conv2d(flat, kernel.reshape(1, 1, -1, 1))
    return flat.reshape(x.shape)


def mask_full_scale(mask) -> float:
    """The value that means "foreground" in a mask image: 1 for bool and 0/1 masks, 255 for 0/255 masks
    (8-bit, also stored in 16 bits), 65535 for 0/65535 16-bit masks. Decided from the largest value, so
    masks written by other tools (0/1 PNGs are common) read as they were meant; an all-zero mask is empty
    whatever its scale."""
    if isinstance(mask, torch.Tensor):
        top = float(mask.max()) if mask.numel() else 0.0
    else:
        arr = np.asarray(mask)
        top = float(arr.max()) if arr.size else 0.0
    return 1.0 if top <= 1.0 + 1e-6 else 255.0 if top <= 255.0 else 65535.0


def binary_mask(mask) -> np.ndarray:
    """(H, W) bool foreground of a mask image: bool, 0/1, 0/255 or 16-bit, grey (H, W) or colour (H, W, C)
    (any colour channel; a 4th channel, alpha, is ignored). Foreground is above half the full scale
    (:func:`mask_full_scale`), so anti-aliased edges split at mid-grey."""
    arr = np.asarray(mask)
    if arr.ndim == 3:
        arr = arr[..., :3].max(-1)
    if arr.dtype == np.bool_:
        return arr.copy()
    return arr > mask_full_scale(arr) / 2


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

    Attributes:
        masks: (V, H, W) foreground in [0, 1] (bool, 0/1, 0/255 and 16-bit masks accepted and rescaled by
            :func:`mask_full_scale`), or (..., V, H, W) for a batch of independent sequences: the leading
            dims then match the particles' (``(B, V, H, W)`` masks go with ``(B, N, D)`` particles), as a
            batched :class:`PointCloud`.
        valid: (V,) or (..., V) bool, False for a camera whose frame is missing (its terms are skipped).
        offset: optional (V,) or (..., V) pixels by which each mask's outline lies outside the body's (a
            segmentation that dilates the person, > 0, or erodes it, < 0, e.g. a threshold or exposure
            that differs per camera and frame). The silhouette cues widen (or thin) the projected capsules
            by it, so that a fattened or thinned mask is not explained by a wrong pose. ``None``: 0.
            :meth:`~torchpf.likelihoods.images.ImageLikelihood.boundary_offset` measures it (what
            ``Tracker(boundary_offset=True)`` does each frame).
        weight: optional (V,) or (..., V) weight (>= 0) of each mask's term in the silhouette cues' sums over
            the cameras (``silhouette``, ``dual_silhouette``, ``silhouette_distance``, ``overlap``). ``None``:
            1. :class:`~torchpf.smooth.TrajectorySmoother` sets it to down-weight the masks a defect spoiled.

    Derived (cached): :meth:`blurred` soft masks for smooth look-ups, :meth:`foreground_samples` fixed
    stratified points on the foreground (dual silhouette cue), :meth:`area` foreground pixel counts.
    """

    masks: torch.Tensor
    valid: torch.Tensor | None = None
    offset: torch.Tensor | None = None
    weight: torch.Tensor | None = None
    # not an init field: a copy (dataclasses.replace, e.g. the tracker's per-frame device copy) starts with
    # its own empty cache instead of filling the original's
    _cache: dict = field(default_factory=dict, repr=False, init=False)

    def __post_init__(self):
        m = self.masks
        scale = mask_full_scale(m)
        m = _to_tensor(m)
        if scale > 1.0:  # 0/255 or 16-bit images
            m = m / scale
        if m.ndim == 2:
            m = m[None]
        if m.ndim < 3:
            raise ValueError(f"masks must have shape (V, H, W) or (..., V, H, W), got {tuple(m.shape)}")
        self.masks = m
        self.valid = _valid(self.valid, tuple(m.shape[:-2]), "masks")
        self.offset = self._per_mask("offset", self.offset, lambda t: torch.isfinite(t), "finite (pixels)")
        self.weight = self._per_mask(
            "weight", self.weight, lambda t: torch.isfinite(t) & (t >= 0), "finite and >= 0"
        )

    def _per_mask(self, name: str, value, ok, what: str) -> torch.Tensor | None:
        """``value`` (one number per mask, or None) as a tensor on the masks' device, checked by ``ok``."""
        if value is None:
            return None
        m = self.masks
        t = torch.as_tensor(value, dtype=m.dtype if m.is_floating_point() else None)
        if t.shape != self.valid.shape:
            raise ValueError(
                f"{name} must have one value per mask, shape {tuple(self.valid.shape)}, got {tuple(t.shape)}"
            )
        if not bool(ok(t).all()):
            raise ValueError(f"{name} must be {what}")
        return t.to(m.device)

    def with_offset(self, offset: torch.Tensor | None) -> Silhouettes:
        """These masks with the outline ``offset`` (pixels, see the class docstring); the derived images
        (distance transforms, samples) do not depend on it and are shared with ``self``."""
        return self._sharing_cache(offset=offset)

    def with_weight(self, weight: torch.Tensor | None) -> Silhouettes:
        """These masks with the per-mask ``weight`` of the cues' camera sums (see the class docstring); the
        derived images are shared with ``self``."""
        return self._sharing_cache(weight=weight)

    def _sharing_cache(self, **changes) -> Silhouettes:
        """A copy with ``changes`` to fields the derived images do not depend on, sharing its cache."""
        out = dataclasses.replace(self, **changes)
        out._cache = self._cache
        return out

    @property
    def height(self) -> int:
        return self.masks.shape[-2]

    @property
    def width(self) -> int:
        return self.masks.shape[-1]

    def blurred(self, sigma: float) -> torch.Tensor:
        """(V, H, W) masks smoothed by a Gaussian of ``sigma`` pixels (0: the masks themselves). A bilinear
        look-up in it is a smooth function of the point, which gives the silhouette cue a gradient.

        Computed in torch on the masks' device and dtype (separable kernel of ``2 ceil(3 sigma) + 1`` taps,
        mirrored borders: the same numbers as ``cv2.GaussianBlur``), so GPU masks never leave the GPU."""
        key = ("blur", float(sigma), self.masks.device, self.masks.dtype)
        if key not in self._cache:
            self._cache[key] = gaussian_blur(self.masks, sigma) if sigma > 0 else self.masks
        return self._cache[key]

    def despeckled(self, size: int) -> Silhouettes:
        """These masks with isolated speckles and pinholes removed: a ``size x size`` median filter
        (``cv2.medianBlur``) of the binary masks, cached; ``size <= 1`` returns ``self``. Limbs wider than
        ``size / 2`` pixels keep their shape; salt-and-pepper noise from a background subtraction goes."""
        if size <= 1:
            return self
        key = ("despeckled", int(size), self.masks.device)
        if key not in self._cache:
            import cv2

            k = int(size) | 1  # odd
            hard = ((self.masks > 0.5).reshape(-1, *self.masks.shape[-2:]).cpu().numpy() * 255).astype(
                np.uint8
            )
            out = torch.from_numpy(np.stack([cv2.medianBlur(m, k) for m in hard]) > 127)
            self._cache[key] = Silhouettes(out.reshape(self.masks.shape).to(self.masks), valid=self.valid)
        # the cache is shared by with_offset copies: the offset is this object's
        cleaned = self._cache[key]
        return cleaned if cleaned.offset is self.offset else cleaned.with_offset(self.offset)

    def area(self) -> torch.Tensor:
        """(..., V) foreground area in pixels (sum of the mask)."""
        if ("area", self.masks.device) not in self._cache:
            self._cache[("area", self.masks.device)] = self.masks.sum((-1, -2))
        return self._cache[("area", self.masks.device)]

    def outside_distance(self) -> torch.Tensor:
        """(..., V, H, W) distance (pixels) from each pixel centre to the foreground (mask > 0.5), 0 inside;
        its zero level is the foreground's pixel edge (``cv2.distanceTransform`` minus half a pixel). A
        bilinear look-up in it grows linearly away from the silhouette, so a model point outside the mask
        has a gradient however far it lies (the distance cue of :mod:`torchpf.refine`)."""
        key = ("outside", self.masks.device)
        if key not in self._cache:
            hard = (self.masks > 0.5).reshape(-1, *self.masks.shape[-2:]).cpu().numpy()
            out = torch.stack([torch.from_numpy(distance_image(m)).sub(0.5).clamp_min(0.0) for m in hard])
            self._cache[key] = out.reshape(self.masks.shape).to(self.masks.device)
        return self._cache[key]

    def foreground_samples(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` fixed points on each camera's foreground (Fontmarty's N_s points of the dual cue, §3.2.2).

        Pixels with mask > 0.5 are enumerated in raster order and picked at the indices of the golden-ratio
        sequence ``frac(0.5 + i / phi)``, a deterministic low-discrepancy subsample that covers the
        silhouette evenly without aliasing with the row length.

        Returns:
            points (..., V, n, 2) pixel coordinates (u, v); ok (..., V) bool, False for an empty or invalid
            mask.
        """
        key = ("samples", int(n), self.masks.device)
        if key not in self._cache:
            masks = self.masks.reshape(-1, *self.masks.shape[-2:])
            valid = self.valid.reshape(-1)
            device = masks.device
            pts = torch.zeros(len(masks), n, 2, device=device)
            ok = torch.zeros(len(masks), dtype=torch.bool, device=device)
            golden = torch.frac(
                0.5 + torch.arange(n, dtype=torch.float64, device=device) * (math.sqrt(5) - 1) / 2
            )
            for v in range(len(masks)):  # once per frame and camera, cached
                ys, xs = torch.nonzero(masks[v] > 0.5, as_tuple=True)
                if len(xs) == 0 or not bool(valid[v]):
                    continue
                idx = (golden * len(xs)).long().clamp_max(len(xs) - 1)
                pts[v] = torch.stack([xs[idx], ys[idx]], -1).float()
                ok[v] = True
            self._cache[key] = (pts.reshape(*self.masks.shape[:-2], n, 2), ok.reshape(self.valid.shape))
        return self._cache[key]


@dataclass(eq=False)
class Keypoints2D:
    """Detected 2D body points of one frame (Brubaker et al. §3.1).

    Attributes:
        uv: (V, J, 2) pixel coordinates per camera, in the order of the likelihood's ``joints``; NaN marks
            a missing detection. (..., V, J, 2) for a batch of sequences (leading dims as the particles').
        visible: optional (..., V, J) bool; False also marks a missing detection.
        image_size: (width, height) of the pixel grid ``uv`` is in when it is not the cameras' own (the
            masks' grid of a sequence directory, :class:`~torchpf.sequence.SequenceData`), else None.
    """

    uv: torch.Tensor
    visible: torch.Tensor | None = None
    image_size: tuple[int, int] | None = None

    def __post_init__(self):
        self.uv = _to_tensor(self.uv)
        if self.uv.ndim == 2:
            self.uv = self.uv[None]
        if self.uv.ndim < 3 or self.uv.shape[-1] != 2:
            raise ValueError(f"uv must have shape (V, J, 2) or (..., V, J, 2), got {tuple(self.uv.shape)}")
        vis = ~torch.isnan(self.uv).any(-1)
        if self.visible is not None:
            vis = vis & torch.as_tensor(self.visible, dtype=torch.bool).reshape(vis.shape)
        self.visible = vis
        self.uv = torch.nan_to_num(self.uv, nan=0.0)


@dataclass(eq=False)
class DistanceMaps:
    """Per-camera distance images (pixels): distance to the nearest skin blob (Fontmarty §3.2.3) or to the
    nearest edge (Chamfer matching, Brubaker eq. 9).

    Fields: ``distance`` (V, H, W) float pixels, or (..., V, H, W) for a batch of sequences (leading dims as
    the particles'); ``valid`` (V,) or (..., V) bool. Build with :meth:`from_features` (binary feature masks:
    skin blobs, edges) or :meth:`from_edges_of` (grey or colour images, Canny).
    """

    distance: torch.Tensor
    valid: torch.Tensor | None = None

    def __post_init__(self):
        self.distance = _to_tensor(self.distance)
        if self.distance.ndim == 2:
            self.distance = self.distance[None]
        self.valid = _valid(self.valid, tuple(self.distance.shape[:-2]), "distance images")

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

    def has_evidence(self, fields=None) -> bool:
        """Whether anything here can tell poses apart: a valid camera with a non-empty silhouette, a point,
        a visible keypoint, or a valid distance map. ``fields``: only these fields count (the ones the
        likelihood reads, e.g. ``{"silhouettes"}``); default all. A frame without evidence leaves every
        particle's weight as it was (the tracker flags it: ``TrackResult.no_evidence``)."""

        def wanted(name: str) -> bool:
            return (fields is None or name in fields) and getattr(self, name) is not None

        if wanted("silhouettes"):
            s = self.silhouettes
            if bool((s.valid & (s.masks > 0.5).flatten(1).any(-1)).any()):
                return True
        if wanted("points") and self.points.points.shape[-2] > 0:
            return True
        if wanted("keypoints") and bool(self.keypoints.visible.any()):
            return True
        return any(wanted(name) and bool(getattr(self, name).valid.any()) for name in ("skin", "edges"))
