"""Batched 3-D capsule geometry: signed distances (Hauberg §5) and ray casting.

The body model is a union of *capsules* (sphere-swept segments): one per bone, from the parent joint ``a`` to
the child joint ``b`` with radius ``r`` (``Skeleton.capsules``). This module answers, for many poses at once:

* :func:`capsule_distance` - signed distance (m) from K points to the union of C capsules for every pose,
  the ``D`` of Hauberg et al. eq. 15. With ``view_point`` only the half of each capsule facing that point
  is kept (Hauberg §5: a single depth camera sees only the front halves). Exact (closed form): the axial
  coordinate and the squared distance to each axis line are linear in the points' quadratic monomials, so
  two GEMMs plus a few elementwise passes do the work, chunked over poses to bound memory;
  :func:`capsule_truncated_cost` reduces eq. 15 on the fly (optionally ``torch.compile``-fused).
* :func:`raycast_capsules` - first hit of rays with the capsules (depth images with self-occlusion).

Shapes: ``...`` batch (poses), ``C`` capsules, ``K`` points, ``R`` rays. Units: metres. dtype and device
follow the inputs; everything is differentiable where the geometry is.

Example::

    from torchpf.geometry import capsule_distance
    ends, radii = skel.capsules(theta)                               # (N, C, 2, 3), (C,)
    d = capsule_distance(cloud, ends[..., 0, :], ends[..., 1, :], radii)   # cloud (K, 3) -> (N, K)
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

__all__ = [
    "capsule_distance",
    "capsule_truncated_cost",
    "raycast_capsules",
]

# Elements (poses x capsules x points) per chunk of the distance kernels: large enough that per-op
# overhead is amortised, small enough (~1 MB per float32 temporary) to stay in the L2 cache.
_CHUNK_ELEMENTS = 1 << 18
# On a GPU the kernel launches per chunk are the cost, not the cache: chunks there only bound the memory
# (64 MB per float32 temporary). On an H200 with the CPU's chunk sizes (BENCHMARKS.md), the dual silhouette
# cue (~800 chunks at 10,000 poses) and the point-cloud cue (~1,000) ran no faster than 16 CPU cores.
_GPU_CHUNK_ELEMENTS = 1 << 24


def chunk_elements(device: torch.device | str, cpu_elements: int = _CHUNK_ELEMENTS) -> int:
    """Elements per chunk of a chunked kernel on ``device``: ``cpu_elements`` on the CPU (cache-sized), at
    least ``2^24`` elsewhere (memory-bounded)."""
    return cpu_elements if torch.device(device).type == "cpu" else max(cpu_elements, _GPU_CHUNK_ELEMENTS)


def _chunk_rows(per_row: int, chunk_size: int | None, device: torch.device | str = "cpu") -> int:
    if chunk_size is not None:
        return max(1, int(chunk_size))
    return max(1, chunk_elements(device) // max(1, per_row))


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
    n = _chunk_rows(C * K, chunk_size, a.device)
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
    per_row = max(1, a.shape[-2] * points.shape[-2])
    cs = chunk_size if chunk_size is not None else max(1, chunk_elements(a.device, 1 << 20) // per_row)
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
    n = _chunk_rows(a.shape[0] * 8, chunk_size, d.device)
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
