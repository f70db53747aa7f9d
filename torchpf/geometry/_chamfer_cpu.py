"""Fused CPU kernel of the truncated chamfer distance of :mod:`torchpf.geometry.chamfer` (numba; optional).

The tensor version runs each small step of both terms (area points, bilinear look-ups, nearest capsules and
their gradients) as its own tensor operation: for the few poses a refinement step moves, that is ~200
operations per call, and their dispatch, not the arithmetic, is the cost (about half of a refinement step).
This kernel computes the same values and closed-form gradients point by point in one pass per image and
pose. Same inputs and results as the tensor version to rounding (checked by the tests); CPU only, no
autograd (:func:`torchpf.geometry.chamfer.capsule_chamfer` wraps it in its autograd node).

:func:`area_mean` is the model term's sibling for the silhouette cue (Fontmarty eq. 2): the same area
points, an image looked up bilinearly with zeros outside, their area-weighted mean
(:func:`torchpf.geometry.chamfer.capsule_area_mean`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchpf.devices import kernel_array

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; a platform without it keeps the tensor path
    numba = None

AVAILABLE = numba is not None


def _lookup(image, g, px, py):
    """Bilinear look-up of ``image[g]`` at pixel ``(px, py)`` continued outside the image by the distance
    to it, and its slope ``(gx, gy)`` (``_lookup_with_gradient`` of the tensor version, replicate padding)."""
    if math.isnan(px) or math.isnan(py):  # a NaN pose: NaN, and no index computed from it
        return math.nan, 0.0, 0.0
    H, W = image.shape[1], image.shape[2]
    ix = min(max(px, 0.0), W - 1.0)
    iy = min(max(py, 0.0), H - 1.0)
    ox, oy = px - ix, py - iy
    oo = ox * ox + oy * oy
    x0 = min(math.floor(ix), W - 2.0) if W >= 2 else 0.0
    y0 = min(math.floor(iy), H - 2.0) if H >= 2 else 0.0
    fx, fy = ix - x0, iy - y0
    c0, r0 = int(x0), int(y0)
    c1 = c0 + 1 if W >= 2 else c0
    r1 = r0 + 1 if H >= 2 else r0
    v00, v01 = image[g, r0, c0], image[g, r0, c1]
    v10, v11 = image[g, r1, c0], image[g, r1, c1]
    dx0, dx1 = v01 - v00, v11 - v10
    top = v00 + fx * dx0
    dy = (v10 + fx * dx1) - top
    value = top + fy * dy + math.sqrt(oo)
    r_inv = 1.0 / math.sqrt(max(oo, 1e-12))
    gx = dx0 + fy * (dx1 - dx0) if ox == 0 else ox * r_inv
    gy = dy if oy == 0 else oy * r_inv
    return value, gx, gy


def _capsule(pa, pb, ra, rb, g, i, c):
    """Capsule ``c`` of image ``g`` and pose ``i``: its axis' start ``ax, ay``, the axis ``ex, ey`` (``pb -
    pa``), the axis' length ``L`` (at least 1e-9) and the radii ``ra, rb``."""
    ax, ay = pa[g, i, c, 0], pa[g, i, c, 1]
    ex, ey = pb[g, i, c, 0] - ax, pb[g, i, c, 1] - ay
    return ax, ay, ex, ey, max(math.hypot(ex, ey), 1e-9), ra[g, i, c], rb[g, i, c]


