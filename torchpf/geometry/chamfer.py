"""The two-sided truncated chamfer distance between projected capsules and a silhouette, with its gradient
in the capsules written out (the terms of :class:`~torchpf.likelihoods.SilhouetteDistanceLikelihood`, the
cue of the gradient refinement :mod:`torchpf.refine`; Gall et al., IJCV 2010, §4).

Per image and pose (pixels)::

    model = sum_i w_i rho(d_mask(p_i)) / sum_i w_i        p_i, w_i: sample_in_capsules (area points)
    cover = (1 / n) sum_j rho(d_model(q_j))               q_j: n foreground samples of the mask
    rho(d) = min(d, tau)^2

``d_mask`` is a bilinear look-up in the mask's outside-distance image (growing by the distance to the image
outside it), ``d_model`` the distance to the nearest capsule (:func:`distance_to_capsules`).

Autograd through these few hundred small operations per pose costs several times the forward pass for the
handful of poses a refinement moves (the per-operation overhead dominates); :func:`capsule_chamfer` is one
autograd node whose forward also forms each pose's gradient in its capsules in closed form (the area points'
Jacobian in the capsule, the bilinear look-up's gradient, the nearest capsule's outline gradient), and whose
backward only scales it. Values and gradients equal those of the composition of :func:`sample_in_capsules`,
a ``grid_sample`` look-up and :func:`distance_to_capsules` to rounding (``tests/torchpf/geometry/
test_chamfer.py``).

Example::

    caps = project_capsules(rig, a, b, radii)                       # (N, V, C) -> camera-major (V, N, C)
    model, cover = capsule_chamfer(caps, outside, fg, tau=6.0)      # outside (V, H, W), fg (V, 1, n, 2)
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from torchpf.geometry.projected import (
    Capsules2D,
    _nearest_axis_distance,
    _nearest_capsules,
    _point_coordinates,
)

__all__ = ["capsule_chamfer"]


def capsule_chamfer(
    caps: Capsules2D,
    distance: Tensor,
    samples: Tensor,
    *,
    tau: float,
    n_body: int = 8,
    n_cap: int = 2,
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
        model, cover = _Chamfer.apply(*fields, valid, image, fg, float(tau), int(n_body), int(n_cap))
    else:
        model, cover, _ = _chamfer(*fields, valid, image, fg, float(tau), int(n_body), int(n_cap), False)
    return model.reshape(*group, N), cover.reshape(*group, N)


class _Chamfer(torch.autograd.Function):
    """:func:`_chamfer` as one autograd node: the forward keeps each row's gradient, the backward scales
    it."""

    @staticmethod
    def forward(ctx, pa, pb, ra, rb, valid, image, fg, tau, n_body, n_cap):
        model, cover, (jm, jc) = _chamfer(pa, pb, ra, rb, valid, image, fg, tau, n_body, n_cap, True)
        # (inference tensors, see _chamfer: autograd needs ordinary ones)
        ctx.save_for_backward(jm.clone(), jc.clone())
        return model.clone(), cover.clone()

    @staticmethod
    def backward(ctx, g_model, g_cover):
        jm, jc = ctx.saved_tensors
        g = jm * g_model[..., None, None] + jc * g_cover[..., None, None]  # (G, N, C, 6)
        return g[..., 0:2], g[..., 2:4], g[..., 4:5], g[..., 5:6], None, None, None, None, None, None


def _chamfer(pa, pb, ra, rb, valid, image, fg, tau: float, n_body: int, n_cap: int, grad: bool):
    """Both terms ``(G, N)`` of capsules ``pa``, ``pb`` (G, N, C, 2), ``ra``, ``rb`` (G, N, C, 1), ``valid``
    (G, N, C) against images (G, H, W) and samples (G, n, 2); with ``grad`` also each term's gradient in
    ``(pa, pb, ra, rb)`` ``(G, N, C, 6)``, else None."""
    # inference mode: no graph and no version counters, a tenth less per-operation overhead than no_grad
    with torch.inference_mode():
        caps = Capsules2D(pa, pb, ra[..., 0], rb[..., 0], valid)
        model, jm = _model_term(caps, image, tau, n_body, n_cap, grad)
        cover, jc = _cover_term(caps, fg, tau, grad)
    return model, cover, ((jm, jc) if grad else None)


def _model_term(caps: Capsules2D, image, tau: float, n_body: int, n_cap: int, grad: bool):
    """``sum_i w_i rho(d_mask(p_i)) / sum_i w_i`` (G, N) and its gradient (G, N, C, 6) or None."""
    G, N, C = caps.valid.shape
    out = _point_coordinates(caps, n_body, n_cap, derivatives=grad)
    e, n, L, alpha, beta, w = out[:6]
    pts = torch.addcmul(caps.pa.unsqueeze(-2), alpha.unsqueeze(-1), e.unsqueeze(-2))
    pts = torch.addcmul(pts, beta.unsqueeze(-1), n.unsqueeze(-2))  # (G, N, C, M, 2)
    M = pts.shape[-2]
    value, d_value = _distance_lookup(image, pts.reshape(G, -1, 2), grad)
    value = value.view(G, N, C, M)
    d = value.clamp_max(tau)
    f = d * d
    W = w.sum((-2, -1))
    Wc = W.clamp_min(1e-9)
    model = (w * f).sum((-2, -1)) / Wc
    if not grad:
        return model, None
    coef = out[6]
    inv = (1.0 / Wc)[..., None, None]
    # d model / d p_i (G, N, C, M, 2) and d model / d w_i (G, N, C, M)
    g_pts = (w * inv * 2 * d * (value <= tau)).unsqueeze(-1) * d_value.view(G, N, C, M, 2)
    g_w = (f - (model * (W > 1e-9))[..., None, None]) * inv
    # p = pa + alpha e + beta n(e), n = (-e_y, e_x): d/de of beta n^T g is beta (g_y, -g_x)
    s_e = (g_pts * e.unsqueeze(-2)).sum(-1)
    s_n = (g_pts * n.unsqueeze(-2)).sum(-1)
    g_a = (alpha.unsqueeze(-1) * g_pts).sum(-2)
    g_b = (beta.unsqueeze(-1) * g_pts).sum(-2)
    g_e = g_a + torch.stack([g_b[..., 1], -g_b[..., 0]], -1)
    # alpha, beta and w through ra, rb and L: one product with their derivatives
    g_rl = (torch.cat([s_e, s_n, g_w], -1).unsqueeze(-2) @ coef).squeeze(-2)  # (G, N, C, 3)
    g_e = g_e + (g_rl[..., 2] * (L > 1e-9) / L).unsqueeze(-1) * e
    g_pa = g_pts.sum(-2) - g_e
    return model, torch.cat([g_pa, g_e, g_rl[..., :2]], -1)


def _cover_term(caps: Capsules2D, fg, tau: float, grad: bool):
    """``(1 / n) sum_j rho(d_model(q_j))`` (G, N) and its gradient (G, N, C, 6) or None."""
    G, N, C = caps.valid.shape
    n = fg.shape[1]
    fields = [f.reshape(G, N * C, -1) for f in (caps.pa, caps.pb, caps.ra, caps.rb)]
    best, nearest = _nearest_capsules(fg, fields, caps.valid.reshape(G, N * C, 1), C)
    if not grad:
        d = best.clamp(0.0, tau)
        return (d * d).mean(-1), None
    d, k = _nearest_axis_distance(fg, fields, nearest, best)
    dc = d.clamp(0.0, tau)
    cover = (dc * dc).view(G, N, n).mean(-1)
    # d = |q| - ra - t (rb - ra), q = diff - t e, t = clamp(s, 0, 1), s = diff.e / |e|^2, diff = p - pa
    pa, pb, ra, rb = k["capsule"]
    e, diff, ee, s, t, q = k["e"], k["diff"], k["ee"], k["s"], k["t"], k["q"]
    g_d = 2 * dc / n * ((d >= 0) & (d <= tau))  # d cover / d d_j (inf: no valid capsule, no gradient)
    u = q * ((k["qq"] >= 1e-12) / k["qq"].clamp_min(1e-12).sqrt()).unsqueeze(-1)  # d |q| / d q
    t1 = t.unsqueeze(-1)
    # d d / d t, through s where the clamp passes it
    d_t = -(u * e).sum(-1) - (rb - ra).squeeze(-1)
    active = (ee > 1e-12) & (s >= 0) & (s <= 1)
    d_s = (d_t * active / ee.clamp_min(1e-12)).unsqueeze(-1)
    two_se = 2 * s.unsqueeze(-1) * e
    g_pa = -(1 - t1) * u + d_s * (two_se - e - diff)
    g_pb = -t1 * u + d_s * (diff - two_se)
    rows = torch.cat([g_pa, g_pb, t1 - 1, -t1], -1) * g_d.unsqueeze(-1)  # (G, N n, 6)
    j = torch.zeros(G * N * C, 6, dtype=rows.dtype, device=rows.device)
    index = (k["rows"] + torch.arange(G, device=rows.device).unsqueeze(-1) * (N * C)).reshape(-1)
    j.index_add_(0, index, rows.reshape(-1, 6))
    return cover, j.view(G, N, C, 6)


def _distance_lookup(image, uv, grad: bool):
    """Bilinear look-up of distance images (G, H, W) at pixel coords ``uv`` (G, P, 2) (pixel centres at
    integers), continued outside the image by the distance to it (the value at the nearest border pixel
    plus that distance: what ``grid_sample(..., padding_mode="border")`` plus the offset gives); returns
    the values (G, P) and, with ``grad``, their gradient in ``uv`` (G, P, 2), else None."""
    G, H, W = image.shape
    hi = uv.new_tensor([W - 1.0, H - 1.0])
    inside = torch.minimum(uv.clamp_min(0.0), hi)
    off = uv - inside
    oo = (off * off).sum(-1)
    out_dist = oo.clamp_min(1e-12).sqrt() * (oo > 0)
    if H < 2 or W < 2:  # a one-pixel-wide image: its border replicated, so both neighbours exist
        image = F.pad(image.unsqueeze(1), (0, int(W < 2), 0, int(H < 2)), mode="replicate").squeeze(1)
        H, W = image.shape[-2:]
    corner = inside.floor().clamp_max_(uv.new_tensor([W - 2.0, H - 2.0]))
    frac = inside - corner
    fx, fy = frac.unbind(-1)
    ci = corner.long()
    idx = ci[..., 1] * W + ci[..., 0]
    v = image.reshape(G, H * W).gather(1, torch.cat([idx, idx + 1, idx + W, idx + W + 1], 1)).view(G, 4, -1)
    v00, v01, v10, v11 = v.unbind(1)
    dx0, dx1 = v01 - v00, v11 - v10
    top = torch.addcmul(v00, fx, dx0)
    bottom = torch.addcmul(v10, fx, dx1)
    value = torch.addcmul(top, fy, bottom - top) + out_dist
    if not grad:
        return value, None
    within = (uv >= 0) & (uv <= hi)  # where the clamp passes the gradient
    g = torch.stack([torch.addcmul(dx0, fy, dx1 - dx0), bottom - top], -1) * within
    g = g + off * ((oo >= 1e-12) / oo.clamp_min(1e-12).sqrt()).unsqueeze(-1)
    return value, g
