"""URDF in and out: reading a URDF into flattened frames, and writing human-skeleton URDFs.

**Reading** (:func:`read_urdf_text`, :func:`build_chain`, :func:`flatten_chain`, :func:`link_geometry`): the
text of a file or an XML string, the pytorch-kinematics chain built from it (parser complaints turned into
warnings), that chain flattened depth-first into :class:`Frame` records (one per link, with the joint above
it), and the capsule radii that ``<collision>``/``<visual>`` elements give. :class:`torchpf.skeleton.Skeleton`
compiles these into its :class:`~torchpf.kinematics.tree.KinematicTree` and FK kernel.

**Writing** (:func:`build_urdf`; :func:`rebody_urdf` gives an existing URDF another body: scaled lengths,
new capsule radii): pytorch-kinematics (and URDF itself) has no ball or floating joint, so a
body joint with several degrees of freedom becomes a run of single-DOF URDF joints linked by massless
intermediate links::

    parent --[first DOF, origin = bone offset]--> J__dof1 --[dof2, identity origin]--> ... --> J

Every DOF is one URDF joint whose name is the DOF name (so ``Skeleton.dof_names`` are the URDF joint names),
and the last link of the run carries the body joint's name. A body joint with no DOF is a ``fixed`` joint
(an End Site, a head top). A root body joint with DOFs hangs below a base link named ``world``.

Capsule geometry is written as ``<collision name="CHILD">`` cylinders on the parent body link, one per bone,
posed along the bone; :func:`link_geometry` reads the radii back. A non-leaf body link whose bones all have
zero length gets a small ``<collision>`` sphere, so that it is never mistaken for an intermediate link (see
``Skeleton.from_urdf`` for the rule).

Example::

    joints = [BodyJoint("pelvis", None, (0, 0, 0), floating_root_dofs("pelvis")),
              BodyJoint("knee", "pelvis", (0, 0, -0.45), [Dof("knee_rx", "revolute", (1, 0, 0), 0, 2.6)])]
    xml = build_urdf("toy", joints, radii={"knee": 0.07})
    chain = build_chain(xml, "<urdf string>")
    frames = flatten_chain(chain)                # depth-first, parents first
"""

from __future__ import annotations

import math
import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from xml.sax.saxutils import quoteattr

import torch

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


def _scaled_attr(el: ET.Element, key: str, factor: float) -> None:
    value = el.get(key)
    if value is not None and factor != 1.0:
        el.set(key, _fmt([float(v) * factor for v in value.split()]))


