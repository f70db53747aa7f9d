"""Structural random-walk stds: each DOF's step std from the kinematic tree and capsules, never from names.

A DOF's std is the angle (or, prismatic, the distance) that moves the farthest capsule point it drives by a
set distance per frame, ``speed / fps``, with ``speed`` (m/s) one of :data:`SPEEDS` per body-part class
found from the tree structure (:func:`dof_classes`): the root's translations and rotations, the torso chain
and the limbs (:func:`torchpf.kinematics.body_partition`); short levers (hands, feet, head) are capped at
an angular speed per class (:data:`ANGULAR_SPEEDS`). A shoulder, a knee or a spine joint gets a
sensible std whatever it is called, and a DOF that moves no capsule (a zero-length leaf bone, fingers
without geometry) gets 0: held still.

* :func:`lever_arms` -- ``(D,)`` the largest distance (m) from each revolute DOF's pivot to a capsule surface
  point it moves, at the rest pose (0 where it moves no capsule); prismatic DOFs: 1 where they move one.
* :func:`structural_sigma` -- ``(D,)`` the std per frame at ``fps``: ``2 asin(s / 2L)`` rad (a rotation by
  it moves a point at distance ``L`` from the pivot by at most the chord ``s``), capped for short levers at
  a measured angular speed (:data:`ANGULAR_SPEEDS`), ``s`` m for prismatic DOFs.
* :func:`sigma_summary` -- the one-line summary of a std vector per body part that the factories log.
* :func:`diffusion_sigma` -- the std vector a factory asks for by name: ``"structural"`` (default),
  ``"table5"`` (Fontmarty Table 5 by joint names, :mod:`priors.table5`, refined so that it never holds still a
  DOF that moves a capsule) or explicit values; it logs :func:`sigma_summary` and warns when it guesses.
* :data:`SPEEDS`, :data:`ANGULAR_SPEEDS` -- the default per-class speeds, measured on the CMU walks and runs
  (``/work/shared/mocap/cmu``, 11 clips at 120 fps).
* :func:`at_rate` -- per-frame stds and α learned at one frame rate, at another.
* :class:`LearnedDynamics` -- per-DOF step stds and the constant-velocity α (Rius eq. 3) learned from mocap
  (``python -m training fit-dynamics``), saved as a versioned ``.npz``; the ``learned`` factory
  (:func:`priors.factories.learned`) reads it.

Example::

    from priors.diffusion import structural_sigma, sigma_summary
    sigma = structural_sigma(skel, fps=30.0)          # (D,) float64, rad or m per frame
    print(sigma_summary(skel, sigma, fps=30.0))
"""

from __future__ import annotations

import io
import json
import logging
import math
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from torchpf.io import read_versioned_npz, write_atomic
from torchpf.kinematics import body_partition

_log = logging.getLogger("priors")

#: Default speed (m/s) of the farthest capsule point each class of DOF drives. Measured
#: (:func:`training.dynamics.class_speeds`) on the 11 CMU walk and run clips of ``/work/shared/mocap/cmu``
#: (120 fps, rest frame dropped): per DOF the robust step ``1.4826 · median |Δθ_d|`` as the chord it moves
#: its farthest capsule point at the rest-pose lever (:func:`lever_arms`), times the fps; per clip the upper
#: quartile over the class's moving DOFs; the median over clips (1.28 / 0.76 / 0.27 / 0.50 m/s), rounded.
#: The class median (0.19 / 0.73 / 0.17 / 0.22 m/s) is set by small distal joints and under-spreads hips,
#: knees and shoulders; the 90th percentile (1.93 / 0.78 / 0.33 / 1.29 m/s) over-spreads a budget of a few
#: hundred particles: on notebook 03's walk (human.urdf, 15 fps, 450 evaluations, 2 runs) it gave APF / SIR
#: / partitioned RMSE 0.29 / 0.16 / 0.18 m against 0.19 / 0.11 / 0.13 m with the upper quartile (Table 5 by
#: names: 0.22 / 0.12 / 0.11 m). Per-frame steps of real motion are velocity-dominated (on the same clips
#: the step std at 30 fps is 3.3x the one at 120 fps, 2.5x from 30 to 10 fps: close to the ``1 / fps`` of a
#: speed, far from the ``sqrt(1 / fps)`` of a random walk), so the std scales as ``1 / fps``.
SPEEDS: dict[str, float] = {
    "root_translation": 1.3,
    "root_rotation": 0.75,
    "torso": 0.27,
    "limb": 0.5,
}

