"""Resampling schemes: turn log-weights into ancestor indices.

A particle filter keeps a weighted sample ``{(x_i, w_i)}``. Resampling replaces it by an evenly weighted one,
drawing each new particle's *ancestor* ``a_i`` with ``P(a_i = j) = w_j`` (Brubaker Alg. 1; Fontmarty Table 1,
step 5). All four schemes here are unbiased, ``E[#{i : a_i = j}] = N w_j``; they differ in the variance of the
offspring counts:

=============  ==============================================================================================
multinomial    ``N`` independent draws from the categorical distribution (the textbook scheme; most variance)
stratified     one uniform draw in each of the ``N`` strata ``[k/N, (k+1)/N)``
systematic     a single uniform ``U`` shared by all strata: ``u_k = (k + U) / N`` (least work, low variance)
residual       ``floor(N w_j)`` copies of each particle, the remaining ones drawn multinomially from the
               residual weights ``N w_j - floor(N w_j)``
=============  ==============================================================================================

Schemes take log-weights ``(..., N)`` (any leading batch dims, unnormalised is fine, ``-inf`` = impossible)
and return ancestor indices ``(..., N)`` (``torch.long``; sorted, except the multinomial tail of residual
resampling). A row whose weights are all ``-inf`` or NaN has no distribution to sample; it
gets the identity ``a_i = i`` so that callers can flag the frame instead of crashing.

Schemes are registered by name in :data:`RESAMPLERS` (the library's one :class:`~torchpf.registry.Registry`
mechanism), so a filter takes ``resampler="systematic"`` or any callable with the same signature.

Example::

    from torchpf.resampling import resample
    ancestors = resample(log_weights, "systematic", generator=torch.Generator().manual_seed(0))  # (..., N)
    particles = particles.gather(-2, ancestors[..., None].expand_as(particles))
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from torchpf.registry import Registry

Resampler = Callable[[Tensor, "torch.Generator | None"], Tensor]
"""Signature of a scheme: ``(log_weights (..., N), generator) -> ancestors (..., N) long``."""

RESAMPLERS: Registry[Resampler] = Registry("resampler")
"""Resampling schemes by name (:class:`torchpf.registry.Registry`); add one with
``@RESAMPLERS.register("name")``, look one up with ``RESAMPLERS.resolve(name_or_callable)``."""


def resample(
    log_weights: Tensor, scheme: str | Resampler = "systematic", generator: torch.Generator | None = None
) -> Tensor:
    """Draw ancestor indices with the named scheme.

    Args:
        log_weights: ``(..., N)`` log-weights, normalised or not; ``-inf`` marks a zero weight.
        scheme: a name in :data:`RESAMPLERS` (``"multinomial"``, ``"systematic"``, ``"stratified"``,
            ``"residual"``) or a callable ``(log_weights, generator) -> ancestors``.
        generator: source of randomness (on the device of ``log_weights``); ``None`` uses torch's global one.

    Returns:
        ``(..., N)`` long ancestor indices into the last dim of ``log_weights``.
    """
    return RESAMPLERS.resolve(scheme)(log_weights, generator)


def offspring_counts(ancestors: Tensor, n: int | None = None) -> Tensor:
    """Number of children of each particle: ``(..., N)`` ancestors -> ``(..., n)`` long counts."""
    n = ancestors.shape[-1] if n is None else n
    counts = ancestors.new_zeros(ancestors.shape[:-1] + (n,))
    return counts.scatter_add_(-1, ancestors, torch.ones_like(ancestors))


def _cdf(log_weights: Tensor) -> tuple[Tensor, Tensor]:
    """Normalised cumulative weights ``(..., N)`` and a ``(...,)`` mask of rows with no valid weight.

    The CDF is built from ``exp(log_w - max)`` so that no weight underflows before normalisation; its last
    entry is forced to exactly 1 so that ``searchsorted`` never runs off the end through rounding.
    """
    lw = torch.nan_to_num(log_weights.detach(), nan=-math.inf, posinf=math.inf, neginf=-math.inf)
    top = lw.amax(-1, keepdim=True)
    bad = ~torch.isfinite(top.squeeze(-1))
    w = torch.exp(lw - torch.where(torch.isfinite(top), top, torch.zeros_like(top)))
    cdf = torch.cumsum(w, -1)
    total = cdf[..., -1:]
    cdf = cdf / torch.where(total > 0, total, torch.ones_like(total))
    cdf[..., -1] = 1.0
    return cdf, bad


def _search(cdf: Tensor, u: Tensor, bad: Tensor) -> Tensor:
    # right=True skips zero-weight particles: their CDF interval [c_{j-1}, c_j) is empty.
    idx = torch.searchsorted(cdf.contiguous(), u.contiguous(), right=True).clamp_(max=cdf.shape[-1] - 1)
    identity = torch.arange(cdf.shape[-1], device=cdf.device).expand_as(idx)
    return torch.where(bad.unsqueeze(-1), identity, idx)


def _uniform(shape: tuple[int, ...], like: Tensor, generator: torch.Generator | None) -> Tensor:
    return torch.rand(shape, generator=generator, device=like.device, dtype=like.dtype)


@RESAMPLERS.register("multinomial")
def multinomial(log_weights: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Multinomial resampling: ``N`` i.i.d. categorical draws (returned sorted). ``(..., N) -> (..., N)``."""
    cdf, bad = _cdf(log_weights)
    u = _uniform(cdf.shape, cdf, generator).sort(-1).values
    return _search(cdf, u, bad)


