"""Observation likelihoods of the four papers, batched over particles: ``lik(theta, obs) -> (..., N)``.

Every likelihood is an ``nn.Module`` built from a skeleton (anything with ``capsules(theta)`` and
``fk(theta)``, normally :class:`torchpf.Skeleton`) and, for image cues, the cameras. It maps poses
``theta`` (..., N, D) and one frame's observation to **log**-likelihoods (..., N) (up to a constant), so
terms add, annealing exponents multiply, and the filter normalises with ``logsumexp``.

* :class:`PointCloudLikelihood` (Hauberg et al. eq. 15): ``-sum_k min(D^2(theta, z_k), tau) / 2 sigma^2``,
  D the distance from point z_k to the (half-)capsule skin. obs: ``PointCloud``.
* :class:`SilhouetteLikelihood` (Fontmarty et al. eq. 2): ``-sum_l D_l^2 / 2 sigma^2``, D_l the share of the
  projected model's area outside camera l's mask. obs: ``Silhouettes``.
* :class:`DualSilhouetteLikelihood` (Fontmarty §3.2.2): same form, D_l the share of N_s foreground points
  not covered by the projected model. obs: ``Silhouettes``.
* :class:`OverlapLikelihood` (Rius et al. eq. 7): ``beta sum_l log(|model & mask| / |model | mask|)``.
  obs: ``Silhouettes``.
* :class:`Keypoints2DLikelihood` (Brubaker et al. eq. 3-4): ``sum_{l,i} log p(m_li - P_l(X_i))``, Gaussian or
  Student-t, missing points skipped. obs: ``Keypoints2D``.
* :class:`SkinBlobLikelihood` (Fontmarty §3.2.3): ``-sum_l D_l^2 / 2 sigma^2``, D_l the mean skin-distance
  image value at the projected head and hands. obs: ``DistanceMaps`` (field ``skin`` of a ``Frame``).
* :class:`ChamferLikelihood` (Brubaker eq. 9): ``-sum_l mean_i min(d_l(b_i)^2, tau^2) / 2 sigma^2`` over
  model outline points b_i. obs: ``DistanceMaps`` of edges (field ``edges``).
* :class:`ProductLikelihood` (Fontmarty §3.2.4, Brubaker eq. 10): ``sum_k w_k log p_k``. obs: ``Frame``.

``obs`` is the container named above (:mod:`torchpf.observations`) or a
:class:`~torchpf.observations.Frame` holding it; a missing container (None) or camera contributes 0.
Image terms hold their cameras as a :class:`~torchpf.camera.CameraRig` (buffers that move with ``.to()``) and
work in the observation's pixel grid: masks may be smaller than the camera images (the rig is
:meth:`~torchpf.camera.CameraRig.resized` to them), which is how 640x480 cameras are scored on 160x120 masks.

Sampling: the model points of the silhouette cues come from a **fixed quasi-random pattern**
(:func:`torchpf.geometry.sample_pattern`) mapped into every projected capsule, and the dual cue uses
fixed stratified foreground points (:meth:`Silhouettes.foreground_samples`). Likelihoods are therefore
deterministic, smooth functions of the pose - the same particle always gets the same weight - unless a
``generator`` is passed, which draws fresh i.i.d. model points on each call.

Gradients: the point-cloud, silhouette (bilinear mask look-ups ramp across boundary pixels), overlap, 2D
point, skin and Chamfer terms are differentiable in ``theta``; the dual cue is too with ``softness > 0``.

Example::

    from torchpf.likelihoods import PointCloudLikelihood, SilhouetteLikelihood, ProductLikelihood
    lik = ProductLikelihood({"sil": SilhouetteLikelihood(skel, cams), "pc": PointCloudLikelihood(skel)},
                            weights={"sil": 1.0, "pc": 0.5})
    logw = lik(particles, Frame(silhouettes=Silhouettes(masks), points=PointCloud(cloud)))   # (N,)
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from torchpf.camera import CameraRig
from torchpf.geometry import (
    Capsules2D,
    capsule_coverage,
    capsule_truncated_cost,
    outline_points,
    project_capsules,
    sample_in_capsules,
)
from torchpf.observations import DistanceMaps, Frame, Keypoints2D, PointCloud, Silhouettes

__all__ = [
    "ChamferLikelihood",
    "DualSilhouetteLikelihood",
    "Keypoints2DLikelihood",
    "Likelihood",
    "OverlapLikelihood",
    "PointCloudLikelihood",
    "ProductLikelihood",
    "SilhouetteLikelihood",
    "SkinBlobLikelihood",
]

# Within one ProductLikelihood call the terms share the forward kinematics of the same theta.
_FK_CACHE: contextvars.ContextVar[dict | None] = contextvars.ContextVar("torchpf_fk_cache", default=None)


def _tensor_key(t: torch.Tensor) -> tuple:
    # The flattened theta is a new view per term; its storage, layout and version identify the values.
    return (t.data_ptr(), tuple(t.shape), tuple(t.stride()), t._version, t.dtype, t.device)


class Likelihood(nn.Module):
    """Base class: skeleton handling, obs selection, flattening of the leading batch dims.

    Subclasses set ``obs_type`` (the container class) and ``obs_field`` (its name in :class:`Frame`) and
    implement ``_log_lik(theta (B, D), obs) -> (B,)``.
    """

    obs_type: type = object
    obs_field: str = ""

    def __init__(self, skeleton, bones: Sequence[int] | None = None):
        super().__init__()
        self.skeleton = skeleton
        self.bones = None if bones is None else list(bones)

    # -- helpers
    def _select(self, obs):
        if obs is None or isinstance(obs, self.obs_type):
            return obs
        if isinstance(obs, Frame):
            return getattr(obs, self.obs_field)
        if isinstance(obs, Mapping):
            return obs.get(self.obs_field)
        if isinstance(obs, torch.Tensor) and self.obs_type in (PointCloud, Silhouettes):
            return self.obs_type(obs)
        raise TypeError(
            f"{type(self).__name__} expects a {self.obs_type.__name__} or a Frame with field "
            f"{self.obs_field!r}, got {type(obs).__name__}"
        )

    def _capsules(self, theta: torch.Tensor):
        """(B, D) -> a, b (B, C, 3), radii (C,), shared with other terms inside a ProductLikelihood."""
        cache = _FK_CACHE.get()
        key = ("caps", id(self.skeleton), *_tensor_key(theta), tuple(self.bones or ()))
        if cache is not None and key in cache:
            return cache[key]
        ends, radii = self.skeleton.capsules(theta)
        if self.bones is not None:
            ends, radii = ends[:, self.bones], radii[self.bones]
        out = (ends[..., 0, :], ends[..., 1, :], radii.to(ends))
        if cache is not None:
            cache[key] = out
        return out

    def _joints(self, theta: torch.Tensor) -> torch.Tensor:
        cache = _FK_CACHE.get()
        key = ("fk", id(self.skeleton), *_tensor_key(theta))
        if cache is not None and key in cache:
            return cache[key]
        out = self.skeleton.fk(theta)
        if cache is not None:
            cache[key] = out
        return out

    def forward(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """Log-likelihood (..., N) of poses ``theta`` (..., N, D) given one frame's ``obs``."""
        sel = self._select(obs)
        batch = theta.shape[:-1]
        if sel is None:
            return theta.new_zeros(batch)
        flat = theta.reshape(-1, theta.shape[-1])
        return self._log_lik(flat, sel, batch).reshape(batch)

    def _log_lik(self, theta: torch.Tensor, obs, batch) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError


