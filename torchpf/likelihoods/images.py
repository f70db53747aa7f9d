"""Image cues, batched over particles: silhouettes (Fontmarty eq. 2, §3.2.2; Rius eq. 7), skin blobs
(Fontmarty §3.2.3) and Chamfer edges (Brubaker eq. 9).

Each cue holds its cameras as a :class:`~torchpf.camera.CameraRig` (buffers that move with ``.to()``) and
works in the observation's pixel grid: masks may be smaller than the camera images (the rig is
:meth:`~torchpf.camera.CameraRig.resized` to them), which is how 640x480 cameras are scored on 160x120 masks.
Model points come from a fixed quasi-random pattern (:func:`torchpf.geometry.sample_pattern`) mapped into
every projected capsule, so a cue is a deterministic, smooth function of the pose unless a ``generator`` is
passed.

Example::

    from torchpf.likelihoods import SilhouetteLikelihood
    lik = SilhouetteLikelihood(skel, cameras, sigma=0.1)
    logw = lik(particles, Silhouettes(masks))                 # (..., N, D), (V, H, W) -> (..., N)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from torchpf.camera import CameraRig
from torchpf.geometry import (
    Capsules2D,
    capsule_area_mean,
    capsule_chamfer,
    capsule_coverage,
    distance_to_capsules,
    outline_points,
    project_capsules,
    sample_in_capsules,
)
from torchpf.geometry.chamfer import distance_lookup as _distance_lookup
from torchpf.geometry.chamfer import sample_image as _sample
from torchpf.likelihoods.base import LIKELIHOODS, Body, Likelihood, resolve_joints
from torchpf.observations import DistanceMaps, Silhouettes

__all__ = [
    "ChamferLikelihood",
    "DualSilhouetteLikelihood",
    "SilhouetteDistanceLikelihood",
    "ImageLikelihood",
    "OverlapLikelihood",
    "SilhouetteLikelihood",
    "SkinBlobLikelihood",
]


class ImageLikelihood(Likelihood):
    """Shared machinery of the image cues: the cameras (a :class:`~torchpf.camera.CameraRig`, its buffers
    move with the module), projection into the observation's pixel grid, bilinear look-ups."""

    needs_cameras = True

    def __init__(self, skeleton, cameras, bones=None):
        super().__init__(skeleton, bones)
        # a rig is held as given (edits and learnable parameters of the caller's rig take effect here), a
        # list of cameras is stacked into one
        self.cameras = cameras if isinstance(cameras, CameraRig) else CameraRig(cameras)
        if not len(self.cameras):
            raise ValueError("at least one camera is needed")

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    def distances(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """The per-camera distances ``D_l`` of the cue (its class docstring says what and in which units; 0
        is best): ``(..., N, D) -> (..., N, V)``. Silhouette, dual-silhouette and skin-blob cues have them."""
        body = self.body(theta)
        return self._distances(body, self.select(obs)).reshape(*body.batch, -1)

    def _distances(self, body: Body, obs) -> torch.Tensor:
        raise NotImplementedError(f"{type(self).__name__} has no per-camera distances")

    def camera_log_likelihoods(self, body: Body, obs) -> torch.Tensor:
        """(B, V) each camera's term of the log-likelihood, unweighted (a cue that sums per-camera terms)."""
        raise NotImplementedError(f"{type(self).__name__} has no per-camera terms")

    def _log_lik(self, body: Body, obs) -> torch.Tensor:
        """The sum of :meth:`camera_log_likelihoods` over the cameras, each weighted by the masks'
        :attr:`~torchpf.observations.Silhouettes.weight` where they have one."""
        terms = self.camera_log_likelihoods(body, obs)
        weight = getattr(obs, "weight", None)
        if weight is not None:
            terms = terms * body.rows(weight, 1).to(terms)
        return terms.sum(-1)

    def _caps2d(self, body: Body, S: int, height: int, width: int, offset=None) -> Capsules2D:
        """The cue's capsules (:attr:`bones`) projected into the V cameras, in the pixel frame of a
        ``height x width`` observation (the cameras resized to it), camera-major: ``(S, V, N, C)`` for the
        B = S N poses of ``S`` sequences (S = 1: one observation for all). In this layout one ``grid_sample``
        of the (S, V, H, W) images, or one matrix product per camera, serves every camera
        (:func:`_sample`, :func:`~torchpf.geometry.capsule_coverage`). ``offset``: the masks' outline offset
        ``(*S, V)`` pixels (:attr:`Silhouettes.offset`) added to every projected radius (kept >= 0.5 px); a
        capsule whose radii both fall to 0.5 px or less is marked invalid in that camera."""
        rig = self.cameras.resized(width, height)

        def project():
            caps = project_capsules(rig, *body.capsules(self.bones))  # (B, V, C)
            return tuple(_camera_major(f, S) for f in (caps.pa, caps.pb, caps.ra, caps.rb, caps.valid))

        # computed once for the cues of a product likelihood that project the same bones into the same rig
        bones = None if self.bones is None else tuple(self.bones)
        pa, pb, ra, rb, valid = body.shared(("caps2d", bones, S), rig, project)
        if offset is not None:
            off = _per_camera(offset.to(ra), S, 0).unsqueeze(-1)  # (S, V, 1, 1)
            ra, rb = ra + off, rb + off
            # an erosion wipes out what is thinner than it (a limb of half-width < |offset|): the mask cannot
            # show such a capsule, so the cue must neither look for it nor pull it onto what is left
            valid = valid & ((ra > 0.5) | (rb > 0.5))
            ra, rb = ra.clamp_min(0.5), rb.clamp_min(0.5)
        return Capsules2D(pa, pb, ra, rb, valid)

    @torch.no_grad()
    def boundary_offset(
        self, pose: torch.Tensor, obs: Silhouettes, *, limit: float = 2.0, despeckle: int = 3
    ):
        """The masks' outline offset (:attr:`Silhouettes.offset`, pixels) measured against this cue's body at
        a reference ``pose`` ``(*S, D)`` (the previous frame's estimate): per camera, the ``delta`` such that
        the projected capsules widened by ``delta`` cover as many pixels as the (``despeckle``-median
        filtered) mask, i.e. ``#{pixels : d(p) <= delta} = area`` with ``d`` the signed distance to the
        capsules' union: a quantile of ``d``. Matching areas, not outlines, keeps it blind to where the
        body is (a pose error moves the model, not its area, up to self-occlusion), and to the pose
        itself. Clamped to ``[-limit, limit]``; 0 for an empty or invalid mask.

        Returns:
            ``(*S, V)`` offsets in the masks' dtype and device (:meth:`Silhouettes.with_offset` takes them).
        """
        obs = self.select(obs).despeckled(despeckle)
        pose = torch.as_tensor(pose)
        lead = tuple(obs.masks.shape[:-3])
        S = math.prod(lead)
        body = self.body(pose.reshape(S, 1, pose.shape[-1]).to(self.skeleton.lower))
        H, W = obs.height, obs.width
        caps = self._caps2d(body, S, H, W)  # (S, V, 1, C)
        # only pixels within `limit` of the model can be its k-th nearest: those of each camera's box around
        # the capsules (one box size for all, offset per camera); the rest count as beyond the limit
        reach = torch.maximum(caps.ra, caps.rb).unsqueeze(-1) + limit + 1.0
        ends = torch.stack([caps.pa, caps.pb], -2)  # (S, V, 1, C, 2, 2)
        big = torch.where(caps.valid[..., None, None], ends, math.inf)
        lo = (torch.minimum(big[..., 0, :], big[..., 1, :]) - reach).amin(-2).floor()  # (S, V, 1, 2)
        small = torch.where(caps.valid[..., None, None], ends, -math.inf)
        hi = (torch.maximum(small[..., 0, :], small[..., 1, :]) + reach).amax(-2).ceil()
        seen = caps.valid.any(-1)  # (S, V, 1): some capsule in front of the camera
        size = lo.new_tensor([W, H])
        lo = torch.where(seen.unsqueeze(-1), lo.clamp(min=0).minimum(size - 1), 0.0)
        hi = torch.where(seen.unsqueeze(-1), hi.minimum(size - 1).maximum(lo), 0.0)
        bw, bh = (int(v) + 1 for v in (hi - lo).amax((0, 1, 2)).tolist())
        vv, uu = torch.meshgrid(torch.arange(bh), torch.arange(bw), indexing="ij")
        grid = lo.unsqueeze(-2) + torch.stack([uu, vv], -1).reshape(-1, 2).to(lo)  # (S, V, 1, P, 2)
        d = distance_to_capsules(grid, caps, signed=True)
        in_image = ((grid >= 0) & (grid <= size - 1)).all(-1)
        d = torch.where(in_image & torch.isfinite(d), d, 2.0 * limit + 1.0).squeeze(-2)  # (S, V, P)
        area = (obs.masks > 0.5).reshape(S, -1, H * W).sum(-1)  # (S, V)
        ranked = d.sort(-1).values
        k = area.clamp(1, d.shape[-1]) - 1
        delta = ranked.gather(-1, k.unsqueeze(-1)).squeeze(-1)
        delta = torch.where(area > d.shape[-1], limit, delta).clamp(-limit, limit)
        ok = (area > 0) & obs.valid.reshape(S, -1).to(area.device) & seen.squeeze(-1)
        return torch.where(ok, delta, 0.0).reshape(*lead, -1).to(obs.masks)

    def _check_cameras(self, images: torch.Tensor, body: Body, event_dims: int = 3) -> int:
        """``images`` (..., V, *event) must have the likelihood's V cameras and leading dims that batch the
        poses (:meth:`Body.check_batch`); returns S, the number of observations (1 without leading dims)."""
        n = images.shape[-event_dims]
        if n != self.n_cameras:
            raise ValueError(
                f"{type(self).__name__}: the observation has {n} cameras, the likelihood {self.n_cameras}"
            )
        lead = images.shape[:-event_dims]
        body.check_batch(lead)
        return math.prod(lead)


def _camera_major(t: torch.Tensor, S: int) -> torch.Tensor:
    """Per-pose, per-camera values ``(B, V, *e)`` of B = S N poses -> ``(S, V, N, *e)``, contiguous."""
    return t.reshape(S, -1, *t.shape[1:]).transpose(1, 2).contiguous()


def _pose_major(t: torch.Tensor) -> torch.Tensor:
    """Camera-major ``(S, V, N)`` -> ``(B, V)`` with B = S N, the rows of :class:`Body`."""
    return t.transpose(1, 2).reshape(-1, t.shape[1])


def _per_camera(t: torch.Tensor, S: int, event_dims: int) -> torch.Tensor:
    """An observation tensor ``(*S, V, *event)`` (or ``(V, *event)``) -> ``(S, V, 1, *event)``: broadcasts
    against camera-major ``(S, V, N, ...)`` values."""
    return t.reshape(S, *t.shape[t.ndim - event_dims - 1 :]).unsqueeze(2)


def _foreground(obs: Silhouettes, n: int, S: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The masks' ``n`` fixed foreground samples (:meth:`Silhouettes.foreground_samples`) shaped to broadcast
    against camera-major ``(S, V, N, ...)`` values: points ``(S, V, 1, n, 2)`` in ``like``'s dtype and
    device, ``ok (S, V, 1)`` False for a camera without samples (empty or invalid mask)."""
    fg, ok = obs.foreground_samples(n)
    return _per_camera(fg.to(like), S, 2), _per_camera(ok.to(like.device), S, 0)


@LIKELIHOODS.register("silhouette")
class SilhouetteLikelihood(ImageLikelihood):
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
        learnable: ``True`` (or ``["sigma"]``) makes ``sigma`` an ``nn.Parameter`` (see :class:`Likelihood`).

    obs: :class:`~torchpf.observations.Silhouettes` (V, H, W).
    """

    obs_type = Silhouettes
    obs_field = "silhouettes"
    scales = ("sigma",)

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
        learnable: bool | Sequence[str] = False,
    ):
        super().__init__(skeleton, cameras, bones)
        if interpolation not in ("bilinear", "nearest"):
            raise ValueError(f"interpolation must be 'bilinear' or 'nearest', got {interpolation!r}")
        self.scale_parameter("sigma", sigma, learnable)
        self.n_body, self.n_cap, self.blur = int(n_body), int(n_cap), float(blur)
        self.interpolation, self.union, self.generator = interpolation, bool(union), generator

    def _model_points(self, caps: Capsules2D):
        pts, w = sample_in_capsules(caps, self.n_body, self.n_cap, generator=self.generator)
        if self.union:
            M = self.n_body + 2 * self.n_cap
            others = capsule_coverage(pts, caps, reduce="sum", exclude_own=M)
            w = w / (1.0 + others)
        return pts, w

    def _distances(self, body, obs: Silhouettes):
        S = self._check_cameras(obs.masks, body)
        caps = self._caps2d(body, S, obs.height, obs.width, obs.offset)  # (S, V, N, C)
        if not self.union and self.generator is None and self.interpolation == "bilinear":
            # the fixed pattern's weighted mean in one call (a fused kernel on a CPU without autograd)
            image = obs.blurred(self.blur).to(caps.pa)
            return _pose_major(1.0 - capsule_area_mean(caps, image, self.n_body, self.n_cap))
        pts, w = self._model_points(caps)  # (S, V, N, P, 2)
        inside = _sample(obs.blurred(self.blur), pts, self.interpolation)
        return _pose_major(1.0 - (w * inside).sum(-1) / w.sum(-1).clamp_min(1e-9))

    def camera_log_likelihoods(self, body, obs: Silhouettes):
        D = self._distances(body, obs)
        D = D * body.rows(obs.valid, 1).to(D.device)
        return -(D * D) / (2 * self.sigma**2)


@LIKELIHOODS.register("dual_silhouette")
class DualSilhouetteLikelihood(ImageLikelihood):
    """Fontmarty et al. §3.2.2: ``D_l = (1/N_s) sum_j (1 - f(p_j, theta))``,
    ``log p = -sum_l D_l^2 / 2 sigma^2``; ``p_j`` are ``n_samples`` fixed stratified foreground points per
    mask, ``f`` = 1 where the projected model covers ``p_j``.

    Args:
        sigma: the paper's sigma_s2 (0.07 in Fontmarty et al.).
        n_samples: N_s per camera.
        softness: 0 for the paper's hard 0/1 coverage; > 0 (pixels) ramps coverage across each capsule
            boundary so the cue has a gradient.
        learnable: ``True`` (or ``["sigma"]``) makes ``sigma`` an ``nn.Parameter``.

    obs: :class:`~torchpf.observations.Silhouettes`. A camera with an empty mask contributes 0.
    """

    obs_type = Silhouettes
    obs_field = "silhouettes"
    scales = ("sigma",)

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        sigma: float = 0.07,
        n_samples: int = 128,
        softness: float = 0.0,
        bones: Sequence[int] | None = None,
        learnable: bool | Sequence[str] = False,
    ):
        super().__init__(skeleton, cameras, bones)
        self.scale_parameter("sigma", sigma, learnable)
        self.n_samples, self.softness = int(n_samples), float(softness)

    def _distances(self, body, obs: Silhouettes):
        S = self._check_cameras(obs.masks, body)
        caps = self._caps2d(body, S, obs.height, obs.width, obs.offset)  # (S, V, N, C)
        fg, ok = _foreground(obs, self.n_samples, S, caps.pa)
        cov = capsule_coverage(fg, caps, softness=self.softness)  # (S, V, N, n)
        # a camera without foreground samples (empty or invalid mask) contributes 0
        return _pose_major(torch.where(ok, 1.0 - cov.mean(-1), 0.0))

    def camera_log_likelihoods(self, body, obs: Silhouettes):
        D = self._distances(body, obs)
        return -(D * D) / (2 * self.sigma**2)


