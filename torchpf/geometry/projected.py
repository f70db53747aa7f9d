"""Capsules projected into an image: tapered 2-D capsules, their rasterisation, sample points and coverage.

Each 3-D capsule (:mod:`torchpf.geometry.capsules`) seen by a camera becomes a 2-D *tapered capsule*: the
convex hull of two discs (the projected end spheres, radius ~``f r / z`` pixels) - the "projected truncated
cones" of Fontmarty et al. §3.2.1.

* :func:`project_capsules` - 3-D capsules and a camera -> :class:`Capsules2D`.
* :func:`capsule_masks` - rasterise projected capsules into (..., H, W) silhouettes (bool or soft).
* :func:`sample_in_capsules` - area-uniform sample points inside projected capsules with their area
  weights (fixed quasi-random pattern :func:`sample_pattern`, or random with a ``torch.Generator``),
  :func:`capsule_coverage` - whether image points are covered by the projected model, and
  :func:`outline_points` - points on the capsule outlines (Chamfer matching).

Shapes: ``...`` batch (poses), ``C`` capsules, ``P`` points. Units: pixels. dtype and device follow the
inputs; everything is differentiable where the geometry is.

Example::

    from torchpf.geometry import capsule_masks, project_capsules
    ends, radii = skel.capsules(theta)                               # (N, C, 2, 3), (C,)
    caps = project_capsules(camera, ends[..., 0, :], ends[..., 1, :], radii)
    masks = capsule_masks(caps, camera.height, camera.width)         # (N, H, W) bool
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from torchpf.camera import CameraRig, _camera_to_pixels
from torchpf.devices import fused_cpu
from torchpf.geometry import _coverage_cpu, _project_cpu
from torchpf.geometry.capsules import _chunk_rows, chunk_elements

#: pose-capsule-point triples per chunk of :func:`capsule_coverage` (its passes then stay in cache)
_COVERAGE_CHUNK = 1 << 17

__all__ = [
    "Capsules2D",
    "capsule_coverage",
    "capsule_masks",
    "distance_to_capsules",
    "outline_points",
    "project_capsules",
    "sample_in_capsules",
    "sample_pattern",
]


@dataclass
class Capsules2D:
    """Projected capsules: tapered 2D capsules = convex hulls of two discs, in pixels.

    Fields (all with leading ``...`` batch dims): ``pa``, ``pb`` (..., C, 2) disc centres; ``ra``, ``rb``
    (..., C) disc radii; ``valid`` (..., C) bool, False where an end lies behind the camera (such a
    capsule is dropped from masks, samples and coverage).
    """

    pa: torch.Tensor
    pb: torch.Tensor
    ra: torch.Tensor
    rb: torch.Tensor
    valid: torch.Tensor

    def unbind(self, dim: int) -> list[Capsules2D]:
        """Split along batch dim ``dim`` (>= 0, counted from the front): e.g. the V cameras of a rig
        projection (..., V, C) with ``dim = len(...)``."""
        fields = (self.pa, self.pb, self.ra, self.rb, self.valid)
        return [Capsules2D(*parts) for parts in zip(*(f.unbind(dim) for f in fields), strict=True)]


def project_capsules(camera, a: torch.Tensor, b: torch.Tensor, radius: torch.Tensor, near: float = 1e-2):
    """Project 3D capsules into a camera (Fontmarty et al. §3.2.1 "projected truncated cones").

    Args:
        camera: a :class:`torchpf.camera.Camera`, or a :class:`torchpf.camera.CameraRig` of V cameras
            projected into all at once.
        a, b: (..., C, 3) ends (m); radius: (C,) radii (m); near: minimum depth (m) of a valid end.

    Returns:
        :class:`Capsules2D` (..., C) for a camera, (..., V, C) for a rig, with radii ``f r / (z sqrt(cos t))``
        (pixels) at each end's depth ``z`` and angle ``t`` off the optical axis: the perspective image of a
        sphere is an ellipse, this circle has its area (exact on the optical axis).
    """
    K, R, t, dist = camera._params(a)
    if isinstance(camera, CameraRig) and dist is None and a.shape == b.shape:
        if not (torch.is_grad_enabled() and (K.requires_grad or R.requires_grad or t.requires_grad)):
            pa, pb, ra, rb, valid = _RigProjection.apply(a, b, radius.to(a), K, R, t, float(near))
            return Capsules2D(pa, pb, ra, rb, valid)
    ends = torch.stack([a, b], -2)  # (..., C, 2, 3)
    xc = camera.to_camera(ends)
    uv = _camera_to_pixels(xc, K, dist)  # camera.project(ends), from the camera-frame points
    focal = camera.focal
    if isinstance(camera, CameraRig):  # (..., C, 2, V, k) -> (..., V, C, 2, k)
        uv, xc = uv.movedim(-2, -4), xc.movedim(-2, -4)
        focal = (0.5 * (K[:, 0, 0] + K[:, 1, 1]))[:, None, None]  # camera.focal(xc)
    z = xc[..., 2]
    r = radius.to(z)
    # A sphere at angle t off the optical axis images as an ellipse with semi-axes ~ f r / z (across) and
    # f r / (z cos t) (radially); the area-preserving circle has radius f r / (z sqrt(cos t)).
    zc = z.clamp_min(near)
    rad = focal * r.unsqueeze(-1) / zc * (xc.norm(dim=-1) / zc).sqrt()
    valid = (z > near).all(-1)
    return Capsules2D(uv[..., 0, :], uv[..., 1, :], rad[..., 0], rad[..., 1], valid)


class _RigProjection(torch.autograd.Function):
    """:func:`project_capsules` into a rig without distortion, as one autograd node: the forward keeps the
    projection's derivatives (perspective division and the radius ``f r |x_c|^(1/2) z^(-3/2)``), the
    backward maps the capsules' gradient to the ends (and radii) with them, instead of back-propagating
    through some forty small operations (a refinement step's cost, :mod:`torchpf.refine`). Same values as
    the general path. Everything runs in the output's layout ``(B, V, 2 C)`` (pose, camera, capsule end).
    On a CPU both directions are fused numba kernels (:mod:`torchpf.geometry._project_cpu`)."""

    @staticmethod
    def forward(ctx, a, b, radius, K, R, t, near: float):
        # a, b (..., C, 3), radius (C,), K, R (V, 3, 3), t (V, 3); runs without a graph (autograd.Function)
        batch, C, V = a.shape[:-2], a.shape[-2], R.shape[0]
        ctx.fused = _project_cpu.applies(a) and b.dtype == a.dtype
        if ctx.fused:  # one pass per direction (the backward recomputes what it needs from the inputs)
            out = _project_cpu.forward(a, b, radius, K, R, t, near)
            ctx.save_for_backward(a, b, radius, K, R, t)
            ctx.near = near
            ctx.mark_non_differentiable(out[4])
            return out
        ends = torch.stack([a, b], -2).reshape(-1, 1, 2 * C, 3)
        xc = torch.matmul(ends, R.transpose(-1, -2)) + t.view(V, 1, 3)  # (B, V, 2 C, 3)
        x, y, z = xc.unbind(-1)
        iz = torch.where(z.abs() < 1e-12, 1e-12, z).reciprocal()
        k00, k01, k02, k11, k12 = (K[:, i, j].view(V, 1) for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2)))
        xn, yn = x * iz, y * iz
        u = torch.addcmul(torch.addcmul(k02, k00, xn), k01, yn)
        v = torch.addcmul(k12, k11, yn)
        nn2 = torch.addcmul(torch.addcmul(x * x, y, y), z, z)
        zc = z.clamp_min(near)
        # f r / zc (|x_c| / zc)^(1/2), per metre of sphere radius
        q = 0.5 * (k00 + k11) / zc * (nn2.sqrt() / zc).sqrt()
        rad = q * radius.view(C, 1).expand(C, 2).reshape(2 * C)
        front = z > near
        uv = torch.stack([u, v], -1).view(-1, V, C, 2, 2)
        rad4, front4 = rad.view(-1, V, C, 2), front.view(-1, V, C, 2)
        ctx.save_for_backward(R, k00, k01, k11, iz, u - k02, v - k12, xc, nn2, rad, q, zc, front)
        ctx.shape = (batch, C, V)
        valid = (front4[..., 0] & front4[..., 1]).reshape(*batch, V, C)
        ctx.mark_non_differentiable(valid)
        return (
            uv[..., 0, :].reshape(*batch, V, C, 2),
            uv[..., 1, :].reshape(*batch, V, C, 2),
            rad4[..., 0].reshape(*batch, V, C),
            rad4[..., 1].reshape(*batch, V, C),
            valid,
        )

    @staticmethod
    def backward(ctx, g_pa, g_pb, g_ra, g_rb, _):
        if ctx.fused:
            g_a, g_b, g_radius = _project_cpu.backward(*ctx.saved_tensors, ctx.near, g_pa, g_pb, g_ra, g_rb)
            return g_a, g_b, g_radius if ctx.needs_input_grad[2] else None, None, None, None, None
        R, k00, k01, k11, iz, du, dv, xc, nn2, rad, q, zc, front = ctx.saved_tensors
        batch, C, V = ctx.shape
        x, y, z = xc.unbind(-1)
        shape = (*batch, V, C)
        g_pa = g_pa if g_pa is not None else x.new_zeros(*shape, 2)
        g_pb = g_pb if g_pb is not None else x.new_zeros(*shape, 2)
        g_ra = g_ra if g_ra is not None else x.new_zeros(shape)
        g_rb = g_rb if g_rb is not None else x.new_zeros(shape)
        gu, gv = torch.stack([g_pa, g_pb], -2).reshape(-1, V, 2 * C, 2).unbind(-1)
        gr = torch.stack([g_ra, g_rb], -1).reshape(-1, V, 2 * C)
        # u = k00 x / z + k01 y / z + k02, v = k11 y / z + k12; rad = q r, q ~ |x_c|^(1/2) zc^(-3/2)
        half = gr * rad * 0.5 / nn2
        gx = torch.addcmul(half * x, gu * k00, iz)
        gy = torch.addcmul(half * y, torch.addcmul(gu * k01, gv, k11), iz)
        gz = torch.addcmul(half * z, torch.addcmul(gu * du, gv, dv), iz, value=-1.0)
        gz = torch.addcmul(gz, gr * rad * front, zc.reciprocal(), value=-1.5)
        # x_c = R X + t: the ends' gradient is sum over cameras of R^T g
        g_ends = torch.matmul(torch.stack([gx, gy, gz], -1), R).sum(1).view(*batch, C, 2, 3)
        g_radius = None
        if ctx.needs_input_grad[2]:
            g_radius = (gr * q).view(-1, V, C, 2).sum((0, 1, 3))
        return g_ends[..., 0, :], g_ends[..., 1, :], g_radius, None, None, None, None


def _uneven_capsule_sdf(p, pa, pb, ra, rb):
    """Exact 2D signed distance to the convex hull of discs (pa, ra) and (pb, rb); broadcasting."""
    p = p - pa
    e = pb - pa
    h = (e * e).sum(-1).clamp_min(1e-12)
    qx = (p[..., 0] * e[..., 1] - p[..., 1] * e[..., 0]).abs() / h
    qy = (p * e).sum(-1) / h
    bdiff = ra - rb
    cx2 = h - bdiff * bdiff
    cx = cx2.clamp_min(0).sqrt()
    k = cx * qy - bdiff * qx
    m = cx * qx + bdiff * qy
    nq = qx * qx + qy * qy
    d_a = (h * nq).sqrt() - ra
    d_b = (h * (nq + 1 - 2 * qy)).clamp_min(0).sqrt() - rb
    d = torch.where(k < 0, d_a, torch.where(k > cx, d_b, m - ra))
    # One disc inside the other (or a zero-length axis: a bone seen end-on): the hull is the larger disc.
    # Distances straight from the centres, since the normalised coordinates above divide by |e|^2.
    nested = cx2 <= 1e-9
    d_nested = torch.minimum(
        (p * p).sum(-1).clamp_min(1e-12).sqrt() - ra, ((p - e) ** 2).sum(-1).clamp_min(1e-12).sqrt() - rb
    )
    return torch.where(nested, d_nested, d)


def distance_to_capsules(points: torch.Tensor, caps: Capsules2D, *, signed: bool = False) -> torch.Tensor:
    """Distance (pixels) from image points to the union of projected capsules, 0 inside (``signed``: minus
    the depth inside, the union's signed distance).

    ``min_c max(0, |p - q_c(t)| - r_c(t))`` with ``q_c(t)`` the point of capsule ``c``'s axis nearest to
    ``p`` and ``r_c(t)`` its radius interpolated there: the region of :func:`sample_in_capsules` (the hull of
    the end discs up to a sliver of relative width ``((ra - rb) / L)^2``). Invalid capsules (behind a
    camera) are ignored; a point with no valid capsule gets ``inf``. The gradient in the capsule parameters
    is that of the nearest capsule's outline, non-zero however far the point lies from the model, which is
    what a local optimiser needs (:mod:`torchpf.refine`). ``|p - a|^2`` and ``(p - a) . e`` come from two
    matrix products (as in :func:`capsule_coverage`), so the cost is a few element-wise passes over
    ``(..., C, P)``.

    Args:
        points: (P, 2) points shared by every pose, or (..., P, 2) whose leading dims broadcast against the
            capsules' (per pose, or e.g. (V, 1, P, 2) per camera for (V, N, C) capsules: one matrix product
            per camera, as in :func:`capsule_coverage`).
        caps: :class:`Capsules2D` (..., C).

    Returns:
        (..., P) distances.
    """
    batch, C = caps.pa.shape[:-2], caps.pa.shape[-2]
    G, R, pts = _point_groups(points, batch)
    pts = pts.to(caps.pa)
    fields = [f.reshape(G, R * C, -1) for f in (caps.pa, caps.pb, caps.ra, caps.rb)]  # (G, R C, 2 or 1)
    best, nearest = _nearest_capsules(pts, fields, caps.valid.reshape(G, R * C, 1), C)
    floor = -math.inf if signed else 0.0
    if not (torch.is_grad_enabled() and any(f.requires_grad for f in fields)):
        return best.clamp_min(floor).reshape(*batch, -1)
    # The gradient is the nearest capsule's (that of the min): recomputed with autograd for that capsule
    # only, (G, R, P) values instead of (G, R, C, P).
    d, _ = _nearest_axis_distance(pts, fields, nearest, best)
    return d.clamp_min(floor).reshape(*batch, -1)


def _nearest_capsules(pts, fields, valid, C: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance ``best`` (G, R, P) of points ``pts`` (G, P, 2) to the nearest of C valid capsules per
    row (``inf`` without one) and that capsule's index ``nearest`` (G, R, P); ``fields`` are ``pa``, ``pb``
    (G, R C, 2), ``ra``, ``rb`` (G, R C, 1), ``valid`` (G, R C, 1). No graph; every capsule is tested in
    cache-sized chunks of rows."""
    G, RC = valid.shape[:2]
    R = RC // max(1, C)
    with torch.no_grad():
        n = max(1, chunk_elements(pts.device, _COVERAGE_CHUNK) // max(1, G * C * pts.shape[1]))
        parts = []
        for r0 in range(0, R, n):
            rows = slice(r0 * C, min(R, r0 + n) * C)
            sdf = _capsule_sdf(pts, *(f[:, rows] for f in fields), valid[:, rows])
            parts.append(sdf.view(G, -1, C, sdf.shape[-1]).min(-2))
        best = torch.cat([b for b, _ in parts], 1) if len(parts) > 1 else parts[0][0]  # (G, R, P)
        nearest = torch.cat([i for _, i in parts], 1) if len(parts) > 1 else parts[0][1]
    return best, nearest


def _nearest_axis_distance(pts, fields, nearest, best):
    """``|p - q(t)| - r(t)`` (G, R P) of every point to its ``nearest`` capsule (:func:`_nearest_capsules`),
    differentiable in ``fields``; ``inf`` where ``best`` is (no valid capsule).

    Coordinates are separate (G, R P) tensors (element-wise operations on them cost a fraction of those over
    a trailing dim of size 2). Also returns the terms its gradient needs (:mod:`torchpf.geometry.chamfer`):
    ``index`` (G R P) the capsule's row among the G R C flattened ones, ``ax``, ``ay``, ``ra``, ``rb``, the
    axis ``ex``, ``ey``, ``dx``, ``dy`` = p - pa, ``inv_ee`` = 1 / |e|^2 (0 for a point-like axis), the axis
    parameter ``s`` and ``t = clamp(s, 0, 1)``, ``qx``, ``qy`` = p - pa - t e and ``qq = |q|^2``."""
    G, R, P = nearest.shape
    RC = fields[0].shape[1]
    C = RC // max(1, R)
    rows = torch.arange(R, device=nearest.device).repeat_interleave(P) * C + nearest.reshape(G, R * P)
    index = (rows + torch.arange(G, device=rows.device).unsqueeze(-1) * RC).reshape(-1)
    table = torch.cat(fields, -1).reshape(G * RC, 6)  # (pa, pb, ra, rb) per capsule
    ax, ay, bx, by, ra, rb = table.index_select(0, index).view(G, R * P, 6).unbind(-1)
    p = pts.repeat(1, R, 1)  # (G, R P, 2), row r's copy of the points
    dx, dy = p[..., 0] - ax, p[..., 1] - ay
    ex, ey = bx - ax, by - ay
    ee = torch.addcmul(ex * ex, ey, ey)
    inv_ee = torch.where(ee > 1e-12, ee.clamp_min(1e-12).reciprocal(), 0.0)
    s = torch.addcmul(dx * ex, dy, ey) * inv_ee  # the axis parameter of p
    t = s.clamp(0.0, 1.0)
    qx, qy = dx - t * ex, dy - t * ey
    qq = torch.addcmul(qx * qx, qy, qy)
    d = qq.clamp_min(1e-12).sqrt() - torch.addcmul(ra, t, rb - ra)
    d = torch.where(torch.isfinite(best).reshape(G, R * P), d, math.inf)  # no valid capsule: inf
    terms = {"index": index, "ax": ax, "ay": ay, "ra": ra, "rb": rb, "ex": ex, "ey": ey, "dx": dx, "dy": dy}
    return d, {**terms, "inv_ee": inv_ee, "s": s, "t": t, "qx": qx, "qy": qy, "qq": qq}


def _capsule_sdf(pts, pa, pb, ra, rb, valid) -> torch.Tensor:
    """Signed distance (pixels) of points ``pts`` (G, P, 2) to capsules ``pa``, ``pb`` (G, K, 2), ``ra``,
    ``rb`` (G, K, 1): (G, K, P), ``inf`` where not ``valid`` (G, K, 1). ``|p - a|^2`` and the axis
    parameter ``s = (p - a) . e / |e|^2`` are two matrix products (rows ``x, y, x^2 + y^2, 1`` of the
    points), then ``|p - a - t e|^2 = |p - a|^2 + |e|^2 t (t - 2 s)``: a dozen passes over (G, K, P), in
    place (no autograd)."""
    e = pb - pa
    ee = (e * e).sum(-1, keepdim=True)  # (G, K, 1)
    inv = torch.where(ee > 1e-12, ee.clamp_min(1e-12).reciprocal(), 0.0)
    one = torch.ones_like(ee)
    # an invalid capsule is infinitely far from every point
    aa = (pa * pa).sum(-1, keepdim=True).masked_fill_(~valid, math.inf)
    A_uu = torch.cat([-2 * pa, one, aa], -1)
    A_s = torch.cat([e * inv, 0 * one, -(pa * e).sum(-1, keepdim=True) * inv], -1)
    PtT = torch.cat([pts, (pts * pts).sum(-1, keepdim=True), torch.ones_like(pts[..., :1])], -1).transpose(
        -1, -2
    )
    qa = torch.bmm(A_uu, PtT)  # |p - a|^2
    s = torch.bmm(A_s, PtT)
    t = s.clamp(0.0, 1.0)
    d2 = qa.addcmul_(torch.add(t, s, alpha=-2.0).mul_(t), ee).clamp_min_(1e-12)  # |p - a - t e|^2
    return d2.sqrt_().sub_(torch.addcmul(ra, t, rb - ra))


def _point_groups(points: torch.Tensor, batch: torch.Size) -> tuple[int, int, torch.Tensor]:
    """Points (P, 2) or (..., P, 2) broadcasting against the capsules' batch dims ``batch``, split into G
    groups with points of their own and R rows (the trailing batch dims where the points broadcast) that
    share them: returns G, R and the (G, P, 2) points. The R rows of a group are one matrix product."""
    lead = tuple(points.shape[:-2])
    if len(lead) > len(batch):
        raise ValueError(
            f"points {tuple(points.shape)} have more batch dims than the capsules {tuple(batch)}"
        )
    aligned = (1,) * (len(batch) - len(lead)) + lead
    k = len(batch)
    while k > 0 and aligned[k - 1] == 1:
        k -= 1
    P = points.shape[-2]
    pts = points.expand(*batch[:k], *aligned[k:], P, 2).reshape(math.prod(batch[:k]), P, 2)
    return math.prod(batch[:k]), math.prod(batch[k:]), pts


def capsule_masks(
    caps: Capsules2D,
    height: int,
    width: int,
    *,
    soft: float = 0.0,
    chunk_size: int | None = None,
) -> torch.Tensor:
    """Rasterise projected capsules into silhouettes: pixel (i, j) (centre at u=j, v=i) is inside if it
    lies in any capsule's convex hull of discs.

    Args:
        caps: :class:`Capsules2D` with batch dims ``...``; height, width: mask size (pixels, same pixel
            frame as the capsules - use ``camera.resized`` for another resolution).
        soft: 0 for a bool mask; > 0 for a float coverage ``sigmoid(-sdf / soft)`` (differentiable).
        chunk_size: batch elements per chunk.

    Returns:
        (..., height, width) bool (``soft == 0``) or float mask.
    """
    batch = caps.pa.shape[:-2]
    C = caps.pa.shape[-2]
    pa, pb = caps.pa.reshape(-1, C, 1, 2), caps.pb.reshape(-1, C, 1, 2)
    ra, rb = caps.ra.reshape(-1, C, 1), caps.rb.reshape(-1, C, 1)
    valid = caps.valid.reshape(-1, C, 1)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=pa.dtype, device=pa.device),
        torch.arange(width, dtype=pa.dtype, device=pa.device),
        indexing="ij",
    )
    grid = torch.stack([u, v], -1).reshape(1, 1, -1, 2)
    n = _chunk_rows(C * height * width, chunk_size, pa.device)
    outs = []
    for s in range(0, pa.shape[0], n):
        sl = slice(s, s + n)
        sdf = _uneven_capsule_sdf(grid, pa[sl], pb[sl], ra[sl], rb[sl])
        sdf = torch.where(valid[sl], sdf, torch.full_like(sdf, float("inf")))
        sdf = sdf.amin(1)
        outs.append(sdf <= 0 if soft <= 0 else torch.sigmoid(-sdf / soft))
    out = torch.cat(outs, 0)
    return out.reshape(*batch, height, width)


