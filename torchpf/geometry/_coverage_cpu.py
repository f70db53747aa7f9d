"""Fused CPU kernel of the hard coverage of :func:`torchpf.geometry.capsule_coverage` (numba; optional).

The tensor version tests every point against every capsule with two matrix products and a dozen passes
over a (poses, capsules, points) array: for the dual silhouette cue (Fontmarty §3.2.2) of 500 poses in 3
cameras with 128 foreground samples each, 5 million point-capsule pairs per frame, each written to memory
several times. This kernel takes the points sorted by row once per call; each capsule of a pose then tests
only the points in the rows of its bounding box (a binary search), and a point already covered is skipped.
Same test as the tensor version (the point within the radius interpolated at the nearest axis point,
``|p - a - t e|^2 <= (ra + t (rb - ra))^2``); results equal except for points within rounding of a boundary
(checked by the tests). CPU only, no autograd: the hard test has no gradient.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torchpf.devices import kernel_array

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; a platform without it keeps the tensor path
    numba = None

AVAILABLE = numba is not None


def _kernel(pa, pb, ra, rb, valid, pts, out):
    """``out[g, r, p]`` = 1 where point ``pts[g, p]`` lies in any valid capsule of row ``r`` of group ``g``,
    else 0. pa, pb (G, R, C, 2), ra, rb (G, R, C), valid (G, R, C) bool, pts (G, P, 2) sorted by ``y`` within
    each group (so a capsule tests only the points in its band of rows), out (G, R, P)."""
    G, R, C = valid.shape
    P = pts.shape[1]
    for g in range(G):
        ys = np.ascontiguousarray(pts[g, :, 1])
        for r in range(R):
            out[g, r, :] = 0.0
            for c in range(C):
                a_x, a_y = pa[g, r, c, 0], pa[g, r, c, 1]
                e_x, e_y = pb[g, r, c, 0] - a_x, pb[g, r, c, 1] - a_y
                rad_a, rad_b = ra[g, r, c], rb[g, r, c]
                ee = e_x * e_x + e_y * e_y
                if not valid[g, r, c] or rad_a != rad_a or rad_b != rad_b or ee != ee:
                    continue  # invalid, or NaN: covers nothing
                inv = 1.0 / ee if ee > 1e-12 else 0.0
                reach = max(abs(rad_a), abs(rad_b))
                x_lo, x_hi = min(a_x, a_x + e_x) - reach, max(a_x, a_x + e_x) + reach
                y_lo, y_hi = min(a_y, a_y + e_y) - reach, max(a_y, a_y + e_y) + reach
                first = np.searchsorted(ys, y_lo)
                last = np.searchsorted(ys, y_hi, side="right")
                for p in range(first, min(last, P)):
                    if out[g, r, p] > 0.0:
                        continue
                    x = pts[g, p, 0]
                    if x < x_lo or x > x_hi:
                        continue
                    dx, dy = x - a_x, ys[p] - a_y
                    t = min(max((dx * e_x + dy * e_y) * inv, 0.0), 1.0)
                    qx, qy = dx - t * e_x, dy - t * e_y
                    rad = rad_a + t * (rad_b - rad_a)
                    if qx * qx + qy * qy <= rad * rad:
                        out[g, r, p] = 1.0


_compiled = numba.njit(cache=True, nogil=True)(_kernel) if AVAILABLE else None


def coverage(pa: Tensor, pb: Tensor, ra: Tensor, rb: Tensor, valid: Tensor, pts: Tensor) -> Tensor:
    """Hard coverage ``(G, R, P)`` in ``pa``'s dtype by the kernel: capsules ``pa, pb`` (G, R, C, 2),
    ``ra, rb, valid`` (G, R, C), points ``pts`` (G, P, 2) shared by the R rows of their group (any order:
    sorted here, the result in the given order)."""
    np_dtype = np.float32 if pa.dtype == torch.float32 else np.float64
    G, R, C = valid.shape
    order = torch.argsort(pts[..., 1], dim=-1, stable=True)  # (G, P) each group's points by row
    sorted_pts = torch.gather(pts, 1, order.unsqueeze(-1).expand(-1, -1, 2))
    out = np.empty((G, R, pts.shape[1]), np_dtype)
    floats = (kernel_array(t, pa.dtype) for t in (pa, pb, ra, rb))
    _compiled(*floats, kernel_array(valid), kernel_array(sorted_pts, pa.dtype), out)
    cov = torch.from_numpy(out)
    return torch.empty_like(cov).scatter_(2, order.unsqueeze(1).expand(-1, R, -1), cov)