@LIKELIHOODS.register("silhouette_distance")
class SilhouetteDistanceLikelihood(ImageLikelihood):
    """Two-sided distance-transform silhouette cue: a symmetric chamfer distance between the projected model
    and the mask, whose gradient is informative away from the silhouette's boundary (the cue of the local
    optimisation in Gall et al., IJCV 2010, §4; :mod:`torchpf.refine`).

    Per camera ``l`` (pixels of the mask grid)::

        E_l = sum_i w_i rho(d_mask(p_i)) / sum_i w_i + (1 / N_s) sum_j rho(d_model(q_j))
        rho(d) = min(d, tau)^2 + 2 a min(d, tau)                  a = linear
        log p = -sum_l E_l / (2 sigma^2)

    ``p_i`` are the model's area points with their areas ``w_i`` (the pattern of
    :class:`SilhouetteLikelihood`), ``d_mask`` the distance to the mask (0 inside,
    :meth:`~torchpf.observations.Silhouettes.outside_distance`): model outside the silhouette; ``q_j`` the
    ``N_s`` foreground samples of :class:`DualSilhouetteLikelihood`, ``d_model`` their distance to the
    projected capsules (0 inside, :func:`~torchpf.geometry.distance_to_capsules`): silhouette not covered.
    Where Fontmarty's two cues count the share of points on the wrong side (flat away from the boundary),
    this one measures how far they are, so a limb one limb-width off is pulled back. ``tau`` bounds what one
    point can cost (a mask defect, a spurious blob); beyond it the point no longer pulls.

    Args:
        sigma: pixels; a camera costs one nat at ``E_l = 2 sigma^2`` (with ``linear = 0``: an RMS point
            distance of ``sigma``; scale it with the mask size).
        linear: pixels; ``a`` above, the linear part of ``rho``. A squared distance alone has no slope at
            the mask's boundary: a body shifted by half a pixel costs almost nothing (0.001 nats per cm on
            the test suite's renders), so the cue is flat around its optimum and the refinement's Adam
            steps, normalised by the gradient's size, walk along it (on foreign renders it moved the whole
            body ~2 cm down from the true pose). With ``a = 4`` a point just outside costs ``8 d``: the same
            shift costs 30x more. On the foreign renders of 11 CMU clips (``track``'s defaults, 2 runs)
            clean masks 43 -> 38 mm, noisy ones 119 -> 104 mm over three draws of their defects; ``a`` = 2
            and 8 were no better (BENCHMARKS.md). 0 gives the plain squared distance.
        tau: pixels; truncation of each point's distance. 6 (about a limb's width at 160x120) was better
            than 10 and 20 on foreign renders with mask defects (a limb missing from one camera, merged
            limbs: a point beyond ``tau`` no longer pulls) and no worse on clean ones (BENCHMARKS.md).
        n_body, n_cap: model area points per capsule body / end cap.
        n_samples: ``N_s`` foreground samples per camera.
        despeckle: median filter size (pixels) applied to the masks first
            (:meth:`~torchpf.observations.Silhouettes.despeckled`); 1 (the default) turns it off. A stray
            foreground pixel within ``tau`` pulls a distance cue, but a 3x3 median also wipes out a limb
            that a segmentation's erosion has thinned to 1-2 pixels, and the cue then pulls the model's limb
            into the torso. On the noisy foreign renders (11 CMU clips x 2 runs, ``track``'s defaults) the
            tracker's error fell from 140 to 111 mm without it, and on clean ones stayed at 46 mm
            (BENCHMARKS.md).

    obs: :class:`~torchpf.observations.Silhouettes` (V, H, W), or (S, V, H, W) for ``S`` sequences. A camera
    with an empty or invalid mask contributes 0.
    """

    obs_type = Silhouettes
    obs_field = "silhouettes"
    scales = ("sigma",)

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        sigma: float = 2.0,
        tau: float = 6.0,
        n_body: int = 8,
        n_cap: int = 2,
        n_samples: int = 128,
        despeckle: int = 1,
        linear: float = 4.0,
        bones: Sequence[int] | None = None,
        learnable: bool | Sequence[str] = False,
    ):
        super().__init__(skeleton, cameras, bones)
        self.despeckle = int(despeckle)
        if not (sigma > 0 and tau > 0):
            raise ValueError(f"sigma and tau must be positive pixels, got sigma={sigma}, tau={tau}")
        if not linear >= 0:
            raise ValueError(f"linear must be >= 0 pixels, got {linear}")
        self.linear = float(linear)
        self.scale_parameter("sigma", sigma, learnable)
        self.tau = float(tau)
        self.n_body, self.n_cap, self.n_samples = int(n_body), int(n_cap), int(n_samples)

    def _distances(self, body, obs: Silhouettes):
        """(B, V) ``E_l`` in squared pixels."""
        S = self._check_cameras(obs.masks, body)
        obs = obs.despeckled(self.despeckle)
        caps = self._caps2d(body, S, obs.height, obs.width, obs.offset)  # (S, V, N, C)
        fg, ok = _foreground(obs, self.n_samples, S, caps.pa)
        # both terms and, in one autograd node, their gradient in the capsules (written out: autograd
        # through the few hundred small operations cost several forwards)
        model_term, cover_term = capsule_chamfer(
            caps,
            obs.outside_distance(),
            fg,
            tau=self.tau,
            n_body=self.n_body,
            n_cap=self.n_cap,
            linear=self.linear,
        )
        # a camera without foreground samples (empty or invalid mask) contributes 0
        return _pose_major(torch.where(ok, model_term + cover_term, 0.0))

    def camera_log_likelihoods(self, body, obs: Silhouettes):
        return -self._distances(body, obs) / (2 * self.sigma**2)