def _area_point(k, u, h, cos_c, sin_c, L, r_a, r_b):
    """Area point ``k`` of a capsule of axis length ``L`` and radii ``r_a``, ``r_b`` in the fixed pattern
    (body ``u``, ``h`` (n_body,), caps ``cos_c``, ``sin_c`` (2, n_cap); the points of the tensor version's
    ``_area_points``): its coordinates ``alpha`` along the axis (in axis lengths) and ``beta`` across it
    (``p = pa + alpha e + beta n``, ``n = (-e_y, e_x)``), and the area ``w`` (px^2) it stands for."""
    n_body, n_cap = u.shape[0], cos_c.shape[1]
    inv = 1.0 / L
    if k < n_body:
        dr = r_b - r_a
        qc = u[k] * (0.5 * (r_a + r_b))
        t = 2 * qc / max(r_a + math.sqrt(max(r_a * r_a + 2.0 * dr * qc, 0.0)), 1e-12)
        return t, h[k] * (r_a + t * dr) * inv, L * (r_a + r_b) / n_body
    half_disc = 0.5 * math.pi / n_cap
    if k < n_body + n_cap:  # the cap of pa, facing away from pb
        j = k - n_body
        return -cos_c[0, j] * r_a * inv, sin_c[0, j] * r_a * inv, r_a * r_a * half_disc
    j = k - n_body - n_cap  # the cap of pb
    return 1.0 + cos_c[1, j] * r_b * inv, sin_c[1, j] * r_b * inv, r_b * r_b * half_disc


def _on_axis(dx, dy, ex, ey, inv_ee):
    """A point ``(dx, dy)`` from the axis' start, on the axis ``(ex, ey)`` (``inv_ee = 1 / |e|^2``, 0 for a
    point-like axis): its parameter ``s``, ``t`` = ``s`` clamped to [0, 1], and its offset ``(qx, qy)`` from
    the nearest axis point (``_nearest_axis_distance`` of the tensor version)."""
    s = (dx * ex + dy * ey) * inv_ee
    t = min(max(s, 0.0), 1.0)
    return s, t, dx - t * ex, dy - t * ey


if AVAILABLE:
    _lookup = numba.njit(cache=True, inline="always")(_lookup)
    _capsule = numba.njit(cache=True, inline="always")(_capsule)
    _on_axis = numba.njit(cache=True, inline="always")(_on_axis)
    _area_point = numba.njit(cache=True, inline="always")(_area_point)