# ---------------------------------------------------------------------- point cloud
class PointCloudLikelihood(Likelihood):
    """Hauberg et al. eq. 15: ``log p(Z | theta) = -sum_k min(D^2(theta, z_k), tau) / (2 sigma^2)``.

    Args:
        skeleton: provides ``capsules(theta)``.
        sigma: standard deviation (m) of the point-to-skin distance.
        tau: truncation of ``D^2`` (m^2) that makes outliers cost a constant; default ``(3 sigma)^2``.
        view_point: (3,) sensor position (m) or a :class:`~torchpf.camera.Camera` (its centre): score
            against the half-capsules facing the sensor (Hauberg §5); None scores full capsules.
        bones: optional subset of capsule indices (e.g. drop fingers and toes for speed).
        chunk_size: poses per chunk of the distance kernel (memory bound; see ``capsule_distance``).
        compile: fuse the distance kernel with ``torch.compile`` (about 2x faster on CPU after a one-off
            compilation of 10-20 s; see ``capsule_truncated_cost``).

    obs: :class:`~torchpf.observations.PointCloud` with ``points`` (K, 3), or a (K, 3) tensor.
    Cost: O(N K C) in chunks of ~2^20 pose-capsule-point triples; memory O(N) beyond the chunk.
    """

    obs_type = PointCloud
    obs_field = "points"

    def __init__(
        self,
        skeleton,
        *,
        sigma: float = 0.02,
        tau: float | None = None,
        view_point=None,
        bones: Sequence[int] | None = None,
        chunk_size: int | None = None,
        compile: bool = False,
    ):
        super().__init__(skeleton, bones)
        self.compile = bool(compile)
        self.sigma = float(sigma)
        self.tau = float(tau) if tau is not None else (3 * self.sigma) ** 2
        if view_point is not None and hasattr(view_point, "center"):
            view_point = view_point.center
        if view_point is not None:
            self.register_buffer("view_point", torch.as_tensor(view_point, dtype=torch.float64).reshape(3))
        else:
            self.view_point = None
        self.chunk_size = chunk_size

    def _log_lik(self, theta, obs: PointCloud, batch):
        a, b, r = self._capsules(theta)
        pts = obs.points.to(a)
        if pts.shape[-2] == 0:
            return a.new_zeros(a.shape[0])
        if pts.ndim > 2:
            # (..., K, 3) clouds go with theta's leading dims (one cloud per sequence, shared by its N).
            pts = pts.unsqueeze(-3).expand(*batch, *pts.shape[-2:]).reshape(-1, *pts.shape[-2:])
        tau = self.tau
        view = None if self.view_point is None else self.view_point.to(a)
        ssq = capsule_truncated_cost(
            pts, a, b, r, tau=tau, view_point=view, chunk_size=self.chunk_size, compile=self.compile
        )
        return -ssq / (2 * self.sigma**2)