def sample_pattern(n: int, dim: int = 2, *, dtype=torch.float64, device=None, offset: float = 0.5):
    """Fixed low-discrepancy points in [0, 1)^dim: the R_d sequence of M. Roberts (additive recurrence with
    the generalised golden ratio). Deterministic, so a likelihood built on it is a smooth function of the
    pose and the same for every call (common random numbers across particles)."""
    # phi_d is the unique positive root of x^(d+1) = x + 1.
    g = 2.0
    for _ in range(64):
        g = (1 + g) ** (1.0 / (dim + 1))
    alpha = torch.tensor([g ** -(k + 1) for k in range(dim)], dtype=torch.float64)
    i = torch.arange(1, n + 1, dtype=torch.float64)[:, None]
    return torch.frac(offset + i * alpha).to(dtype=dtype, device=device)


def _unit_samples(n_body: int, n_cap: int, generator, dtype, device, batch: tuple[int, ...] = ()):
    """The unit samples of :func:`sample_in_capsules`: body ``u`` and ``2 s - 1`` (n_body,) (or
    (*batch, n_body)), and the caps' ``rho cos(phi)``, ``rho sin(phi)`` (2, n_cap) (or (*batch, 2, n_cap)),
    polar coordinates in a unit half-disc. The fixed pattern is built once per size, dtype and device."""
    if generator is None:
        return _fixed_unit_samples(n_body, n_cap, dtype, device)
    ub = torch.rand(*batch, n_body, 2, generator=generator, dtype=dtype, device=device)
    uc = torch.rand(*batch, 2, n_cap, 2, generator=generator, dtype=dtype, device=device)
    return _polar(ub, uc)