def _document(root: ET.Element) -> str:
    """A URDF tree as indented text with its XML declaration."""
    ET.indent(root, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def rebody_urdf(
    xml: str,
    *,
    scale: float = 1.0,
    joint_scales: Mapping[str, float] | None = None,
    capsules: Mapping[str, Sequence[tuple[str, Sequence[float], float]]] | None = None,
    source: str = "<urdf string>",
) -> str:
    """The URDF text ``xml`` with another body: lengths scaled and bone capsules rewritten.

    Everything else (joints, axes, limits, names, other links' geometry) is kept, so the skeleton read back
    has the same DOFs and body joints.

    Args:
        xml: URDF text.
        scale: global factor on every ``<origin xyz>`` (joints and link geometry) and on the sizes of the
            geometry that is not rewritten; prismatic limits are not scaled (a pose's root translation is a
            position in the world, not a body length).
        joint_scales: URDF joint name -> extra factor on that joint's ``<origin xyz>`` (a bone-length
            scale: the joint whose origin is the bone's offset from its parent body joint).
        capsules: parent link name -> ``[(child body joint, offset (3,) m of the child in the link frame,
            radius m)]``: each becomes a ``<collision name="child">`` cylinder posed along the bone (the
            form :func:`link_geometry` reads radii from, :func:`build_urdf`'s form); collisions of that
            link with the same name, and its unnamed cylinders/capsules (which described the bones), are
            removed. The offsets are taken as given (already scaled).

    Returns:
        The new URDF document as a string.
    """
    root = parse_urdf_xml(xml, source)
    joint_scales = dict(joint_scales or {})
    capsules = dict(capsules or {})
    for joint in root.iter("joint"):
        origin = joint.find("origin")
        if origin is not None:
            _scaled_attr(origin, "xyz", scale * float(joint_scales.get(joint.get("name"), 1.0)))
    for link in root.iter("link"):
        rewritten = capsules.get(link.get("name"), ())
        names = {child for child, _, _ in rewritten}
        for el in list(link):
            geom = el.find("geometry")
            shape = None if geom is None else next(iter(geom), None)
            if el.tag == "collision" and (
                el.get("name") in names
                or (rewritten and el.get("name") is None and shape is not None and shape.tag != "sphere")
            ):
                link.remove(el)
                continue
            origin = el.find("origin")
            if origin is not None:
                _scaled_attr(origin, "xyz", scale)
            if shape is not None:
                for key in ("radius", "length", "size"):
                    _scaled_attr(shape, key, scale)
        for child, offset, radius in rewritten:
            offset = [float(v) for v in offset]
            length = math.sqrt(sum(v * v for v in offset))
            rpy = _rpy_aligning_z(offset) if length > 1e-12 else (0.0, 0.0, 0.0)
            el = ET.SubElement(link, "collision", name=child)
            ET.SubElement(el, "origin", xyz=_fmt([0.5 * v for v in offset]), rpy=_fmt(rpy))
            geom = ET.SubElement(el, "geometry")
            ET.SubElement(geom, "cylinder", radius=f"{float(radius):.9g}", length=f"{length:.9g}")
    return _document(root)


def relimit_urdf(
    xml: str, limits: Mapping[str, tuple[float, float]], *, source: str = "<urdf string>"
) -> str:
    """The URDF text ``xml`` with other joint limits: ``limits`` maps a URDF joint name (a DOF of
    :attr:`~torchpf.skeleton.Skeleton.dof_names`) to ``(lower, upper)`` (rad or m, ``lower <= upper``,
    finite). A ``continuous`` joint given limits becomes ``revolute`` (URDF has no limited continuous
    joint); a joint without ``<limit>`` gets one (``effort`` and ``velocity`` 100, which URDF requires and
    torchpf does not read). Everything else is kept."""
    root = parse_urdf_xml(xml, source)
    joints = {j.get("name"): j for j in root.iter("joint")}
    unknown = sorted(set(limits) - set(joints))
    if unknown:
        raise ValueError(f"{source}: no joint named {unknown[:5]} to set limits on")
    for name, (lo, hi) in limits.items():
        lo, hi = float(lo), float(hi)
        joint = joints[name]
        if joint.get("type") not in ("revolute", "continuous", "prismatic"):
            raise ValueError(f"{source}: joint {name!r} is {joint.get('type')!r}, it has no limits to set")
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(
                f"{source}: limits of {name!r} must be finite with lower <= upper, got {lo}, {hi}"
            )
        if joint.get("type") == "continuous":
            joint.set("type", "revolute")
        el = joint.find("limit")
        if el is None:
            el = ET.SubElement(joint, "limit", effort="100", velocity="100")
        el.set("lower", f"{lo:.9g}")
        el.set("upper", f"{hi:.9g}")
    return _document(root)


# ------------------------------------------------------------------------------------------------ reading


@dataclass
class Frame:
    """One pytorch-kinematics frame (a link and the URDF joint above it), flattened.

    Attributes:
        name: the link name.
        parent: index of the parent frame in the flattened list, -1 for the root.
        static: (4, 4) float64 link offset @ joint offset (the joint's origin in the parent link frame).
        joint_type: ``"fixed"``, ``"revolute"`` or ``"prismatic"`` (a URDF continuous joint is revolute).
        axis: (3,) float64 joint axis in the joint frame.
        dof: index into ``chain.get_joint_parameter_names()``, -1 for a fixed joint.
        children: indices of the child frames.
    """

    name: str
    parent: int
    static: torch.Tensor
    joint_type: str
    axis: torch.Tensor
    dof: int
    children: list[int]


def is_identity(static: torch.Tensor) -> bool:
    """Whether a (4, 4) frame origin (:attr:`Frame.static`) is the identity, to 1e-12."""
    return bool(torch.allclose(static, torch.eye(4, dtype=static.dtype), atol=1e-12, rtol=0))


def read_urdf_text(path_or_xml: str | os.PathLike) -> tuple[str, str]:
    """(xml text, where it came from) for a URDF path or an XML string (one that starts with ``<``); a
    ``floating`` joint comes back as six single-DOF joints (:func:`expand_floating_joints`)."""
    if isinstance(path_or_xml, str) and path_or_xml.lstrip().startswith("<"):
        return expand_floating_joints(path_or_xml, "<urdf string>"), "<urdf string>"
    path = os.fspath(path_or_xml)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"URDF file not found: {path}")
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a UTF-8 URDF file ({e.reason} at byte {e.start})") from None
    return expand_floating_joints(text, path), path


