"""Randomised quasi-Monte-Carlo noise for QRS sampling (Fontmarty Table 4, "QRS-CONDENSATION").

Plain Monte Carlo draws the children of a resampled parent with i.i.d. noise, which leaves "gaps and
clusters" in high dimension. QRS replaces the ``C_j`` children of parent ``j`` by the first ``C_j`` points of
a randomised Sobol sequence in ``[0, 1)^M`` mapped through the Gaussian inverse CDF, so the children cover the
dynamics noise evenly (Fontmarty §2.4: error ``O(N^-1 log^M N)`` instead of ``O(N^-1/2)`` for smooth
integrands).

Vectorised form used here: one scrambled Sobol sequence per call (``torch.quasirandom.SobolEngine``,
Owen-style scrambling seeded from the caller's generator), and an independent uniform Cranley-Patterson shift
per parent (and per sequence), ``u = frac(sobol[rank] + shift[parent])``. The child of rank ``r`` within its
parent gets point ``r``; each parent's children therefore form a randomised low-discrepancy set, each point is
marginally uniform (the estimator stays unbiased), and parents do not share points. Sobol dimension is limited
to ``SobolEngine.MAXDIM`` = 21201.

Example::

    from torchpf.filters.qmc import qrs_normal
    eps = qrs_normal(ancestors, noise_dim=30, generator=g, dtype=torch.float64)   # (..., N, 30), ~N(0, I)
    x_new = x_parent + eps * std
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.quasirandom import SobolEngine

from torchpf.filters.state import gather_particles


def host_seed(generator: torch.Generator | None, device: torch.device | str | None = None) -> int:
    """A Python int seed drawn from ``generator`` (one host sync; used to seed a :class:`SobolEngine`)."""
    device = generator.device if generator is not None else (device or "cpu")
    return int(torch.randint(0, 2**31 - 1, (1,), generator=generator, device=device).item())


def rank_within_parent(ancestors: Tensor) -> Tensor:
    """Rank of each child among the children of the same parent: ``(..., N) long -> (..., N) long``.

    The children of parent ``j`` get ranks ``0, ..., C_j - 1`` in the order they appear in ``ancestors``.
    """
    n = ancestors.shape[-1]
    sorted_anc, perm = ancestors.sort(dim=-1, stable=True)
    first = torch.searchsorted(sorted_anc.contiguous(), sorted_anc.contiguous(), right=False)
    rank_sorted = torch.arange(n, device=ancestors.device).expand_as(first) - first
    return torch.empty_like(ancestors).scatter_(-1, perm, rank_sorted)


def sobol_uniform(
    n: int, dim: int, generator: torch.Generator | None, *, device=None, dtype=torch.float32
) -> Tensor:
    """First ``n`` points of a scrambled Sobol sequence in ``[0, 1)^dim``: ``(n, dim)``."""
    if dim > SobolEngine.MAXDIM:
        raise ValueError(f"Sobol sequences exist up to dimension {SobolEngine.MAXDIM}, got {dim}")
    engine = SobolEngine(dim, scramble=True, seed=host_seed(generator, device))
    draw_dtype = dtype if dtype in (torch.float32, torch.float64) else torch.float64
    return engine.draw(n, dtype=draw_dtype).to(device=device, dtype=dtype)


def _to_normal(u: Tensor) -> Tensor:
    # Keep u strictly inside (0, 1): ndtri(0) = -inf would poison a particle.
    tiny = torch.finfo(u.dtype).eps
    return torch.special.ndtri(u.clamp(tiny, 1 - tiny))


def qrs_normal(
    ancestors: Tensor, noise_dim: int, generator: torch.Generator | None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """Randomised-QMC standard-normal noise for resampled children: ``(..., N)`` ancestors -> ``(..., N, M)``.

    Args:
        ancestors: ``(..., N)`` parent index of each child (from a resampler, or ``arange(N)`` if none ran).
        noise_dim: ``M``, dimension of the noise (the dynamics' ``noise_dim``).
        generator: randomness for the scrambling and the per-parent shifts (device of ``ancestors``).
        dtype: floating dtype of the output.
    """
    n = ancestors.shape[-1]
    device = ancestors.device
    base = sobol_uniform(n, noise_dim, generator, device=device, dtype=dtype)  # (N, M)
    shifts = torch.rand(ancestors.shape + (noise_dim,), generator=generator, device=device, dtype=dtype)
    points = base[rank_within_parent(ancestors)]  # (..., N, M)
    u = torch.remainder(points + gather_particles(shifts, ancestors), 1.0)
    return _to_normal(u)


def sobol_normal(
    shape: tuple[int, ...], generator: torch.Generator | None, *, device=None, dtype=None
) -> Tensor:
    """Scrambled-Sobol standard normals ``(..., N, M)`` for a QMC initial draw (Fontmarty Table 4, step 1).

    Every ``(...)`` slice gets the same Sobol points with its own random shift. Example:
    ``x0 = mean + std * sobol_normal((B, N, D), g)``.
    """
    *batch, n, dim = shape
    dtype = dtype or torch.get_default_dtype()
    ancestors = torch.zeros(tuple(batch) + (n,), dtype=torch.long, device=device)
    return qrs_normal(ancestors, dim, generator, dtype)