#: Most angular speed (rad/s) of a revolute DOF per class: a cap on :data:`SPEEDS`' angle for short levers.
#: Same clips and statistic (:func:`training.dynamics.class_speeds` with ``angular=True``: the upper
#: quartile over the class's moving DOFs of ``1.4826 · median |Δθ_d| · fps``, median over clips: 0.76 /
#: 0.48 / 1.80 rad/s). Segments turn at a bounded rate whatever their size: the tip of a hand, a foot or a
#: head moves far slower than a hip swings the foot, so one distance per frame alone would give the 4 cm
#: lever of a thumb 0.43 rad per frame at 30 fps (40x its measured step) where the cap gives 0.06.
ANGULAR_SPEEDS: dict[str, float] = {
    "root_rotation": 0.75,
    "torso": 0.48,
    "limb": 1.8,
}

_CLASSES = tuple(SPEEDS)


def rest_pose(skeleton) -> torch.Tensor:
    """``(D,)`` float64 rest pose: zero angles clamped into the joint limits (on the skeleton's device)."""
    zero = torch.zeros(len(skeleton.dof_names), dtype=torch.float64, device=skeleton.lower.device)
    return skeleton.clamp(zero)


def dof_classes(skeleton) -> list[str]:
    """``(D,)`` the class (a key of :data:`SPEEDS`) of each DOF, from the tree structure only.

    The root joint's (parent ``-1``) DOFs are ``root_translation`` (prismatic) or ``root_rotation``
    (revolute, ``skeleton.dof_revolute``); other DOFs of the torso chain (``tree.joint_part == 0``: pelvis to
    head, :func:`torchpf.kinematics.body_partition`) are ``torso``; every other DOF is ``limb``.
    """
    tree = skeleton.tree
    part, parents = tree.joint_part.tolist(), tree.parents.tolist()
    revolute = tree.dof_revolute.tolist()
    out = []
    for d, j in enumerate(tree.dof_joint.tolist()):
        if j >= 0 and parents[j] < 0:
            out.append("root_rotation" if revolute[d] else "root_translation")
        elif j >= 0 and part[j] == 0:
            out.append("torso")
        else:
            out.append("limb")
    return out


def lever_arms(skeleton, pose: torch.Tensor | None = None) -> torch.Tensor:
    """``(D,)`` float64: each DOF's lever arm (m) at ``pose`` (default :func:`rest_pose`).

    A capsule end point ``e`` (a body joint) moves with DOF ``d`` when it lies below ``d``
    (``tree.dof_moves``) and, for a revolute ``d``, off its pivot (``skeleton.dof_axes``; a point on the
    pivot stays put). A capsule moves when one of its ends does. A revolute DOF's lever is the largest
    distance from its pivot to the surface of a capsule it moves, ``max (|e - pivot| + radius)`` over the
    moving ends ``e`` (a capsule is the convex hull of its end spheres), so a rotation by ``φ`` moves no
    capsule point by more than the chord ``2 L sin(φ / 2)``, and exactly that where the farthest point lies
    square to the axis. The distance to the pivot rather than to the axis makes the lever independent of how
    the rest pose happens to orient the axes: a ball joint's three DOFs get one lever, and twisting a limb
    that is straight in the rest pose (its end on the axis) is not taken for invisible. A prismatic DOF that
    moves a capsule gets 1 (its step is a distance already). A DOF that moves no capsule gets 0.
    """
    theta = rest_pose(skeleton) if pose is None else torch.as_tensor(pose, dtype=torch.float64)
    theta = theta.to(skeleton.lower.device)
    tree = skeleton.tree
    _, pivots = skeleton.dof_axes(theta)  # (D, 3)
    pivots = pivots.cpu()
    joints = skeleton.fk(theta).cpu()  # (J, 3)
    bones = tree.bones.cpu()  # (C, 2)
    radii = skeleton.radii.to("cpu", torch.float64)  # (C,)
    revolute = tree.dof_revolute.cpu()
    moves = tree.dof_moves.cpu()  # (D, J)

    rel = joints[None] - pivots[:, None]  # (D, J, 3)
    from_pivot = rel.norm(dim=-1)  # (D, J)
    off_pivot = from_pivot > 1e-9
    moving = moves & (off_pivot | ~revolute[:, None])  # (D, J) the joint's position changes
    end_moving = moving[:, bones]  # (D, C, 2)
    capsule_moving = end_moving.any(-1)  # (D, C)
    reach = from_pivot[:, bones] + radii[None, :, None]  # (D, C, 2) farthest surface point of each end sphere
    reach = torch.where(end_moving, reach, torch.zeros_like(reach)).amax(-1)  # (D, C)
    reach = torch.where(capsule_moving, reach, torch.zeros_like(reach))
    none = torch.zeros(len(revolute), 1, dtype=torch.float64)  # a skeleton without capsules
    lever = torch.cat([reach, none], -1).amax(-1)
    moves_capsule = capsule_moving.any(-1)
    return torch.where(revolute, lever, moves_capsule.to(torch.float64))


