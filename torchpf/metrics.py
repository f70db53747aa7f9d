"""Tracking metrics: the Fontmarty evaluation protocol, Hauberg's marker-to-skin error and ESS, MPJPE.

Positions are joint positions ``(..., K, J, 3)`` in metres (``K`` frames, ``J`` joints); several runs of a
stochastic tracker on one sequence stack on a leading ``R`` dim: estimates ``(R, K, J, 3)`` against a truth
``(K, J, 3)``. A single run may be passed without the ``R`` dim.

* :func:`rmse` (Fontmarty eq. 3), :func:`bias` (eq. 4), :func:`dispersion` (eq. 5),
  :func:`failure_rate` (eq. 6) -- the four criteria of Fontmarty et al. §3.3.3;
* :func:`effective_sample_size` and :func:`mean_ess` (Hauberg eq. 17 / Brubaker eq. 18, with squared
  normalised weights);
* :func:`marker_to_skin` (Hauberg eq. 16): mean distance of mocap markers to the capsule skin;
* :func:`mpjpe` (mean per-joint position error), :func:`angle_mse` (Rius: mean squared joint-angle error,
  angles compared on the circle).

Example::

    truth = skel.fk(true_angles)                     # (K, J, 3)
    runs = skel.fk(torch.stack(estimated_angles))    # (R, K, J, 3)
    table = evaluate(truth, runs)                    # {"rmse": ..., "bias": ..., ...} in metres
"""

from __future__ import annotations

import torch

from torchpf.distributions import wrap_angle
from torchpf.filters import weights
from torchpf.geometry import capsule_distance

#: ``(..., N)`` log-weights -> ``(...)`` ESS (0 for a dead row); one home: :func:`torchpf.filters.weights.ess`
effective_sample_size = weights.ess


def _runs(truth: torch.Tensor, estimates: torch.Tensor) -> torch.Tensor:
    """Estimates as (R, K, J, 3), checked against the truth's (K, J, 3)."""
    if truth.ndim != 3 or truth.shape[-1] != 3:
        raise ValueError(f"truth must be (K, J, 3) joint positions, got {tuple(truth.shape)}")
    if estimates.shape == truth.shape:
        estimates = estimates[None]
    if estimates.ndim != 4 or estimates.shape[1:] != truth.shape:
        raise ValueError(
            f"estimates must be (R, K, J, 3) or (K, J, 3) matching truth {tuple(truth.shape)}, "
            f"got {tuple(estimates.shape)}"
        )
    return estimates


def rmse(truth: torch.Tensor, estimates: torch.Tensor) -> torch.Tensor:
    """Fontmarty eq. 3: per-joint RMS error over frames and runs, averaged over joints (m).

    ``(1/J) sum_j sqrt((1/K)(1/R) sum_k sum_r ||m_j^{t_k} - m_j^{x_{k,r}}||^2)``.

    Args:
        truth: (K, J, 3) true joint positions.
        estimates: (R, K, J, 3) estimates of R runs, or (K, J, 3) for one run.
    """
    est = _runs(truth, estimates)
    sq = (est - truth).pow(2).sum(-1)  # (R, K, J)
    return sq.mean((0, 1)).sqrt().mean()


def bias(truth: torch.Tensor, estimates: torch.Tensor) -> torch.Tensor:
    """Fontmarty eq. 4: norm of the time-averaged error of the run-averaged estimate, joint-averaged (m).

    ``(1/J) sum_j || (1/K) sum_k (m_j^{t_k} - (1/R) sum_r m_j^{x_{k,r}}) ||``.
    """
    est = _runs(truth, estimates)
    return (truth - est.mean(0)).mean(0).norm(dim=-1).mean()


def dispersion(estimates: torch.Tensor) -> torch.Tensor:
    """Fontmarty eq. 5: RMS spread of the estimates around their run average, joint-averaged (m).

    Args:
        estimates: (R, K, J, 3); zero for a single run.
    """
    if estimates.ndim != 4 or estimates.shape[-1] != 3:
        raise ValueError(f"estimates must be (R, K, J, 3), got {tuple(estimates.shape)}")
    dev = (estimates - estimates.mean(0)).pow(2).sum(-1)  # (R, K, J)
    return dev.mean((0, 1)).sqrt().mean()


