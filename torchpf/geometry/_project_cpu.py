"""Fused CPU kernels of the capsules' projection into a rig (numba, optional): the forward and backward of
:func:`torchpf.geometry.projected.project_capsules` without lens distortion.

The tensor version (``_RigProjection``) runs some forty small operations forward and twenty backward: for
the few poses a refinement step moves (4 poses, 3 cameras, 27 capsules), their dispatch, not the
arithmetic, is the cost (~0.3 ms forward and ~0.2 ms backward per call, 20 calls per frame). These kernels
do the same per capsule end in one pass each: the pinhole projection ``u = k00 x/z + k01 y/z + k02``,
``v = k11 y/z + k12`` of ``x_c = R X + t`` and the radius ``f r |x_c|^(1/2) zc^(-3/2)`` (``f`` the mean of
``k00`` and ``k11``, ``zc`` the depth clamped at ``near``) forward; backward the same derivatives the tensor
version writes out, recomputed from the inputs instead of kept.

Same inputs and results as the tensor version to rounding (checked by the tests). CPU only, no autograd of
their own: ``_RigProjection`` calls them when :func:`applies`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchpf.devices import fused_cpu, kernel_array

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; a platform without it keeps the tensor path
    numba = None

AVAILABLE = numba is not None


def applies(a: Tensor) -> bool:
    """Whether the projection of capsule ends ``a (..., C, 3)`` may run the fused kernels: numba installed
    and :func:`torchpf.devices.fused_cpu` (no autograd through ``a`` needed of the tensor version, a CPU
    float tensor, ``TORCHPF_FUSED`` not ``0``)."""
    return AVAILABLE and fused_cpu(a, a[..., 0, 0].numel())


def _end(K, R, t, X0, X1, X2, v, near):
    """Camera ``v``'s view of the point ``X``: camera-frame ``x, y, z``, ``1/z`` (``z`` held off 0 by
    1e-12), the pixel offsets ``du, dv`` from the principal point, ``|x_c|^2``, the clamped depth ``zc`` and
    ``q``, the projected radius per metre of sphere radius."""
    x = R[v, 0, 0] * X0 + R[v, 0, 1] * X1 + R[v, 0, 2] * X2 + t[v, 0]
    y = R[v, 1, 0] * X0 + R[v, 1, 1] * X1 + R[v, 1, 2] * X2 + t[v, 1]
    z = R[v, 2, 0] * X0 + R[v, 2, 1] * X1 + R[v, 2, 2] * X2 + t[v, 2]
    iz = 1.0 / (1e-12 if abs(z) < 1e-12 else z)
    du = K[v, 0, 0] * (x * iz) + K[v, 0, 1] * (y * iz)
    dv = K[v, 1, 1] * (y * iz)
    nn2 = x * x + y * y + z * z
    zc = max(z, near)
    q = 0.5 * (K[v, 0, 0] + K[v, 1, 1]) / zc * math.sqrt(math.sqrt(nn2) / zc)
    return x, y, z, iz, du, dv, nn2, zc, q


if AVAILABLE:
    _end = numba.njit(cache=True, inline="always")(_end)


def _forward(a, b, radius, K, R, t, near, pa, pb, ra, rb, valid):
    """Ends ``a, b (N, C, 3)`` into cameras ``K, R (V, 3, 3)``, ``t (V, 3)``: writes ``pa, pb (N, V, C,
    2)`` pixels, ``ra, rb (N, V, C)`` radii and ``valid (N, V, C)`` (both ends deeper than ``near``)."""
    N, C = a.shape[0], a.shape[1]
    V = R.shape[0]
    for n in range(N):
        for v in range(V):
            for c in range(C):
                _, _, za, _, dua, dva, _, _, qa = _end(K, R, t, a[n, c, 0], a[n, c, 1], a[n, c, 2], v, near)
                _, _, zb, _, dub, dvb, _, _, qb = _end(K, R, t, b[n, c, 0], b[n, c, 1], b[n, c, 2], v, near)
                pa[n, v, c, 0] = dua + K[v, 0, 2]
                pa[n, v, c, 1] = dva + K[v, 1, 2]
                pb[n, v, c, 0] = dub + K[v, 0, 2]
                pb[n, v, c, 1] = dvb + K[v, 1, 2]
                ra[n, v, c] = qa * radius[c]
                rb[n, v, c] = qb * radius[c]
                valid[n, v, c] = za > near and zb > near


def _backward(a, b, radius, K, R, t, near, g_pa, g_pb, g_ra, g_rb, g_a, g_b, g_radius):
    """The gradients of :func:`_forward`'s outputs ``g_pa, g_pb (N, V, C, 2)``, ``g_ra, g_rb (N, V, C)``
    mapped to the ends, ``g_a, g_b (N, C, 3)`` (summed over cameras), and to the radii, ``g_radius (C,)``
    (summed over poses, cameras and both ends); the outputs start at 0."""
    N, C = a.shape[0], a.shape[1]
    V = R.shape[0]
    for n in range(N):
        for v in range(V):
            k00, k01, k11 = K[v, 0, 0], K[v, 0, 1], K[v, 1, 1]
            for c in range(C):
                for e in range(2):
                    ends, gp, gr_all, out = (a, g_pa, g_ra, g_a) if e == 0 else (b, g_pb, g_rb, g_b)
                    x, y, z, iz, du, dv, nn2, zc, q = _end(
                        K, R, t, ends[n, c, 0], ends[n, c, 1], ends[n, c, 2], v, near
                    )
                    gu, gv, gr = gp[n, v, c, 0], gp[n, v, c, 1], gr_all[n, v, c]
                    rad = q * radius[c]
                    half = gr * rad * 0.5 / nn2
                    gx = half * x + gu * k00 * iz
                    gy = half * y + (gu * k01 + gv * k11) * iz
                    gz = half * z - (gu * du + gv * dv) * iz
                    if z > near:
                        gz -= 1.5 * gr * rad / zc
                    # x_c = R X + t: the end's gradient is R^T (gx, gy, gz)
                    for i in range(3):
                        out[n, c, i] += R[v, 0, i] * gx + R[v, 1, i] * gy + R[v, 2, i] * gz
                    g_radius[c] += gr * q


_forward_compiled = numba.njit(cache=True, nogil=True)(_forward) if AVAILABLE else None
_backward_compiled = numba.njit(cache=True, nogil=True)(_backward) if AVAILABLE else None


def _inputs(a: Tensor, b: Tensor, radius: Tensor, K: Tensor, R: Tensor, t: Tensor, near: float):
    """The kernels' leading arguments as contiguous arrays in ``a``'s dtype, and ``(batch, N, C, V, dtype)``
    (``N`` poses: ``batch`` flattened)."""
    batch, C, V = a.shape[:-2], a.shape[-2], R.shape[0]
    N = math.prod(batch)
    dt = np.float32 if a.dtype == torch.float32 else np.float64

    def arr(x: Tensor) -> np.ndarray:
        return kernel_array(x, a.dtype)

    args = (
        arr(a.reshape(N, C, 3)),
        arr(b.reshape(N, C, 3)),
        arr(radius),
        arr(K),
        arr(R),
        arr(t),
        float(near),
    )
    return args, (batch, N, C, V, dt)


def forward(a: Tensor, b: Tensor, radius: Tensor, K: Tensor, R: Tensor, t: Tensor, near: float):
    """``(pa, pb, ra, rb, valid)`` of ends ``a, b (..., C, 3)`` in a rig, shaped as ``_RigProjection``'s
    outputs ``(..., V, C, 2)`` and ``(..., V, C)``, in ``a``'s dtype."""
    args, (batch, N, C, V, dt) = _inputs(a, b, radius, K, R, t, near)
    pa, pb = np.empty((N, V, C, 2), dt), np.empty((N, V, C, 2), dt)
    ra, rb = np.empty((N, V, C), dt), np.empty((N, V, C), dt)
    valid = np.empty((N, V, C), np.bool_)
    _forward_compiled(*args, pa, pb, ra, rb, valid)
    outs = (torch.from_numpy(pa), torch.from_numpy(pb), torch.from_numpy(ra), torch.from_numpy(rb))
    pa, pb, ra, rb = (o.reshape(*batch, *o.shape[1:]) for o in outs)
    return pa, pb, ra, rb, torch.from_numpy(valid).reshape(*batch, V, C)


def backward(a, b, radius, K, R, t, near: float, g_pa, g_pb, g_ra, g_rb):
    """The ends' gradients ``(g_a, g_b)`` ``(..., C, 3)`` and the radii's ``g_radius (C,)`` from the
    outputs' (any of them may be None: no gradient), in ``a``'s dtype."""
    args, (batch, N, C, V, dt) = _inputs(a, b, radius, K, R, t, near)

    def grad(g, shape):
        return (
            np.zeros(shape, dt) if g is None else np.ascontiguousarray(g.detach().reshape(shape).numpy(), dt)
        )

    g_a, g_b, g_radius = np.zeros((N, C, 3), dt), np.zeros((N, C, 3), dt), np.zeros(C, dt)
    grads = (grad(g_pa, (N, V, C, 2)), grad(g_pb, (N, V, C, 2)), grad(g_ra, (N, V, C)), grad(g_rb, (N, V, C)))
    _backward_compiled(*args, *grads, g_a, g_b, g_radius)
    return (
        torch.from_numpy(g_a).reshape(*batch, C, 3),
        torch.from_numpy(g_b).reshape(*batch, C, 3),
        torch.from_numpy(g_radius),
    )