@functools.lru_cache(maxsize=64)
def _fixed_unit_samples(n_body: int, n_cap: int, dtype, device):
    # ordinary tensors even when first asked for in inference mode (capsule_chamfer): autograd reuses them
    with torch.inference_mode(False):
        ub = sample_pattern(n_body, 2, dtype=dtype, device=device)
        uc = sample_pattern(n_cap, 2, dtype=dtype, device=device, offset=0.25).expand(2, n_cap, 2)
        return _polar(ub, uc)


def _polar(ub: torch.Tensor, uc: torch.Tensor):
    rho, phi = uc[..., 0].sqrt(), math.pi * (uc[..., 1] - 0.5)
    return ub[..., 0], 2 * ub[..., 1] - 1, rho * torch.cos(phi), rho * torch.sin(phi)


def sample_in_capsules(
    caps: Capsules2D,
    n_body: int = 12,
    n_cap: int = 2,
    *,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Area-uniform points inside each projected capsule, with the area each point stands for.

    Each capsule is split into its trapezoid body and two outer half-discs; ``n_body`` points fill the
    body with density proportional to the local width, ``n_cap`` points fill each half-disc. The region is
    ``{p : |p - q(t)| <= r(t)}`` with ``q(t)`` the axis point nearest to ``p`` and ``r`` linear along the
    axis, which equals the hull of the two discs up to a sliver of relative width ``((ra - rb) / L)^2``.

    Args:
        caps: :class:`Capsules2D` (..., C).
        n_body, n_cap: points per capsule body and per end cap (M = n_body + 2 n_cap per capsule).
        generator: None for the fixed quasi-random pattern of :func:`sample_pattern` (deterministic; the
            same unit pattern mapped into every capsule), or a ``torch.Generator`` for i.i.d. points.

    Returns:
        points: (..., C * M, 2) pixels, capsule-major (capsule c owns rows ``c*M:(c+1)*M``).
        weights: (..., C * M) pixel area per point (0 for invalid capsules); their sum over a capsule is
        its area, differentiable with respect to the capsule parameters.
    """
    px, py, k = _area_points(caps, n_body, n_cap, generator)
    batch = caps.pa.shape[:-2]
    return torch.stack([px, py], -1).reshape(*batch, -1, 2), k["w"].reshape(*batch, -1)


def _area_points(caps: Capsules2D, n_body: int, n_cap: int, generator=None, derivatives: bool = False):
    """The points of :func:`sample_in_capsules` as x and y coordinates ``px``, ``py`` (..., C, M) (separate
    tensors: a pass over a trailing dim of size 2 costs several plain ones) and the terms of
    :func:`_point_coordinates` by name: the axis ``ex``, ``ey`` and its length ``L`` (..., C), ``alpha``,
    ``beta``, ``w`` and, with ``derivatives``, ``der``."""
    ax, ay = caps.pa.unbind(-1)
    ex, ey = (caps.pb - caps.pa).unbind(-1)
    L = torch.hypot(ex, ey).clamp_min(1e-9)
    alpha, beta, w, *der = _point_coordinates(
        L, caps.ra, caps.rb, caps.valid, n_body, n_cap, generator, derivatives
    )
    exu, eyu = ex.unsqueeze(-1), ey.unsqueeze(-1)
    # p = pa + alpha e + beta n with n = (-e_y, e_x)
    px = torch.addcmul(torch.addcmul(ax.unsqueeze(-1), alpha, exu), beta, eyu, value=-1.0)
    py = torch.addcmul(torch.addcmul(ay.unsqueeze(-1), alpha, eyu), beta, exu)
    k = {"ex": ex, "ey": ey, "L": L, "alpha": alpha, "beta": beta, "w": w, "der": der[0] if der else None}
    return px, py, k


def _cap_rows(cos_c: torch.Tensor, sin_c: torch.Tensor) -> dict[str, torch.Tensor]:
    """The caps' unit samples as rows over both caps' ``2 n_cap`` points (the cap of ``pa``, then that of
    ``pb``), zero on the other cap, so that a cap term is one product of a row with a per-capsule scalar
    for both caps at once: ``ca = (-cos_a, 0)``, ``cb = (0, cos_b)``, ``sa = (sin_a, 0)``, ``sb = (0,
    sin_b)``, and the indicators ``ea = (1, 0)``, ``eb = (0, 1)``."""
    z = torch.zeros_like(cos_c[..., 0, :])
    one = torch.ones_like(z)
    cos_a, cos_b, sin_a, sin_b = cos_c[..., 0, :], cos_c[..., 1, :], sin_c[..., 0, :], sin_c[..., 1, :]
    rows = {
        "ca": (-cos_a, z),
        "cb": (z, cos_b),
        "sa": (sin_a, z),
        "sb": (z, sin_b),
        "ea": (one, z),
        "eb": (z, one),
    }
    return {k: torch.cat(v, -1) for k, v in rows.items()}


@functools.lru_cache(maxsize=64)
def _fixed_cap_rows(n_body: int, n_cap: int, dtype, device) -> dict[str, torch.Tensor]:
    """:func:`_cap_rows` of the fixed pattern (:func:`_fixed_unit_samples`), built once."""
    with torch.inference_mode(False):
        _, _, cos_c, sin_c = _fixed_unit_samples(n_body, n_cap, dtype, device)
        return _cap_rows(cos_c, sin_c)


def _point_coordinates(L, ra, rb, valid, n_body: int, n_cap: int, generator=None, derivatives: bool = False):
    """The points of :func:`sample_in_capsules` in the frame of capsules of axis length ``L`` (clamped to
    1e-9) and radii ``ra``, ``rb`` (..., C): ``p = pa + alpha e + beta n`` with ``e = pb - pa`` and its
    normal ``n = (-e_y, e_x)``, and their areas ``w`` (0 where not ``valid``).

    Returns ``alpha``, ``beta``, ``w`` (..., C, M) with M = n_body + 2 n_cap (body points, then the caps of
    ``pa`` and of ``pb``); with ``derivatives`` also their derivatives in ``ra``, ``rb`` and ``L``: three
    (..., C, 3 M) tensors ``[d alpha, d beta, d w]`` (with ``dL/de = e / L`` the points' and areas'
    Jacobian in the capsule, :func:`torchpf.geometry.capsule_chamfer`).

    The caps' terms are products of per-capsule scalars with the rows of :func:`_cap_rows` (both caps in
    one operation): a refinement step evaluates this for a few poses, where the number of operations is
    the cost."""
    batch = L.shape
    u, h, cos_c, sin_c = _unit_samples(n_body, n_cap, generator, L.dtype, L.device, tuple(batch))
    rows = _fixed_cap_rows(n_body, n_cap, L.dtype, L.device) if generator is None else _cap_rows(cos_c, sin_c)
    ca, cb, sa, sb, ea, eb = (rows[k] for k in ("ca", "cb", "sa", "sb", "ea", "eb"))
    inv = L.reciprocal().unsqueeze(-1)  # (reciprocal: 1.0 / tensor dispatches through Python)
    # Body: t has density proportional to r(t) = ra + t (rb - ra) (inverse CDF of a linear density:
    # ra t + qa t^2 = qc), the offset across the axis is (2 s - 1) r(t).
    ra_, rb_ = ra.unsqueeze(-1), rb.unsqueeze(-1)
    dr = rb_ - ra_
    qc = u * (0.5 * (ra_ + rb_))
    t = 2 * qc / (ra_ + torch.addcmul(ra_ * ra_, dr, qc, value=2.0).clamp_min(0).sqrt()).clamp_min(1e-12)
    rt = torch.addcmul(ra_, t, dr)
    # Caps: uniform in a half-disc facing away from the other end (centre pa: along -e; pb: along +e).
    ra_l, rb_l = ra_ * inv, rb_ * inv
    cap_a = torch.addcmul(ca * ra_l, cb, rb_l)  # alpha of the caps less their start (0 for pa, 1 for pb)
    alpha = torch.cat([t, cap_a + eb], -1)
    body_beta = h * rt * inv
    beta = torch.cat([body_beta, torch.addcmul(sa * ra_l, sb, rb_l)], -1)
    half_disc = 0.5 * math.pi / n_cap
    valid = valid.unsqueeze(-1).to(L.dtype)
    vh = valid * half_disc
    w = torch.cat(
        [
            ((L.unsqueeze(-1) * valid) * ((ra_ + rb_) / n_body)).expand(*batch, n_body),
            torch.addcmul(ea * (ra_ * ra_ * vh), eb, rb_ * rb_ * vh),
        ],
        -1,
    )
    if not derivatives:
        return alpha, beta, w
    # implicit derivatives of the body's t: F = ra t + qa t^2 - qc = 0, dF/dt = r(t)
    irt = rt.reciprocal()
    tt = t * t
    t_ra = (0.5 * (tt + u) - t) * irt
    t_rb = 0.5 * (u - tt) * irt
    hi = h * inv
    wb = ((L.unsqueeze(-1) * valid) / n_body).expand(*batch, n_body)
    zb = torch.zeros_like(t)
    ninv = -inv
    d_ra = torch.cat(
        [t_ra, ca * inv, hi * torch.addcmul(torch.rsub(t, 1.0), dr, t_ra), sa * inv, wb, ea * (2 * vh * ra_)],
        -1,
    )
    d_rb = torch.cat([t_rb, cb * inv, hi * torch.addcmul(t, dr, t_rb), sb * inv, wb, eb * (2 * vh * rb_)], -1)
    # d / dL: -x / L for beta and the caps' alpha - alpha_0 (the cap of pb starts at 1)
    d_L = torch.cat(
        [
            zb,
            cap_a * ninv,
            beta * ninv,
            (valid * (ra_ + rb_) / n_body).expand(*batch, n_body),
            torch.zeros_like(cap_a),
        ],
        -1,
    )
    return alpha, beta, w, (d_ra, d_rb, d_L)


def outline_points(caps: Capsules2D, n_side: int = 6, n_cap: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Points on each projected capsule's outline: ``n_side`` along each flank (at ``r(t)`` from the axis)
    and ``n_cap`` on each outer half-circle, at fixed stratified positions.

    Returns:
        points (..., C * M, 2) with M = 2 n_side + 2 n_cap, and valid (..., C * M) bool.
    """
    pa, pb, ra, rb = caps.pa, caps.pb, caps.ra, caps.rb
    e = pb - pa
    L = e.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    ex = e / L
    nx = torch.stack([-ex[..., 1], ex[..., 0]], -1)
    t = (torch.arange(n_side, dtype=pa.dtype, device=pa.device) + 0.5) / n_side
    rt = ra.unsqueeze(-1) + t * (rb - ra).unsqueeze(-1)
    axis = pa.unsqueeze(-2) + (t.unsqueeze(-1) * e.unsqueeze(-2))
    sides = [axis + sgn * rt.unsqueeze(-1) * nx.unsqueeze(-2) for sgn in (1.0, -1.0)]
    phi = math.pi * ((torch.arange(n_cap, dtype=pa.dtype, device=pa.device) + 0.5) / n_cap - 0.5)
    cph, sph = torch.cos(phi).unsqueeze(-1), torch.sin(phi).unsqueeze(-1)
    capl = []
    for centre, rad, out in ((pa, ra, -ex), (pb, rb, ex)):
        dirs = cph * out.unsqueeze(-2) + sph * nx.unsqueeze(-2)
        capl.append(centre.unsqueeze(-2) + rad.unsqueeze(-1).unsqueeze(-1) * dirs)
    pts = torch.cat(sides + capl, -2)
    C, M = pts.shape[-3], pts.shape[-2]
    valid = caps.valid.unsqueeze(-1).expand(*caps.valid.shape, M)
    batch = pa.shape[:-2]
    return pts.reshape(*batch, C * M, 2), valid.reshape(*batch, C * M)


