"""Writing human-skeleton URDFs from a list of body joints.

pytorch-kinematics (and URDF itself) has no ball or floating joint, so a body joint with several degrees of
freedom becomes a run of single-DOF URDF joints linked by massless intermediate links::

    parent --[first DOF, origin = bone offset]--> J__dof1 --[dof2, identity origin]--> ... --> J

Every DOF is one URDF joint whose name is the DOF name (so ``Skeleton.dof_names`` are the URDF joint names),
and the last link of the run carries the body joint's name. A body joint with no DOF is a ``fixed`` joint
(an End Site, a head top). A root body joint with DOFs hangs below a base link named ``world``.

Capsule geometry is written as ``<collision name="CHILD">`` cylinders on the parent body link, one per bone,
posed along the bone; ``torchpf.skeleton`` reads the radii back. A non-leaf body link whose bones all have
zero length gets a small ``<collision>`` sphere, so that it is never mistaken for an intermediate link (see
``Skeleton.from_urdf`` for the rule).

Example::

    joints = [BodyJoint("pelvis", None, (0, 0, 0), floating_root_dofs("pelvis")),
              BodyJoint("knee", "pelvis", (0, 0, -0.45), [Dof("knee_rx", "revolute", (1, 0, 0), 0, 2.6)])]
    xml = build_urdf("toy", joints, radii={"knee": 0.07})
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from xml.sax.saxutils import quoteattr

#: Default limit (m) of the prismatic root translations; URDF needs finite limits on prismatic joints.
ROOT_TRANSLATION_LIMIT = 100.0


@dataclass(frozen=True)
class Dof:
    """One degree of freedom: a URDF revolute (rad) or prismatic (m) joint about/along ``axis``."""

    name: str
    type: str
    axis: tuple[float, float, float]
    lower: float = -math.pi
    upper: float = math.pi

    def __post_init__(self):
        if self.type not in ("revolute", "prismatic"):
            raise ValueError(f"Dof {self.name!r}: type must be 'revolute' or 'prismatic', got {self.type!r}")
        if not self.lower <= self.upper:
            raise ValueError(f"Dof {self.name!r}: lower limit {self.lower} > upper limit {self.upper}")


@dataclass(frozen=True)
class BodyJoint:
    """A body joint: its offset (m) from the parent body joint in the parent's frame, and its DOFs.

    The joint's frame is ``T_parent @ Trans(offset) @ M(dofs[0]) @ M(dofs[1]) @ ...`` where ``M`` is a
    rotation about (revolute) or a translation along (prismatic) the DOF axis, in the order listed.
    """

    name: str
    parent: str | None
    offset: tuple[float, float, float]
    dofs: Sequence[Dof] = field(default_factory=tuple)


def floating_root_dofs(
    name: str, rotation_axes: str = "zyx", translation_limit: float = ROOT_TRANSLATION_LIMIT
) -> list[Dof]:
    """Six DOFs of a floating root: prismatic x, y, z then revolute about ``rotation_axes`` (in order).

    DOF names are ``{name}_tx``, ``{name}_ty``, ``{name}_tz``, ``{name}_r{axis}``.
    """
    unit = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
    dofs = [Dof(f"{name}_t{a}", "prismatic", unit[a], -translation_limit, translation_limit) for a in "xyz"]
    dofs += [Dof(f"{name}_r{a}", "revolute", unit[a], -math.pi, math.pi) for a in rotation_axes]
    return dofs


def _fmt(values: Sequence[float]) -> str:
    return " ".join(f"{float(v):.9g}" for v in values)


def _rpy_aligning_z(direction: Sequence[float]) -> tuple[float, float, float]:
    """Roll-pitch-yaw (URDF fixed-axis xyz) of a rotation taking +z onto ``direction``."""
    x, y, z = direction
    n = math.sqrt(x * x + y * y + z * z)
    x, y, z = x / n, y / n, z / n
    # R = Rz(yaw) Ry(pitch) maps z to (cos(yaw) sin(pitch), sin(yaw) sin(pitch), cos(pitch)).
    pitch = math.acos(max(-1.0, min(1.0, z)))
    yaw = math.atan2(y, x) if math.hypot(x, y) > 1e-12 else 0.0
    return (0.0, pitch, yaw)


def build_urdf(
    robot_name: str,
    joints: Sequence[BodyJoint],
    radii: Mapping[str, float] | None = None,
    default_radius: float = 0.03,
) -> str:
    """URDF XML text for a tree of body joints.

    Args:
        robot_name: the ``<robot name>``.
        joints: body joints, parents before children; exactly one has ``parent=None``.
        radii: capsule radius (m) of the bone ending at each named child body joint; bones not listed get
            ``default_radius``. Zero-length bones get no capsule.
        default_radius: radius (m) of unlisted bones.

    Returns:
        The URDF document as a string.
    """
    radii = dict(radii or {})
    names = [j.name for j in joints]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"duplicate body joint names: {dup}")
    roots = [j for j in joints if j.parent is None]
    if len(roots) != 1:
        raise ValueError(f"expected exactly one root body joint, got {[j.name for j in roots]}")
    seen: set[str] = set()
    for j in joints:
        if j.parent is not None and j.parent not in seen:
            raise ValueError(f"body joint {j.name!r}: parent {j.parent!r} is not listed before it")
        seen.add(j.name)
    dof_names = [d.name for j in joints for d in j.dofs]
    link_like = set(names) | {"world"}
    clash = sorted(set(dof_names) & link_like)
    if len(set(dof_names)) != len(dof_names) or clash:
        raise ValueError(f"DOF names must be unique and differ from link names (clash: {clash})")

    children: dict[str, list[BodyJoint]] = {n: [] for n in names}
    for j in joints:
        if j.parent is not None:
            children[j.parent].append(j)

    out = ['<?xml version="1.0"?>', f"<robot name={quoteattr(robot_name)}>"]
    root = roots[0]
    if root.dofs:
        out.append('  <link name="world"/>')
    for j in joints:
        out.extend(_body_link(j, children[j.name], radii, default_radius))
        parent_link = j.parent if j.parent is not None else "world"
        if not j.dofs:
            if j.parent is None:
                continue  # a fixed-base root is the base link itself
            out.append(f'  <joint name={quoteattr(j.name + "_fixed")} type="fixed">')
            out.append(f"    <parent link={quoteattr(parent_link)}/><child link={quoteattr(j.name)}/>")
            out.append(f'    <origin xyz="{_fmt(j.offset)}" rpy="0 0 0"/>')
            out.append("  </joint>")
            continue
        for k, dof in enumerate(j.dofs):
            last = k == len(j.dofs) - 1
            child = j.name if last else f"{j.name}__{dof.name}"
            if not last:
                out.append(f"  <link name={quoteattr(child)}/>")
            origin = j.offset if k == 0 else (0.0, 0.0, 0.0)
            out.append(f'  <joint name={quoteattr(dof.name)} type="{dof.type}">')
            out.append(f"    <parent link={quoteattr(parent_link)}/><child link={quoteattr(child)}/>")
            out.append(f'    <origin xyz="{_fmt(origin)}" rpy="0 0 0"/>')
            out.append(f'    <axis xyz="{_fmt(dof.axis)}"/>')
            out.append(
                f'    <limit lower="{dof.lower:.9g}" upper="{dof.upper:.9g}" effort="100" velocity="100"/>'
            )
            out.append("  </joint>")
            parent_link = child
    out.append("</robot>")
    return "\n".join(out) + "\n"


def _body_link(j: BodyJoint, kids: list[BodyJoint], radii: Mapping[str, float], default: float) -> list[str]:
    geoms = []
    for c in kids:
        length = math.sqrt(sum(v * v for v in c.offset))
        if length < 1e-9:
            continue
        r = float(radii.get(c.name, default))
        mid = [0.5 * v for v in c.offset]
        geoms.append(
            f"    <collision name={quoteattr(c.name)}>"
            f'<origin xyz="{_fmt(mid)}" rpy="{_fmt(_rpy_aligning_z(c.offset))}"/>'
            f'<geometry><cylinder radius="{r:.9g}" length="{length:.9g}"/></geometry></collision>'
        )
    if kids and not geoms:
        r = float(radii.get(j.name, default))
        geoms.append(
            f"    <collision name={quoteattr(j.name + '_joint')}>"
            f'<geometry><sphere radius="{r:.9g}"/></geometry></collision>'
        )
    if not geoms:
        return [f"  <link name={quoteattr(j.name)}/>"]
    return [f"  <link name={quoteattr(j.name)}>", *geoms, "  </link>"]
