"""Per-DOF motion statistics from mocap: the learned random walk and constant-velocity prior (Rius eq. 3).

:func:`fit_dynamics` learns, from performances of any action (mocap CSVs loaded with
:func:`training.mocap.load_csv`), what the ``learned`` motion prior (:func:`priors.factories.learned`) needs,
as a :class:`priors.diffusion.LearnedDynamics` (saved as a versioned ``.npz``):

1. *Frame rate.* Every performance is unwrapped along time (revolute DOFs, from the skeleton's
   ``dof_revolute``) and resampled to ``fps`` (:func:`training.align.resample`; default: the performances'
   median rate). The statistics are per frame at that rate; fit at the rate you track at (the ``learned``
   factory rescales otherwise).
2. *Step stds.* Per DOF, the robust std of the frame steps ``δ_t = θ_t - θ_{t-1}`` of all performances:
   ``1.4826 · median |δ|`` (the normal-consistent median absolute deviation about 0, insensitive to the
   Euler-angle flips and marker glitches of real mocap). About 0 rather than about the median step because
   a random walk must cover the whole step, drift (walking forward) included.
3. *Constant velocity* (Rius eq. 3, :class:`priors.motion.ConstantVelocity`): α minimises the squared
   prediction error of ``φ̂_{t+1} = φ_t + V_t``, ``V_t = α V_{t-1} + (1 - α) δ_t``, per DOF (Rius §3.1,
   ``per_dof=True``) or over all DOFs, and ``cv_std`` is the robust std of those prediction errors at α
   (:func:`cv_statistics`, also the action-model fitter's σ_φ: one home for both).

:func:`class_speeds` measures, per body-part class, the speed of the farthest capsule point a DOF drives
and the angular speed of its revolute DOFs: how :data:`priors.diffusion.SPEEDS` and
:data:`priors.diffusion.ANGULAR_SPEEDS` were set.

Example::

    stats = fit_dynamics([load_csv(p, dof_names=skel.dof_names) for p in paths], skeleton=skel, fps=30)
    stats.save("dyn.npz")      # then Tracker(..., dynamics="learned", dynamics_options={"path": "dyn.npz"})

or ``python -m training fit-dynamics DATA/*.csv --skeleton S.urdf --fps 30 --out dyn.npz``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import minimize_scalar
from scipy.signal import lfilter

from priors.action import guess_revolute
from priors.diffusion import LearnedDynamics, dof_classes, lever_arms
from training.align import resample
from training.mocap import Motion

#: Consistency factor of the median absolute deviation for a normal distribution.
MAD_TO_STD = 1.4826


def robust_std(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """``1.4826 · median |x|`` along ``axis``: the std of zero-mean normal data, robust to outliers."""
    return MAD_TO_STD * np.median(np.abs(x), axis) if x.shape[axis] else np.zeros(np.delete(x.shape, axis))


def constant_velocity_errors(deltas: np.ndarray, alpha) -> np.ndarray:
    """Prediction errors of Rius eq. 3 along one performance.

    Args:
        deltas: ``(T-1, D)`` frame differences ``φ_t - φ_{t-1}``.
        alpha: velocity smoothing α, a float or ``(D,)`` per DOF.

    Returns:
        ``(T-2, D)`` errors ``e_{t+1} = (φ_{t+1} - φ_t) - V_t`` with ``V_t = α V_{t-1} + (1-α) δ_t``,
        ``V`` started at the first difference.
    """
    if deltas.shape[0] < 2:
        return np.zeros((0, deltas.shape[1]))
    alpha = np.asarray(alpha, dtype=float)
    if alpha.ndim == 0:
        v = lfilter([1.0 - alpha], [1.0, -alpha], deltas, axis=0, zi=alpha * deltas[:1])[0]
    else:  # one filter per DOF
        v = np.stack(
            [
                lfilter([1.0 - a], [1.0, -a], deltas[:, d], zi=[a * deltas[0, d]])[0]
                for d, a in enumerate(alpha)
            ],
            axis=1,
        )
    return deltas[1:] - v[:-1]


def fit_alpha(deltas: Sequence[np.ndarray], *, per_dof: bool = False):
    """Rius eq. 3's α: the velocity smoothing in ``[0, 0.999]`` that minimises the squared prediction error
    ``Σ ||constant_velocity_errors(δ, α)||²`` over performances.

    Args:
        deltas: per performance, ``(T_r - 1, D)`` frame differences of the DOFs that count.
        per_dof: one α per DOF (``(D,)`` array, each minimising its own DOF's error: Rius §3.1 per DOF;
            a grid of 0.001 steps) instead of one for all (a float, bounded scalar least squares).
    """
    if per_dof:
        grid = np.linspace(0.0, 0.999, 1000)
        losses = np.stack(
            [sum(np.sum(constant_velocity_errors(d, a) ** 2, 0) for d in deltas) for a in grid[::10]]
        )  # coarse pass, then a fine one around each DOF's best
        best = grid[::10][np.argmin(losses, 0)]
        fine = np.clip(best[None, :] + np.linspace(-0.01, 0.01, 21)[:, None], 0.0, 0.999)
        losses = np.stack([sum(np.sum(constant_velocity_errors(d, a) ** 2, 0) for d in deltas) for a in fine])
        return fine[np.argmin(losses, 0), np.arange(fine.shape[1])]

    def loss(alpha: float) -> float:
        return float(sum(np.sum(constant_velocity_errors(d, alpha) ** 2) for d in deltas))

    return float(minimize_scalar(loss, bounds=(0.0, 0.999), method="bounded").x)


def cv_statistics(deltas: Sequence[np.ndarray], alpha=None, *, per_dof: bool = False):
    """Rius eq. 3 fitted to frame differences: ``(alpha, cv_std)`` with ``alpha`` from :func:`fit_alpha`
    (unless given) and ``cv_std (D,)`` the robust std (:func:`robust_std`) of the prediction errors at it;
    the one rule for the action models' σ_φ and the learned dynamics."""
    a = fit_alpha(deltas, per_dof=per_dof) if alpha is None else alpha
    errors = np.concatenate([constant_velocity_errors(d, a) for d in deltas])
    return a, robust_std(errors)