def _table(
    default: Mapping[str, float], overrides: Mapping[str, float] | None, what: str
) -> dict[str, float]:
    out = dict(default)
    for key, value in dict(overrides or {}).items():
        if key not in default:
            raise ValueError(f"unknown {what} class {key!r}; choose from {list(default)}")
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{what} {key!r} must be finite and >= 0, got {value}")
        out[key] = float(value)
    return out


def structural_sigma(
    skeleton,
    fps: float,
    scale: float = 1.0,
    *,
    speeds: Mapping[str, float] | None = None,
    angular_speeds: Mapping[str, float] | None = None,
) -> torch.Tensor:
    """``(D,)`` float64 per-DOF random-walk std per frame at ``fps`` (rad or m), from the structure.

    With ``s = scale · speed / fps`` (``speed`` of the DOF's class, :func:`dof_classes`, :data:`SPEEDS`
    overridden by ``speeds``) and ``L`` its lever arm (:func:`lever_arms`): a revolute DOF gets
    ``2 asin(min(1, s / 2L))`` (a rotation by it moves the farthest capsule point by the chord ``s``), at
    most ``scale · ω / fps`` with ``ω`` its class's :data:`ANGULAR_SPEEDS` (overridden by
    ``angular_speeds``); a prismatic one ``s``; a DOF that moves no capsule 0.
    """
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be > 0, got {fps}")
    if not (math.isfinite(scale) and scale >= 0):
        raise ValueError(f"scale must be finite and >= 0, got {scale}")
    classes = dof_classes(skeleton)
    table = _table(SPEEDS, speeds, "speed")
    turn = _table(ANGULAR_SPEEDS, angular_speeds, "angular speed")
    step = torch.tensor([table[c] for c in classes], dtype=torch.float64) * (scale / fps)
    cap = torch.tensor([turn.get(c, math.inf) for c in classes], dtype=torch.float64) * (scale / fps)
    lever = lever_arms(skeleton)
    angle = 2.0 * torch.asin((step / (2.0 * lever.clamp_min(1e-12))).clamp(max=1.0))
    sigma = torch.where(skeleton.tree.dof_revolute.cpu(), torch.minimum(angle, cap), step)
    return torch.where(lever > 0, sigma, torch.zeros_like(sigma))


def part_names(skeleton) -> list[tuple[str, list[int]]]:
    """``[(label, DOF indices)]`` per body part: ``root`` (the root joint's DOFs), ``torso`` (the rest of the
    torso chain), then one entry per limb of :func:`torchpf.kinematics.body_partition` (``per_limb``),
    labelled ``armK`` when the torso joint it hangs from lies above the root in the rest pose, else ``legK``.
    DOFs in no part (below every body joint, another root's tree) come last as ``other``."""
    classes = dof_classes(skeleton)
    groups = body_partition(skeleton, per_limb=True)
    torso = groups[0] if groups else []
    out = [
        ("root", [d for d in torso if classes[d].startswith("root")]),
        ("torso", [d for d in torso if not classes[d].startswith("root")]),
    ]
    z = skeleton.fk(rest_pose(skeleton))[:, 2].cpu()
    part, parents = skeleton.tree.joint_part.tolist(), skeleton.tree.parents.tolist()
    root_z = float(z[parents.index(-1)]) if -1 in parents else 0.0
    counts = {"leg": 0, "arm": 0}
    for k, g in enumerate(groups[1:], start=1):
        top = next(j for j, p in enumerate(part) if p == k and parents[j] >= 0 and part[parents[j]] == 0)
        kind = "arm" if float(z[parents[top]]) > root_z + 1e-6 else "leg"
        counts[kind] += 1
        out.append((f"{kind}{counts[kind]}", g))
    seen = {d for _, g in out for d in g}
    out.append(("other", [d for d in range(len(classes)) if d not in seen]))
    return [(label, g) for label, g in out if g]


