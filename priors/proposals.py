"""Data-driven importance distributions for articulated tracking (Hauberg §2 and §4, eq. 4 and 8-14).

A particle filter that samples from the motion prior places its particles blind to the current frame. These
proposals ``q(θ_t | θ_{t-1}, Z_t)`` use the observation to put them where the person is, and follow the
filters' proposal protocol (:mod:`torchpf.filters.protocols`): ``sample(state, obs, generator) -> (x, log_q)``
with ``state.particles (..., N, D)`` the (resampled) parents.

* :class:`SilhouetteGuided` (eq. 12): per joint ``l`` and particle, independently, draw
  ``μ_l ~ N(μ_{l,t-1}, Σ_l)`` until its image projection lies inside the silhouette in every camera
  (rejection vectorised over all particles and joints at once, at most ``max_tries`` rounds; rejections are
  counted), then project all joints onto the skeleton with :func:`torchpf.ik.project` (eq. 7).
* :class:`DepthGuided` (eq. 13-14): the same, and additionally the joint must lie within ``r_l`` of an
  observed 3D point, ``min_k ||μ_l - z_k|| < r_l`` (small for hands, larger on the spine). Nearest-neighbour
  distances come from chunked ``torch.cdist`` (device-agnostic) or a k-d tree built once per frame.
* :class:`AngularRejection` (eq. 4, the paper's "failed experiment"): whole poses are drawn from the angular
  prior (eq. 3) until *all* joints project inside the silhouettes, capped at 10,000 rejections.

Weighting. The filter adds ``log p(θ_t | θ_{t-1}) - log q`` to the weights (the correction factor of eq. 2).
Under the paper's approximation (eq. 11: the data-driven restriction is imposed in the embedding space
before projecting, and the correction factor is treated as constant), ``log_q`` is reported as the
*prior's* log-density of the returned pose, ``prior.log_prob(θ_t, θ_{t-1})``, so that with that prior as the
filter's dynamics the correction cancels and the weights are the likelihood alone, as in the paper. For the
guided proposals the default prior is a :class:`priors.motion.ProjectedGaussian` with the same ``Σ_l``,
whose ``log_prob`` is the embedding-space surrogate; the angular baseline uses its
:class:`priors.motion.AngularRandomWalk`, whose ``log_prob`` is exact (for eq. 4 the correction factor is
the parent's acceptance probability, which the paper notes is constant over the samples of a parent and
ignores). Exact pieces are exposed by :meth:`SilhouetteGuided.draw`: the Gaussian log-density of the sampled
joint positions before projection and the per-joint rejection counts (whose geometric law estimates the
acceptance probability, the normaliser of the truncated Gaussian).

Example::

    prior = ProjectedGaussian(skel, joint_sigma=0.03)
    q = DepthGuided(skel, cameras, joint_sigma=0.03)
    pf = ParticleFilter(prior, PointCloudLikelihood(skel), proposal=q, n_particles=150)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from priors.motion import AngularRandomWalk, ProjectedGaussian
from torchpf.camera import CameraRig
from torchpf.observations import Frame, PointCloud, Silhouettes


@dataclass(frozen=True)
class GuidedDraw:
    """Everything a data-driven proposal drew for one frame (``...`` batch, ``N`` particles, ``J`` joints).

    Attributes:
        x: ``(..., N, D)`` proposed poses.
        log_q: ``(..., N)`` what :meth:`sample` returns as ``log q`` (module docstring, "Weighting").
        joints: ``(..., N, J, 3)`` sampled joint positions before projection (guided proposals; the poses'
            joints for the angular baseline).
        rejections: ``(..., N, J)`` (guided, per joint) or ``(..., N)`` (angular, per pose) rejected draws.
        accepted: same shape, bool: the final draw met the constraints (False once ``max_tries`` ran out).
        log_q_gauss: ``(..., N)`` exact Gaussian log-density ``Σ_l log N(joints_l; μ_l, Σ_l)`` of the
            embedding-space draw (guided proposals; None for the angular baseline).
    """

    x: Tensor
    log_q: Tensor
    joints: Tensor
    rejections: Tensor
    accepted: Tensor
    log_q_gauss: Tensor | None = None


def _parents(state: Any) -> Tensor:
    return state.particles if hasattr(state, "particles") else state


def _field(obs: Any, kind: type, name: str):
    if isinstance(obs, kind):
        return obs
    if isinstance(obs, Frame):
        return getattr(obs, name)
    return getattr(obs, name, None)


class _CameraSet:
    """Cameras for the inside-the-silhouette test, projected into each observation's pixel grid."""

    def __init__(self, cameras):
        # Not a submodule: projection casts the rig's buffers to the points' device and dtype.
        self.rig = CameraRig(cameras)
        if not len(self.rig):
            raise ValueError("at least one camera is needed")

    def inside(self, X: Tensor, sil: Silhouettes, masks: Tensor) -> Tensor:
        """``(..., 3)`` world points -> ``(...)`` bool: inside the (dilated) mask of every valid camera.

        Nearest-pixel look-up; a point behind a camera or outside its image is outside. A camera whose frame
        is missing (``sil.valid`` False) does not constrain.
        """
        V = len(self.rig)
        if V != masks.shape[0]:
            raise ValueError(f"{masks.shape[0]} masks for {V} cameras")
        H, W = masks.shape[-2:]
        rig = self.rig.resized(W, H)
        uv = torch.round(rig.project(X))  # (..., V, 2)
        u, w = uv[..., 0], uv[..., 1]
        valid = (u >= 0) & (u <= W - 1) & (w >= 0) & (w <= H - 1) & rig.in_front(X)
        ui = u.clamp(0, W - 1).long()
        wi = w.clamp(0, H - 1).long()
        hit = masks.to(X.device)[torch.arange(V, device=X.device), wi, ui] > 0.5
        free = ~sil.valid.to(X.device)
        return ((valid & hit) | free).all(-1)


