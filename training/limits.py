"""Joint limits learned from mocap: the range of motion a skeleton's DOFs take in performances.

A skeleton converted from BVH (``python -m training convert``) has no joint limits: BVH has none, so every
rotation is free over a full turn, a knee may twist and bend sideways and a hip may cross a leg over the
other. On masks with real defects the tracker then finds such poses as often as the right one: the
silhouettes of crossed legs and of a walker's legs differ by a few pixels (BENCHMARKS.md, "Joint limits
learned from mocap"). :func:`fit_limits` learns, per DOF, the interval the performances cover, widened by a
margin, and :meth:`torchpf.skeleton.Skeleton.with_limits` writes it into the skeleton, so the filters'
priors, the refinement and the smoothing keep every pose inside it::

    lower, upper, report = fit_limits([load_csv(p, dof_names=skel.dof_names) for p in paths], skel)
    skel.with_limits(lower, upper).save_urdf("limited.urdf")    # then track --skeleton limited.urdf

or ``python -m training fit-limits DATA/*.csv --skeleton S.urdf --out limited.urdf``.

What is learned, per revolute DOF that is not the root's (the root's translation and heading are where the
person is, not a posture): the shortest arc of the circle that holds every sample (angles wrapped to
``(-pi, pi]``), widened by ``margin`` on each side, intersected with the skeleton's own limits. A DOF whose
arc crosses ``+-pi`` (a URDF interval cannot say so) or covers nearly the full turn keeps the skeleton's
limits, and the report says which. Prismatic DOFs keep theirs (bone lengths vary between performers).

The limits are what the performances did, not what a body can do: learn them from the actions you will
track (walks and runs limit the arms to a walker's swing). Learned from the other performers' walks and
runs of the CMU clips (leave one performer out), the default tracker's error on noisy foreign renders fell
from 84 to 62 mm over three draws of the mask defects, and on clean masks from 31 to 28 mm (BENCHMARKS.md,
"Joint limits learned from mocap"). Anatomical ranges (what a body can do: the shipped ``human.urdf``'s) did
not help there (78 against 74.5 mm on one draw), nor did ranges widened by 0.5 rad (75): it is the
action's range that holds a lost leg.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from training.mocap import Motion

__all__ = ["LimitsReport", "circular_range", "fit_limits"]

#: Default widening of each learned range (rad, ~8.6 degrees) on each side.
MARGIN = 0.15


@dataclass
class LimitsReport:
    """What :func:`fit_limits` did: ``learned`` DOF names (limited by the data), ``wrapped`` (their arc
    crosses +-pi: kept), ``full_turn`` (the data cover nearly a full turn: kept), ``conflicts`` (the learned
    range lies outside the skeleton's limits: kept), ``unseen`` (no performance has the DOF), and
    ``frames``, the number of frames read."""

    learned: list[str] = field(default_factory=list)
    wrapped: list[str] = field(default_factory=list)
    full_turn: list[str] = field(default_factory=list)
    conflicts: list[str] = field(default_factory=list)
    unseen: list[str] = field(default_factory=list)
    frames: int = 0

    def summary(self) -> str:
        """One paragraph for a terminal: counts, then the names of the DOFs that kept their limits."""
        lines = [f"{len(self.learned)} DOFs limited from {self.frames} frames"]
        for label, names in (
            ("arc crosses +-pi, kept", self.wrapped),
            ("nearly a full turn, kept", self.full_turn),
            ("outside the skeleton's limits, kept", self.conflicts),
            ("in no performance, kept", self.unseen),
        ):
            if names:
                shown = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
                lines.append(f"{label}: {shown}")
        return "\n".join(lines)


def circular_range(angles: Tensor) -> tuple[Tensor, Tensor]:
    """The shortest arc holding every sample of each column of ``angles (T, D)`` (rad): ``(start, width)``
    (D,), ``start`` in ``(-pi, pi]`` and the arc ``[start, start + width]`` (so ``start + width`` may pass
    ``pi`` where the arc crosses the cut). The complement of the largest gap between circularly sorted
    samples; a column of one value has width 0."""
    if angles.ndim != 2 or angles.shape[0] < 1:
        raise ValueError(f"angles must be (T >= 1, D), got {tuple(angles.shape)}")
    a = torch.atan2(torch.sin(angles), torch.cos(angles)).sort(0).values  # (T, D) in (-pi, pi]
    gaps = torch.cat([a[1:] - a[:-1], (a[:1] + 2 * math.pi - a[-1:])])  # gap after each sample, circularly
    k = gaps.argmax(0)  # the arc starts after the largest gap
    T = a.shape[0]
    start = a.gather(0, ((k + 1) % T).unsqueeze(0)).squeeze(0)
    width = 2 * math.pi - gaps.gather(0, k.unsqueeze(0)).squeeze(0)
    return start, width.clamp_min(0.0)


def fit_limits(
    motions: Sequence[Motion], skeleton, *, margin: float = MARGIN, full_turn: float = 1.9 * math.pi
) -> tuple[Tensor, Tensor, LimitsReport]:
    """Joint limits ``(lower, upper)`` (D,) float64 in ``skeleton.dof_names`` order from the range of
    motion of ``motions`` (module docstring), and a :class:`LimitsReport`.

    Args:
        motions: performances whose columns are (a subset of) the skeleton's DOFs, matched by name (e.g.
            :func:`training.mocap.load_csv` with ``dof_names=skeleton.dof_names``).
        skeleton: the :class:`~torchpf.skeleton.Skeleton` the limits are for; its own limits bound them.
        margin: rad added on each side of every learned range (>= 0).
        full_turn: a DOF whose widened arc reaches this width (rad) keeps the skeleton's limits.

    Returns:
        ``lower``, ``upper``: the new limits (the skeleton's own where nothing was learned; pass them to
        :meth:`~torchpf.skeleton.Skeleton.with_limits`), and the report.
    """
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin must be a finite number of radians >= 0, got {margin}")
    if not motions:
        raise ValueError("fit_limits needs at least one performance")
    names = list(skeleton.dof_names)
    index = {n: d for d, n in enumerate(names)}
    columns: list[list[Tensor]] = [[] for _ in names]
    report = LimitsReport()
    for m in motions:
        unknown = [n for n in m.dof_names if n not in index]
        if unknown:
            label = m.name or "a performance"
            raise ValueError(f"{label}: columns {unknown[:5]} are not DOFs of {skeleton.source}")
        angles = m.angles.detach().to("cpu", torch.float64)
        finite = torch.isfinite(angles).all(1)  # a frame with a gap says nothing about the range
        for c, n in enumerate(m.dof_names):
            columns[index[n]].append(angles[finite, c])
        report.frames += int(finite.sum())
    lower = skeleton.lower.detach().to("cpu", torch.float64).clone()
    upper = skeleton.upper.detach().to("cpu", torch.float64).clone()
    posture = skeleton.posture_dofs.cpu()
    for d, name in enumerate(names):
        if not bool(posture[d]):
            continue  # prismatic DOFs and the root's: where the person is, not a posture
        data = torch.cat(columns[d]) if columns[d] else torch.zeros(0, dtype=torch.float64)
        if len(data) == 0:
            report.unseen.append(name)
            continue
        start, width = (v.item() for v in circular_range(data.unsqueeze(1)))
        if width + 2 * margin >= full_turn:
            report.full_turn.append(name)
            continue
        if start + width > math.pi:
            report.wrapped.append(name)
            continue
        lo, hi = max(start - margin, float(lower[d])), min(start + width + margin, float(upper[d]))
        if lo > hi:
            report.conflicts.append(name)
            continue
        lower[d], upper[d] = lo, hi
        report.learned.append(name)
    return lower, upper, report