def sigma_summary(
    skeleton, sigma: torch.Tensor, *, fps: float, source: str = "structural", name: str = "random_walk"
) -> str:
    """One line: the std range per body part (:func:`part_names`; deg per frame for angles, mm for
    translations) and how many DOFs are held still, e.g. ``random_walk stds (structural, 30 fps): root
    3.3 mm, 0.29-0.31 deg; torso 0.4-1.2 deg; limb1 0.8-4.0 deg (3 still); ...``."""
    sigma = torch.as_tensor(sigma, dtype=torch.float64).cpu()
    revolute = skeleton.tree.dof_revolute.cpu()
    parts = []
    for label, dofs in part_names(skeleton):
        idx = torch.tensor(dofs)
        s, rev = sigma[idx], revolute[idx]
        moving = s > 0
        items = []
        for mask, unit, factor in ((~rev, "mm", 1e3), (rev, "deg", 180 / math.pi)):
            values = s[mask & moving] * factor
            if len(values):
                lo, hi = float(values.min()), float(values.max())
                items.append(
                    f"{lo:.2g} {unit}" if math.isclose(lo, hi, rel_tol=0.01) else f"{lo:.2g}-{hi:.2g} {unit}"
                )
        still = int((~moving).sum())
        text = ", ".join(items) if items else "all still"
        if still and items:
            text += f" ({still} still)"
        parts.append(f"{label} {text}")
    return f"{name} stds ({source}, {fps:g} fps, per frame): " + "; ".join(parts)


def diffusion_sigma(
    skeleton,
    stds="structural",
    *,
    fps: float | None = None,
    scale: float = 1.0,
    speeds: Mapping[str, float] | None = None,
    name: str = "random_walk",
) -> torch.Tensor:
    """``(D,)`` float64 per-frame diffusion stds for a factory's ``stds`` option, logged as one line.

    Args:
        skeleton: the :class:`torchpf.Skeleton`.
        stds: ``"structural"`` (:func:`structural_sigma`), ``"table5"`` (:func:`priors.table5.table5_sigma`
            by joint names, refined: a DOF Table 5 would hold still although it moves a capsule, or whose
            joint no name rule recognises, takes the structural std instead, with a warning), or explicit
            ``(D,)`` values (rad / m per frame, used as given, times ``scale``).
        fps: the tracking frame rate (Hz). ``None``: :data:`priors.table5.TABLE5_FPS` with a warning.
        scale: multiplies the stds.
        speeds: per-class speed overrides (m/s) for the structural stds (:data:`SPEEDS`).
        name: the prior's name in the logged summary.

    The one-line :func:`sigma_summary` goes to the ``priors`` logger at INFO level.
    """
    from priors.table5 import TABLE5_FPS, dof_groups, table5_sigma

    if fps is None:
        warnings.warn(
            f"{name}: no fps given; assuming {TABLE5_FPS:g} Hz for the per-frame stds", stacklevel=3
        )
        fps = TABLE5_FPS
    if isinstance(stds, str):
        kind = stds.lower()
        if kind == "structural":
            sigma = structural_sigma(skeleton, fps, scale, speeds=speeds)
            if (skeleton.tree.joint_part.cpu() < 0).any():
                warnings.warn(
                    f"{name}: some joints are in no body part (a second root?); their DOFs get the limb "
                    "speed",
                    stacklevel=3,
                )
        elif kind == "table5":
            sigma = table5_sigma(skeleton, fps, scale)
            structural = structural_sigma(skeleton, fps, scale, speeds=speeds)
            groups = dof_groups(skeleton)
            guess = torch.tensor([g == "other" for g in groups]) | ((sigma == 0) & (structural > 0))
            if guess.any():
                names = [n for n, g in zip(skeleton.dof_names, guess.tolist(), strict=True) if g]
                warnings.warn(
                    f"{name}: Table 5 holds still or does not recognise {len(names)} DOFs that move the body "
                    f"({', '.join(names[:6])}{' ...' if len(names) > 6 else ''}); they take structural stds",
                    stacklevel=3,
                )
                sigma = torch.where(guess, structural, sigma)
        else:
            raise ValueError(f"stds must be 'structural', 'table5' or (D,) values, got {stds!r}")
        source = kind
    else:
        sigma = torch.as_tensor(stds, dtype=torch.float64).clone() * scale
        if sigma.shape != (len(skeleton.dof_names),):
            raise ValueError(f"stds must have shape ({len(skeleton.dof_names)},), got {tuple(sigma.shape)}")
        source = "given"
    _log.info(sigma_summary(skeleton, sigma, fps=fps, source=source, name=name))
    return sigma