def _dilated(sil: Silhouettes, px: int) -> Tensor:
    m = sil.masks
    if px <= 0:
        return m
    return F.max_pool2d(m[:, None], 2 * px + 1, stride=1, padding=px)[:, 0]


def nearest_distance(points: Tensor, queries: Tensor, *, chunk: int = 4096, backend: str = "cdist") -> Tensor:
    """Distance from each query ``(..., 3)`` to its nearest point of ``points (K, 3)``: ``(...)`` metres.

    ``backend="cdist"``: chunks of ``chunk`` queries against all points with ``torch.cdist`` (any device).
    ``backend="kdtree"``: a ``scipy.spatial.cKDTree`` built on the points (CPU; build once per frame and
    query all joints at once, which is what the proposals do). ``inf`` when there are no points.
    """
    shape = queries.shape[:-1]
    q = queries.reshape(-1, 3)
    if points.shape[0] == 0:
        return torch.full(shape, math.inf, dtype=queries.dtype, device=queries.device)
    if backend == "kdtree":
        from scipy.spatial import cKDTree

        tree = cKDTree(points.detach().cpu().double().numpy())
        d, _ = tree.query(q.detach().cpu().double().numpy(), k=1)
        return torch.as_tensor(d, dtype=queries.dtype, device=queries.device).reshape(shape)
    if backend != "cdist":
        raise ValueError(f"backend must be 'cdist' or 'kdtree', got {backend!r}")
    pts = points.to(q)
    # direct differences, not the |a|² - 2ab + |b|² expansion: exact near the r_l thresholds
    mode = "donot_use_mm_for_euclid_dist"
    out = [
        torch.cdist(q[i : i + chunk], pts, compute_mode=mode).amin(-1) for i in range(0, q.shape[0], chunk)
    ]
    return torch.cat(out).reshape(shape) if out else q.new_zeros(shape)


def joint_radii(skeleton, *, margin: float = 0.03, default: float = 0.1) -> Tensor:
    """Per-joint ``r_l`` (m) for :class:`DepthGuided` (Hauberg eq. 13): capsule radius at the joint + margin.

    A joint centre lies about one limb radius under the skin a depth camera sees, so ``r_l`` is the largest
    radius of the capsules meeting at joint ``l`` plus ``margin`` (small for hands, large on the spine, as
    the paper prescribes); a joint without a capsule (the pelvis of a CMU skeleton) gets ``default``.
    """
    J = len(skeleton.joint_names)
    r = torch.full((J,), -1.0, dtype=torch.float64)
    for (a, b), rad in zip(skeleton.bones, skeleton.radii.tolist(), strict=True):
        r[a] = max(r[a].item(), rad)
        r[b] = max(r[b].item(), rad)
    return torch.where(r < 0, torch.full_like(r, default), r) + margin