# ---------------------------------------------------------------------- image cues
class _ImageLikelihood(Likelihood):
    """Shared machinery of the image cues: the cameras (a :class:`~torchpf.camera.CameraRig`, its buffers
    move with the module), projection into the observation's pixel grid, bilinear look-ups."""

    def __init__(self, skeleton, cameras, bones=None):
        super().__init__(skeleton, bones)
        self.cameras = CameraRig(cameras)  # the likelihood's own copy: moving it leaves the caller's alone
        if not len(self.cameras):
            raise ValueError("at least one camera is needed")

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    def distances(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """The per-camera distances ``D_l`` of the cue (its class docstring says what and in which units; 0
        is best): ``(..., N, D) -> (..., N, V)``. Silhouette, dual-silhouette and skin-blob cues have them."""
        obs = self._select(obs)
        batch = theta.shape[:-1]
        return self._distances(theta.reshape(-1, theta.shape[-1]), obs).reshape(*batch, -1)

    def _distances(self, theta: torch.Tensor, obs) -> torch.Tensor:
        raise NotImplementedError(f"{type(self).__name__} has no per-camera distances")

    def _caps2d(self, a, b, r, height: int, width: int) -> list[Capsules2D]:
        """Capsules (B, C) projected into each of the V cameras, in the pixel frame of a ``height x width``
        observation (the cameras resized to it)."""
        caps = project_capsules(self.cameras.resized(width, height), a, b, r)  # (B, V, C)
        return caps.unbind(caps.valid.ndim - 2)

    def _check_cameras(self, n: int, what: str):
        if n != self.n_cameras:
            raise ValueError(
                f"{type(self).__name__}: {what} has {n} cameras, the likelihood {self.n_cameras}"
            )


def _lookup(image: torch.Tensor, uv: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Look-up of one (H, W) image at (..., 2) pixel coords (u, v), "bilinear" or "nearest"; 0 outside."""
    H, W = image.shape
    shape = uv.shape[:-1]
    grid = torch.stack([(2 * uv[..., 0] + 1) / W - 1, (2 * uv[..., 1] + 1) / H - 1], -1).reshape(1, 1, -1, 2)
    out = F.grid_sample(image.to(uv)[None, None], grid, mode=mode, padding_mode="zeros", align_corners=False)
    return out.reshape(shape)


def _distance_lookup(dist: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Distance-image look-up that keeps growing outside the image: value at the nearest border pixel plus
    the distance to it, so a marker that leaves the image is not mistaken for a close one."""
    H, W = dist.shape
    u = uv[..., 0].clamp(0, W - 1)
    v = uv[..., 1].clamp(0, H - 1)
    inside = torch.stack([u, v], -1)
    extra = (uv - inside).square().sum(-1).clamp_min(1e-12).sqrt() * ((uv - inside).abs().sum(-1) > 0)
    grid = torch.stack([(2 * u + 1) / W - 1, (2 * v + 1) / H - 1], -1).reshape(1, 1, -1, 2)
    val = F.grid_sample(
        dist.to(uv)[None, None], grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    return val.reshape(uv.shape[:-1]) + extra


# ---------------------------------------------------------------------- silhouettes
class SilhouetteLikelihood(_ImageLikelihood):
    """Fontmarty et al. eq. 2: ``log p = -sum_l D_l^2 / (2 sigma^2)``, ``D_l = (1/N_p) sum_i (1 - I_l(p_i))``
    with ``p_i`` spread uniformly over the projected model in camera ``l``.

    Model points: per capsule ``n_body + 2 n_cap`` points of a fixed pattern (``sample_in_capsules``),
    each standing for its share of the capsule's area, so ``D_l`` is an area-weighted mean. ``union=True``
    divides each weight by the number of capsules covering its point, i.e. samples the union of capsules
    uniformly (overlaps are not counted twice) at the cost of a coverage test per point.

    Args:
        skeleton, cameras: the body model; a :class:`~torchpf.camera.CameraRig` or list of cameras, in the
            order of the masks' ``V`` axis.
        sigma: the paper's sigma_s1 (0.1 in Fontmarty et al.).
        interpolation: mask look-up at the model points. "bilinear" (default) ramps the binary mask
            linearly across one pixel at its boundary, so the cue is continuous and has a gradient in
            theta; "nearest" counts whole pixels.
        blur: optional Gaussian blur (pixels of the mask grid) applied once per frame before the look-ups.
            It widens the basin of attraction but erodes thin limbs (a 4-pixel forearm loses its
            plateau at 1 pixel of blur), which biases the peak at low resolution: 0 by default.
        generator: None (fixed pattern, deterministic) or a generator for fresh random points per call.

    obs: :class:`~torchpf.observations.Silhouettes` (V, H, W).
    """

    obs_type = Silhouettes
    obs_field = "silhouettes"

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        sigma: float = 0.1,
        n_body: int = 8,
        n_cap: int = 2,
        blur: float = 0.0,
        interpolation: str = "bilinear",
        union: bool = False,
        bones: Sequence[int] | None = None,
        generator: torch.Generator | None = None,
    ):
        super().__init__(skeleton, cameras, bones)
        if interpolation not in ("bilinear", "nearest"):
            raise ValueError(f"interpolation must be 'bilinear' or 'nearest', got {interpolation!r}")
        self.sigma, self.n_body, self.n_cap, self.blur = float(sigma), int(n_body), int(n_cap), float(blur)
        self.interpolation, self.union, self.generator = interpolation, bool(union), generator

    def _model_points(self, caps: Capsules2D):
        pts, w = sample_in_capsules(caps, self.n_body, self.n_cap, generator=self.generator)
        if self.union:
            M = self.n_body + 2 * self.n_cap
            others = capsule_coverage(pts, caps, reduce="sum", exclude_own=M)
            w = w / (1.0 + others)
        return pts, w

    def _distances(self, theta, obs: Silhouettes):
        self._check_cameras(obs.masks.shape[0], "the observation")
        a, b, r = self._capsules(theta)
        images = obs.blurred(self.blur)
        out = []
        for v, caps in enumerate(self._caps2d(a, b, r, obs.height, obs.width)):
            pts, w = self._model_points(caps)
            inside = _lookup(images[v], pts, self.interpolation)
            total = w.sum(-1).clamp_min(1e-9)
            out.append(1.0 - (w * inside).sum(-1) / total)
        return torch.stack(out, -1)

    def _log_lik(self, theta, obs: Silhouettes, batch):
        D = self._distances(theta, obs)
        D = D * obs.valid.to(D.device)
        return -(D * D).sum(-1) / (2 * self.sigma**2)


class DualSilhouetteLikelihood(_ImageLikelihood):
    """Fontmarty et al. §3.2.2: ``D_l = (1/N_s) sum_j (1 - f(p_j, theta))``,
    ``log p = -sum_l D_l^2 / 2 sigma^2``; ``p_j`` are ``n_samples`` fixed stratified foreground points per
    mask, ``f`` = 1 where the projected model covers ``p_j``.

    Args:
        sigma: the paper's sigma_s2 (0.07 in Fontmarty et al.).
        n_samples: N_s per camera.
        softness: 0 for the paper's hard 0/1 coverage; > 0 (pixels) ramps coverage across each capsule
            boundary so the cue has a gradient.

    obs: :class:`~torchpf.observations.Silhouettes`. A camera with an empty mask contributes 0.
    """

    obs_type = Silhouettes
    obs_field = "silhouettes"

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        sigma: float = 0.07,
        n_samples: int = 128,
        softness: float = 0.0,
        bones: Sequence[int] | None = None,
    ):
        super().__init__(skeleton, cameras, bones)
        self.sigma, self.n_samples, self.softness = float(sigma), int(n_samples), float(softness)

    def _distances(self, theta, obs: Silhouettes):
        self._check_cameras(obs.masks.shape[0], "the observation")
        a, b, r = self._capsules(theta)
        fg, ok = obs.foreground_samples(self.n_samples)
        out = []
        for v, caps in enumerate(self._caps2d(a, b, r, obs.height, obs.width)):
            if not bool(ok[v]):
                out.append(a.new_zeros(a.shape[0]))
                continue
            cov = capsule_coverage(fg[v].to(a), caps, softness=self.softness)
            out.append(1.0 - cov.mean(-1))
        return torch.stack(out, -1)

    def _log_lik(self, theta, obs: Silhouettes, batch):
        D = self._distances(theta, obs)
        return -(D * D).sum(-1) / (2 * self.sigma**2)


class OverlapLikelihood(SilhouetteLikelihood):
    """Rius et al. eq. 7: ``p ∝ |model ∩ mask| / |model ∪ mask|`` per camera;
    ``log p = beta * sum_l log(max(ratio_l, eps))``.

    Areas (pixels of the mask grid): ``|model ∩ mask|`` and ``|model|`` from the model points of
    :class:`SilhouetteLikelihood` with ``union=True`` weights (overlapping capsules counted once), ``|mask|``
    from the mask; ``|model ∪ mask| = |model| + |mask| - |model ∩ mask|``.

    Args:
        beta: exponent (sharpness) of the ratio; 1 is the paper's likelihood.
        eps: floor of the ratio, so that a pose missing every mask is very unlikely but not impossible.
        n_body, n_cap, blur, generator: as in :class:`SilhouetteLikelihood`.
        interpolation: "nearest" (default) counts whole mask pixels, like the paper's pixel sums; the
            likelihood stays differentiable through the model's area. "bilinear" also moves with the
            points but under-counts the intersection along the boundary (~5 % for 4-pixel limbs).
    """

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        beta: float = 1.0,
        eps: float = 1e-3,
        n_body: int = 8,
        n_cap: int = 2,
        blur: float = 0.0,
        interpolation: str = "nearest",
        bones: Sequence[int] | None = None,
        generator: torch.Generator | None = None,
    ):
        super().__init__(
            skeleton,
            cameras,
            n_body=n_body,
            n_cap=n_cap,
            blur=blur,
            interpolation=interpolation,
            union=True,
            bones=bones,
            generator=generator,
        )
        self.beta, self.eps = float(beta), float(eps)

    def ratios(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """(..., N, V) overlap ratios |model ∩ mask| / |model ∪ mask| in [0, 1]."""
        obs = self._select(obs)
        batch = theta.shape[:-1]
        return self._ratios(theta.reshape(-1, theta.shape[-1]), obs).reshape(*batch, -1)

    def _ratios(self, theta, obs: Silhouettes):
        self._check_cameras(obs.masks.shape[0], "the observation")
        a, b, r = self._capsules(theta)
        images = obs.blurred(self.blur)
        area = obs.area().to(a)
        out = []
        for v, caps in enumerate(self._caps2d(a, b, r, obs.height, obs.width)):
            pts, w = self._model_points(caps)
            inter = (w * _lookup(images[v], pts, self.interpolation)).sum(-1)
            union = w.sum(-1) + area[v] - inter
            out.append(inter / union.clamp_min(1e-9))
        return torch.stack(out, -1)

    def _log_lik(self, theta, obs: Silhouettes, batch):
        ratio = self._ratios(theta, obs)
        logr = torch.log(ratio.clamp_min(self.eps)) * obs.valid.to(ratio.device)
        return self.beta * logr.sum(-1)


# ---------------------------------------------------------------------- 2D points
def _resolve_joints(skeleton, joints) -> list[int]:
    names = list(skeleton.joint_names)
    if joints is None:
        return list(range(len(names)))
    out = []
    for j in joints:
        if isinstance(j, int):
            out.append(j)
        elif j in names:
            out.append(names.index(j))
        else:
            raise ValueError(f"unknown joint {j!r}; the skeleton has {names}")
    return out


class Keypoints2DLikelihood(_ImageLikelihood):
    """Brubaker et al. eq. 3-4: ``log p = sum_{l, i visible} log p_i(m_{l,i} - P_l(X_i(theta)))``.

    Noise ``p_i``: ``"gaussian"`` (eq. 4, isotropic, ``sigma`` pixels) or ``"student"`` (bivariate
    Student-t with ``dof`` degrees of freedom and scale ``sigma``: heavy tails for unreliable detections).
    Both are normalised densities, so the value compares across frames with different visible counts.

    Args:
        joints: joint names (or indices) the detections refer to, in the obs ``J`` order; default all
            ``skeleton.joint_names``.
        sigma: pixels, in the observation's pixel frame (``image_size``).
        image_size: (width, height) of the detections' pixel frame per camera if not the cameras' own.

    obs: :class:`~torchpf.observations.Keypoints2D` (V, J, 2), NaN or ``visible=False`` for missing ones.
    """

    obs_type = Keypoints2D
    obs_field = "keypoints"

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        joints: Sequence[str | int] | None = None,
        sigma: float = 4.0,
        noise: str = "gaussian",
        dof: float = 3.0,
        image_size: tuple[int, int] | None = None,
    ):
        super().__init__(skeleton, cameras)
        if noise not in ("gaussian", "student"):
            raise ValueError(f"noise must be 'gaussian' or 'student', got {noise!r}")
        self.joint_index = _resolve_joints(skeleton, joints)
        self.sigma, self.noise, self.dof = float(sigma), noise, float(dof)
        self.image_size = image_size

    def _log_lik(self, theta, obs: Keypoints2D, batch):
        self._check_cameras(obs.uv.shape[0], "the observation")
        if obs.uv.shape[1] != len(self.joint_index):
            raise ValueError(f"obs has {obs.uv.shape[1]} points per camera, expected {len(self.joint_index)}")
        X = self._joints(theta)[:, self.joint_index]  # (B, J, 3)
        rig = self.cameras if self.image_size is None else self.cameras.resized(*self.image_size)
        uv = rig.project(X)  # (B, J, V, 2)
        d2 = (uv - obs.uv.transpose(0, 1).to(uv)).square().sum(-1)  # (B, J, V)
        s2 = self.sigma**2
        if self.noise == "gaussian":
            lp = -d2 / (2 * s2) - math.log(2 * math.pi * s2)
        else:
            nu = self.dof
            lp = (
                math.lgamma((nu + 2) / 2)
                - math.lgamma(nu / 2)
                - math.log(nu * math.pi * s2)
                - (nu + 2) / 2 * torch.log1p(d2 / (nu * s2))
            )
        return (lp * obs.visible.transpose(0, 1).to(lp.device)).sum((-1, -2))