def capsule_coverage(
    points: torch.Tensor,
    caps: Capsules2D,
    *,
    softness: float = 0.0,
    reduce: str = "max",
    exclude_own: int | None = None,
    chunk_size: int | None = None,
) -> torch.Tensor:
    """How much each image point is covered by the projected model (the ``f(p, x)`` of Fontmarty's dual
    silhouette cue, §3.2.2).

    Args:
        points: (P, 2) points shared by every pose, or (..., P, 2) whose leading dims broadcast against the
            capsules' (pixels): per pose, or e.g. (V, 1, P, 2) per camera for (V, N, C) capsules (each
            camera's points shared by its N poses: one matrix product per camera).
        caps: :class:`Capsules2D` (..., C).
        softness: 0 for a hard 0/1 inside test; > 0 (pixels) for a linear ramp of that width across each
            capsule boundary, which makes the result differentiable in the capsule parameters.
        reduce: "max" (covered by the union, in [0, 1]) or "sum" (number of capsules covering the point).
        exclude_own: with per-pose points laid out capsule-major, M points per capsule (as returned by
            :func:`sample_in_capsules`/:func:`outline_points`), ignore each point's own capsule.
        chunk_size: poses per chunk (default: about 2^17 pose-capsule-point triples, which keeps the
            element-wise passes in the CPU's cache).

    Returns:
        (..., P) coverage.
    """
    if softness <= 0:  # a hard test has no gradient: no graph, and in-place passes (_coverage_chunk)
        with torch.no_grad():
            batch = caps.pa.shape[:-2]
            if (
                reduce == "max"
                and exclude_own is None
                and _coverage_cpu.AVAILABLE
                and fused_cpu(caps.pa, math.prod(batch))
                and points.dtype == caps.pa.dtype
            ):  # one kernel: each capsule tests the points in its rows that no capsule covers yet
                G, R, pts = _point_groups(points, batch)
                C = caps.pa.shape[-2]
                fields = (caps.pa, caps.pb, caps.ra, caps.rb, caps.valid)
                fields = (f.reshape(G, R, C, *f.shape[len(batch) + 1 :]) for f in fields)
                return _coverage_cpu.coverage(*fields, pts).reshape(*batch, points.shape[-2])
            return _coverage(points, caps, softness, reduce, exclude_own, chunk_size)
    return _coverage(points, caps, softness, reduce, exclude_own, chunk_size)