@LIKELIHOODS.register("overlap")
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
        learnable: ``True`` (or ``["beta"]``) makes ``beta`` an ``nn.Parameter``.
    """

    scales = ("beta",)

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
        learnable: bool | Sequence[str] = False,
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
        del self.sigma  # the ratio has no sigma
        self.scale_parameter("beta", beta, learnable)
        self.eps = float(eps)

    def ratios(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """(..., N, V) overlap ratios ``|model ∩ mask| / |model ∪ mask|`` in [0, 1]."""
        body = self.body(theta)
        return self._ratios(body, self.select(obs)).reshape(*body.batch, -1)

    def _ratios(self, body, obs: Silhouettes):
        S = self._check_cameras(obs.masks, body)
        pts, w = self._model_points(
            self._caps2d(body, S, obs.height, obs.width, obs.offset)
        )  # (S, V, N, P, 2)
        inter = (w * _sample(obs.blurred(self.blur), pts, self.interpolation)).sum(-1)
        union = w.sum(-1) + _per_camera(obs.area().to(w), S, 0) - inter
        return _pose_major(inter / union.clamp_min(1e-9))

    def camera_log_likelihoods(self, body, obs: Silhouettes):
        ratio = self._ratios(body, obs)
        logr = torch.log(ratio.clamp_min(self.eps)) * body.rows(obs.valid, 1).to(ratio.device)
        return self.beta * logr


# Head and hands of the shipped models: human.urdf (CMU names) and fontmarty22.urdf.
_DEFAULT_MARKERS = (
    (("Head", "Head_end"), "LeftHand", "RightHand"),
    (("neck", "head_top"), "l_wrist", "r_wrist"),
)


@LIKELIHOODS.register("skin")
class SkinBlobLikelihood(ImageLikelihood):
    """Fontmarty et al. §3.2.3: ``D_l = (1/3) sum_i I_skin_dist(p_i)``, ``log p = -sum_l D_l^2 / 2 sigma^2``
    with ``p_i`` the projections of virtual markers on the head and hands (``D_l`` in pixels of the distance
    image).

    Args:
        markers: one entry per virtual marker: a joint name (or index), or a tuple of joints whose mean
            position is the marker (the head centre lies between two joints). Default: head centre and
            both wrists of ``human.urdf`` (``(("Head", "Head_end"), "LeftHand", "RightHand")``) or of
            ``fontmarty22.urdf``, whichever names the skeleton has.
        sigma: pixels of the distance image (5 in Fontmarty et al.).
        learnable: ``True`` (or ``["sigma"]``) makes ``sigma`` an ``nn.Parameter``.

    obs: :class:`~torchpf.observations.DistanceMaps` (V, H, W) distances to the nearest skin blob
    (``DistanceMaps.from_features(skin_masks)``).
    """

    obs_type = DistanceMaps
    obs_field = "skin"
    scales = ("sigma",)

    def __init__(
        self, skeleton, cameras, *, markers=None, sigma: float = 5.0, learnable: bool | Sequence[str] = False
    ):
        if markers is None:
            names = set(skeleton.joint_names)
            flat = [[m] if isinstance(m, str) else list(m) for m in _DEFAULT_MARKERS[0]]
            for cand in _DEFAULT_MARKERS:
                if all(n in names for m in cand for n in ([m] if isinstance(m, str) else m)):
                    markers = cand
                    break
            else:
                raise ValueError(f"pass markers=...: the skeleton has none of the default joints {flat}")
        groups = [resolve_joints(skeleton, [m] if isinstance(m, (str, int)) else m) for m in markers]
        super().__init__(skeleton, cameras)
        # Marker positions = (J, M) averaging matrix applied to the joints.
        A = torch.zeros(len(skeleton.joint_names), len(groups), dtype=torch.float64)
        for i, g in enumerate(groups):
            A[g, i] = 1.0 / len(g)
        self.register_buffer("marker_matrix", A)
        self.scale_parameter("sigma", sigma, learnable)

    def markers(self, theta: torch.Tensor) -> torch.Tensor:
        """(..., D) -> (..., M, 3) world positions of the virtual markers."""
        return self._markers(self.skeleton.fk(theta))

    def _markers(self, joints: torch.Tensor) -> torch.Tensor:
        """(..., J, 3) joint positions -> (..., M, 3) marker positions."""
        return torch.einsum("...jk,jm->...mk", joints, self.marker_matrix.to(joints))

    def _distances(self, body, obs: DistanceMaps):
        S = self._check_cameras(obs.distance, body)
        H, W = obs.distance.shape[-2:]
        uv = self.cameras.resized(W, H).project(self._markers(body.joints))  # (B, M, V, 2)
        uv = _camera_major(uv.transpose(1, 2), S)  # (S, V, N, M, 2)
        return _pose_major(_distance_lookup(obs.distance, uv).mean(-1))

    def _log_lik(self, body, obs: DistanceMaps):
        D = self._distances(body, obs) * body.rows(obs.valid, 1).to(body.theta.device)
        return -(D * D).sum(-1) / (2 * self.sigma**2)


@LIKELIHOODS.register("chamfer")
class ChamferLikelihood(ImageLikelihood):
    """Brubaker et al. eq. 9: ``log p = -(1/M) sum_i d(b_i)`` with ``d`` the squared distance to the nearest
    image edge and ``b_i`` points on the projected model's outline, here generalised to
    ``-(1/M) sum_i min(d(b_i), tau^2) / (2 sigma^2)`` summed over cameras (``sigma = 1/sqrt(2)`` and
    ``tau = inf`` give eq. 9 exactly; ``tau`` is the outlier rejection of Gavrila and Davis).

    Args:
        sigma, tau: pixels of the distance image.
        n_side, n_cap: outline points per capsule flank and per end arc.
        outline_only: drop outline points covered by another capsule, keeping the silhouette outline.
        learnable: ``True`` (or ``["sigma"]``) makes ``sigma`` an ``nn.Parameter`` (``tau`` stays fixed).

    obs: :class:`~torchpf.observations.DistanceMaps` (V, H, W) distances to the nearest edge pixel
    (``DistanceMaps.from_edges_of(images)``).
    """

    obs_type = DistanceMaps
    obs_field = "edges"
    scales = ("sigma",)

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
        learnable: bool | Sequence[str] = False,
    ):
        super().__init__(skeleton, cameras, bones)
        self.scale_parameter("sigma", sigma, learnable)
        self.tau = float(tau)
        self.n_side, self.n_cap, self.outline_only = int(n_side), int(n_cap), bool(outline_only)

    def _log_lik(self, body, obs: DistanceMaps):
        S = self._check_cameras(obs.distance, body)
        H, W = obs.distance.shape[-2:]
        caps = self._caps2d(body, S, H, W)  # (S, V, N, C)
        pts, ok = outline_points(caps, self.n_side, self.n_cap)  # (S, V, N, P, 2)
        w = ok.to(pts.dtype)
        if self.outline_only:
            w = w * (1.0 - capsule_coverage(pts, caps, exclude_own=2 * self.n_side + 2 * self.n_cap))
        d2 = _distance_lookup(obs.distance, pts).square().clamp_max(self.tau**2)
        term = (w * d2).sum(-1) / w.sum(-1).clamp_min(1.0) / (2 * self.sigma**2)
        valid = _per_camera(obs.valid.to(term.device), S, 0)
        return -_pose_major(torch.where(valid, term, 0.0)).sum(-1)  # a missing camera contributes 0