# ---------------------------------------------------------------------- distance images
# Head and hands of the shipped models: human.urdf (CMU names) and fontmarty22.urdf.
_DEFAULT_MARKERS = (
    (("Head", "Head_end"), "LeftHand", "RightHand"),
    (("neck", "head_top"), "l_wrist", "r_wrist"),
)


class SkinBlobLikelihood(_ImageLikelihood):
    """Fontmarty et al. §3.2.3: ``D_l = (1/3) sum_i I_skin_dist(p_i)``, ``log p = -sum_l D_l^2 / 2 sigma^2``
    with ``p_i`` the projections of virtual markers on the head and hands (``D_l`` in pixels of the distance
    image).

    Args:
        markers: one entry per virtual marker: a joint name (or index), or a tuple of joints whose mean
            position is the marker (the head centre lies between two joints). Default: head centre and
            both wrists of ``human.urdf`` (``(("Head", "Head_end"), "LeftHand", "RightHand")``) or of
            ``fontmarty22.urdf``, whichever names the skeleton has.
        sigma: pixels of the distance image (5 in Fontmarty et al.).

    obs: :class:`~torchpf.observations.DistanceMaps` (V, H, W) distances to the nearest skin blob
    (``DistanceMaps.from_features(skin_masks)``).
    """

    obs_type = DistanceMaps
    obs_field = "skin"

    def __init__(self, skeleton, cameras, *, markers=None, sigma: float = 5.0):
        super().__init__(skeleton, cameras)
        if markers is None:
            names = set(skeleton.joint_names)
            flat = [[m] if isinstance(m, str) else list(m) for m in _DEFAULT_MARKERS[0]]
            for cand in _DEFAULT_MARKERS:
                if all(n in names for m in cand for n in ([m] if isinstance(m, str) else m)):
                    markers = cand
                    break
            else:
                raise ValueError(f"pass markers=...: the skeleton has none of the default joints {flat}")
        groups = [_resolve_joints(skeleton, [m] if isinstance(m, (str, int)) else m) for m in markers]
        # Marker positions = (J, M) averaging matrix applied to the joints.
        A = torch.zeros(len(skeleton.joint_names), len(groups), dtype=torch.float64)
        for i, g in enumerate(groups):
            A[g, i] = 1.0 / len(g)
        self.register_buffer("marker_matrix", A)
        self.sigma = float(sigma)

    def markers(self, theta: torch.Tensor) -> torch.Tensor:
        """(..., D) -> (..., M, 3) world positions of the virtual markers."""
        J = self._joints(theta)
        return torch.einsum("...jk,jm->...mk", J, self.marker_matrix.to(J))

    def _distances(self, theta, obs: DistanceMaps):
        self._check_cameras(obs.distance.shape[0], "the observation")
        X = self.markers(theta)
        H, W = obs.distance.shape[-2:]
        uv = self.cameras.resized(W, H).project(X)  # (B, M, V, 2)
        out = [_distance_lookup(obs.distance[v], uv[..., v, :]).mean(-1) for v in range(len(obs.distance))]
        return torch.stack(out, -1)

    def _log_lik(self, theta, obs: DistanceMaps, batch):
        D = self._distances(theta, obs) * obs.valid.to(theta.device)
        return -(D * D).sum(-1) / (2 * self.sigma**2)