def _kernel(pa, pb, ra, rb, valid, image, fg, u, h, cos_c, sin_c, tau, linear, grad, model, cover, jm, jc):
    """Both terms of every image ``g`` and pose ``i``: ``model[g, i]``, ``cover[g, i]`` and, with ``grad``,
    their gradients ``jm``, ``jc`` (G, N, C, 6) in ``(pa_x, pa_y, pb_x, pb_y, ra, rb)`` of each capsule
    (zero-filled by the caller: the cover term adds into ``jc``, and invalid capsules keep 0).

    pa, pb (G, N, C, 2), ra, rb (G, N, C), valid (G, N, C) bool, image (G, H, W), fg (G, n, 2) sorted by
    ``y`` within each image; the area points' fixed pattern: body ``u``, ``h`` (n_body,), caps ``cos_c``,
    ``sin_c`` (2, n_cap)."""
    G, N, C = valid.shape
    n = fg.shape[1]
    n_body, n_cap = u.shape[0], cos_c.shape[1]
    M = n_body + 2 * n_cap
    half_disc = 0.5 * math.pi / n_cap
    a = linear
    # per point of one pose, in double precision as the arithmetic: look-up value, slope, alpha, beta, area
    val = np.empty((C, M), np.float64)
    sgx = np.empty((C, M), np.float64)
    sgy = np.empty((C, M), np.float64)
    al = np.empty((C, M), np.float64)
    be = np.empty((C, M), np.float64)
    wt = np.empty((C, M), np.float64)
    best = np.empty(n, np.float64)
    near = np.empty(n, np.int64)
    rows = np.ascontiguousarray(fg[:, :, 1])  # (G, n), ascending per image
    for g in range(G):
        for i in range(N):
            # ---- model term: sum_p w_p rho(d_mask(p)) / sum_p w_p over the capsules' area points
            wsum = 0.0
            fsum = 0.0
            for c in range(C):
                if not valid[g, i, c]:
                    continue
                ax, ay, ex, ey, L, r_a, r_b = _capsule(pa, pb, ra, rb, g, i, c)
                inv = 1.0 / L
                dr = r_b - r_a
                for k in range(M):
                    alpha, beta, w = _area_point(k, u, h, cos_c, sin_c, L, r_a, r_b)
                    px = ax + alpha * ex - beta * ey
                    py = ay + alpha * ey + beta * ex
                    v, gx, gy = _lookup(image, g, px, py)
                    d = min(v, tau)
                    wsum += w
                    fsum += w * d * (d + 2 * a)
                    val[c, k], sgx[c, k], sgy[c, k] = v, gx, gy
                    al[c, k], be[c, k], wt[c, k] = alpha, beta, w
            W_c = max(wsum, 1e-9)
            m = fsum / W_c
            model[g, i] = m
            if grad:
                inv_W = 1.0 / W_c
                for c in range(C):
                    if not valid[g, i, c]:
                        continue
                    ax, ay, ex, ey, L, r_a, r_b = _capsule(pa, pb, ra, rb, g, i, c)
                    inv = 1.0 / L
                    dr = r_b - r_a
                    g_ex = g_ey = s_px = s_py = g_ra = g_rb = g_L = 0.0
                    for k in range(M):
                        v = val[c, k]
                        d = min(v, tau)
                        w = wt[c, k]
                        alpha, beta = al[c, k], be[c, k]
                        slope = (d + a) * 2.0 * inv_W * w if v <= tau else 0.0
                        g_px, g_py = slope * sgx[c, k], slope * sgy[c, k]
                        g_w = (d * (d + 2 * a) - m) * inv_W
                        s_e = g_px * ex + g_py * ey
                        s_n = g_py * ex - g_px * ey
                        g_ex += alpha * g_px + beta * g_py
                        g_ey += alpha * g_py - beta * g_px
                        s_px += g_px
                        s_py += g_py
                        # d alpha, d beta, d w in ra, rb and L (the tensor version's `der` rows)
                        if k < n_body:
                            uk, hk = u[k], h[k]
                            t = alpha
                            irt = 1.0 / (r_a + t * dr)
                            t_ra = (0.5 * (t * t + uk) - t) * irt
                            t_rb = 0.5 * (uk - t * t) * irt
                            hi = hk * inv
                            wb = L / n_body
                            g_ra += s_e * t_ra + s_n * hi * ((1.0 - t) + dr * t_ra) + g_w * wb
                            g_rb += s_e * t_rb + s_n * hi * (t + dr * t_rb) + g_w * wb
                            g_L += -s_n * beta * inv + g_w * (r_a + r_b) / n_body
                        elif k < n_body + n_cap:
                            j = k - n_body
                            g_ra += (
                                -s_e * cos_c[0, j] * inv + s_n * sin_c[0, j] * inv + g_w * 2 * half_disc * r_a
                            )
                            g_L += s_e * alpha * -inv - s_n * beta * inv
                        else:
                            j = k - n_body - n_cap
                            g_rb += (
                                s_e * cos_c[1, j] * inv + s_n * sin_c[1, j] * inv + g_w * 2 * half_disc * r_b
                            )
                            g_L += -s_e * (alpha - 1.0) * inv - s_n * beta * inv
                    g_L *= inv
                    g_ex += g_L * ex
                    g_ey += g_L * ey
                    jm[g, i, c, 0] = s_px - g_ex
                    jm[g, i, c, 1] = s_py - g_ey
                    jm[g, i, c, 2] = g_ex
                    jm[g, i, c, 3] = g_ey
                    jm[g, i, c, 4] = g_ra
                    jm[g, i, c, 5] = g_rb
            # ---- cover term: (1 / n) sum_j rho(d_model(q_j)) over the foreground samples
            # the nearest capsule of every sample, capsule by capsule; a sample farther than tau from a
            # capsule costs rho(tau) whichever capsule is nearest, so each capsule visits only the samples
            # in the rows of its bounding box widened by tau (the samples come sorted by row)
            for j in range(n):
                best[j] = np.inf
                near[j] = -1
            for c in range(C):
                if not valid[g, i, c]:
                    continue
                ax, ay, ex, ey, _, r_a, r_b = _capsule(pa, pb, ra, rb, g, i, c)
                ee = ex * ex + ey * ey
                inv_ee = 1.0 / ee if ee > 1e-12 else 0.0
                dr = r_b - r_a
                reach = max(abs(r_a), abs(r_b)) + tau
                first = np.searchsorted(rows[g], min(ay, ay + ey) - reach)
                last = np.searchsorted(rows[g], max(ay, ay + ey) + reach, side="right")
                for j in range(first, last):  # no other branch: the loop vectorises
                    _, t, qx, qy = _on_axis(fg[g, j, 0] - ax, fg[g, j, 1] - ay, ex, ey, inv_ee)
                    sd = math.sqrt(max(qx * qx + qy * qy, 1e-12)) - (r_a + t * dr)
                    if sd < best[j]:
                        best[j] = sd
                        near[j] = c
            total = 0.0
            for j in range(n):
                qx0, qy0 = fg[g, j, 0], fg[g, j, 1]
                if near[j] < 0:  # no valid capsule: the point costs rho(tau)
                    total += tau * (tau + 2 * a)
                    continue
                d = best[j]
                dc = min(max(d, 0.0), tau)
                total += dc * (dc + 2 * a)
                if not grad or dc != d:
                    continue
                c = near[j]
                ax, ay, ex, ey, _, r_a, r_b = _capsule(pa, pb, ra, rb, g, i, c)
                dx, dy = qx0 - ax, qy0 - ay
                ee = ex * ex + ey * ey
                inv_ee = 1.0 / ee if ee > 1e-12 else 0.0
                s, t, qx, qy = _on_axis(dx, dy, ex, ey, inv_ee)
                r_inv = 1.0 / math.sqrt(max(qx * qx + qy * qy, 1e-12))
                ux, uy = qx * r_inv, qy * r_inv
                g_d = (dc + a) * (2.0 / n)
                d_t = -(ux * ex + uy * ey) - (r_b - r_a)
                d_s = d_t * inv_ee if t == s else 0.0
                g_bx = -t * ux + d_s * (dx - 2 * s * ex)
                g_by = -t * uy + d_s * (dy - 2 * s * ey)
                jc[g, i, c, 0] += (-ux - g_bx - d_s * ex) * g_d
                jc[g, i, c, 1] += (-uy - g_by - d_s * ey) * g_d
                jc[g, i, c, 2] += g_bx * g_d
                jc[g, i, c, 3] += g_by * g_d
                jc[g, i, c, 4] += (t - 1.0) * g_d
                jc[g, i, c, 5] += -t * g_d
            cover[g, i] = total / n if n > 0 else math.nan


