"""Log-weights: the only home of normalisation, effective sample size, reweighting and tempering.

Every filter, metric and diagnostic of the library goes through these functions, so they agree on the edge
cases. Shapes: log-weights ``(..., N)``, particles on the last dim. The rules:

* NaN counts as ``-inf`` (an impossible particle).
* A *dead* row, every weight ``-inf``/NaN, has no distribution: its ESS is 0, :func:`reweight` flags it as
  failed and gives it uniform weights, and the resamplers give it the identity (see
  :mod:`torchpf.resampling`).

Example::

    from torchpf.filters import weights
    log_w, log_z, failed = weights.reweight(log_w, loglik)   # Brubaker Alg. 1 step 3, in log space
    weights.ess(log_w)                                        # (...,) in [1, N], 0 for a dead row
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def _clean(log_weights: Tensor) -> Tensor:
    return torch.nan_to_num(log_weights, nan=-math.inf, posinf=math.inf, neginf=-math.inf)


def normalise(log_weights: Tensor) -> Tensor:
    """``(..., N)`` log-weights shifted so that ``logsumexp`` over ``N`` is 0 (NaN counts as ``-inf``).

    A dead row stays dead (NaN after the shift); :func:`reweight` is what repairs one.
    """
    lw = _clean(log_weights)
    return lw - torch.logsumexp(lw, -1, keepdim=True)


def probabilities(log_weights: Tensor) -> Tensor:
    """Normalised weights ``(..., N)`` (a softmax of the log-weights, NaN counting as ``-inf``)."""
    return torch.softmax(_clean(log_weights), -1)


def ess(log_weights: Tensor) -> Tensor:
    """Effective sample size ``1 / sum_i w_i^2`` of the normalised weights (Brubaker eq. 18; Hauberg eq. 17
    with squared weights, see the seeds' README): ``(..., N) -> (...)`` in ``[1, N]``, 0 for a dead row.

    The log-weights may be unnormalised.
    """
    lw = _clean(log_weights)
    norm = torch.logsumexp(lw, -1, keepdim=True)
    ok = torch.isfinite(norm.squeeze(-1))
    lw = torch.where(ok.unsqueeze(-1), lw - norm, torch.zeros_like(lw))
    out = torch.exp(-torch.logsumexp(2 * lw, -1))
    return torch.where(ok, out, torch.zeros_like(out))


def survival_fraction(log_weights: Tensor) -> Tensor:
    """``ESS / N`` of (unnormalised) log-weights ``(..., N) -> (...)``: Deutscher's particle survival rate
    (0 for a dead row)."""
    return ess(log_weights) / log_weights.shape[-1]


def reweight(log_weights: Tensor, increment: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Add an incremental log-weight and renormalise, in log space (Brubaker Alg. 1, eq. 17).

    Args:
        log_weights: ``(..., N)`` normalised log-weights before the update.
        increment: ``(..., N)`` log of the incremental weight (NaN counts as ``-inf``).

    Returns:
        ``(log_weights (..., N), log_normaliser (...), failed (...) bool)``. ``log_normaliser`` is
        ``logsumexp(log_weights + increment)``, the log of the evidence increment. Rows with a non-finite
        normaliser are *failed*: they get uniform weights and a normaliser that callers must not use.
    """
    total = _clean(log_weights + increment)
    lse = torch.logsumexp(total, -1)
    failed = ~torch.isfinite(lse)
    uniform = torch.full_like(total, -math.log(total.shape[-1]))
    new = torch.where(failed.unsqueeze(-1), uniform, total - lse.unsqueeze(-1))
    return new, lse, failed


def temper(beta: Tensor, energy: Tensor) -> Tensor:
    """``beta * energy`` with ``-inf``/NaN energies kept at ``-inf`` (``0 * -inf`` would be NaN): the
    annealed log-target of Brubaker eq. 20. ``beta (...)`` broadcasts against ``energy (..., N)``."""
    energy = _clean(energy)
    out = beta.unsqueeze(-1) * energy
    return torch.where(energy == -math.inf, torch.full_like(out, -math.inf), out)
