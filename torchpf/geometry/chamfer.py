"""The two-sided truncated chamfer distance between projected capsules and a silhouette, with its gradient
in the capsules written out (the terms of :class:`~torchpf.likelihoods.SilhouetteDistanceLikelihood`, the
cue of the gradient refinement :mod:`torchpf.refine`; Gall et al., IJCV 2010, §4).

Per image and pose (pixels)::

    model = sum_i w_i rho(d_mask(p_i)) / sum_i w_i        p_i, w_i: sample_in_capsules (area points)
    cover = (1 / n) sum_j rho(d_model(q_j))               q_j: n foreground samples of the mask
    rho(d) = min(d, tau)^2 + 2 a min(d, tau)                  a = linear (pixels)

``d_mask`` is a bilinear look-up in the mask's outside-distance image (growing by the distance to the image
outside it), ``d_model`` the distance to the nearest capsule (:func:`distance_to_capsules`).

Autograd through these few hundred small operations per pose costs several times the forward pass for the
handful of poses a refinement moves (the per-operation overhead dominates); :func:`capsule_chamfer` is one
autograd node whose forward also forms each pose's gradient in its capsules in closed form (the area points'
Jacobian in the capsule, the bilinear look-up's gradient, the nearest capsule's outline gradient), and whose
backward only scales it. Values and gradients equal those of the composition of :func:`sample_in_capsules`,
a ``grid_sample`` look-up and :func:`distance_to_capsules` to rounding (``tests/torchpf/geometry/
test_chamfer.py``). On a CPU the same values and gradients come from one fused numba kernel
(:mod:`torchpf.geometry._chamfer_cpu`, :data:`FUSED_CPU`): a refinement step of 4 poses in 3 cameras spends
~0.4 ms in it against ~0.8 ms of tensor operations, and the default hybrid tracker's frame takes 73 instead of
98 ms (BENCHMARKS.md, "Speed of a tracking step"). Other devices run the tensor operations.

Example::

    caps = project_capsules(rig, a, b, radii)                       # (N, V, C) -> camera-major (V, N, C)
    model, cover = capsule_chamfer(caps, outside, fg, tau=6.0)      # outside (V, H, W), fg (V, 1, n, 2)
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from torchpf.devices import fused_cpu
from torchpf.geometry import _chamfer_cpu
from torchpf.geometry.projected import (
    Capsules2D,
    _area_points,
    _fixed_unit_samples,
    _nearest_axis_distance,
    _nearest_capsules,
    sample_in_capsules,
)

__all__ = ["capsule_area_mean", "capsule_chamfer", "distance_lookup", "sample_image"]

#: On a CPU, both terms and their gradients by one fused numba kernel (:mod:`torchpf.geometry._chamfer_cpu`)
#: instead of ~200 tensor operations; False (or ``TORCHPF_FUSED=0`` in the environment, the switch of every
#: fused CPU kernel) keeps the tensor version everywhere (the tests compare the two).
FUSED_CPU = True


def capsule_chamfer(
    caps: Capsules2D,
    distance: Tensor,
    samples: Tensor,
    *,
    tau: float,
    n_body: int = 8,
    n_cap: int = 2,
    linear: float = 0.0,
) -> tuple[Tensor, Tensor]:
    """The model and cover terms of the truncated chamfer distance (module docstring), per image and pose.

    Args:
        caps: :class:`Capsules2D` ``(..., N, C)``: N poses' capsules in each image of ``...`` (camera-major,
            e.g. ``(S, V, N, C)``), pixels.
        distance: ``(..., H, W)`` each image's distance (pixels) to its mask, 0 inside
            (:meth:`~torchpf.observations.Silhouettes.outside_distance`); leading dims broadcast to the
            capsules' ``...``.
        samples: ``(..., 1, n, 2)`` foreground points of each image (pixels), shared by its N poses.
        tau: truncation (pixels) of each point's distance.
        n_body, n_cap: area points per capsule body and end cap (:func:`sample_in_capsules`).
        linear: pixels, ``a`` of ``rho`` (0: the squared distance alone).

    Returns:
        ``model``, ``cover`` ``(..., N)`` in squared pixels; differentiable in the capsules' ``pa``, ``pb``,
        ``ra``, ``rb`` (not in the images or samples). A point with no valid capsule has ``d_model = inf``
        (its term is ``tau^2``).
    """
    group, (N, C) = caps.pa.shape[:-3], caps.pa.shape[-3:-1]
    G = math.prod(group)
    H, W = distance.shape[-2:]
    image = distance.to(caps.pa).expand(*group, H, W).reshape(G, H, W)
    fg = samples.to(caps.pa).expand(*group, 1, samples.shape[-2], 2).reshape(G, -1, 2)
    fields = [f.reshape(G, N, C, -1) for f in (caps.pa, caps.pb, caps.ra, caps.rb)]
    valid = caps.valid.reshape(G, N, C)
    if torch.is_grad_enabled() and any(f.requires_grad for f in fields):
        model, cover = _Chamfer.apply(
            *fields, valid, image, fg, float(tau), int(n_body), int(n_cap), float(linear)
        )
    else:
        model, cover, _ = _chamfer(
            *fields, valid, image, fg, float(tau), int(n_body), int(n_cap), float(linear), False
        )
    return model.reshape(*group, N), cover.reshape(*group, N)


def sample_image(image: Tensor, uv: Tensor, mode: str = "bilinear", padding: str = "zeros") -> Tensor:
    """``grid_sample`` of images ``(..., H, W)`` (G in all) at pixel coords ``uv (B, ..., 2)``, pixel
    centres at integers (u right, v down): one image for all points, or one per group of rows (the B rows
    are G groups of equal size in the images' order: sequences of a batch as in ``Body.rows``, or the
    ``(S, V)`` images of camera-major ``(S, V, N, P, 2)`` points, one call for every camera). ``mode``
    "bilinear" or "nearest"; ``padding`` "zeros" or "border" outside the image. Returns ``(B, ...)``."""
    H, W = image.shape[-2:]
    images = image.reshape(-1, 1, H, W).to(uv)
    # pixel centres at integers, align_corners=False: (2 u + 1) / W - 1, one multiply-add for u and v
    scale, shift = uv.new_tensor([2.0 / W, 2.0 / H]), uv.new_tensor([1.0 / W - 1.0, 1.0 / H - 1.0])
    grid = torch.addcmul(shift, uv, scale).reshape(len(images), 1, -1, 2)
    out = F.grid_sample(images, grid, mode=mode, padding_mode=padding, align_corners=False)
    return out.reshape(uv.shape[:-1])


def capsule_area_mean(caps: Capsules2D, image: Tensor, n_body: int = 8, n_cap: int = 2) -> Tensor:
    """Area-weighted mean of an image over each pose's projected capsules: ``sum_i w_i I(p_i) / sum_i w_i``
    over the fixed area points ``p_i`` and areas ``w_i`` of :func:`sample_in_capsules`, ``I`` a bilinear
    look-up that is 0 outside the image (Fontmarty et al. eq. 2's share of the model inside the mask, with
    ``image`` the mask). Overlapping capsules count twice, as in the sampled sum.

    Args:
        caps: camera-major :class:`Capsules2D` ``(..., N, C)`` (pixels).
        image: ``(..., H, W)`` one image per leading index of ``caps`` (or one for all).
        n_body, n_cap: area points per capsule body and end cap.

    Returns:
        ``(..., N)``; 0 where no valid capsule has area. Differentiable in the capsules (tensor version);
        on a CPU without autograd, one fused numba kernel (:func:`torchpf.geometry._chamfer_cpu.area_mean`,
        the same values to rounding) instead of ~20 tensor passes over ``N C (n_body + 2 n_cap)`` points.
    """
    group, (N, C) = caps.pa.shape[:-3], caps.pa.shape[-3:-1]
    G = math.prod(group)
    H, W = image.shape[-2:]
    if FUSED_CPU and _chamfer_cpu.AVAILABLE and fused_cpu(caps.pa) and image.dtype == caps.pa.dtype:
        fields = [f.reshape(G, N, C, -1) for f in (caps.pa, caps.pb, caps.ra, caps.rb)]
        images = image.expand(*group, H, W).reshape(G, H, W)
        pattern = _fixed_unit_samples(int(n_body), int(n_cap), caps.pa.dtype, caps.pa.device)
        mean = _chamfer_cpu.area_mean(*fields, caps.valid.reshape(G, N, C), images, pattern)
        return mean.reshape(*group, N)
    pts, w = sample_in_capsules(caps, n_body, n_cap)
    return (w * sample_image(image, pts)).sum(-1) / w.sum(-1).clamp_min(1e-9)


def distance_lookup(dist: Tensor, uv: Tensor) -> Tensor:
    """Distance-image look-up that keeps growing outside the image: value at the nearest border pixel plus
    the distance to it, so a marker that leaves the image is not mistaken for a close one. ``dist`` (H, W)
    or (G, H, W), grouped as in :func:`sample_image`; differentiable in ``uv`` (finite everywhere, also at
    the image's edge). :func:`capsule_chamfer` uses it for its value, and a closed form for its gradient."""
    H, W = dist.shape[-2:]
    inside = torch.clamp(uv, uv.new_zeros(2), uv.new_tensor([W - 1.0, H - 1.0]))
    off = uv - inside
    extra = off.square().sum(-1).clamp_min(1e-12).sqrt() * (off.abs().sum(-1) > 0)
    return sample_image(dist, inside, "bilinear", "border") + extra


class _Chamfer(torch.autograd.Function):
    """:func:`_chamfer` as one autograd node: the forward keeps each row's gradient, the backward scales
    it."""

    @staticmethod
    def forward(ctx, pa, pb, ra, rb, valid, image, fg, tau, n_body, n_cap, linear):
        model, cover, (jm, jc) = _chamfer(pa, pb, ra, rb, valid, image, fg, tau, n_body, n_cap, linear, True)
        # (inference tensors, see _chamfer: autograd needs ordinary ones)
        ctx.save_for_backward(jm.clone(), jc.clone())
        return model.clone(), cover.clone()

    @staticmethod
    def backward(ctx, g_model, g_cover):
        jm, jc = ctx.saved_tensors
        g = jm * g_model[..., None, None] + jc * g_cover[..., None, None]  # (G, N, C, 6)
        return g[..., 0:2], g[..., 2:4], g[..., 4:5], g[..., 5:6], None, None, None, None, None, None, None


def _chamfer(
    pa, pb, ra, rb, valid, image, fg, tau: float, n_body: int, n_cap: int, linear: float, grad: bool
):
    """Both terms ``(G, N)`` of capsules ``pa``, ``pb`` (G, N, C, 2), ``ra``, ``rb`` (G, N, C, 1), ``valid``
    (G, N, C) against images (G, H, W) and samples (G, n, 2); with ``grad`` also each term's gradient in
    ``(pa, pb, ra, rb)`` ``(G, N, C, 6)``, else None.

    Coordinates are kept as separate x and y tensors: on a CPU an element-wise pass over a trailing dim of
    size 2 (a broadcast, a sum, a stack) costs several plain passes of the same size."""
    if FUSED_CPU and _chamfer_cpu.AVAILABLE and fused_cpu(pa):
        pattern = _fixed_unit_samples(n_body, n_cap, pa.dtype, pa.device)
        return _chamfer_cpu.chamfer(pa, pb, ra, rb, valid, image, fg, pattern, tau, linear, grad)
    # inference mode: no graph and no version counters, a tenth less per-operation overhead than no_grad
    with torch.inference_mode():
        model, jm = _model_term(
            pa, pb, ra[..., 0], rb[..., 0], valid, image, tau, n_body, n_cap, linear, grad
        )
        cover, jc = _cover_term(pa, pb, ra, rb, valid, fg, tau, linear, grad)
    return model, cover, ((jm, jc) if grad else None)


def _model_term(pa, pb, ra, rb, valid, image, tau: float, n_body: int, n_cap: int, linear: float, grad: bool):
    """``sum_i w_i rho(d_mask(p_i)) / sum_i w_i`` (G, N) and its gradient (G, N, C, 6) or None."""
    G, N, C = valid.shape
    px, py, k = _area_points(Capsules2D(pa, pb, ra, rb, valid), n_body, n_cap, derivatives=grad)
    ex, ey, L, alpha, beta, w = k["ex"], k["ey"], k["L"], k["alpha"], k["beta"], k["w"]
    exu, eyu = ex.unsqueeze(-1), ey.unsqueeze(-1)
    M = px.shape[-1]
    value, gx, gy = _lookup_with_gradient(image, px.view(G, -1), py.view(G, -1), grad)
    value = value.view(G, N, C, M)
    d = value.clamp_max(tau)
    f = d * (d + 2 * linear)
    Wc = w.sum((-2, -1)).clamp_min(1e-9)
    model = (w * f).sum((-2, -1)) / Wc
    if not grad:
        return model, None
    inv = Wc.reciprocal()[..., None, None]
    # d model / d p_i and d model / d w_i (G, N, C, M); (all weights 0: the model term is 0 either way)
    slope = torch.where(value <= tau, d + linear, 0.0) * (2 * inv) * w
    g_px, g_py = slope * gx.view(G, N, C, M), slope * gy.view(G, N, C, M)
    g_w = (f - model[..., None, None]) * inv
    s_e = torch.addcmul(g_px * exu, g_py, eyu)  # g . e
    s_n = torch.addcmul(g_py * exu, g_px, eyu, value=-1.0)  # g . n
    # d/de of alpha g . e + beta g . n(e) at fixed alpha, beta: alpha g + beta (g_y, -g_x)
    g_ex = (alpha * g_px + beta * g_py).sum(-1)
    g_ey = (alpha * g_py - beta * g_px).sum(-1)
    # alpha, beta and w through ra, rb and L
    vec = torch.cat([s_e, s_n, g_w], -1)
    g_ra, g_rb, g_L = ((vec * c).sum(-1) for c in k["der"])
    g_L = g_L / L
    g_ex, g_ey = torch.addcmul(g_ex, g_L, ex), torch.addcmul(g_ey, g_L, ey)
    g_ax, g_ay = g_px.sum(-1) - g_ex, g_py.sum(-1) - g_ey
    return model, torch.stack([g_ax, g_ay, g_ex, g_ey, g_ra, g_rb], -1)


def _cover_term(pa, pb, ra, rb, valid, fg, tau: float, linear: float, grad: bool):
    """``(1 / n) sum_j rho(d_model(q_j))`` (G, N) and its gradient (G, N, C, 6) or None."""
    G, N, C = valid.shape
    n = fg.shape[1]
    fields = [f.reshape(G, N * C, -1) for f in (pa, pb, ra, rb)]
    best, nearest = _nearest_capsules(fg, fields, valid.reshape(G, N * C, 1), C)
    if not grad:
        d = best.clamp(0.0, tau)
        return (d * (d + 2 * linear)).mean(-1), None
    d, k = _nearest_axis_distance(fg, fields, nearest, best)
    dc = d.clamp(0.0, tau)
    cover = (dc * (dc + 2 * linear)).view(G, N, n).mean(-1)
    # d = |q| - ra - t (rb - ra), q = p - pa - t e, t = clamp(s, 0, 1), s = (p - pa) . e / |e|^2
    ex, ey, dx, dy, s, t = k["ex"], k["ey"], k["dx"], k["dy"], k["s"], k["t"]
    # d cover / d d_j where the clamps pass it (not inf)
    g_d = torch.where(dc == d, dc + linear, 0.0) * (2.0 / n)
    r_inv = k["qq"].clamp_min(1e-12).rsqrt()
    ux, uy = k["qx"] * r_inv, k["qy"] * r_inv  # d |q| / d q
    d_t = -torch.addcmul(ux * ex, uy, ey) - (k["rb"] - k["ra"])  # d d / d t
    d_s = torch.where(t == s, d_t, 0.0) * k["inv_ee"]  # through s where the clamp passes it
    two_s = 2 * s
    # d s / d pa = (2 s e - e - (p - pa)) / |e|^2, d s / d pb = ((p - pa) - 2 s e) / |e|^2
    g_bx, g_by = torch.addcmul(-t * ux, d_s, dx - two_s * ex), torch.addcmul(-t * uy, d_s, dy - two_s * ey)
    g_ax = torch.addcmul(-ux - g_bx, d_s, -ex)  # -(1 - t) u + d_s (2 s e - e - diff)
    g_ay = torch.addcmul(-uy - g_by, d_s, -ey)
    rows = torch.stack([g_ax, g_ay, g_bx, g_by, t - 1, -t], -1) * g_d.unsqueeze(-1)  # (G, N n, 6)
    j = torch.zeros(G * N * C, 6, dtype=rows.dtype, device=rows.device)
    j.index_add_(0, k["index"], rows.view(-1, 6))
    return cover, j.view(G, N, C, 6)


def _lookup_with_gradient(image, px, py, grad: bool):
    """Bilinear look-up of distance images (G, H, W) at pixel coords ``px``, ``py`` (G, P) (pixel centres
    at integers), continued outside the image by the distance to it (the value at the nearest border pixel
    plus that distance: ``grid_sample(..., padding_mode="border")`` plus the offset); returns the values
    (G, P) and, with ``grad``, their gradient in ``px`` and ``py`` (G, P each; the value and the slope from
    the four corners, gathered once), else Nones."""
    if not grad:  # the value alone
        return distance_lookup(image, torch.stack([px, py], -1)), None, None
    G, H, W = image.shape
    ix, iy = px.clamp(0.0, W - 1.0), py.clamp(0.0, H - 1.0)
    ox, oy = px - ix, py - iy
    oo = torch.addcmul(ox * ox, oy, oy)
    if H < 2 or W < 2:  # a one-pixel-wide image: its border replicated, so both neighbours exist
        image = F.pad(image.unsqueeze(1), (0, int(W < 2), 0, int(H < 2)), mode="replicate").squeeze(1)
        H, W = image.shape[-2:]
    x0, y0 = ix.floor().clamp_max_(W - 2.0), iy.floor().clamp_max_(H - 2.0)
    fx, fy = ix - x0, iy - y0
    idx = torch.add(x0, y0, alpha=W).long().unsqueeze(1)
    corners = torch.tensor([0, 1, W, W + 1], device=idx.device).view(1, 4, 1)
    v = image.reshape(G, H * W).gather(1, (idx + corners).view(G, -1)).view(G, 4, -1)
    v00, v01, v10, v11 = v.unbind(1)
    dx0, dx1 = v01 - v00, v11 - v10
    top = torch.addcmul(v00, fx, dx0)
    dy = torch.addcmul(v10, fx, dx1) - top
    value = torch.addcmul(top, fy, dy) + oo.sqrt()
    # inside the image (no offset along an axis) the bilinear slope, outside the offset's direction
    r_inv = oo.clamp_min(1e-12).rsqrt()
    gx = torch.where(ox == 0, torch.addcmul(dx0, fy, dx1 - dx0), ox * r_inv)
    gy = torch.where(oy == 0, dy, oy * r_inv)
    return value, gx, gy