@RESAMPLERS.register("stratified")
def stratified(log_weights: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Stratified resampling: ``u_k = (k + U_k) / N`` with independent ``U_k``. ``(..., N) -> (..., N)``."""
    cdf, bad = _cdf(log_weights)
    n = cdf.shape[-1]
    k = torch.arange(n, device=cdf.device, dtype=cdf.dtype)
    u = (k + _uniform(cdf.shape, cdf, generator)) / n
    return _search(cdf, u, bad)


@RESAMPLERS.register("systematic")
def systematic(log_weights: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Systematic resampling: ``u_k = (k + U) / N`` with one ``U`` per row. ``(..., N) -> (..., N)``."""
    cdf, bad = _cdf(log_weights)
    n = cdf.shape[-1]
    k = torch.arange(n, device=cdf.device, dtype=cdf.dtype)
    u = (k + _uniform(cdf.shape[:-1] + (1,), cdf, generator)) / n
    return _search(cdf, u, bad)


@RESAMPLERS.register("residual")
def residual(log_weights: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Residual resampling: ``floor(N w_j)`` deterministic copies, the rest multinomial on the residuals.

    ``(..., N) -> (..., N)``. The first ``sum_j floor(N w_j)`` slots hold the deterministic copies (sorted),
    the remaining slots the multinomial draws (in random order).
    """
    cdf, bad = _cdf(log_weights)
    n = cdf.shape[-1]
    w = torch.diff(cdf, dim=-1, prepend=torch.zeros_like(cdf[..., :1])).clamp_(min=0)
    scaled = n * w
    det = torch.floor(scaled)
    det_cum = torch.cumsum(det, -1)  # exact small integers in any float dtype used here (N < 2**24)
    n_det = det_cum[..., -1:]
    slots = torch.arange(n, device=cdf.device, dtype=cdf.dtype).expand_as(cdf)
    # Slot k < n_det belongs to the particle whose cumulative count first exceeds k.
    det_idx = torch.searchsorted(det_cum.contiguous(), slots.contiguous(), right=True).clamp_(max=n - 1)
    rest = (scaled - det).clamp_(min=0)
    rest_cdf = torch.cumsum(rest, -1)
    rest_total = rest_cdf[..., -1:]
    rest_cdf = rest_cdf / torch.where(rest_total > 0, rest_total, torch.ones_like(rest_total))
    rest_cdf[..., -1] = 1.0
    # Unsorted: only the slots past n_det are used, and a sorted draw would bias them towards large u.
    u = _uniform(cdf.shape, cdf, generator)
    rest_idx = torch.searchsorted(rest_cdf.contiguous(), u, right=True).clamp_(max=n - 1)
    idx = torch.where(slots < n_det, det_idx, rest_idx)
    identity = torch.arange(n, device=cdf.device).expand_as(idx)
    return torch.where(bad.unsqueeze(-1), identity, idx)
