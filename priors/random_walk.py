"""Angular random walk restricted to the joint limits (Hauberg eq. 3; Fontmarty §3.1 and Table 5).

``p(θ_t | θ_{t-1}) ∝ N(θ_t | θ_{t-1}, diag σ²) · U_limits(θ_t)``: independent Gaussian steps per DOF,
truncated to ``[lower, upper]``. Because the truncation is a box, the density is a product of
one-dimensional truncated normals, so rejection can be done **per DOF** (only the offending DOFs are
redrawn) and is exact. After ``max_tries`` rounds the few DOFs still outside (a particle pressed against a
limit) are drawn by the inverse CDF of their truncated normal, which is exact too, so no sample is ever
clamped by default.

``limits`` chooses how the box is enforced:

* ``"reject"`` (default): the truncated normal above. ``log_prob`` is exact: the Gaussian density divided
  by the mass ``Φ(b) - Φ(a)`` of the box around the previous pose, ``-inf`` outside the limits.
* ``"reflect"``: ``θ + σ ε`` folded back into the box at the limits. ``log_prob`` sums the Gaussian over
  the three nearest mirror images (exact unless ``σ`` is comparable to the range).
* ``"clamp"``: ``θ + σ ε`` clamped to the box; the clamped mass piles up on the limits. ``log_prob``
  returns the Gaussian density of the clamped point (it ignores those point masses: an approximation).

DOFs with ``σ = 0`` stay where they are (a Dirac; left out of ``log_prob``). ``sample_from_noise`` maps
standard normal noise through the inverse CDF of the truncated normal (``"reject"``) or through the fold /
clamp, so quasi-random (Sobol) sampling works (Fontmarty Table 4).

Example::

    from priors.factories import table5_sigma
    walk = AngularRandomWalk(table5_sigma(skel, fps=15), lower=skel.lower, upper=skel.upper)
    x = walk.sample(particles, generator)        # (..., N, D) inside the limits
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.special import ndtr, ndtri

_LIMITS = ("reject", "reflect", "clamp")
_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


class AngularRandomWalk(nn.Module):
    """Gaussian random walk on the DOFs, restricted to the joint limits (Hauberg eq. 3).

    Args:
        sigma: scalar or (D,) std per frame (rad, or m for translations); 0 freezes a DOF.
        lower, upper: (D,) limits (``Skeleton.lower`` / ``upper``; +-inf allowed).
        limits: ``"reject"`` (exact truncated normal), ``"reflect"`` or ``"clamp"`` (module docstring).
        max_tries: rejection rounds before the inverse-CDF draw of the remaining DOFs.

    Attributes:
        std: (D,) the step std, read by the annealed filter as its layer diffusion (Brubaker eq. 19).
        stats: after :meth:`sample`, ``{"rejected": (...) number of redrawn DOF values per sequence}``.
    """

    def __init__(self, sigma, lower, upper, *, limits: str = "reject", max_tries: int = 10):
        super().__init__()
        if limits not in _LIMITS:
            raise ValueError(f"limits must be one of {_LIMITS}, got {limits!r}")
        lower = torch.as_tensor(lower, dtype=torch.float64).reshape(-1)
        upper = torch.as_tensor(upper, dtype=torch.float64).reshape(-1)
        sigma = torch.as_tensor(sigma, dtype=torch.float64).expand(lower.shape).clone()
        if lower.shape != upper.shape or not torch.all(lower <= upper):
            raise ValueError("lower and upper must have the same shape (D,) with lower <= upper")
        if not torch.all(torch.isfinite(sigma) & (sigma >= 0)):
            raise ValueError("sigma must be finite and >= 0")
        self.register_buffer("std", sigma)
        self.register_buffer("lower", lower)
        self.register_buffer("upper", upper)
        self.limits = limits
        self.max_tries = int(max_tries)
        self.stats: dict[str, Tensor] = {}

    def _params(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return tuple(t.to(device=x.device, dtype=x.dtype) for t in (self.std, self.lower, self.upper))

    def _inside(self, x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        return (x >= lo) & (x <= hi)

    def sample(self, x: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Draw ``θ_t`` for every particle: ``(..., N, D) -> (..., N, D)``, inside the limits."""
        sigma, lo, hi = self._params(x)
        eps = torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
        if self.limits != "reject":
            return self.sample_from_noise(x, eps)
        # per-DOF rejection: exact because the box truncation factorises over the DOFs
        new = x + sigma * eps
        bad = ~self._inside(new, lo, hi)
        rejected = bad.flatten(-2).sum(-1)
        for _ in range(self.max_tries):
            if not bool(bad.any()):
                break
            redraw = x + sigma * torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)
            new = torch.where(bad, redraw, new)
            bad = ~self._inside(new, lo, hi)
            rejected = rejected + bad.flatten(-2).sum(-1)
        if bool(bad.any()):  # pressed against a limit: finish exactly with the inverse CDF
            u = torch.rand(x.shape, generator=generator, dtype=x.dtype, device=x.device)
            new = torch.where(bad, self._truncated_inverse_cdf(x, u), new)
        self.stats = {"rejected": rejected}
        return new

    def _truncated_inverse_cdf(self, x: Tensor, u: Tensor) -> Tensor:
        """``x + σ Φ^{-1}(Φ(a) + u (Φ(b) - Φ(a)))``: the truncated normal's quantile at ``u`` in (0, 1)."""
        sigma, lo, hi = self._params(x)
        safe = torch.where(sigma > 0, sigma, torch.ones_like(sigma))
        x64 = x.double()
        a, b = ((lo.double() - x64) / safe.double()), ((hi.double() - x64) / safe.double())
        pa, pb = ndtr(a), ndtr(b)
        p = (pa + u.double() * (pb - pa)).clamp(1e-300, 1 - 1e-16)
        z = ndtri(p).clamp(a, b)
        out = (x64 + safe.double() * z).to(x.dtype)
        return torch.where(sigma > 0, out, x)

    def sample_from_noise(self, x: Tensor, eps: Tensor) -> Tensor:
        """Deterministic map of standard normal ``eps (..., N, D)`` to ``θ_t`` (for QRS sampling)."""
        sigma, lo, hi = self._params(x)
        if self.limits == "reject":
            return self._truncated_inverse_cdf(x, ndtr(eps.double()).to(x.dtype))
        new = x + sigma * eps
        if self.limits == "clamp":
            return torch.maximum(torch.minimum(new, hi), lo)
        # reflect: fold into [lo, hi] with period 2 (hi - lo); unbounded DOFs pass through
        span = hi - lo
        finite = torch.isfinite(span) & (span > 0)
        span_safe = torch.where(finite, span, torch.ones_like(span))
        lo_safe = torch.where(finite, lo, torch.zeros_like(lo))
        folded = torch.remainder(new - lo_safe, 2 * span_safe)
        folded = lo_safe + torch.where(folded > span_safe, 2 * span_safe - folded, folded)
        return torch.where(finite, folded, torch.maximum(torch.minimum(new, hi), lo))

    def log_prob(self, x_new: Tensor, x_old: Tensor) -> Tensor:
        """``log p(θ_new | θ_old)`` summed over DOFs: ``(..., N, D), (..., N, D) -> (..., N)`` (see above)."""
        sigma, lo, hi = self._params(x_new)
        moving = sigma > 0
        safe = torch.where(moving, sigma, torch.ones_like(sigma))
        z = (x_new - x_old) / safe
        log_n = -0.5 * z * z - torch.log(safe) - _LOG_SQRT_2PI
        if self.limits == "reject":
            mass = ndtr((hi - x_old) / safe) - ndtr((lo - x_old) / safe)
            log_n = log_n - torch.log(mass.clamp_min(torch.finfo(x_new.dtype).tiny))
            log_n = torch.where(self._inside(x_new, lo, hi), log_n, torch.full_like(log_n, -math.inf))
        elif self.limits == "reflect":
            images = [x_new, 2 * lo - x_new, 2 * hi - x_new]
            terms = torch.stack([-0.5 * ((im - x_old) / safe) ** 2 for im in images])
            terms = torch.where(torch.isfinite(terms), terms, torch.full_like(terms, -math.inf))
            log_n = torch.logsumexp(terms, 0) - torch.log(safe) - _LOG_SQRT_2PI
        return torch.where(moving, log_n, torch.zeros_like(log_n)).sum(-1)

    def extra_repr(self) -> str:
        return f"D={self.std.numel()}, limits={self.limits!r}, max_tries={self.max_tries}"