class ChamferLikelihood(_ImageLikelihood):
    """Brubaker et al. eq. 9: ``log p = -(1/M) sum_i d(b_i)`` with ``d`` the squared distance to the nearest
    image edge and ``b_i`` points on the projected model's outline, here generalised to
    ``-(1/M) sum_i min(d(b_i), tau^2) / (2 sigma^2)`` summed over cameras (``sigma = 1/sqrt(2)`` and
    ``tau = inf`` give eq. 9 exactly; ``tau`` is the outlier rejection of Gavrila and Davis).

    Args:
        sigma, tau: pixels of the distance image.
        n_side, n_cap: outline points per capsule flank and per end arc.
        outline_only: drop outline points covered by another capsule, keeping the silhouette outline.

    obs: :class:`~torchpf.observations.DistanceMaps` (V, H, W) distances to the nearest edge pixel
    (``DistanceMaps.from_edges_of(images)``).
    """

    obs_type = DistanceMaps
    obs_field = "edges"

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        sigma: float = 2.0,
        tau: float = 20.0,
        n_side: int = 4,
        n_cap: int = 2,
        outline_only: bool = True,
        bones: Sequence[int] | None = None,
    ):
        super().__init__(skeleton, cameras, bones)
        self.sigma, self.tau = float(sigma), float(tau)
        self.n_side, self.n_cap, self.outline_only = int(n_side), int(n_cap), bool(outline_only)

    def _log_lik(self, theta, obs: DistanceMaps, batch):
        self._check_cameras(obs.distance.shape[0], "the observation")
        a, b, r = self._capsules(theta)
        H, W = obs.distance.shape[-2:]
        total = a.new_zeros(a.shape[0])
        M = 2 * self.n_side + 2 * self.n_cap
        for v, caps in enumerate(self._caps2d(a, b, r, H, W)):
            if not bool(obs.valid[v]):
                continue
            pts, ok = outline_points(caps, self.n_side, self.n_cap)
            w = ok.to(a.dtype)
            if self.outline_only:
                w = w * (1.0 - capsule_coverage(pts, caps, exclude_own=M))
            d2 = _distance_lookup(obs.distance[v], pts).square().clamp_max(self.tau**2)
            total = total - (w * d2).sum(-1) / w.sum(-1).clamp_min(1.0) / (2 * self.sigma**2)
        return total


