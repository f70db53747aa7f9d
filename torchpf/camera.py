"""Pinhole cameras with OpenCV conventions, batched and differentiable projection, ``cameras.yaml`` I/O.

A :class:`Camera` maps world points to pixels exactly as ``cv2.projectPoints`` does::

    x_cam = R @ x_world + t                        # world -> camera (metres), camera looks along +z
    x, y  = x_cam[0] / x_cam[2], x_cam[1] / x_cam[2]
    r2    = x**2 + y**2
    x'    = x (1 + k1 r2 + k2 r2**2 + k3 r2**3) + 2 p1 x y + p2 (r2 + 2 x**2)
    y'    = y (1 + k1 r2 + k2 r2**2 + k3 r2**3) + p1 (r2 + 2 y**2) + 2 p2 x y
    u, v  = K @ (x', y', 1)                        # pixels; (0, 0) is the centre of the top-left pixel

Image x grows to the right, y grows down; with a z-up world a camera's ``R`` has its third row (the optical
axis) pointing at the scene and its second row pointing down in the world. :func:`look_at` builds such
cameras, and :func:`camera_ring` places ``n`` of them on a circle around a subject (the 3-camera triangle
of Fontmarty et al. is ``camera_ring(3, ...)``).

Files: :func:`load_cameras` reads the ``cameras.yaml`` of a sequence directory (DESIGN.md) and also
OpenCV ``cv2.FileStorage`` YAML/XML files written by calibration pipelines; :func:`save_cameras` writes
``cameras.yaml`` atomically. The format::

    cameras:
      cam0:
        K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
        dist: [k1, k2, p1, p2, k3]        # optional, 0 to 5 numbers (missing ones are 0)
        R: [[...], [...], [...]]          # world -> camera rotation
        t: [tx, ty, tz]                   # world -> camera translation (m)
        width: 640
        height: 480
    depth_camera: cam0                    # optional: the camera that produced points/<frame>.npy

Example::

    from torchpf.camera import camera_ring
    cams = camera_ring(3, radius=4.0, height=1.5, target=(0, 0, 1), width=160, height_px=120)
    uv = cams[0].project(torch.randn(1000, 17, 3))      # (1000, 17, 2) pixels
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from torchpf.io import load_yaml, write_atomic

__all__ = [
    "Camera",
    "CameraFileError",
    "CameraRig",
    "camera_ring",
    "check_camera_name",
    "load_cameras",
    "load_opencv_camera",
    "look_at",
    "merge_camera_files",
    "project_points",
    "save_cameras",
    "single_camera_advice",
]


class CameraFileError(ValueError):
    """A camera file is missing a key or holds a value of the wrong shape; the message names both."""


# Camera names become folder names (masks/<camera>/): letters, digits, '_', '-', '.', not starting with '.'
# or '-', so no name reaches outside the sequence (no '/', '..', absolute paths) or hides its folder.
_SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}")
_MAX_IMAGE_SIDE = 1 << 16  # pixels; larger sizes are typos (or overflow on the way to int)


def check_camera_name(name, source: str = "<cameras>") -> str:
    """``name`` if it is a safe camera name (1-64 of ``A-Z a-z 0-9 _ - .``, not starting with ``.`` or
    ``-``), else :class:`CameraFileError` naming ``source`` and the camera. Names become folder names of a
    sequence directory, so this is checked where files are read and written."""
    if not isinstance(name, str) or not _SAFE_NAME.fullmatch(name):
        raise CameraFileError(
            f"{source}: camera name {name!r} is not a safe identifier (1-64 letters, digits, '_', '-', '.', "
            f"not starting with '.' or '-'): it names the folder masks/<camera>/"
        )
    return name


def _check_size(value, key: str, where: str) -> int:
    v = value
    if isinstance(v, np.generic):
        v = v.item()
    if (
        isinstance(v, bool)
        or not isinstance(v, (int, float))
        or (isinstance(v, float) and not v.is_integer())
    ):
        raise CameraFileError(f"{where}: key {key!r} must be a positive integer, got {value!r}")
    if not 0 < v <= _MAX_IMAGE_SIDE:
        raise CameraFileError(f"{where}: key {key!r} must be between 1 and {_MAX_IMAGE_SIDE}, got {value!r}")
    return int(v)


def _check_rotation(R: np.ndarray, where: str) -> None:
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise CameraFileError(f"{where}: key 'R' is not a rotation matrix (R R^T != I or det < 0)")


def _check_intrinsics(K: np.ndarray, where: str) -> None:
    """A pinhole K: positive focal lengths, bottom row (0, 0, 1), K[1, 0] = 0 (the projection ignores it)."""
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CameraFileError(
            f"{where}: key 'K' needs positive focal lengths fx = K[0][0], fy = K[1][1], got {K[0, 0]!r}, "
            f"{K[1, 1]!r}"
        )
    if not np.array_equal(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise CameraFileError(
            f"{where}: key 'K' must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got rows {K.tolist()}"
        )


def project_points(
    points: torch.Tensor,
    K: torch.Tensor,
    R: torch.Tensor,
    t: torch.Tensor,
    dist: torch.Tensor | None = None,
    *,
    return_depth: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Functional OpenCV projection (the formula in the module docstring), batched and differentiable.

    Args:
        points: (..., 3) world points (m).
        K: (3, 3) intrinsics; R: (3, 3) rotation; t: (3,) translation (world -> camera).
        dist: (5,) distortion ``k1 k2 p1 p2 k3`` or None.

    Returns:
        (..., 2) pixel coordinates (u right, v down). Points at or behind the camera plane give
        meaningless (but finite where z != 0) values; check :meth:`Camera.depth`, or pass
        ``return_depth=True`` for ``(pixels, depth (...))`` from the same transform.
    """
    if dist is None:
        # Without distortion the projection is linear up to the division: [u z, v z, z] = K' (R x + t), with
        # K' the intrinsics the formula reads (K[1, 0] = 0, last row (0, 0, 1)). One matrix product and one
        # division instead of a dozen passes over the points (a visual hull projects ~10^5 voxels).
        Kp = K * _PINHOLE_MASK.to(K) + _PINHOLE_ONE.to(K)
        h = _affine(points, Kp @ R, Kp @ t)
        z = h[..., 2:]
        uv = h[..., :2] / torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    else:
        h = points @ R.transpose(-1, -2) + t
        uv = _camera_to_pixels(h, K, dist)
    return (uv, h[..., 2]) if return_depth else uv