class SilhouetteGuided(nn.Module):
    """Silhouette-guided importance distribution (Hauberg eq. 12).

    ``q_bg(θ_t | B_t, θ_{t-1}) ≈ proj_M[ Π_l N(μ_{l,t} | μ_{l,t-1}, Σ_l) U_{B_t}(proj_im[μ_{l,t}]) ]``: each
    joint is drawn from its Gaussian around the parent's joint position until it projects inside the
    silhouette in every camera (``L`` three-dimensional rejection problems instead of one ``3L``-dimensional
    one), then the joints are projected onto the skeleton (eq. 7). After ``max_tries`` rounds a joint keeps
    its last (unconstrained) draw and is flagged in :meth:`draw`'s ``accepted``.

    Args:
        skeleton: the :class:`torchpf.Skeleton`.
        cameras: the silhouette cameras (``Camera`` list or ``CameraRig``), in the masks' order.
        joint_sigma: ``Σ_l``: isotropic std per joint (scalar or ``(J,)``, m) or ``(J, 3, 3)`` covariances.
        max_tries: most redraws per joint (only the joints still outside are redrawn).
        batch_tries: candidates drawn at once per joint still outside (the first acceptable one is kept: the
            same law as one at a time, fewer rounds of the constraint test).
        dilate_px: grow the masks by this many pixels first (tolerance to segmentation noise).
        prior: the dynamics whose ``log_prob`` is reported as ``log_q`` (paper's weighting); default a
            :class:`~priors.motion.ProjectedGaussian` with the same ``Σ_l`` and IK options.
        ik_options: keyword arguments for :func:`torchpf.ik.project`; default those of ``prior`` when it
            is a :class:`~priors.motion.ProjectedGaussian` (same frozen DOFs and iterations as the filter's
            dynamics), else the projection's defaults.

    obs: a :class:`~torchpf.observations.Frame` with ``silhouettes`` (or a ``Silhouettes``). Without
    silhouettes the proposal is the projected prior.
    """

    def __init__(
        self,
        skeleton,
        cameras,
        joint_sigma=0.03,
        *,
        max_tries: int = 30,
        batch_tries: int = 8,
        dilate_px: int = 0,
        prior: Any = None,
        ik_options: Mapping | None = None,
    ):
        super().__init__()
        if max_tries < 0:
            raise ValueError("max_tries must be >= 0")
        if batch_tries < 1:
            raise ValueError("batch_tries must be >= 1")
        self.batch_tries = int(batch_tries)
        self.skeleton = skeleton
        self.cams = _CameraSet(cameras)
        if ik_options is None and isinstance(prior, ProjectedGaussian):
            ik_options = prior.ik_options
        self.spatial = ProjectedGaussian(skeleton, joint_sigma, ik_options=ik_options)
        self.prior = prior if prior is not None else self.spatial
        self.max_tries = int(max_tries)
        self.dilate_px = int(dilate_px)

    # -- constraint -----------------------------------------------------------------------------------
    def _prepare(self, obs: Any) -> dict:
        """Per-frame data for :meth:`_ok`, computed once per call (dilated masks, ...)."""
        sil = _field(obs, Silhouettes, "silhouettes")
        return {"sil": sil, "masks": None if sil is None else _dilated(sil, self.dilate_px)}

    def _ok(self, X: Tensor, joint_index: Tensor, ctx: dict) -> Tensor:
        """``(M, 3)`` candidate positions of joints ``joint_index (M,)`` -> ``(M,)`` bool acceptable."""
        if ctx["sil"] is None:
            return torch.ones(X.shape[:-1], dtype=torch.bool, device=X.device)
        return self.cams.inside(X, ctx["sil"], ctx["masks"])

    # -- sampling -------------------------------------------------------------------------------------
    def draw(self, parents: Any, obs: Any, generator: torch.Generator | None = None) -> GuidedDraw:
        """Sample the proposal for parents ``(..., N, D)`` (or a filter state); see :class:`GuidedDraw`."""
        x_old = _parents(parents)
        ctx = self._prepare(obs)
        mu = self.spatial.mean_joints(x_old)  # (..., N, J, 3)
        J = mu.shape[-2]
        joint_of = torch.arange(J, device=mu.device).expand(mu.shape[:-1])
        eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
        X = self.spatial.joints_from_noise(mu, eps)
        ok = self._ok(X.reshape(-1, 3), joint_of.reshape(-1), ctx).reshape(mu.shape[:-1])
        rejections = torch.zeros(mu.shape[:-1], dtype=torch.long, device=mu.device)
        tries = 0
        while tries < self.max_tries:
            bad = ~ok
            n_bad = int(bad.sum())
            if n_bad == 0:
                break
            # Redraw only the joints still outside, all particles and joints in one batch, ``k`` i.i.d.
            # candidates each: the first acceptable one is exactly what ``k`` sequential rejection rounds
            # would keep (and the rejections before it are counted), in one constraint test instead of k.
            k = min(self.batch_tries, self.max_tries - tries)
            tries += k
            e = torch.randn(n_bad, k, 3, generator=generator, dtype=mu.dtype, device=mu.device)
            idx = joint_of[bad]
            L = self.spatial.scale_tril.to(mu)[idx][:, None]  # (n_bad, 1, 3, 3)
            cand = mu[bad][:, None] + (L @ e[..., None])[..., 0]  # (n_bad, k, 3)
            good = self._ok(cand.reshape(-1, 3), idx.repeat_interleave(k), ctx).reshape(n_bad, k)
            hit = good.any(1)
            # index of the first acceptable candidate; the last one when none is (it is kept, flagged)
            first = torch.where(hit, good.long().argmax(1), torch.full_like(idx, k - 1))
            rejections = rejections.index_put((bad,), rejections[bad] + torch.where(hit, first, k))
            X = X.index_put((bad,), cand[torch.arange(n_bad, device=mu.device), first])
            ok = ok.index_put((bad,), hit)
        theta = self.spatial.project(X, x_old)
        log_q = self.prior.log_prob(theta, x_old)
        return GuidedDraw(
            x=theta,
            log_q=log_q,
            joints=X,
            rejections=rejections,
            accepted=ok,
            log_q_gauss=self.spatial.log_prob_joints(X, x_old),
        )

    def sample(self, state: Any, obs: Any, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Proposal protocol: ``(x (..., N, D), log_q (..., N))`` for the parents in ``state``."""
        d = self.draw(state, obs, generator)
        return d.x, d.log_q


class DepthGuided(SilhouetteGuided):
    """Depth-guided importance distribution (Hauberg eq. 13-14).

    As :class:`SilhouetteGuided`, and a joint draw is accepted only when it also lies in ``Z^{⊕ r_l}``, the
    set of points within ``r_l`` of an observed 3D point (eq. 13). Without silhouettes in the frame only the
    depth test applies; without points only the silhouette test.

    Beyond the arguments of :class:`SilhouetteGuided`:

    Args:
        radii: ``r_l`` per joint ``(J,)`` or scalar (m); default :func:`joint_radii` (capsule radius + 3 cm).
        backend: nearest-neighbour search, ``"cdist"`` (chunked ``torch.cdist``) or ``"kdtree"`` (scipy k-d
            tree built once per frame).
        max_points: subsample the cloud to at most this many points (evenly, deterministic) for the search.

    obs: a :class:`~torchpf.observations.Frame` with ``points`` (and optionally ``silhouettes``).
    """

    def __init__(
        self,
        skeleton,
        cameras,
        joint_sigma=0.03,
        *,
        radii=None,
        backend: str = "kdtree",
        max_points: int | None = 4000,
        **kwargs,
    ):
        super().__init__(skeleton, cameras, joint_sigma, **kwargs)
        J = len(skeleton.joint_names)
        r = joint_radii(skeleton) if radii is None else torch.as_tensor(radii, dtype=torch.float64).expand(J)
        self.register_buffer("radii", r.clone())
        if backend not in ("cdist", "kdtree"):
            raise ValueError(f"backend must be 'cdist' or 'kdtree', got {backend!r}")
        self.backend = backend
        self.max_points = max_points

    def _prepare(self, obs: Any) -> dict:
        ctx = super()._prepare(obs)
        pc = _field(obs, PointCloud, "points")
        pts = None
        if pc is not None:
            pts = pc.points if isinstance(pc, PointCloud) else torch.as_tensor(pc)
            if self.max_points is not None and pts.shape[0] > self.max_points:
                step = math.ceil(pts.shape[0] / self.max_points)
                pts = pts[::step]
        ctx["points"] = pts
        ctx["tree"] = None
        if pts is not None and self.backend == "kdtree" and pts.shape[0]:
            from scipy.spatial import cKDTree

            ctx["tree"] = cKDTree(pts.detach().cpu().double().numpy())  # built once per frame
        return ctx

    def _ok(self, X: Tensor, joint_index: Tensor, ctx: dict) -> Tensor:
        ok = super()._ok(X, joint_index, ctx)
        pts = ctx["points"]
        if pts is None:
            return ok
        if ctx["tree"] is not None:
            d, _ = ctx["tree"].query(X.detach().cpu().double().numpy(), k=1)
            dist = torch.as_tensor(d, dtype=X.dtype, device=X.device)
        else:
            dist = nearest_distance(pts, X, backend="cdist")
        return ok & (dist < self.radii.to(X)[joint_index])


class AngularRejection(nn.Module):
    """Angular rejection baseline (Hauberg eq. 4, §2, "a failed experiment").

    ``q̃(θ_t | B_t, θ_{t-1}) ∝ N(θ_t | θ_{t-1}, diag σ²) U_Θ(θ_t) U_{B_t}(proj_im[F(θ_t)])``: whole poses are
    drawn from the angular prior (eq. 3) until every joint projects inside the silhouette in every camera.
    Rejections per particle are capped at ``max_rejections`` (the paper's 10,000); a particle that runs out
    keeps its last draw (flagged in :meth:`draw`'s ``accepted``). Candidates are drawn in rounds of about
    ``batch`` poses spread over the particles still waiting, each round one FK and one mask look-up.

    ``log_q`` is ``prior.log_prob(θ_t, θ_{t-1})`` (exact for the angular prior): the correction factor of
    eq. 2 is then the parent's acceptance probability, constant over that parent's samples, which the
    paper ignores.

    Args:
        skeleton, cameras: as :class:`SilhouetteGuided`.
        prior: an :class:`~priors.motion.AngularRandomWalk` (default: ``from_skeleton(skeleton)``).
        max_rejections: cap per particle.
        batch: candidates per round.
        dilate_px: as :class:`SilhouetteGuided`.
    """

    def __init__(
        self,
        skeleton,
        cameras,
        prior: AngularRandomWalk | None = None,
        *,
        max_rejections: int = 10_000,
        batch: int = 4096,
        dilate_px: int = 0,
    ):
        super().__init__()
        self.skeleton = skeleton
        self.cams = _CameraSet(cameras)
        self.prior = prior if prior is not None else AngularRandomWalk.from_skeleton(skeleton)
        self.max_rejections = int(max_rejections)
        self.batch = int(batch)
        self.dilate_px = int(dilate_px)

    def draw(self, parents: Any, obs: Any, generator: torch.Generator | None = None) -> GuidedDraw:
        """Sample for parents ``(..., N, D)`` (or a filter state); :class:`GuidedDraw`, per-pose counts."""
        x_old = _parents(parents)
        sil = _field(obs, Silhouettes, "silhouettes")
        flat = x_old.reshape(-1, x_old.shape[-1])
        M = flat.shape[0]
        x = self.prior.sample(flat, generator)
        rejections = torch.zeros(M, dtype=torch.long, device=flat.device)
        accepted = torch.ones(M, dtype=torch.bool, device=flat.device)
        if sil is not None:
            masks = _dilated(sil, self.dilate_px)

            def all_inside(theta):
                return self.cams.inside(self.skeleton.fk(theta), sil, masks).all(-1)

            accepted = all_inside(x)
            while True:
                pending = (~accepted & (rejections < self.max_rejections)).nonzero().flatten()
                if pending.numel() == 0:
                    break
                # each pending particle gets k candidates this round; the first one inside is taken
                k = max(1, min(self.batch // pending.numel(), self.max_rejections))
                left = self.max_rejections - rejections[pending]
                cand = self.prior.sample(flat[pending].repeat_interleave(k, 0), generator)  # (P k, D)
                inside = all_inside(cand).reshape(-1, k)
                first = torch.where(inside.any(-1), inside.float().argmax(-1), torch.full_like(left, k))
                used = torch.minimum(first, left)  # rejections spent (capped)
                got = (first < k) & (first < left)
                rejections[pending] += torch.where(got, first, used)
                take = got.nonzero().flatten()
                pick = cand.reshape(-1, k, cand.shape[-1])[take, first[take]]
                x[pending[take]] = pick
                accepted[pending[take]] = True
                # a particle that ran out keeps the last candidate it was allowed
                out = (~got & (rejections[pending] >= self.max_rejections)).nonzero().flatten()
                if out.numel():
                    last = (used[out] - 1).clamp(min=0)
                    x[pending[out]] = cand.reshape(-1, k, cand.shape[-1])[out, last]
        x = x.reshape(x_old.shape)
        return GuidedDraw(
            x=x,
            log_q=self.prior.log_prob(x, x_old),
            joints=self.skeleton.fk(x),
            rejections=rejections.reshape(x_old.shape[:-1]),
            accepted=accepted.reshape(x_old.shape[:-1]),
        )

    def sample(self, state: Any, obs: Any, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Proposal protocol: ``(x (..., N, D), log_q (..., N))``."""
        d = self.draw(state, obs, generator)
        return d.x, d.log_q


__all__: Sequence[str] = [
    "AngularRejection",
    "DepthGuided",
    "GuidedDraw",
    "SilhouetteGuided",
    "joint_radii",
    "nearest_distance",
]