def _tracks(motions: Sequence[Motion], revolute: np.ndarray, fps: float) -> list[np.ndarray]:
    """Each performance's ``(T_r, D)`` tracks, angles unwrapped along time, resampled to ``fps``."""
    out = []
    for m in motions:
        a = m.angles.detach().to("cpu", torch.float64).numpy().copy()
        a[:, revolute] = np.unwrap(a[:, revolute], axis=0)  # before resampling: never interpolate across ±π
        out.append(resample(a, m.fps, fps))
    return out


def fit_dynamics(
    motions: Sequence[Motion],
    *,
    skeleton=None,
    fps: float | None = None,
    alpha: float | None = None,
    per_dof: bool = True,
) -> LearnedDynamics:
    """Learn per-DOF step stds and the constant-velocity α from performances (module docstring).

    Args:
        motions: ``R`` performances with the same DOF names (any order, lengths and frame rates); at least 3
            frames at ``fps`` in all.
        skeleton: their :class:`torchpf.Skeleton`: its ``dof_names`` order the result and its
            ``dof_revolute`` says which DOFs are angles (without one: the names,
            :func:`priors.action.guess_revolute`).
        fps: rate (Hz) of the statistics; ``None``: the performances' median rate.
        alpha: fix α instead of fitting it.
        per_dof: fit one α per DOF (default; Rius §3.1 per DOF) rather than one for all.

    Returns:
        :class:`priors.diffusion.LearnedDynamics` (``.save(path)`` writes it).
    """
    motions = list(motions)
    if not motions:
        raise ValueError("fit_dynamics needs at least one performance")
    names = list(skeleton.dof_names) if skeleton is not None else list(motions[0].dof_names)
    for i, m in enumerate(motions):
        if set(m.dof_names) != set(names) or len(m.dof_names) != len(names):
            missing, extra = sorted(set(names) - set(m.dof_names)), sorted(set(m.dof_names) - set(names))
            raise ValueError(
                f"{m.name or f'performance {i}'}: DOFs differ (missing {missing[:5]}, extra {extra[:5]})"
            )
    motions = [m if m.dof_names == names else m.select(names) for m in motions]
    revolute = skeleton.dof_revolute.numpy() if skeleton is not None else np.array(guess_revolute(names))
    rate = float(np.median([m.fps for m in motions])) if fps is None else float(fps)
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"fps must be > 0, got {fps}")
    deltas = [np.diff(a, axis=0) for a in _tracks(motions, revolute, rate)]
    steps = np.concatenate(deltas)
    if len(steps) < 2:
        raise ValueError(f"the performances have fewer than 3 frames at {rate:g} fps; need more data")
    a, cv_std = cv_statistics(deltas, alpha, per_dof=per_dof)
    info = {
        "performances": [m.name or f"performance {i}" for i, m in enumerate(motions)],
        "frames": int(len(steps) + len(deltas)),
        "estimator": "1.4826 * median |x| (x: frame steps; constant-velocity prediction errors)",
    }
    return LearnedDynamics(names, rate, robust_std(steps), a, cv_std, revolute, info)