_compiled = numba.njit(cache=True, nogil=True)(_kernel) if AVAILABLE else None


def _bilinear_zeros(image, g, px, py):
    """Bilinear look-up of ``image[g]`` at pixel ``(px, py)`` (pixel centres at integers), 0 outside the
    image (``grid_sample`` with zeros padding, ``align_corners=False``); NaN at a NaN point."""
    if math.isnan(px) or math.isnan(py):
        return math.nan
    H, W = image.shape[1], image.shape[2]
    x0, y0 = math.floor(px), math.floor(py)
    fx, fy = px - x0, py - y0
    c0, r0 = int(x0), int(y0)
    value = 0.0
    for dy in range(2):
        r = r0 + dy
        if r < 0 or r >= H:
            continue
        wy = fy if dy else 1.0 - fy
        for dx in range(2):
            c = c0 + dx
            if 0 <= c < W:
                value += wy * (fx if dx else 1.0 - fx) * image[g, r, c]
    return value


if AVAILABLE:
    _bilinear_zeros = numba.njit(cache=True, inline="always")(_bilinear_zeros)


def _area_mean_kernel(pa, pb, ra, rb, valid, image, u, h, cos_c, sin_c, out):
    """``out[g, i]``: the area-weighted mean of ``image[g]`` (bilinear, 0 outside) over the area points of
    pose ``i``'s valid capsules (the fixed pattern of :func:`_area_point`); 0 where no valid capsule has
    area. Shapes as in :func:`_kernel`."""
    G, N, C = valid.shape
    M = u.shape[0] + 2 * cos_c.shape[1]
    for g in range(G):
        for i in range(N):
            wsum = 0.0
            fsum = 0.0
            for c in range(C):
                ax, ay, ex, ey, L, r_a, r_b = _capsule(pa, pb, ra, rb, g, i, c)
                if math.isnan(ax + ay + ex + ey + r_a + r_b):
                    fsum = math.nan  # a NaN pose is NaN (as the tensor version's 0 x NaN), valid or not
                if not valid[g, i, c]:
                    continue
                for k in range(M):
                    alpha, beta, w = _area_point(k, u, h, cos_c, sin_c, L, r_a, r_b)
                    value = _bilinear_zeros(
                        image, g, ax + alpha * ex - beta * ey, ay + alpha * ey + beta * ex
                    )
                    wsum += w
                    fsum += w * value
            out[g, i] = fsum / max(wsum, 1e-9)