# ---------------------------------------------------------------------- combination
class ProductLikelihood(nn.Module):
    """Product of independent cues (Fontmarty §3.2.4, Brubaker eq. 10) with per-term exponents:
    ``log p = sum_k w_k log p_k(theta, obs)``. An annealing exponent ``beta`` (APF layer) multiplies the
    whole sum, so it composes: ``beta * lik(theta, obs)``.

    Args:
        terms: name -> likelihood module (or a sequence, named "0", "1", ...).
        weights: name -> exponent (default 1 for each).

    obs: a :class:`~torchpf.observations.Frame` (or a dict of the same fields); each term picks its field
    and a missing field contributes 0. Forward kinematics is computed once per call and shared.
    """

    def __init__(self, terms, weights: Mapping[str, float] | Sequence[float] | None = None):
        super().__init__()
        if not isinstance(terms, Mapping):
            terms = {str(i): t for i, t in enumerate(terms)}
        self.terms = nn.ModuleDict(terms)
        if weights is None:
            weights = {k: 1.0 for k in terms}
        elif not isinstance(weights, Mapping):
            weights = dict(zip(terms, weights, strict=True))
        unknown = set(weights) - set(terms)
        if unknown:
            raise ValueError(f"weights for unknown terms {sorted(unknown)}")
        self.weights = {k: float(weights.get(k, 1.0)) for k in terms}

    def components(self, theta: torch.Tensor, obs) -> dict[str, torch.Tensor]:
        """Unweighted log-likelihood (..., N) of each term, for diagnostics and tuning."""
        with _shared_fk():
            return {k: term(theta, obs) for k, term in self.terms.items()}

    def forward(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """(..., N, D), Frame -> (..., N) weighted sum of the terms' log-likelihoods."""
        total = theta.new_zeros(theta.shape[:-1])
        with _shared_fk():
            for k, term in self.terms.items():
                w = self.weights[k]
                if w != 0:
                    total = total + w * term(theta, obs)
        return total


@contextlib.contextmanager
def _shared_fk():
    token = _FK_CACHE.set({}) if _FK_CACHE.get() is None else None
    try:
        yield
    finally:
        if token is not None:
            _FK_CACHE.reset(token)