def failure_rate(truth: torch.Tensor, estimates: torch.Tensor, threshold: float = 0.25) -> torch.Tensor:
    """Fontmarty eq. 6: fraction of (run, joint, frame) triples whose error exceeds ``threshold`` (m).

    The paper uses ``0.2 < T_failure < 0.3`` depending on the mean error.
    """
    est = _runs(truth, estimates)
    err2 = (est - truth).pow(2).sum(-1)
    return (err2 > threshold**2).to(est.dtype).mean()


def frame_failures(truth: torch.Tensor, estimates: torch.Tensor, threshold: float = 0.25) -> torch.Tensor:
    """(R, K) bool: the frames where at least one joint is further than ``threshold`` (m) from the truth."""
    est = _runs(truth, estimates)
    return ((est - truth).pow(2).sum(-1) > threshold**2).any(-1)


def mpjpe(truth: torch.Tensor, estimates: torch.Tensor) -> torch.Tensor:
    """Mean per-joint position error (m): mean Euclidean distance over runs, frames and joints."""
    est = _runs(truth, estimates)
    return (est - truth).norm(dim=-1).mean()


def per_joint_error(truth: torch.Tensor, estimates: torch.Tensor) -> torch.Tensor:
    """(J,) mean Euclidean error (m) of each joint over runs and frames."""
    est = _runs(truth, estimates)
    return (est - truth).norm(dim=-1).mean((0, 1))


def angle_mse(
    truth: torch.Tensor, estimates: torch.Tensor, revolute: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean squared joint-angle error (rad^2) as in Rius et al.; revolute differences wrapped to [-pi, pi).

    Args:
        truth: (..., D) angles; estimates: broadcastable (..., D).
        revolute: optional (D,) bool, which DOFs are angles (default all); the others (root translation,
            metres) are left out.
    """
    diff = estimates - truth
    diff = wrap_angle(diff)
    if revolute is not None:
        diff = diff[..., revolute.to(device=diff.device, dtype=torch.bool)]
    return diff.pow(2).mean()


def mean_ess(ess_per_frame: torch.Tensor) -> torch.Tensor:
    """Time-averaged ESS: mean over the last (frame) dim of a (..., T) ESS track."""
    return ess_per_frame.mean(-1)


def marker_to_skin(
    markers: torch.Tensor, ends: torch.Tensor, radii: torch.Tensor, *, chunk_size: int | None = None
) -> torch.Tensor:
    """Hauberg eq. 16: mean (over frames and markers) distance from each marker to the capsule skin (m).

    Args:
        markers: (T, M, 3) marker positions (m), e.g. ``skel.fk(true_angles)`` lifted onto the skin, or
            real mocap markers.
        ends: (T, C, 2, 3) capsule end points of the estimated poses (``skel.capsules(theta)[0]``).
        radii: (C,) capsule radii (m).

    Returns:
        Scalar ``(1/(T M)) sum_t sum_m |D(theta_t, v_m)|``, the orthogonal distance to the skin (a marker
        inside the body counts by its depth below the surface).
    """
    if markers.ndim != 3 or ends.ndim != 4 or ends.shape[0] != markers.shape[0]:
        raise ValueError(
            f"markers must be (T, M, 3) and ends (T, C, 2, 3) with the same T, got "
            f"{tuple(markers.shape)} and {tuple(ends.shape)}"
        )
    d = capsule_distance(markers, ends[..., 0, :], ends[..., 1, :], radii, chunk_size=chunk_size)
    return d.abs().mean()


def evaluate(truth: torch.Tensor, estimates: torch.Tensor, threshold: float = 0.25) -> dict[str, float]:
    """All position criteria of one sequence as floats (m, or a fraction for the failure rate)."""
    est = _runs(truth, estimates)
    return {
        "rmse": float(rmse(truth, est)),
        "bias": float(bias(truth, est)),
        "dispersion": float(dispersion(est)),
        "failure_rate": float(failure_rate(truth, est, threshold)),
        "mpjpe": float(mpjpe(truth, est)),
    }