def class_speeds(
    performances: Sequence[tuple], *, quantile: float = 0.75, skip_first: int = 1, angular: bool = False
) -> dict[str, float]:
    """Speed (m/s) of the farthest capsule point each class of DOF drives (how
    :data:`priors.diffusion.SPEEDS` was set), or with ``angular=True`` the angular speed (rad/s) of the
    class's revolute DOFs (:data:`priors.diffusion.ANGULAR_SPEEDS`).

    Per performance, per DOF: the robust step ``1.4826 · median |δ_d|`` (:func:`robust_std`) times the fps,
    as an angle or as the chord it moves the farthest capsule point at the rest-pose lever arm
    (:func:`priors.diffusion.lever_arms`); per class (:func:`priors.diffusion.dof_classes`) the ``quantile``
    over its moving DOFs; then the median over performances.

    Args:
        performances: ``(skeleton, motion)`` pairs, e.g. from :func:`training.mocap.load_bvh`.
        quantile: in [0, 1].
        skip_first: frames dropped at the start of each motion (CMU conversions: 1, a rest pose).
        angular: measure rad/s of the revolute DOFs instead of m/s.
    """
    per_clip: dict[str, list[float]] = {}
    for skel, motion in performances:
        m = motion if motion.dof_names == skel.dof_names else motion.select(skel.dof_names)
        revolute = skel.dof_revolute.numpy()
        track = _tracks([m[skip_first:]], revolute, m.fps)[0]
        step = robust_std(np.diff(track, axis=0))
        lever = lever_arms(skel).numpy()
        chord = np.where(revolute, 2.0 * lever * np.sin(step / 2.0), step)
        speed = (step if angular else chord) * m.fps
        classes = np.array(dof_classes(skel))
        for c in set(classes.tolist()):
            moving = (classes == c) & (lever > 0) & (speed > 1e-4) & (revolute if angular else True)
            if moving.any():
                per_clip.setdefault(c, []).append(float(np.quantile(speed[moving], quantile)))
    return {c: float(np.median(v)) for c, v in sorted(per_clip.items())}


def learn_from_files(paths: Sequence[str | Path], skeleton, *, fps=None, alpha=None, skip_first: int = 0):
    """:func:`fit_dynamics` on mocap CSV files checked against ``skeleton``'s DOF names
    (:func:`training.mocap.load_csv`, whose errors name the file), first ``skip_first`` frames dropped."""
    from training.mocap import load_csv

    names = skeleton.dof_names if skeleton is not None else None
    motions = [load_csv(p, dof_names=names)[skip_first:] for p in paths]
    return fit_dynamics(motions, skeleton=skeleton, fps=fps, alpha=alpha)