def expand_floating_joints(xml: str, source: str) -> str:
    """``xml`` with each ``floating`` joint written as 3 prismatic + 3 revolute joints (x, y, z, then
    rotations about z, y, x: :func:`floating_root_dofs`, DOFs ``{joint}_tx`` ... ``{joint}_rx``) linked by
    massless links ``{child}__{dof}``, the form :func:`build_urdf` writes: pytorch-kinematics has single-DOF
    joints only. The first joint keeps the floating joint's ``<origin>``. ``xml`` unchanged without one; a
    ``planar`` joint is refused with the same advice.
    """
    if "floating" not in xml and "planar" not in xml:
        return xml
    root = parse_urdf_xml(xml, source)
    taken = {el.get("name") for el in root if el.tag in ("link", "joint")}
    changed = False
    for index, joint in reversed(list(enumerate(root))):
        jtype = joint.get("type") if joint.tag == "joint" else None
        if jtype == "planar":
            raise ValueError(
                f"{source}: joint {joint.get('name')!r}: type 'planar' is not supported; write it as "
                "prismatic and revolute joints linked by links without geometry"
            )
        if jtype != "floating":
            continue
        name, parent, child = joint.get("name"), joint.find("parent"), joint.find("child")
        if name is None or parent is None or child is None:
            continue  # validate_urdf names what is missing
        dofs = floating_root_dofs(name)
        links = [f"{child.get('link')}__{d.name}" for d in dofs[:-1]]
        clash = sorted(taken & ({d.name for d in dofs} | set(links)))
        if clash:
            raise ValueError(
                f"{source}: joint {name!r}: cannot expand the floating joint into 3 prismatic + 3 revolute "
                f"joints, the names {clash} are taken; write the six joints yourself"
            )
        root.remove(joint)
        above = parent.get("link")
        for k, dof in enumerate(dofs):
            below = child.get("link") if k == len(dofs) - 1 else links[k]
            el = ET.Element("joint", name=dof.name, type=dof.type)
            ET.SubElement(el, "parent", link=above)
            ET.SubElement(el, "child", link=below)
            origin = joint.find("origin") if k == 0 else None
            el.append(origin if origin is not None else ET.Element("origin", xyz="0 0 0", rpy="0 0 0"))
            ET.SubElement(el, "axis", xyz=_fmt(dof.axis))
            ET.SubElement(
                el, "limit", lower=f"{dof.lower:.9g}", upper=f"{dof.upper:.9g}", effort="100", velocity="100"
            )
            root.insert(index + 2 * k, el)
            if k < len(dofs) - 1:
                root.insert(index + 2 * k + 1, ET.Element("link", name=below))
            above = below
        changed = True
    return ET.tostring(root, encoding="unicode") if changed else xml


def parse_urdf_xml(xml: str, source: str) -> ET.Element:
    """The root element of the URDF text ``xml``; a ValueError naming ``source`` if it is not XML."""
    try:
        return ET.fromstring(xml)
    except ET.ParseError as e:
        raise ValueError(f"{source}: invalid URDF XML ({e})") from None


#: Largest ``|coordinate|`` (m) of a URDF origin, limit or geometry size: beyond it the float32 parse of
#: pytorch-kinematics and the FK products overflow or lose every digit of a human-sized body.
MAX_COORDINATE = 1e6

#: Deepest kinematic tree read: pytorch-kinematics builds (and this module flattens) the chain recursively.
MAX_TREE_DEPTH = 256

_MOVABLE = ("revolute", "continuous", "prismatic")