def _affine(points: torch.Tensor, A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``points @ A^T + b`` for (..., k) points, (n, k) ``A`` and (n,) ``b``: one ``addmm`` (the bias added
    inside the matrix product, not in a second pass over the result: with 10^5 points both passes are
    memory-bound)."""
    if points.ndim < 2 or points.dtype != A.dtype or A.ndim != 2 or b.ndim != 1:
        return points @ A.transpose(-1, -2) + b
    return torch.addmm(b, points.reshape(-1, points.shape[-1]), A.t()).view(*points.shape[:-1], A.shape[0])


#: the entries of K the projection reads (:func:`project_points`), and its fixed last row
_PINHOLE_MASK = torch.tensor([[1.0, 1.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
_PINHOLE_ONE = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _camera_to_pixels(xc: torch.Tensor, K: torch.Tensor, dist: torch.Tensor | None) -> torch.Tensor:
    """(..., 3) camera-frame points -> (..., 2) pixels: perspective division, distortion, intrinsics. ``K``
    (..., 3, 3) and ``dist`` (..., 5) broadcast against the points' leading dims (one camera or a rig's V)."""
    z = xc[..., 2]
    # Keep the division finite for points on the camera plane; they are flagged by depth <= 0 anyway.
    z = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    x, y = xc[..., 0] / z, xc[..., 1] / z
    if dist is not None:
        k1, k2, p1, p2, k3 = dist.unbind(-1)
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = x * y
        x, y = (
            x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy,
        )
    u = K[..., 0, 0] * x + K[..., 0, 1] * y + K[..., 0, 2]
    v = K[..., 1, 1] * y + K[..., 1, 2]
    return torch.stack([u, v], -1)


def _resized_intrinsics(K: torch.Tensor, sx, sy) -> torch.Tensor:
    """Intrinsics (..., 3, 3) of the same camera seen in an image rescaled by ``sx``, ``sy`` (floats or (...,)
    tensors): focal lengths and skew scale, and pixel centres stay consistent, ``u' + 0.5 = sx (u + 0.5)``
    (pixel (0, 0) is the centre of the top-left pixel at every resolution)."""
    K = K.clone()
    K[..., 0, 0] = K[..., 0, 0] * sx
    K[..., 0, 1] = K[..., 0, 1] * sx
    K[..., 1, 1] = K[..., 1, 1] * sy
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K


def _as_tensor(x, shape: tuple[int, ...], what: str) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x, dtype=np.float64) if not isinstance(x, torch.Tensor) else x)
    if not t.is_floating_point():
        t = t.to(torch.float64)
    if tuple(t.shape) != shape:
        try:
            t = t.reshape(shape)
        except RuntimeError:
            raise ValueError(f"{what} must have shape {shape}, got {tuple(t.shape)}") from None
    return t


@dataclass(eq=False)
class Camera:
    """A calibrated pinhole camera, OpenCV conventions (module docstring).

    Args:
        K: (3, 3) intrinsics (pixels). R: (3, 3) world->camera rotation. t: (3,) world->camera translation
            (m). dist: up to 5 distortion coefficients ``k1 k2 p1 p2 k3`` (missing ones are 0) or None.
        width, height: image size in pixels. name: label used in ``cameras.yaml`` and sequence folders.

    Tensors are stored as given (float64 from lists); :meth:`project` casts them to the points' dtype and
    device, so the same camera serves float32 particles on CPU or GPU. A camera is a small value object,
    not an ``nn.Module``; several cameras are stacked in a :class:`CameraRig` (an ``nn.Module`` whose
    buffers move with ``.to()``), which is what likelihoods and proposals hold.
    """

    K: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    dist: torch.Tensor | None = None
    width: int = 0
    height: int = 0
    name: str = "cam"

    def __post_init__(self):
        self.K = _as_tensor(self.K, (3, 3), "K")
        self.R = _as_tensor(self.R, (3, 3), "R")
        self.t = _as_tensor(self.t, (3,), "t")
        if self.dist is not None:
            d = self.dist if isinstance(self.dist, torch.Tensor) else np.asarray(self.dist, dtype=np.float64)
            d = torch.as_tensor(d).reshape(-1)
            if d.numel() > 5:
                # OpenCV's rational/thin-prism models (8-14 coefficients) are not implemented.
                if bool((d[5:] != 0).any()):
                    raise ValueError(
                        f"only 5 distortion coefficients (k1 k2 p1 p2 k3) are supported, got {d}"
                    )
                d = d[:5]
            d = torch.cat([d, d.new_zeros(5 - d.numel())])
            self.dist = None if bool((d == 0).all()) else d.to(self.K)
        self.width, self.height = int(self.width), int(self.height)

    # ------------------------------------------------------------------ geometry
    def _params(self, like: torch.Tensor):
        kw = {"dtype": like.dtype, "device": like.device}
        dist = None if self.dist is None else self.dist.to(**kw)
        return self.K.to(**kw), self.R.to(**kw), self.t.to(**kw), dist

    def project(self, points: torch.Tensor, *, return_depth: bool = False):
        """(..., 3) world points (m) -> (..., 2) pixels, differentiable; agrees with ``cv2.projectPoints``.
        With ``return_depth``, ``(pixels, depth (...) m)`` from one transform (:meth:`depth` does another)."""
        return project_points(points, *self._params(points), return_depth=return_depth)

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (..., 3) camera-frame points ``R x + t`` (m)."""
        _, R, t, _ = self._params(points)
        return _affine(points, R, t)

    def depth(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (...,) depth along the optical axis (m); > 0 means in front."""
        return self.to_camera(points)[..., 2]

    def in_front(self, points: torch.Tensor, near: float = 1e-3) -> torch.Tensor:
        """(..., 3) -> (...,) bool: depth greater than ``near`` (m)."""
        return self.depth(points) > near

    def in_image(self, points: torch.Tensor, near: float = 1e-3) -> torch.Tensor:
        """(..., 3) -> (...,) bool: in front of the camera and projecting inside the image rectangle."""
        uv = self.project(points)
        inside = (uv[..., 0] >= -0.5) & (uv[..., 0] < self.width - 0.5)
        inside &= (uv[..., 1] >= -0.5) & (uv[..., 1] < self.height - 0.5)
        return inside & self.in_front(points, near)

    @property
    def center(self) -> torch.Tensor:
        """(3,) camera centre in world coordinates, ``-R^T t`` (m)."""
        return -(self.R.transpose(0, 1) @ self.t)

    @property
    def focal(self) -> float:
        """Mean focal length (pixels), used to turn a metric radius at depth z into pixels: f r / z."""
        return 0.5 * float(self.K[0, 0] + self.K[1, 1])

    def pixel_rays(
        self, height: int | None = None, width: int | None = None, stride: int = 1
    ) -> torch.Tensor:
        """Unit ray directions in the *world* frame through pixel centres, distortion undone.

        Args:
            height, width: grid size (defaults: the image size; a smaller grid is a resampled image, so
                pixel (i, j) of an ``h x w`` grid covers the camera pixel ``((j + .5) W / w - .5, ...)``).
            stride: keep every ``stride``-th row and column of that grid.

        Returns:
            (h', w', 3) float64 unit directions; rays start at :attr:`center`.
        """
        import cv2

        h, w = height or self.height, width or self.width
        js, is_ = np.meshgrid(np.arange(0, w, stride), np.arange(0, h, stride))
        u = (js + 0.5) * self.width / w - 0.5
        v = (is_ + 0.5) * self.height / h - 0.5
        pix = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
        # OpenCV works on host copies (the camera may sit on a GPU or hold learnable parameters)
        K, R = (m.detach().cpu().double().numpy() for m in (self.K, self.R))
        dist = None if self.dist is None else self.dist.detach().cpu().double().numpy()
        xy = cv2.undistortPoints(pix, K, dist).reshape(is_.shape + (2,))
        d_cam = np.concatenate([xy, np.ones(is_.shape + (1,))], -1)
        d_world = d_cam @ R  # R^T d for row vectors
        d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
        return torch.from_numpy(d_world)

    def resized(self, width: int, height: int) -> Camera:
        """The same camera seen at another resolution: ``width x height`` pixels, intrinsics scaled, pixel
        centres kept consistent (``u' + 0.5 = (u + 0.5) width / self.width``). This is how observations
        smaller than the camera images (160x120 masks of 640x480 cameras) are scored. A camera without an
        image size is taken to be at that resolution already (intrinsics unchanged)."""
        K = self.K.clone()
        if self.width > 0 and self.height > 0 and (width, height) != (self.width, self.height):
            K = _resized_intrinsics(K, width / self.width, height / self.height)
        return Camera(
            K, self.R.clone(), self.t.clone(), self.dist, width=width, height=height, name=self.name
        )

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict:
        """Plain-Python mapping in the ``cameras.yaml`` layout (lists of floats)."""
        d = {
            "K": self.K.tolist(),
            "dist": [0.0] * 5 if self.dist is None else self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "width": self.width,
            "height": self.height,
        }
        return d

    @classmethod
    def from_dict(cls, d: Mapping, name: str = "cam", source: str = "<dict>") -> Camera:
        """Inverse of :meth:`to_dict`; errors name ``source``, the camera and the key."""
        where = f"{source}: camera {check_camera_name(name, source)!r}"
        if not isinstance(d, Mapping):
            raise CameraFileError(f"{where}: expected a mapping of K, dist, R, t, width, height")
        unknown = set(d) - {"K", "dist", "R", "t", "width", "height"}
        if unknown:
            raise CameraFileError(f"{where}: unknown key(s) {sorted(unknown)}")
        values = {}
        for key, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,))):
            if key not in d:
                raise CameraFileError(f"{where}: missing key {key!r}")
            values[key] = _checked_array(d[key], shape, f"{where}: key {key!r}")
        _check_intrinsics(values["K"], where)
        dist = d.get("dist")
        if dist is not None:
            arr = _checked_array(dist, None, f"{where}: key 'dist'").reshape(-1)
            if arr.size > 5:
                raise CameraFileError(
                    f"{where}: key 'dist' has {arr.size} numbers, at most 5 (k1 k2 p1 p2 k3)"
                )
            dist = arr
        size = {}
        for key in ("width", "height"):
            if key not in d:
                raise CameraFileError(f"{where}: missing key {key!r}")
            size[key] = _check_size(d[key], key, where)
        R = values["R"]
        _check_rotation(R, where)
        return cls(values["K"], R, values["t"], dist, name=name, **size)


def _checked_array(value, shape, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraFileError(f"{where} must hold numbers, got {value!r}") from None
    if shape is not None and arr.shape != shape:
        if arr.size == math.prod(shape):
            arr = arr.reshape(shape)
        else:
            raise CameraFileError(f"{where} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CameraFileError(f"{where} holds non-finite numbers")
    return arr


class CameraRig(nn.Module):
    """``V`` cameras stacked on one axis (kornia's ``PinholeCamerasList``): the one way code handles several
    cameras. Projection is batched over the cameras, ``(..., 3) -> (..., V, 2)``, and the intrinsics and
    extrinsics are buffers, so ``.to()`` moves or casts them with the module that holds the rig.

    Args:
        cameras: a sequence of :class:`Camera` (named by ``cam.name``) or a name -> camera mapping (another
            rig included); the order is the ``V`` axis of multi-camera observations (the file order of
            ``cameras.yaml``).
        depth_camera: the name of the depth sensor whose points are in ``points/`` of a sequence, or None.

    Buffers: ``K`` (V, 3, 3), ``R`` (V, 3, 3), ``t`` (V, 3), ``dist`` (V, 5) (zeros for a camera without
    distortion), float64 as built. Plain attributes: ``names``, ``sizes`` ((width, height) per camera),
    ``depth_camera``.

    A rig also reads as an ordered mapping name -> :class:`Camera` (``rig["cam0"]``, ``rig[0]``, ``list(rig)``
    the names, ``rig.values()``, ``len(rig)``); each look-up builds a :class:`Camera` whose tensors are views
    of the rig's, so an in-place edit (``rig["cam0"].K[0, 0] = 500``) changes the rig and every likelihood
    that holds it.

    Learning: ``learnable=True`` (or a subset of ``("K", "R", "t", "dist")``) makes those ``nn.Parameter`` s
    (K (V, 3, 3) as a whole: mask its gradient to fit only the focal lengths). A learnable rotation is
    ``R = exp([w]_x) R_0`` with ``w`` the parameter ``rotation_update`` (V, 3) (rad, axis-angle, starting at
    0) and ``R_0`` the buffer ``R_init``; ``rig.R`` always reads the current rotation.

    Example::

        rig = camera_ring(3, width=160, height_px=120)
        uv = rig.project(joints)                   # (..., J, 3) -> (..., J, V, 2)
        small = rig.resized(80, 60)                # the same cameras seen on 80x60 masks
    """

    def __init__(
        self,
        cameras: Mapping[str, Camera] | Iterable[Camera] = (),
        depth_camera: str | None = None,
        *,
        learnable: bool | Sequence[str] = False,
    ):
        super().__init__()
        if isinstance(cameras, Mapping):
            names = [str(k) for k in cameras.keys()]
            cams = [cameras[k] for k in cameras.keys()]
        else:
            cams = list(cameras)
            names = [c.name for c in cams]
            seen = set()
            for n in names:
                if n in seen:
                    raise ValueError(f"duplicate camera name {n!r}")
                seen.add(n)
        if depth_camera is not None and depth_camera not in names:
            raise ValueError(f"depth_camera {depth_camera!r} is not one of {names}")
        if cams:
            # a new rig holds copies (cut from any graph of the cameras it is built from)
            K = torch.stack([c.K.detach() for c in cams]).double()
            R = torch.stack([c.R.detach() for c in cams]).to(K)
            t = torch.stack([c.t.detach() for c in cams]).to(K)
            dist = torch.stack([K.new_zeros(5) if c.dist is None else c.dist.detach().to(K) for c in cams])
        else:
            K, R = torch.zeros(0, 3, 3, dtype=torch.float64), torch.zeros(0, 3, 3, dtype=torch.float64)
            t, dist = torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 5, dtype=torch.float64)
        self._set(
            names, [(c.width, c.height) for c in cams], [c.dist is not None for c in cams], K, R, t, dist
        )
        self.depth_camera = depth_camera
        self._make_learnable(learnable)

    def _set(self, names, sizes, has_dist, K, R, t, dist) -> None:
        self.names = list(names)
        self.sizes = [(int(w), int(h)) for w, h in sizes]
        self.has_dist = list(has_dist)
        self.register_buffer("K", K)
        self.register_buffer("R", R)
        self.register_buffer("t", t)
        self.register_buffer("dist", dist)

    def _make_learnable(self, learnable: bool | Sequence[str]) -> None:
        names = (
            ("K", "R", "t", "dist") if learnable is True else () if learnable is False else tuple(learnable)
        )
        unknown = set(names) - {"K", "R", "t", "dist"}
        if unknown:
            raise ValueError(f"learnable camera parameters are K, R, t, dist; got {sorted(unknown)}")
        for name in names:
            value = self._buffers.pop(name)
            if name == "R":
                self.register_buffer("R_init", value)
                self.rotation_update = nn.Parameter(value.new_zeros(value.shape[:-1]))
            else:
                self.register_parameter(name, nn.Parameter(value))
        if "dist" in names:
            self.has_dist = [True] * len(self.names)  # a learnable distortion is applied to every camera

    def __getattr__(self, name: str):
        if name == "R" and "rotation_update" in self._parameters:
            w = self._parameters["rotation_update"]
            skew = torch.zeros(*w.shape, 3, dtype=w.dtype, device=w.device)
            skew[..., 0, 1], skew[..., 0, 2], skew[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
            skew = skew - skew.transpose(-1, -2)
            return torch.linalg.matrix_exp(skew) @ self._buffers["R_init"]
        return super().__getattr__(name)

    # ------------------------------------------------------------------ mapping of cameras
    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self) -> Iterator[str]:
        return iter(self.names)

    def __contains__(self, name) -> bool:
        return name in self.names

    def __getitem__(self, key: str | int) -> Camera:
        """The camera named ``key`` (or at index ``key`` of the V axis), built from the buffers."""
        v = key if isinstance(key, int) else self.index(key)
        w, h = self.sizes[v]
        dist = self.dist[v] if self.has_dist[v] else None
        return Camera(self.K[v], self.R[v], self.t[v], dist, w, h, self.names[v])

    def index(self, name: str) -> int:
        """Position of camera ``name`` on the V axis (KeyError if there is none)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(name) from None

    def keys(self) -> list[str]:
        return list(self.names)

    def values(self) -> list[Camera]:
        return [self[v] for v in range(len(self))]

    def items(self) -> list[tuple[str, Camera]]:
        return list(zip(self.names, self.values(), strict=True))

    def get(self, name: str, default=None):
        return self[name] if name in self.names else default

    @property
    def cameras(self) -> list[Camera]:
        """The V cameras in order, as :class:`Camera` objects."""
        return self.values()

    # ------------------------------------------------------------------ batched geometry
    def _params(self, like: torch.Tensor):
        kw = {"dtype": like.dtype, "device": like.device}
        dist = self.dist.to(**kw) if any(self.has_dist) else None
        return self.K.to(**kw), self.R.to(**kw), self.t.to(**kw), dist

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (..., V, 3) camera-frame points ``R_v x + t_v`` (m)."""
        _, R, t, _ = self._params(points)
        V = R.shape[0]
        # One GEMM for all cameras: row (v, j) of R_all is row j of R_v.
        R_all = R.reshape(V * 3, 3)
        return _affine(points, R_all, t.reshape(V * 3)).unflatten(-1, (V, 3))

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points (m) -> (..., V, 2) pixels in every camera (OpenCV model, module docstring);
        differentiable; camera ``v`` gives what ``rig[v].project`` gives."""
        K, _, _, dist = self._params(points)
        return _camera_to_pixels(self.to_camera(points), K, dist)

    def depth(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (..., V) depth along each optical axis (m); > 0 means in front."""
        return self.to_camera(points)[..., 2]

    def in_front(self, points: torch.Tensor, near: float = 1e-3) -> torch.Tensor:
        """(..., 3) -> (..., V) bool: depth greater than ``near`` (m)."""
        return self.depth(points) > near

    def focal(self, like: torch.Tensor | None = None) -> torch.Tensor:
        """(V,) mean focal lengths (pixels), in ``like``'s dtype and device when given (see
        :attr:`Camera.focal`)."""
        K = self.K if like is None else self.K.to(dtype=like.dtype, device=like.device)
        return 0.5 * (K[:, 0, 0] + K[:, 1, 1])

    def resized(self, width: int, height: int) -> CameraRig:
        """Every camera seen at ``width x height`` pixels (:meth:`Camera.resized`, batched): the rig that
        projects into an observation grid other than the cameras' own. Returns ``self`` when every camera
        already has that size; a camera without a size keeps its intrinsics."""
        change = [w > 0 and h > 0 and (w, h) != (width, height) for w, h in self.sizes]
        if all((w, h) == (width, height) for w, h in self.sizes):
            return self
        sx = self.K.new_tensor(
            [width / w if c else 1.0 for c, (w, h) in zip(change, self.sizes, strict=True)]
        )
        sy = self.K.new_tensor(
            [height / h if c else 1.0 for c, (w, h) in zip(change, self.sizes, strict=True)]
        )
        # Cameras already at that size (or without one) keep their intrinsics bit for bit.
        K = torch.where(
            self.K.new_tensor(change, dtype=torch.bool)[:, None, None],
            _resized_intrinsics(self.K, sx, sy),
            self.K,
        )
        rig = CameraRig.__new__(CameraRig)
        nn.Module.__init__(rig)
        sizes = [(width, height)] * len(self)
        rig._set(self.names, sizes, self.has_dist, K, self.R.clone(), self.t.clone(), self.dist.clone())
        rig.depth_camera = self.depth_camera
        return rig

    def extra_repr(self) -> str:
        return f"names={self.names}, sizes={self.sizes}, depth_camera={self.depth_camera!r}"


# A rig reads as a mapping (isinstance checks, dict(rig)) without Mapping's value equality, which would make
# the module unhashable.
Mapping.register(CameraRig)


# ---------------------------------------------------------------------- files
_FS_KEYS = {
    "K": ("K", "camera_matrix", "cameraMatrix", "CameraMatrix", "intrinsics", "M", "M1", "mtx"),
    "dist": ("dist", "D", "distortion_coefficients", "distCoeffs", "dist_coeffs", "distortion", "D1"),
    "R": ("R", "rotation", "rotation_matrix", "Rot"),
    "rvec": ("rvec", "rvecs", "rotation_vector"),
    "t": ("t", "T", "tvec", "tvecs", "translation", "translation_vector"),
    "width": ("width", "image_width", "imageWidth", "cols"),
    "height": ("height", "image_height", "imageHeight", "rows"),
    "size": ("image_size", "imageSize", "size", "img_size"),
}


def _is_filestorage(text: str) -> bool:
    head = text.lstrip()[:200]
    return (
        head.startswith("%YAML:")
        or head.startswith("<?xml")
        or "<opencv_storage>" in head
        or ("!!opencv-matrix" in text)
    )


def _fs_value(node):
    if node.isMap() and "data" in node.keys() and "rows" in node.keys():
        return node.mat()
    if node.isMap():
        return {k: _fs_value(node.getNode(k)) for k in node.keys()}
    if node.isSeq():
        return [_fs_value(node.at(i)) for i in range(node.size())]
    if node.isInt() or node.isReal():
        return node.real()
    if node.isString():
        return node.string()
    mat = node.mat()
    return mat


def _camera_from_fs_map(m: Mapping, name: str, source: str) -> Camera:
    def pick(key):
        for alias in _FS_KEYS[key]:
            if alias in m:
                return m[alias]
        return None

    where = f"{source}: camera {check_camera_name(name, source)!r}"
    K = pick("K")
    if K is None:
        raise CameraFileError(f"{where}: missing key 'camera_matrix' (or one of {_FS_KEYS['K']})")
    K = _checked_array(K, (3, 3), f"{where}: key 'camera_matrix'")
    _check_intrinsics(K, where)
    dist = pick("dist")
    dist = None if dist is None else _checked_array(dist, None, f"{where}: key 'distortion'").reshape(-1)
    R, rvec = pick("R"), pick("rvec")
    if R is not None:
        R = _checked_array(R, (3, 3), f"{where}: key 'R'")
    elif rvec is not None:
        import cv2

        rv = _checked_array(rvec, None, f"{where}: key 'rvec'").reshape(-1)
        if rv.size != 3:
            raise CameraFileError(f"{where}: key 'rvec' must hold 3 numbers (one view), got {rv.size}")
        R = cv2.Rodrigues(rv)[0]
    else:
        R = np.eye(3)
    t = pick("t")
    t = np.zeros(3) if t is None else _checked_array(t, (3,), f"{where}: key 't'")
    w, h = pick("width"), pick("height")
    size = pick("size")
    if (w is None or h is None) and size is not None:
        sz = _checked_array(size, None, f"{where}: key 'image_size'").reshape(-1)
        if sz.size != 2:
            raise CameraFileError(f"{where}: key 'image_size' must hold 2 numbers (width, height)")
        w, h = sz[0], sz[1]  # OpenCV writes Size as (width, height)
    if w is None or h is None:
        raise CameraFileError(f"{where}: missing key 'image_width'/'image_height' (or 'image_size')")
    if dist is not None and dist.size > 5 and np.any(dist[5:] != 0):
        raise CameraFileError(
            f"{where}: key 'distortion' has {dist.size} numbers; only k1 k2 p1 p2 k3 are used"
        )
    _check_rotation(R, where)
    w, h = _check_size(w, "image_width", where), _check_size(h, "image_height", where)
    return Camera(K, R, t, None if dist is None else dist[:5], width=w, height=h, name=name)


# A FileStorage matrix larger than this is no camera parameter (K 3x3, dist up to 1x14, R 3x3, t 3x1).
_FS_MAX_MATRIX = 64


def _read_fs_yaml(text: str, path: str) -> dict:
    """A FileStorage YAML file (``%YAML:1.0``, ``!!opencv-matrix`` maps) read with PyYAML. OpenCV's own
    parser is not used for YAML: on some malformed files it aborts the process, which no ``except`` can
    turn into an error message."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def matrix(loader, node):
        m = loader.construct_mapping(node, deep=True)
        rows, cols, values = m.get("rows"), m.get("cols"), m.get("data")
        ok = all(type(v) is int and 0 < v <= _FS_MAX_MATRIX for v in (rows, cols))
        if not ok or not isinstance(values, list) or len(values) != rows * cols:
            raise CameraFileError(
                f"{path}: line {node.start_mark.line + 1}: an opencv-matrix needs rows and cols (1 to "
                f"{_FS_MAX_MATRIX}) and rows x cols numbers in data"
            )
        return _checked_array(values, None, f"{path}: line {node.start_mark.line + 1}").reshape(rows, cols)

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", matrix)
    # the "%YAML:1.0" line is no YAML directive: commented out, so that line numbers stay the file's
    body = re.sub(r"^(\s*)%YAML", r"\1#%YAML", text, count=1)
    try:
        return yaml.load(body, Loader=Loader)  # noqa: S506 (a SafeLoader with one more constructor)
    except yaml.YAMLError as e:
        raise CameraFileError(f"{path}: not valid FileStorage YAML ({_first_line(e)})") from None


def _read_fs_xml(path: str) -> dict:
    """A FileStorage XML file, read by OpenCV."""
    import cv2

    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError, UnicodeError) as e:  # OpenCV's parser raises on malformed files
        raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file ({_first_line(e)})") from None
    if not fs.isOpened():
        raise CameraFileError(f"{path}: OpenCV cannot read this file as FileStorage YAML/XML")
    try:
        root = fs.root()
        return {k: _fs_value(root.getNode(k)) for k in root.keys()}
    except (cv2.error, SystemError, UnicodeError, ValueError) as e:
        raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file ({_first_line(e)})") from None
    finally:
        fs.release()


def _first_line(e: BaseException) -> str:
    lines = str(e).strip().splitlines()
    return f"{type(e).__name__}: {lines[-1] if lines else ''}"


def load_opencv_camera(path: str | os.PathLike, name: str | None = None) -> CameraRig:
    """Read a ``cv2.FileStorage`` YAML/XML calibration file.

    Accepted layouts: one camera at the top level (``camera_matrix``/``cameraMatrix``/``K``,
    ``distortion_coefficients``/``distCoeffs``/``D``, ``image_width`` + ``image_height`` or
    ``image_size``, optional extrinsics ``R`` or ``rvec`` and ``T``/``tvec``; identity pose when absent),
    or one top-level map per camera holding those keys. Returns a :class:`CameraRig`.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except UnicodeDecodeError as e:
        raise CameraFileError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    data = _read_fs_yaml(text, path) if text.lstrip().startswith("%YAML") else _read_fs_xml(path)
    if not isinstance(data, Mapping):
        raise CameraFileError(f"{path}: expected a map of calibration keys or of cameras")
    if any(alias in data for alias in _FS_KEYS["K"]):
        # a name taken from the file name is made safe; a name given by the caller is checked
        stem = os.path.splitext(os.path.basename(path))[0]
        cam_name = name or re.sub(r"[^A-Za-z0-9_.\-]", "_", stem)[:64].lstrip(".-") or "cam"
        return CameraRig([_camera_from_fs_map(data, cam_name, path)])
    cams = [_camera_from_fs_map(v, k, path) for k, v in data.items() if isinstance(v, Mapping)]
    if not cams:
        raise CameraFileError(f"{path}: no camera found (expected key 'camera_matrix' or per-camera maps)")
    depth = data.get("depth_camera")
    return CameraRig(cams, depth_camera=depth if isinstance(depth, str) else None)


def load_cameras(path: str | os.PathLike) -> CameraRig:
    """Read ``cameras.yaml`` (module docstring) or an OpenCV FileStorage file; see :func:`load_opencv_camera`.

    Returns:
        :class:`CameraRig` (ordered name -> :class:`Camera`, with ``depth_camera``).

    Raises:
        FileNotFoundError: no such file. CameraFileError: malformed content (message names file and key).
    """
    import yaml

    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except UnicodeDecodeError as e:
        raise CameraFileError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    if _is_filestorage(text):
        return load_opencv_camera(path)
    try:
        data = load_yaml(text)  # plain numbers only: "1_000" is no width
    except yaml.YAMLError as e:
        raise CameraFileError(f"{path}: not valid YAML ({e})") from None
    if not isinstance(data, Mapping):
        raise CameraFileError(f"{path}: expected a mapping with key 'cameras'")
    unknown = set(data) - {"cameras", "depth_camera"}
    if "cameras" not in data:
        raise CameraFileError(f"{path}: missing key 'cameras'")
    if unknown:
        raise CameraFileError(f"{path}: unknown top-level key(s) {sorted(unknown)}")
    cams_data = data["cameras"]
    if not isinstance(cams_data, Mapping) or not cams_data:
        raise CameraFileError(f"{path}: key 'cameras' must map camera names to camera entries")
    cams = [
        Camera.from_dict(v, name=str(k) if type(k) is int else k, source=path) for k, v in cams_data.items()
    ]
    depth = data.get("depth_camera")
    if depth is not None and not isinstance(depth, str):
        raise CameraFileError(f"{path}: key 'depth_camera' must be a camera name, got {depth!r}")
    if len({c.name for c in cams}) != len(cams):
        raise CameraFileError(f"{path}: two cameras have the same name")
    if depth is not None and str(depth) not in {c.name for c in cams}:
        raise CameraFileError(f"{path}: key 'depth_camera' names {depth!r}, not one of the cameras")
    return CameraRig(cams, depth_camera=None if depth is None else str(depth))


def single_camera_advice(path: str | os.PathLike) -> str | None:
    """None, or a sentence for an error message when ``path`` is a one-camera OpenCV calibration file
    (camera keys at the top level, the camera named after the file) where a rig is expected: it names the
    camera and says how to merge the per-camera files (:func:`merge_camera_files`,
    ``python -m torchpf cameras merge``). None for a ``cameras.yaml``, a multi-camera or an unreadable file.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
        if not _is_filestorage(text):
            return None
        data = _read_fs_yaml(text, path) if text.lstrip().startswith("%YAML") else _read_fs_xml(path)
        if not isinstance(data, Mapping) or not any(alias in data for alias in _FS_KEYS["K"]):
            return None
        name = load_opencv_camera(path).names[0]
    except (OSError, ValueError):
        return None
    return (
        f"{path} is a one-camera OpenCV calibration file (its camera is named {name!r} after the file): "
        "merge the per-camera files into one cameras.yaml with 'python -m torchpf cameras merge CAM1.yml "
        "CAM2.yml ... --out cameras.yaml'"
    )


def merge_camera_files(paths: Sequence[str | os.PathLike], depth_camera: str | None = None) -> CameraRig:
    """One :class:`CameraRig` from several camera files, in the order given: per-camera OpenCV calibration
    files (each camera named after its file, ``cam_left.yml`` -> ``cam_left``), multi-camera OpenCV files
    and ``cameras.yaml`` files alike (:func:`load_cameras`). Save it with :func:`save_cameras`.

    Args:
        paths: the files; their cameras must have distinct names.
        depth_camera: the depth sensor's name; default: the one a file names, if any.

    Raises:
        CameraFileError: two cameras with one name (both files named), two files naming different depth
            cameras, or a ``depth_camera`` that is none of the cameras.
    """
    cams: list[Camera] = []
    origin: dict[str, str] = {}
    depths = set()
    for path in paths:
        path = os.fspath(path)
        rig = load_cameras(path)
        for name, cam in rig.items():
            if name in origin:
                raise CameraFileError(
                    f"{path}: camera {name!r} is also in {origin[name]}; rename a file (a one-camera file "
                    "names its camera after the file)"
                )
            origin[name] = path
            cams.append(cam)
        if rig.depth_camera is not None:
            depths.add(rig.depth_camera)
    if not cams:
        raise CameraFileError("no camera file given")
    if depth_camera is None and len(depths) > 1:
        raise CameraFileError(f"the files name different depth cameras {sorted(depths)}: choose one")
    depth = depth_camera if depth_camera is not None else next(iter(depths), None)
    if depth is not None and depth not in origin:
        raise CameraFileError(f"depth camera {depth!r} is not one of the cameras {list(origin)}")
    return CameraRig(cams, depth_camera=depth)


def save_cameras(
    path: str | os.PathLike,
    cameras: Mapping[str, Camera] | Sequence[Camera],
    depth_camera: str | None = None,
) -> None:
    """Write ``cameras.yaml`` atomically (temp file + ``os.replace``).

    Args:
        cameras: a :class:`CameraRig`, a name -> camera mapping or a sequence (names from ``cam.name``).
        depth_camera: name of the depth sensor; defaults to ``cameras.depth_camera`` for a rig.
    """
    import yaml

    rig = cameras if isinstance(cameras, CameraRig) else CameraRig(cameras)
    for name in rig:
        check_camera_name(name, os.fspath(path))
    depth = depth_camera if depth_camera is not None else rig.depth_camera
    if depth is not None and depth not in rig:
        raise ValueError(f"depth_camera {depth!r} is not one of {list(rig)}")
    data: dict = {"cameras": {str(k): cam.to_dict() for k, cam in rig.items()}}
    if depth is not None:
        data["depth_camera"] = depth
    write_atomic(path, yaml.safe_dump(data, sort_keys=False, default_flow_style=None))


# ---------------------------------------------------------------------- rigs
def look_at(
    eye: Sequence[float],
    target: Sequence[float] = (0.0, 0.0, 1.0),
    *,
    up: Sequence[float] = (0.0, 0.0, 1.0),
    width: int = 640,
    height: int = 480,
    fov_deg: float = 60.0,
    name: str = "cam",
) -> Camera:
    """A distortion-free camera at ``eye`` looking at ``target`` with world ``up`` pointing up in the image.

    ``fov_deg`` is the horizontal field of view; square pixels, principal point at the image centre.
    """
    eye_, tgt, up_ = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = tgt - eye_
    if np.linalg.norm(z) < 1e-9:
        raise ValueError("eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, up_)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any horizontal x axis
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image y points down, i.e. against world up
    R = np.stack([x, y, z])
    t = -R @ eye_
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(K, R, t, None, width=width, height=height, name=name)


def camera_ring(
    n: int = 3,
    *,
    radius: float = 4.0,
    height: float = 1.5,
    target: Sequence[float] = (0.0, 0.0, 1.0),
    width: int = 160,
    height_px: int = 120,
    fov_deg: float = 50.0,
    start_deg: float = -90.0,
    prefix: str = "cam",
) -> CameraRig:
    """``n`` cameras evenly spaced on a horizontal circle of ``radius`` (m) around ``target``, at ``height``
    (m) above the ground, all looking at ``target``. ``start_deg`` is the azimuth of the first camera
    (-90: on the -y axis, facing +y). ``n=3`` is the triangle set-up of Fontmarty et al."""
    tx, ty, _ = (float(v) for v in target)
    cams = []
    for i in range(n):
        phi = math.radians(start_deg + 360.0 * i / n)
        eye = (tx + radius * math.cos(phi), ty + radius * math.sin(phi), height)
        cams.append(look_at(eye, target, width=width, height=height_px, fov_deg=fov_deg, name=f"{prefix}{i}"))
    return CameraRig(cams)