# ------------------------------------------------------------------------------------- learned dynamics


def at_rate(std, alpha, from_fps: float, to_fps: float):
    """Per-frame motion statistics learned at ``from_fps`` as per-frame statistics at ``to_fps`` (Hz).

    ``std (...)`` (rad / m per frame: step stds, constant-velocity prediction errors σ_φ) scale like a
    speed, ``x (from_fps / to_fps)`` (:func:`priors.table5.rescale` with ``exponent=1``; on the CMU walks
    the fitted step stds grow 1.9x from 120 to 60 fps and 3.4x to 30 fps); the velocity smoothing α of Rius
    eq. 3 (a float or a per-DOF tensor) keeps its time constant, ``α ** (from_fps / to_fps)``. The one
    rule for :class:`LearnedDynamics` and :class:`priors.action.ActionModel` alike.

    Returns:
        ``(std, alpha)`` at ``to_fps``.
    """
    from priors.table5 import rescale

    if not (math.isfinite(float(to_fps)) and float(to_fps) > 0):
        raise ValueError(f"fps must be > 0, got {to_fps}")
    return rescale(std, to_fps, from_fps=from_fps, exponent=1.0), alpha ** (from_fps / to_fps)


def alpha_summary(alpha) -> str:
    """Rius eq. 3's α for a log line: one number, or the range and median of per-DOF values."""
    a = torch.as_tensor(alpha, dtype=torch.float64).reshape(-1)
    if a.numel() == 1 or bool((a == a[0]).all()):
        return f"{float(a[0]):.3g}"
    return f"{float(a.min()):.3g}..{float(a.max()):.3g} per DOF (median {float(a.median()):.3g})"


#: ``metadata["format"]`` of a learned-dynamics file.
FORMAT = "torchpf-learned-dynamics"
#: Current file-format version; files with a higher version are refused.
FORMAT_VERSION = 1


class LearnedDynamicsFormatError(ValueError):
    """A learned-dynamics file that cannot be read; the message names the file."""