def _numbers(
    el: ET.Element, attr: str, n: int, where: str, default: str | None = None, bound: float = MAX_COORDINATE
) -> list[float]:
    """The ``n`` finite numbers (``|v| <= bound``) of attribute ``attr`` of ``el``; a ValueError naming
    ``where`` otherwise."""
    from torchpf.io import plain_float

    text = el.get(attr, default)
    if text is None:
        raise ValueError(f"{where}: <{el.tag}> has no {attr!r}")
    try:
        values = [plain_float(v) for v in text.split()]
    except ValueError:
        raise ValueError(f"{where}: <{el.tag} {attr}={text!r}>: not {n} number(s)") from None
    if len(values) != n:
        raise ValueError(f"{where}: <{el.tag} {attr}={text!r}>: expected {n} number(s), got {len(values)}")
    if not all(math.isfinite(v) and abs(v) <= bound for v in values):
        raise ValueError(
            f"{where}: <{el.tag} {attr}={text!r}>: numbers must be finite and within +-{bound:g}"
        )
    return values


def _check_origin(el: ET.Element, where: str) -> None:
    origin = el.find("origin")
    if origin is not None:
        _numbers(origin, "xyz", 3, where, "0 0 0")
        _numbers(origin, "rpy", 3, where, "0 0 0")


def _check_geometry(link: ET.Element, where: str) -> None:
    for el in [*link.findall("collision"), *link.findall("visual")]:
        label = f"{where} <{el.tag}{' name=' + repr(el.get('name')) if el.get('name') else ''}>"
        _check_origin(el, label)
        geom = el.find("geometry")
        for shape in [] if geom is None else list(geom):
            sizes = {"sphere": ("radius",), "cylinder": ("radius", "length"), "capsule": ("radius", "length")}
            keys = sizes.get(shape.tag, ("size",) if shape.tag == "box" else ())
            for key in keys:
                if shape.get(key) is None:
                    continue
                values = _numbers(shape, key, 3 if key == "size" else 1, label)
                if not all(v > 0 if key != "length" else v >= 0 for v in values):
                    raise ValueError(f"{label}: <{shape.tag} {key}={shape.get(key)!r}> must be > 0")


def _by_name(root: ET.Element, tag: str, source: str) -> dict[str, ET.Element]:
    """The ``<tag>`` children of ``root`` by name, in file order; every one named, no name twice."""
    out: dict[str, ET.Element] = {}
    for k, el in enumerate(root.findall(tag)):
        name = el.get("name")
        if not name:
            raise ValueError(f"{source}: <{tag}> number {k + 1} has no name")
        if name in out:
            raise ValueError(f"{source}: duplicate {tag} name {name!r}")
        out[name] = el
    return out


def validate_urdf(root: ET.Element, source: str) -> None:
    """Refuse a URDF that would load as a different or broken skeleton; the ValueError names the element.

    Checked: joint and link names present and unique; every joint's ``<parent link>`` and ``<child link>``
    name a ``<link>`` of the file; no link is the child of two joints; one root (one link that is no joint's
    child) from which every link is reached (a typo in a parent link would otherwise drop the subtree
    silently), at most :data:`MAX_TREE_DEPTH` deep; origins, axes and geometry sizes finite numbers within
    +-:data:`MAX_COORDINATE`; movable joints' axes non-zero; limits finite with ``lower <= upper``; radii
    and box sizes > 0, lengths >= 0.
    """
    if root.tag != "robot":
        raise ValueError(f"{source}: the root element is <{root.tag}>, expected <robot>")
    links = _by_name(root, "link", source)
    for name, link in links.items():
        _check_geometry(link, f"{source}: link {name!r}")
    if not links:
        raise ValueError(f"{source}: no <link>")
    parent_of: dict[str, str] = {}
    children: dict[str, list[str]] = {n: [] for n in links}
    for name, joint in _by_name(root, "joint", source).items():
        where = f"{source}: joint {name!r}"
        ends = {}
        for end in ("parent", "child"):
            el = joint.find(end)
            ref = None if el is None else el.get("link")
            if ref is None:
                raise ValueError(f"{where}: no <{end} link=...>")
            if ref not in links:
                raise ValueError(f"{where}: {end} link {ref!r} is not a <link> of the file")
            ends[end] = ref
        if ends["child"] in parent_of:
            raise ValueError(
                f"{where}: link {ends['child']!r} is already the child of joint {parent_of[ends['child']]!r}"
            )
        parent_of[ends["child"]] = name
        children[ends["parent"]].append(ends["child"])
        _check_origin(joint, where)
        jtype = joint.get("type")
        if jtype in _MOVABLE:
            axis_el = joint.find("axis")
            axis = [1.0, 0.0, 0.0] if axis_el is None else _numbers(axis_el, "xyz", 3, where, "1 0 0")
            if math.sqrt(sum(v * v for v in axis)) < 1e-9:
                raise ValueError(f"{where}: the axis is zero")
            limit = joint.find("limit")
            if limit is not None and jtype != "continuous":
                # robot files write "no limit" as +-1e16 and the like: any finite float32 passes
                lower = _numbers(limit, "lower", 1, where, "0", bound=3e38)[0]
                upper = _numbers(limit, "upper", 1, where, "0", bound=3e38)[0]
                if lower > upper:
                    raise ValueError(f"{where}: lower limit {lower:g} > upper limit {upper:g}")
    roots = [n for n in links if n not in parent_of]
    if len(roots) != 1:
        what = "no link is" if not roots else f"links {roots} are"
        raise ValueError(f"{source}: {what} without a parent joint; a URDF must be one tree from one root")
    depth = {roots[0]: 0}
    todo = [roots[0]]
    while todo:
        link = todo.pop()
        for child in children[link]:
            depth[child] = depth[link] + 1
            if depth[child] > MAX_TREE_DEPTH:
                raise ValueError(
                    f"{source}: link {child!r} is more than {MAX_TREE_DEPTH} joints below the root"
                )
            todo.append(child)
    lost = [n for n in links if n not in depth]
    if lost:
        raise ValueError(f"{source}: links {lost[:5]} are not reached from the root {roots[0]!r} (a cycle)")