_area_mean_compiled = numba.njit(cache=True, nogil=True)(_area_mean_kernel) if AVAILABLE else None


def _arrays(pa, pb, ra, rb, valid, pattern) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """The kernels' capsule arrays ``(pa, pb, ra, rb, valid)`` (radii as (G, N, C)) and fixed pattern
    ``(u, h, cos_c, sin_c)`` (caps' rows as (2, n_cap)), contiguous, in ``pa``'s dtype."""
    G, N, C = valid.shape
    capsules = tuple(kernel_array(t, pa.dtype) for t in (pa, pb, ra.reshape(G, N, C), rb.reshape(G, N, C)))
    u, h, cos_c, sin_c = (kernel_array(p, pa.dtype) for p in pattern)
    rows = (np.ascontiguousarray(cos_c.reshape(2, -1)), np.ascontiguousarray(sin_c.reshape(2, -1)))
    return (*capsules, kernel_array(valid)), (u, h, *rows)


def area_mean(pa, pb, ra, rb, valid, image, pattern) -> Tensor:
    """``(G, N)`` area-weighted mean of the images ``(G, H, W)`` (bilinear, 0 outside) over the fixed area
    points of the capsules ``pa``, ``pb`` (G, N, C, 2), ``ra``, ``rb``, ``valid`` (G, N, C) by the kernel:
    ``sum_i w_i I(p_i) / sum_i w_i`` of :func:`~torchpf.geometry.sample_in_capsules` and a bilinear
    ``grid_sample``, in ``pa``'s dtype. ``pattern`` as in :func:`chamfer`."""
    G, N = valid.shape[:2]
    capsules, pattern = _arrays(pa, pb, ra, rb, valid, pattern)
    out = np.empty((G, N), np.float32 if pa.dtype == torch.float32 else np.float64)
    _area_mean_compiled(*capsules, kernel_array(image, pa.dtype), *pattern, out)
    return torch.from_numpy(out)


def chamfer(pa, pb, ra, rb, valid, image, fg, pattern, tau: float, linear: float, grad: bool):
    """:func:`torchpf.geometry.chamfer._chamfer` on CPU tensors by the fused kernel: ``(model, cover,
    (jm, jc) or None)`` as tensors of ``pa``'s dtype. ``pattern``: the area points' fixed unit samples
    ``(u, h, cos_c, sin_c)`` (:func:`torchpf.geometry.projected._fixed_unit_samples`)."""
    G, N, C = valid.shape
    np_dtype = np.float32 if pa.dtype == torch.float32 else np.float64
    model = np.empty((G, N), np_dtype)
    cover = np.empty((G, N), np_dtype)
    shape = (G, N, C, 6) if grad else (1, 1, 1, 6)
    jm, jc = np.zeros(shape, np_dtype), np.zeros(shape, np_dtype)
    capsules, pattern = _arrays(pa, pb, ra, rb, valid, pattern)
    by_row = torch.argsort(fg[..., 1], dim=-1, stable=True).unsqueeze(-1).expand(-1, -1, 2)
    _compiled(
        *capsules,
        kernel_array(image, pa.dtype),
        kernel_array(torch.gather(fg, 1, by_row), pa.dtype),
        *pattern,
        float(tau),
        float(linear),
        bool(grad),
        model,
        cover,
        jm,
        jc,
    )
    out = torch.from_numpy(model), torch.from_numpy(cover)
    return (*out, (torch.from_numpy(jm), torch.from_numpy(jc)) if grad else None)