def _coverage(points, caps, softness, reduce, exclude_own, chunk_size) -> torch.Tensor:
    batch = caps.pa.shape[:-2]
    C, P = caps.pa.shape[-2], points.shape[-2]
    G, R, pts = _point_groups(points, batch)
    if G * R == 0:
        return pts.new_zeros(*batch, P)
    pa, pb = caps.pa.reshape(G, R, C, 2), caps.pb.reshape(G, R, C, 2)
    ra, rb = caps.ra.reshape(G, R, C, 1), caps.rb.reshape(G, R, C, 1)
    valid = caps.valid.reshape(G, R, C, 1)
    # Same quadratic-form trick as in 3D: two GEMMs give |p - a|^2 and the segment parameter of p, in
    # coordinates centred on each group's capsules (conditioning, see capsule_distance).
    # (a NaN pose must not shift the centre of the other poses of its group: it would cover nothing for them)
    finite = torch.nan_to_num(pa.detach(), nan=0.0, posinf=0.0, neginf=0.0)
    center = finite.mean((1, 2), keepdim=True) if pa.numel() else pa.new_zeros(G, 1, 1, 2)
    pc = pts - center[:, 0]
    PtT = torch.cat([pc, (pc * pc).sum(-1, keepdim=True), torch.ones_like(pc[..., :1])], -1).transpose(-1, -2)
    own = None
    if exclude_own is not None:
        owner = torch.arange(P, device=pts.device) // exclude_own  # owner capsule of each point
        own = owner[None, :] == torch.arange(C, device=pts.device)[:, None]  # (C, P)
    # chunks of (groups, rows) of about `budget` poses
    budget = (
        int(chunk_size)
        if chunk_size is not None
        else max(1, chunk_elements(pts.device, _COVERAGE_CHUNK) // max(1, C * P))
    )
    n_r = min(R, budget)
    n_g = max(1, budget // n_r) if n_r == R else 1
    outs = []
    for g0 in range(0, G, n_g):
        gs = slice(g0, g0 + n_g)
        row_outs = []
        for r0 in range(0, R, n_r):
            rs = slice(r0, r0 + n_r)
            cov = _coverage_chunk(
                pa[gs, rs] - center[gs],
                pb[gs, rs] - center[gs],
                ra[gs, rs],
                rb[gs, rs],
                valid[gs, rs],
                own,
                PtT[gs],
                softness,
                reduce,
            )
            row_outs.append(cov)
        outs.append(torch.cat(row_outs, 1) if len(row_outs) > 1 else row_outs[0])
    return (torch.cat(outs, 0) if len(outs) > 1 else outs[0]).reshape(*batch, P)


def _coverage_chunk(a, b, ra, rb, valid, own, PtT, softness: float, reduce: str) -> torch.Tensor:
    """Coverage (g, r, P) of the points ``PtT`` (g, 4, P) (rows ``x, y, x^2 + y^2, 1``) by capsules
    ``a``, ``b`` (g, r, C, 2), ``ra``, ``rb``, ``valid`` (g, r, C, 1); ``own`` (C, P) pairs to skip, or
    None."""
    g, r, C = a.shape[:3]
    e = b - a
    ee = (e * e).sum(-1, keepdim=True)  # (g, r, C, 1)
    inv = torch.where(ee > 1e-12, ee.clamp_min(1e-12).reciprocal(), torch.zeros_like(ee))
    one = torch.ones_like(ee)
    aa = (a * a).sum(-1, keepdim=True)
    if softness <= 0:  # an invalid capsule is infinitely far from every point
        aa = aa.masked_fill(~valid, math.inf)
    A_uu = torch.cat([-2 * a, one, aa], -1)
    A_s = torch.cat([e * inv, 0 * one, -(a * e).sum(-1, keepdim=True) * inv], -1)
    G_uu = torch.bmm(A_uu.reshape(g, r * C, 4), PtT).view(g, r, C, -1)  # |p - a|^2
    G_s = torch.bmm(A_s.reshape(g, r * C, 4), PtT).view(g, r, C, -1)  # axis parameter of p, unclamped
    if softness > 0:
        tc = G_s.clamp(0.0, 1.0)
        d2 = G_uu - ee * tc * (2 * G_s - tc)
        rad = ra + tc * (rb - ra)
        # A ramp in distance, linearised in squared distance: (r^2 - d^2) / 2r ~ r - d near the boundary.
        cov = (0.5 + (rad * rad - d2) / (2 * softness * rad.clamp_min(1e-6))).clamp(0.0, 1.0) * valid
        if own is not None:
            cov = cov.masked_fill(own, 0.0)
        return cov.amax(2) if reduce == "max" else cov.sum(2)
    # hard test (run without autograd): in place on the GEMMs' outputs, and "covered by any capsule" as
    # min over capsules of d^2 - r^2 <= 0 (a float reduction, several times faster than bool any)
    tc = G_s.clamp(0.0, 1.0)
    d2 = G_uu.sub_(G_s.mul_(2).sub_(tc).mul_(tc).mul_(ee))  # |p - a - tc e|^2
    rad = tc.mul_(rb - ra).add_(ra)
    margin = d2.sub_(rad.mul_(rad)).nan_to_num_(nan=math.inf)  # a NaN capsule covers nothing
    if own is not None:
        margin.masked_fill_(own, math.inf)
    if reduce == "max":
        return (margin.amin(2) <= 0).to(a.dtype)
    return (margin <= 0).sum(2).to(a.dtype)
