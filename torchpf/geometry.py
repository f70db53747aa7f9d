"""Batched capsule geometry: 3D distances (Hauberg §5), ray casting, projected 2D capsules and silhouettes.

The body model is a union of *capsules* (sphere-swept segments): one per bone, from the parent joint ``a`` to
the child joint ``b`` with radius ``r`` (``Skeleton.capsules``). This module answers, for many poses at once:

* :func:`capsule_distance` - signed distance (m) from K points to the union of C capsules for every pose,
  the ``D`` of Hauberg et al. eq. 15. With ``view_point`` only the half of each capsule facing that point
  is kept (Hauberg §5: a single depth camera sees only the front halves). Exact (closed form): the axial
  coordinate and the squared distance to each axis line are linear in the points' quadratic monomials, so
  two GEMMs plus a few elementwise passes do the work, chunked over poses to bound memory;
  :func:`capsule_truncated_cost` reduces eq. 15 on the fly (optionally ``torch.compile``-fused).
* :func:`raycast_capsules` - first hit of rays with the capsules (depth images with self-occlusion).
* :func:`project_capsules` - each 3D capsule seen by a camera becomes a 2D *tapered capsule*: the convex
  hull of two discs (the projected end spheres, radius ~``f r / z`` pixels) - the "projected truncated
  cones" of Fontmarty et al. §3.2.1.
* :func:`capsule_masks` - rasterise projected capsules into (..., H, W) silhouettes (bool or soft).
* :func:`sample_in_capsules` - area-uniform sample points inside projected capsules with their area
  weights (fixed quasi-random pattern, or random with a ``torch.Generator``), :func:`capsule_coverage`
  - whether image points are covered by the projected model, and :func:`outline_points` - points on the
  capsule outlines (Chamfer matching).

Shapes: ``...`` batch (poses), ``C`` capsules, ``K`` or ``P`` points. Units: metres in 3D, pixels in 2D.
dtype and device follow the inputs; everything is differentiable where the geometry is.

Example::

    ends, radii = skel.capsules(theta)                               # (N, C, 2, 3), (C,)
    d = capsule_distance(cloud, ends[..., 0, :], ends[..., 1, :], radii)   # cloud (K, 3) -> (N, K)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

__all__ = [
    "Capsules2D",
    "capsule_coverage",
    "capsule_distance",
    "capsule_masks",
    "capsule_truncated_cost",
    "outline_points",
    "project_capsules",
    "raycast_capsules",
    "sample_in_capsules",
    "sample_pattern",
]

# Elements (poses x capsules x points) per chunk of the distance kernels: large enough that per-op
# overhead is amortised, small enough (~1 MB per float32 temporary) to stay in the L2 cache.
_CHUNK_ELEMENTS = 1 << 18


def _chunk_rows(per_row: int, chunk_size: int | None) -> int:
    if chunk_size is not None:
        return max(1, int(chunk_size))
    return max(1, _CHUNK_ELEMENTS // max(1, per_row))


# ---------------------------------------------------------------------- 3D distances
def _point_features(P: torch.Tensor) -> torch.Tensor:
    """(..., K, 3) -> (..., K, 10) monomials ``(x, y, z, x^2, y^2, z^2, xy, xz, yz, 1)``: every quantity the
    kernel needs (axial coordinate, squared distance to the axis line) is linear in them, hence a GEMM."""
    x, y, z = P.unbind(-1)
    return torch.stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z, torch.ones_like(x)], -1)


def _capsule_coeffs(a: torch.Tensor, b: torch.Tensor, center: torch.Tensor, view: torch.Tensor | None):
    """Per-capsule rows of the linear forms used by :func:`_sdf_chunk` (coordinates relative to ``center``).

    With ``e = (b - a) / L`` the unit axis and ``L`` the length, ``f(p) . A_q = (p - a) . e`` is the axial
    coordinate (m) and ``f(p) . A_perp = |p - a|^2 - ((p - a) . e)^2`` the squared distance to the axis line;
    with a view direction ``v`` (unit, orthogonal to ``e``), ``f(p) . A_v = (p - a) . v``.
    """
    a = a - center
    e = b - center - a
    L = e.norm(dim=-1)
    e = torch.where(
        L[..., None] > 1e-10, e / L.clamp_min(1e-10)[..., None], torch.zeros_like(e)
    )  # sphere: e = 0
    ae = (a * e).sum(-1)
    ex, ey, ez = e.unbind(-1)
    zeros6 = a.new_zeros(*a.shape[:-1], 6)
    A_q = torch.cat([e, zeros6, -ae[..., None]], -1)
    quad = torch.stack([1 - ex * ex, 1 - ey * ey, 1 - ez * ez, -2 * ex * ey, -2 * ex * ez, -2 * ey * ez], -1)
    A_perp = torch.cat([-2 * a + 2 * ae[..., None] * e, quad, ((a * a).sum(-1) - ae * ae)[..., None]], -1)
    A_v = None
    if view is not None:
        A_v = torch.cat([view, zeros6, -(a * view).sum(-1, keepdim=True)], -1)
    return A_q, A_perp, A_v, L


def _view_directions(a: torch.Tensor, b: torch.Tensor, view_point: torch.Tensor) -> torch.Tensor:
    """Unit vector from each capsule towards ``view_point``, made orthogonal to the capsule axis."""
    m = 0.5 * (a + b)
    w = view_point.unsqueeze(-2) - m
    e = b - a
    ee = (e * e).sum(-1, keepdim=True)
    v = w - (w * e).sum(-1, keepdim=True) / ee.clamp_min(1e-20) * e
    v = torch.where(ee > 1e-20, v, w)  # a sphere faces the camera along the line of sight
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _sdf_chunk(G_q, G_perp, G_v, L, r, inplace: bool):
    """(n, C, K) GEMM outputs -> (n, K) signed distance to the union of (half-)capsules.

    ``d^2 = perp^2 + (q - clamp(q, 0, L))^2``: the squared distance to the axis line plus the axial overshoot
    beyond the segment. ``inplace`` reuses buffers (no autograd); it halves the memory traffic.
    """
    tiny = 1e-24 if G_q.dtype == torch.float64 else 1e-16  # keeps sqrt's gradient finite on the axis
    over = G_q - torch.clamp(G_q, torch.zeros_like(L).unsqueeze(-1), L.unsqueeze(-1))
    rr = r.unsqueeze(-1)
    if G_v is None and inplace:
        d2 = torch.addcmul(G_perp, over, over, out=over)
        return d2.clamp_min_(tiny).sqrt_().sub_(rr).amin(-2)
    d2 = torch.addcmul(G_perp, over, over)
    d = d2.clamp_min(tiny).sqrt()
    if G_v is None:
        return (d - rr).amin(-2)
    # Half capsule: in front of the plane through the axis (n.v >= 0) the nearest skin point is along the
    # normal, as for the full capsule; behind it, the nearest point is on the rim where the shell is cut.
    nv = G_v
    par = (d2 - nv * nv).clamp_min(tiny).sqrt()
    back = (nv * nv + (par - rr).square()).clamp_min(tiny).sqrt()
    sd = torch.where(nv >= 0, d - rr, back)
    return sd.amin(-2)


def _capsule_sdf_chunks(
    points: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    radius: torch.Tensor,
    view_point: torch.Tensor | None,
    chunk_size: int | None,
    reduce: Callable[[torch.Tensor], torch.Tensor] | None,
    fused: Callable | None = None,
) -> torch.Tensor:
    """Engine of :func:`capsule_distance`; ``reduce`` maps each (n, K) chunk to (n, ...) (e.g. a sum).

    ``fused(A_q, A_perp, A_v, featsT, L, r)``, if given, replaces GEMMs, kernel and reduction (per-pose
    point clouds excepted): the ``torch.compile`` path of :func:`capsule_truncated_cost`.
    """
    batch = torch.broadcast_shapes(points.shape[:-2], a.shape[:-2], b.shape[:-2])
    K, C = points.shape[-2], a.shape[-2]
    a = a.expand(*batch, C, 3).reshape(-1, C, 3)
    b = b.expand(*batch, C, 3).reshape(-1, C, 3)
    B = a.shape[0]
    shared = math.prod(points.shape[:-2]) == 1
    P = points.reshape(K, 3) if shared else points.expand(*batch, K, 3).reshape(B, K, 3)
    # Centring on the body keeps |p - c|^2 small near the skin, where precision matters, so the expanded
    # quadratic forms lose no float32 accuracy (far-away points and outliers have large distances anyway).
    center = a.detach().reshape(-1, 3).mean(0) if a.numel() else a.new_zeros(3)
    feats = _point_features(P - center)  # (.., K, 10)
    featsT = feats.transpose(-1, -2).contiguous()
    radius = radius.to(a).expand(*batch, C).reshape(B, C) if radius.ndim > 1 else radius.to(a).expand(B, C)
    view = None
    if view_point is not None:
        vp = torch.as_tensor(view_point, dtype=a.dtype, device=a.device)
        vp = vp.expand(*batch, 3).reshape(B, 3)
        view = _view_directions(a, b, vp)
    inplace = not (
        torch.is_grad_enabled() and any(x.requires_grad for x in (points, a, b, radius) if x is not None)
    )
    n = _chunk_rows(C * K, chunk_size)
    outs = []
    for s in range(0, B, n):
        sl = slice(s, s + n)
        A_q, A_perp, A_v, L = _capsule_coeffs(a[sl], b[sl], center, None if view is None else view[sl])
        m = A_q.shape[0]
        if fused is not None and shared:
            outs.append(fused(A_q, A_perp, A_v, featsT, L, radius[sl]))
            continue
        if shared:
            G_q = (A_q.reshape(m * C, 10) @ featsT).view(m, C, K)
            G_perp = (A_perp.reshape(m * C, 10) @ featsT).view(m, C, K)
            G_v = None if A_v is None else (A_v.reshape(m * C, 10) @ featsT).view(m, C, K)
        else:
            G_q = torch.bmm(A_q, featsT[sl])
            G_perp = torch.bmm(A_perp, featsT[sl])
            G_v = None if A_v is None else torch.bmm(A_v, featsT[sl])
        sd = _sdf_chunk(G_q, G_perp, G_v, L, radius[sl], inplace)
        outs.append(sd if reduce is None else reduce(sd))
    out = torch.cat(outs, 0) if outs else a.new_zeros((0, K))
    return out.reshape(*batch, *out.shape[1:])


def capsule_distance(
    points: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    radius: torch.Tensor,
    *,
    view_point: torch.Tensor | None = None,
    chunk_size: int | None = None,
) -> torch.Tensor:
    """Signed distance from points to the union of capsules (Hauberg et al. §5, the D of eq. 15).

    Args:
        points: (..., K, 3) points (m). Leading dims broadcast against the capsules', so one cloud (K, 3)
            is scored against every pose without copies.
        a, b: (..., C, 3) capsule axis end points (m) (parent and child joints).
        radius: (C,) or (..., C) radii (m).
        view_point: optional (3,) or (..., 3) sensor position (m). If given, each capsule is cut by the
            plane through its axis facing the sensor and only the visible half-shell is kept; points
            behind that plane are scored by their distance to the cut rim (always >= 0).
        chunk_size: poses per chunk (default: about 2^20 pose-capsule-point triples); bounds the
            temporaries to a few MB at any N, e.g. N=10,000, K=2,000 costs only the (N, K) output.

    Returns:
        (..., K) signed distance (m): ``min_c (|p - segment_c| - r_c)``, negative inside the body.
        Differentiable with respect to points, ends and radii.
    """
    return _capsule_sdf_chunks(points, a, b, radius, view_point, chunk_size, None)


def _truncated_cost_kernel(A_q, A_perp, A_v, featsT, L, r, tau: float):
    """Fused form of GEMMs + :func:`_sdf_chunk` + ``sum_k min(sd^2, tau)`` for ``torch.compile``: written
    as broadcast products so that inductor emits one loop with no (n, C, K) temporaries."""
    G_q = (A_q.unsqueeze(-1) * featsT).sum(-2)
    G_perp = (A_perp.unsqueeze(-1) * featsT).sum(-2)
    G_v = None if A_v is None else (A_v.unsqueeze(-1) * featsT).sum(-2)
    sd = _sdf_chunk(G_q, G_perp, G_v, L, r, False)
    return sd.square().clamp_max(tau).sum(-1)


_COMPILED: dict = {}


def _compiled_cost(tau: float) -> Callable:
    import functools

    if "kernel" not in _COMPILED:
        _COMPILED["kernel"] = torch.compile(_truncated_cost_kernel, dynamic=True)
    return functools.partial(_COMPILED["kernel"], tau=tau)


def capsule_truncated_cost(
    points: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    radius: torch.Tensor,
    *,
    tau: float,
    view_point: torch.Tensor | None = None,
    chunk_size: int | None = None,
    compile: bool = False,
) -> torch.Tensor:
    """``sum_k min(D(p_k)^2, tau)`` with D the (half-)capsule distance of :func:`capsule_distance`: the
    data term of Hauberg et al. eq. 15, reduced chunk by chunk so the (..., K) distances are never stored.

    Args:
        points, a, b, radius, view_point, chunk_size: as in :func:`capsule_distance`.
        tau: truncation of the squared distance (m^2).
        compile: fuse GEMMs, distance and reduction with ``torch.compile`` (inductor; needs a C++ compiler
            on CPU). About 2x faster on CPU once compiled; the first call compiles (~10-20 s). Falls back to
            the eager kernel with a warning if compilation fails.

    Returns:
        (...,) cost in m^2.
    """
    tau = float(tau)
    fused = None
    if compile:
        fused = _compiled_cost(tau)

    def reduce(sd):
        return sd.square().clamp_max(tau).sum(-1)

    if fused is None:
        return _capsule_sdf_chunks(points, a, b, radius, view_point, chunk_size, reduce)
    cs = chunk_size if chunk_size is not None else max(1, (1 << 20) // max(1, a.shape[-2] * points.shape[-2]))
    try:
        return _capsule_sdf_chunks(points, a, b, radius, view_point, cs, reduce, fused)
    except Exception as e:  # inductor missing a compiler or failing on this platform
        import warnings

        warnings.warn(f"torch.compile failed ({type(e).__name__}: {e}); using the eager kernel", stacklevel=2)
        _COMPILED["kernel"] = _truncated_cost_kernel
        return _capsule_sdf_chunks(points, a, b, radius, view_point, chunk_size, reduce)


# ---------------------------------------------------------------------- ray casting
def raycast_capsules(
    origins: torch.Tensor,
    directions: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    radius: torch.Tensor,
    *,
    chunk_size: int | None = None,
) -> torch.Tensor:
    """Distance along each ray to its first hit with the union of capsules (closed form, no marching).

    Args:
        origins: (..., R, 3) or (3,) ray origins (m). directions: (..., R, 3) unit directions.
        a, b: (C, 3) capsule ends; radius: (C,) radii (m). One pose: loop over frames outside.

    Returns:
        (..., R) hit distance (m) along the ray; ``inf`` where the ray misses every capsule or only hits
        behind its origin. The nearest capsule wins, so self-occlusion is respected.
    """
    d = directions
    shape = d.shape[:-1]
    d = d.reshape(-1, 3)
    a, b, r = a.to(d), b.to(d), radius.to(d)
    o = origins.to(d)
    shared = o.numel() == 3
    o = o.reshape(1, 3) if shared else o.expand(*shape, 3).reshape(-1, 3)
    ba = b - a  # (C, 3)
    baba = (ba * ba).sum(-1)
    r2 = r * r
    inf = torch.tensor(float("inf"), dtype=d.dtype, device=d.device)
    n = _chunk_rows(a.shape[0] * 8, chunk_size)
    outs = []
    for s in range(0, d.shape[0], n):
        rd = d[s : s + n]
        ro = o if shared else o[s : s + n]
        # Every dot product below is a small GEMM of the rays against the C capsules.
        bard = rd @ ba.T  # (n, C)
        ro_ba, ro_a, ro_b = ro @ ba.T, ro @ a.T, ro @ b.T
        rd_a, rd_b, rd_ro = rd @ a.T, rd @ b.T, (rd * ro).sum(-1, keepdim=True)
        baoa = ro_ba - (a * ba).sum(-1)
        rdoa = rd_ro - rd_a
        ro2 = (ro * ro).sum(-1, keepdim=True)
        oaoa = ro2 - 2 * ro_a + (a * a).sum(-1)
        # Infinite cylinder around the axis (Quilez's capsule intersection), then the end spheres.
        qa = baba - bard * bard
        qb = baba * rdoa - baoa * bard
        qc = baba * oaoa - baoa * baoa - r2 * baba
        h = qb * qb - qa * qc
        ok_cyl = (h >= 0) & (qa > 1e-12 * baba.clamp_min(1e-30))
        t_cyl = (-qb - h.clamp_min(0).sqrt()) / torch.where(ok_cyl, qa, torch.ones_like(qa))
        y = baoa + t_cyl * bard
        hits = torch.where(ok_cyl & (y > 0) & (y < baba) & (t_cyl > 0), t_cyl, inf)
        for bs, cs in (
            (rdoa, oaoa - r2),
            (rd_ro - rd_b, ro2 - 2 * ro_b + (b * b).sum(-1) - r2),
        ):
            hs = bs * bs - cs
            root = hs.clamp_min(0).sqrt()
            t0, t1 = -bs - root, -bs + root
            t_sph = torch.where(t0 > 0, t0, t1)  # origin inside the sphere: exit point
            hits = torch.minimum(hits, torch.where((hs >= 0) & (t_sph > 0), t_sph, inf))
        outs.append(hits.amin(-1))
    return torch.cat(outs).reshape(shape)


# ---------------------------------------------------------------------- projected capsules
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


def project_capsules(camera, a: torch.Tensor, b: torch.Tensor, radius: torch.Tensor, near: float = 1e-2):
    """Project 3D capsules into a camera (Fontmarty et al. §3.2.1 "projected truncated cones").

    Args:
        camera: :class:`torchpf.camera.Camera` (or any object with ``project``, ``to_camera``, ``focal``).
        a, b: (..., C, 3) ends (m); radius: (C,) radii (m); near: minimum depth (m) of a valid end.

    Returns:
        :class:`Capsules2D` with radii ``f r / (z sqrt(cos t))`` (pixels) at each end's depth ``z`` and
        angle ``t`` off the optical axis: the perspective image of a sphere is an ellipse, this circle has
        its area (exact on the optical axis).
    """
    ends = torch.stack([a, b], -2)
    uv = camera.project(ends)
    xc = camera.to_camera(ends)
    z = xc[..., 2]
    r = radius.to(z)
    # A sphere at angle t off the optical axis images as an ellipse with semi-axes ~ f r / z (across) and
    # f r / (z cos t) (radially); the area-preserving circle has radius f r / (z sqrt(cos t)).
    zc = z.clamp_min(near)
    rad = camera.focal * r.unsqueeze(-1) / zc * (xc.norm(dim=-1) / zc).sqrt()
    valid = (z > near).all(-1)
    return Capsules2D(uv[..., 0, :], uv[..., 1, :], rad[..., 0], rad[..., 1], valid)


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
    # One disc inside the other: the hull is the larger disc.
    nested = cx2 <= 1e-9
    d_nested = torch.minimum(d_a, d_b)
    return torch.where(nested, d_nested, d)


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
    n = _chunk_rows(C * height * width, chunk_size)
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
    if generator is None:
        ub = sample_pattern(n_body, 2, dtype=dtype, device=device)
        uc = sample_pattern(n_cap, 2, dtype=dtype, device=device, offset=0.25)
        return ub, uc
    ub = torch.rand(*batch, n_body, 2, generator=generator, dtype=dtype, device=device)
    uc = torch.rand(*batch, 2, n_cap, 2, generator=generator, dtype=dtype, device=device)
    return ub, uc


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
    pa, pb, ra, rb = caps.pa, caps.pb, caps.ra, caps.rb
    batch = pa.shape[:-1]
    ub, uc = _unit_samples(n_body, n_cap, generator, pa.dtype, pa.device, batch)
    e = pb - pa
    L = e.norm(dim=-1).clamp_min(1e-9)
    ex = e / L.unsqueeze(-1)
    nx = torch.stack([-ex[..., 1], ex[..., 0]], -1)
    # Body: t has density proportional to r(t) = ra + t (rb - ra) (inverse CDF of a linear density).
    u, s = ub[..., 0], ub[..., 1]
    ra_, rb_ = ra.unsqueeze(-1), rb.unsqueeze(-1)
    qa = 0.5 * (rb_ - ra_)
    qc = u * 0.5 * (ra_ + rb_)
    t = 2 * qc / (ra_ + (ra_ * ra_ + 4 * qa * qc).clamp_min(0).sqrt()).clamp_min(1e-12)
    rt = ra_ + t * (rb_ - ra_)
    body = (
        pa.unsqueeze(-2)
        + (t * L.unsqueeze(-1)).unsqueeze(-1) * ex.unsqueeze(-2)
        + ((2 * s - 1) * rt).unsqueeze(-1) * nx.unsqueeze(-2)
    )
    w_body = (L * (ra + rb) / n_body).unsqueeze(-1).expand(*batch, n_body)
    # Caps: uniform in a half-disc facing away from the other end.
    if uc.ndim == 2:
        uc = uc.expand(2, n_cap, 2)
    rho, phi = uc[..., 0].sqrt(), math.pi * (uc[..., 1] - 0.5)
    caps_pts, caps_w = [], []
    for k, (centre, rad, out) in enumerate(((pa, ra, -ex), (pb, rb, ex))):
        rk, pk = rho[..., k, :], phi[..., k, :]
        dirs = torch.cos(pk).unsqueeze(-1) * out.unsqueeze(-2) + torch.sin(pk).unsqueeze(-1) * nx.unsqueeze(
            -2
        )
        caps_pts.append(centre.unsqueeze(-2) + (rk * rad.unsqueeze(-1)).unsqueeze(-1) * dirs)
        caps_w.append((0.5 * math.pi * rad * rad / n_cap).unsqueeze(-1).expand(*batch, n_cap))
    pts = torch.cat([body] + caps_pts, -2)  # (..., C, M, 2)
    w = torch.cat([w_body] + caps_w, -1) * caps.valid.unsqueeze(-1)
    C, M = pts.shape[-3], pts.shape[-2]
    return pts.reshape(*batch[:-1], C * M, 2), w.reshape(*batch[:-1], C * M)


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
        points: (P, 2) points shared by every pose, or (..., P, 2) per pose (pixels).
        caps: :class:`Capsules2D` (..., C).
        softness: 0 for a hard 0/1 inside test; > 0 (pixels) for a linear ramp of that width across each
            capsule boundary, which makes the result differentiable in the capsule parameters.
        reduce: "max" (covered by the union, in [0, 1]) or "sum" (number of capsules covering the point).
        exclude_own: with per-pose points laid out capsule-major, M points per capsule (as returned by
            :func:`sample_in_capsules`/:func:`outline_points`), ignore each point's own capsule.
        chunk_size: poses per chunk.

    Returns:
        (..., P) coverage.
    """
    batch = caps.pa.shape[:-2]
    C = caps.pa.shape[-2]
    pa, pb = caps.pa.reshape(-1, C, 2), caps.pb.reshape(-1, C, 2)
    ra, rb = caps.ra.reshape(-1, C), caps.rb.reshape(-1, C)
    valid = caps.valid.reshape(-1, C)
    B = pa.shape[0]
    P = points.shape[-2]
    shared = points.ndim == 2
    pts = points if shared else points.expand(*batch, P, 2).reshape(B, P, 2)
    # Same quadratic-form trick as in 3D: two GEMMs give |p - a|^2 and the segment parameter of p.
    center = pa.detach().reshape(-1, 2).mean(0) if pa.numel() else pa.new_zeros(2)  # see capsule_distance
    pc = pts - center
    Pt = torch.cat([pc, (pc * pc).sum(-1, keepdim=True), torch.ones_like(pc[..., :1])], -1)
    PtT = Pt.transpose(-1, -2)
    own = None
    if exclude_own is not None:
        own = torch.arange(P, device=pts.device) // exclude_own  # owner capsule of each point
        own = own[None, :] == torch.arange(C, device=pts.device)[:, None]  # (C, P)
    n = _chunk_rows(C * P, chunk_size)
    outs = []
    for s in range(0, B, n):
        sl = slice(s, s + n)
        a_, b_ = pa[sl] - center, pb[sl] - center
        e = b_ - a_
        ee = (e * e).sum(-1)
        inv = torch.where(ee > 1e-12, 1.0 / ee.clamp_min(1e-12), torch.zeros_like(ee))
        one = torch.ones_like(ee)[..., None]
        A_uu = torch.cat([-2 * a_, one, (a_ * a_).sum(-1, keepdim=True)], -1)
        A_s = torch.cat([e * inv[..., None], 0 * one, (-(a_ * e).sum(-1) * inv)[..., None]], -1)
        m = A_uu.shape[0]
        if shared:
            G_uu = (A_uu.reshape(m * C, 4) @ PtT).view(m, C, P)
            G_s = (A_s.reshape(m * C, 4) @ PtT).view(m, C, P)
        else:
            G_uu, G_s = torch.bmm(A_uu, PtT[sl]), torch.bmm(A_s, PtT[sl])
        tc = G_s.clamp(0.0, 1.0)
        d2 = G_uu - ee[..., None] * tc * (2 * G_s - tc)
        r = ra[sl, :, None] + tc * (rb[sl] - ra[sl])[..., None]
        if softness > 0:
            # A ramp in distance, linearised in squared distance: (r^2 - d^2) / 2r ~ r - d near the boundary.
            cov = (0.5 + (r * r - d2) / (2 * softness * r.clamp_min(1e-6))).clamp(0.0, 1.0)
        else:
            cov = (d2 <= r * r).to(pts.dtype)
        keep = valid[sl, :, None]
        if own is not None:
            keep = keep & ~own
        cov = cov * keep
        outs.append(cov.amax(1) if reduce == "max" else cov.sum(1))
    out = torch.cat(outs, 0) if outs else pts.new_zeros((0, P))
    return out.reshape(*batch, P)