@dataclass
class LearnedDynamics:
    """Per-DOF motion statistics learned from mocap (``python -m training fit-dynamics``).

    Attributes:
        dof_names: (D,) the pose layout.
        fps: frame rate (Hz) the statistics are per frame at.
        step_std: (D,) robust std of the frame steps ``θ_t - θ_{t-1}`` (``1.4826 · median |step|``), the
            random walk's std (rad / m per frame).
        alpha: the constant-velocity smoothing α of Rius eq. 3 that minimises the squared prediction error:
            a float, or a ``(D,)`` tensor with one α per DOF (``fit-dynamics``' default, Rius §3.1 per DOF).
        cv_std: (D,) robust std of the constant-velocity prediction errors at ``alpha`` (Rius' σ_φ).
        revolute: (D,) bool, angles or distances.
        info: JSON-able provenance (source files, frames, robust estimator).

    File (``.npz``, no pickles): a JSON ``metadata`` (``format``, ``version``, ``dof_names``, ``fps``,
    ``alpha``, ``info``) and arrays ``step_std``, ``cv_std`` (float64) and ``revolute`` (bool).
    """

    dof_names: list[str]
    fps: float
    step_std: torch.Tensor
    alpha: float | torch.Tensor
    cv_std: torch.Tensor
    revolute: torch.Tensor
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        self.dof_names = [str(n) for n in self.dof_names]
        D = len(self.dof_names)
        self.step_std = torch.as_tensor(np.asarray(self.step_std), dtype=torch.float64).clone()
        self.cv_std = torch.as_tensor(np.asarray(self.cv_std), dtype=torch.float64).clone()
        self.revolute = torch.as_tensor(np.asarray(self.revolute), dtype=torch.bool).clone()
        for label, t in (("step_std", self.step_std), ("cv_std", self.cv_std), ("revolute", self.revolute)):
            if t.shape != (D,):
                raise ValueError(f"{label} has shape {tuple(t.shape)}, expected ({D},) for the DOF names")
        for label, t in (("step_std", self.step_std), ("cv_std", self.cv_std)):
            if not torch.isfinite(t).all() or (t < 0).any():
                raise ValueError(f"{label} must be finite and >= 0")
        self.fps = float(self.fps)
        alpha = torch.as_tensor(np.asarray(self.alpha, dtype=np.float64)).clone()
        if alpha.ndim not in (0, 1) or alpha.ndim == 1 and alpha.shape != (D,):
            raise ValueError(f"alpha must be a float or ({D},) per DOF, got shape {tuple(alpha.shape)}")
        self.alpha = float(alpha) if alpha.ndim == 0 else alpha
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be > 0, got {self.fps}")
        if not ((alpha >= 0.0) & (alpha <= 1.0)).all():
            raise ValueError(f"alpha must be in [0, 1], got {self.alpha}")

    def at_fps(self, fps: float) -> LearnedDynamics:
        """The statistics per frame at another rate (:func:`at_rate`)."""
        if math.isclose(fps, self.fps, rel_tol=1e-9):
            return self
        step_std, alpha = at_rate(self.step_std, self.alpha, self.fps, fps)
        cv_std, _ = at_rate(self.cv_std, self.alpha, self.fps, fps)
        return LearnedDynamics(
            self.dof_names, fps, step_std, alpha, cv_std, self.revolute, dict(self.info)
        )  # fmt: skip

    def select(self, dof_names, *, source: str = "learned dynamics") -> LearnedDynamics:
        """Reordered to ``dof_names`` (e.g. ``skel.dof_names``); other DOF names raise a ``ValueError``."""
        want = [str(n) for n in dof_names]
        if want == self.dof_names:
            return self
        missing = [n for n in want if n not in set(self.dof_names)]
        extra = [n for n in self.dof_names if n not in set(want)]
        if missing or extra or len(want) != len(self.dof_names):
            raise ValueError(
                f"{source} was learned on other DOFs: the skeleton has {missing[:5]} ({len(missing)}) "
                f"that the file lacks, the file has {extra[:5]} ({len(extra)}) that the skeleton lacks"
            )
        index = torch.tensor([self.dof_names.index(n) for n in want])
        return LearnedDynamics(
            want, self.fps, self.step_std[index],
            self.alpha if isinstance(self.alpha, float) else self.alpha[index],
            self.cv_std[index], self.revolute[index],
            dict(self.info),
        )  # fmt: skip

    def save(self, path: str | os.PathLike) -> None:
        """Write the ``.npz`` file atomically (:func:`torchpf.io.write_atomic`)."""
        meta = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "dof_names": self.dof_names,
            "fps": self.fps,
            "alpha": self.alpha if isinstance(self.alpha, float) else self.alpha.tolist(),
            "info": self.info,
        }
        buffer = io.BytesIO()
        np.savez(
            buffer,
            metadata=np.array(json.dumps(meta)),
            step_std=self.step_std.numpy(),
            cv_std=self.cv_std.numpy(),
            revolute=self.revolute.numpy(),
        )
        write_atomic(path, buffer.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike, dof_names=None) -> LearnedDynamics:
        """Read a file written by :meth:`save`, reordered to ``dof_names`` when given.

        Raises:
            FileNotFoundError: no such file (the message names it).
            LearnedDynamicsFormatError: not a learned-dynamics file, a newer version, missing or malformed
                entries; the message names the file.
            ValueError: ``dof_names`` differs from the file's (names the file and the differences).
        """
        path = os.fspath(path)

        def bad(reason: str) -> LearnedDynamicsFormatError:
            return LearnedDynamicsFormatError(f"{path}: {reason}")

        data, meta, _ = read_versioned_npz(
            path, FORMAT, FORMAT_VERSION, "learned-dynamics", LearnedDynamicsFormatError
        )
        absent = [k for k in ("step_std", "cv_std", "revolute") if k not in data]
        absent += [k for k in ("dof_names", "fps", "alpha") if k not in meta]
        if absent:
            raise bad(f"missing entries {absent}")
        try:
            out = cls(
                meta["dof_names"], meta["fps"], data["step_std"], meta["alpha"], data["cv_std"],
                data["revolute"], dict(meta.get("info") or {}),
            )  # fmt: skip
        except (ValueError, TypeError) as e:
            raise bad(" ".join(str(e).split())) from None
        return out if dof_names is None else out.select(dof_names, source=path)