def build_chain(xml: str, source: str):
    """The pytorch-kinematics chain of the URDF text ``xml``; errors and warnings name ``source``.

    The text is checked first (:func:`validate_urdf`). The URDF parser prints its complaints to stderr;
    they become warnings here, except the one about the optional ``name`` of ``<collision>``/``<visual>``
    (URDF spec; used by :func:`link_geometry`).
    """
    import pytorch_kinematics as pk
    from pytorch_kinematics.urdf_parser_py.xml_reflection import core as xml_core

    validate_urdf(parse_urdf_xml(xml, source), source)

    complaints: list[str] = []
    saved = xml_core.on_error
    xml_core.on_error = complaints.append
    try:
        chain = pk.build_chain_from_urdf(xml.encode("utf-8"))
    except Exception as e:  # the URDF parser raises many types on malformed input
        raise ValueError(f"{source}: cannot build a kinematic chain ({type(e).__name__}: {e})") from e
    finally:
        xml_core.on_error = saved
    for msg in complaints:
        if not ('Unknown attribute "name"' in msg and ("/collision" in msg or "/visual" in msg)):
            warnings.warn(f"{source}: {msg}", stacklevel=3)
    return chain


def link_geometry(root: ET.Element) -> dict[str, list[tuple[str | None, float | None]]]:
    """link name -> [(element name, radius (m) or None)] for every <collision>/<visual> of the link."""
    geoms: dict[str, list[tuple[str | None, float | None]]] = {}
    for link in root.iter("link"):
        entries = []
        for el in [*link.findall("collision"), *link.findall("visual")]:
            radius = None
            geom = el.find("geometry")
            if geom is not None:
                for kind in ("capsule", "cylinder", "sphere"):
                    g = geom.find(kind)
                    if g is not None and g.get("radius") is not None:
                        radius = float(g.get("radius"))
                        break
            entries.append((el.get("name"), radius))
        geoms[link.get("name")] = entries
    return geoms


def flatten_chain(chain) -> list[Frame]:
    """The frames of a pytorch-kinematics chain, depth-first from the root (parents before children)."""
    dof_index = {n: i for i, n in enumerate(chain.get_joint_parameter_names())}
    frames: list[Frame] = []

    def matrix(t):
        if t is None:
            return torch.eye(4, dtype=torch.float64)
        return t.get_matrix().reshape(4, 4).to(torch.float64)

    def visit(frame, parent):
        joint = frame.joint
        jt = joint.joint_type
        me = Frame(
            name=frame.name.strip("\n"),
            parent=parent,
            static=matrix(frame.link.offset) @ matrix(joint.offset),
            joint_type=jt,
            axis=joint.axis.detach().to(torch.float64).reshape(3),
            dof=dof_index[joint.name] if jt != "fixed" else -1,
            children=[],
        )
        frames.append(me)
        idx = len(frames) - 1
        if parent >= 0:
            frames[parent].children.append(idx)
        for child in frame.children:
            visit(child, idx)

    visit(chain._root, -1)
    return frames
