"""Articulated skeletons from URDF with a fused, level-batched forward-kinematics kernel.

A :class:`Skeleton` is built from a URDF through pytorch-kinematics (``skel.chain``) and then compiled into a
kernel that is much faster than ``chain.forward_kinematics_tensor``: it is the innermost loop of every
particle filter step, IK iteration and annealing layer.

* The body joints are the links whose origin is an anatomical joint. pytorch-kinematics has no ball or
  floating joint, so a ball joint is a run of revolute URDF joints joined by intermediate links; those are
  recognised and hidden (see :meth:`Skeleton.from_urdf`).
* Consecutive single-DOF motions between two body joints are fused into one rotation and translation per
  body joint, static offsets are precomputed, and the tree is traversed one depth level at a time (one
  batched product per level, no Python loop over joints at call time).
* Transforms are carried as rotation ``(..., 3, 3)`` and translation ``(..., 3)`` instead of 4x4 matrices.

Conventions (those of URDF and pytorch-kinematics): column vectors, ``p_world = R @ p_local + t``; a link's
frame is ``T_parent @ T_origin @ M(q)`` with ``M`` a rotation of ``q`` rad about (revolute) or a translation
of ``q`` m along (prismatic) the joint axis.

Capsule geometry (Hauberg §5): one capsule per bone (parent body joint -> child body joint) whose radius is
read from the URDF ``<collision>``/``<visual>`` cylinder or capsule of the parent link (``name`` = child),
else from a radii table, else ``0.15 x`` bone length.

Example::

    skel = Skeleton.from_urdf(torchpf.assets.path("human.urdf"))
    theta = skel.clamp(torch.randn(1000, len(skel.dof_names)))
    joints = skel.fk(theta)                      # (1000, J, 3) metres
    ends, radii = skel.capsules(theta)           # (1000, C, 2, 3), (C,)
"""

from __future__ import annotations

import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn

_REVOLUTE, _PRISMATIC = "revolute", "prismatic"


@dataclass
class _Frame:
    """One pytorch-kinematics frame (a link and the joint above it), flattened."""

    name: str
    parent: int
    static: torch.Tensor  # (4, 4) float64: link offset @ joint offset
    joint_type: str  # "fixed" | "revolute" | "prismatic"
    axis: torch.Tensor  # (3,) float64
    dof: int  # index into dof_names, -1 if fixed
    children: list[int]


def _read_urdf_text(path_or_xml: str | os.PathLike) -> tuple[str, str]:
    """(xml text, where it came from) for a URDF path or an XML string."""
    if isinstance(path_or_xml, str) and path_or_xml.lstrip().startswith("<"):
        return path_or_xml, "<urdf string>"
    path = os.fspath(path_or_xml)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"URDF file not found: {path}")
    with open(path, encoding="utf-8") as f:
        return f.read(), path


def _link_geometry(root: ET.Element) -> dict[str, list[tuple[str | None, float | None]]]:
    """link name -> [(element name, radius or None)] for every <collision>/<visual> of the link."""
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


def _flatten_chain(chain) -> list[_Frame]:
    dof_index = {n: i for i, n in enumerate(chain.get_joint_parameter_names())}
    frames: list[_Frame] = []

    def matrix(t):
        if t is None:
            return torch.eye(4, dtype=torch.float64)
        return t.get_matrix().reshape(4, 4).to(torch.float64)

    def visit(frame, parent):
        joint = frame.joint
        jt = joint.joint_type
        me = _Frame(
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


def _is_identity(m: torch.Tensor) -> bool:
    return bool(torch.allclose(m, torch.eye(4, dtype=m.dtype), atol=1e-12, rtol=0))


def _skew(a: torch.Tensor) -> torch.Tensor:
    x, y, z = a.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(*a.shape[:-1], 3, 3)


def _as_slice_or(rows: torch.Tensor | None, device) -> torch.Tensor | slice | None:
    """Parent rows as a slice when contiguous or all equal (a view, no copy), else an index on ``device``."""
    if rows is None or len(rows) == 0:
        return rows
    if bool((rows == rows[0]).all()):
        return slice(int(rows[0]), int(rows[0]) + 1)  # one parent for the level: broadcast it
    if torch.equal(rows, torch.arange(int(rows[0]), int(rows[0]) + len(rows))):
        return slice(int(rows[0]), int(rows[0]) + len(rows))
    return rows.to(device)


def _feature_basis(kind: str, axis: torch.Tensor) -> torch.Tensor:
    """(F, 4, 4) matrices G with M(q) = sum_f phi_f(q) G_f; phi = (cos, sin, 1) or (q, 1)."""
    if kind == _REVOLUTE:
        G = torch.zeros(3, 4, 4, dtype=torch.float64)
        aat = torch.outer(axis, axis)
        G[0, :3, :3] = torch.eye(3, dtype=torch.float64) - aat
        G[1, :3, :3] = _skew(axis)
        G[2, :3, :3] = aat
        G[2, 3, 3] = 1.0
        return G
    G = torch.zeros(2, 4, 4, dtype=torch.float64)
    G[0, :3, 3] = axis
    G[1] = torch.eye(4, dtype=torch.float64)
    return G


def _run_frame(static: torch.Tensor, motions: list, moving: int) -> torch.Tensor:
    """(P, 4, 4) matrices G with ``S @ M_1(q_1) @ ... @ M_moving(q_moving) = sum_p monomial_p G_p``.

    The monomials are the run's: the products of one feature per DOF, the first DOF's feature varying
    slowest. DOFs after ``moving`` do not move this frame: only their constant feature (the last one)
    enters, with the identity.
    """
    acc = static[None]
    for j, (kind, axis, _) in enumerate(motions):
        G = _feature_basis(kind, axis)
        if j >= moving:
            G = torch.zeros_like(G)
            G[-1] = torch.eye(4, dtype=G.dtype)
        acc = (acc[:, None] @ G[None]).reshape(-1, 4, 4)
    return acc


def _run_coefficients(static: torch.Tensor, motions: list) -> torch.Tensor:
    """(12, P) matrix W with top3x4(S @ M_1(q_1) @ ... @ M_m(q_m)) = W @ monomials (:func:`_run_frame`)."""
    return _run_frame(static, motions, len(motions))[:, :3, :].reshape(-1, 12).t().contiguous()


def _run_axes(static: torch.Tensor, motions: list, pivots: bool) -> torch.Tensor:
    """(3m or 6m, P) matrix A with, for DOF i of the run, rows ``3i..3i+2`` its axis and (``pivots``) rows
    ``3m + 3i..3m + 3i+2`` its pivot (a point on the axis), in the run's parent frame, as ``A @ monomials``:
    those of the frame ``S @ M_1 @ ... @ M_{i-1}`` right above DOF ``i`` (:func:`_run_frame`).
    """
    frames = [_run_frame(static, motions, i) for i in range(len(motions))]
    axes = [(f[:, :3, :3] @ axis).t() for f, (_, axis, _) in zip(frames, motions, strict=True)]
    points = [f[:, :3, 3].t() for f in frames] if pivots else []
    return torch.cat(axes + points, 0).contiguous()


def _pivot_is_origin(motions: list) -> bool:
    """Whether every revolute DOF of the run turns about the run's own origin: no prismatic DOF follows it
    (rotations about axes through a point leave it in place; the origins inside a run are the identity)."""
    kinds = [kind for kind, _, _ in motions]
    return not any(k == _REVOLUTE and _PRISMATIC in kinds[i + 1 :] for i, k in enumerate(kinds))


class Skeleton(nn.Module):
    """A kinematic tree of body joints with joint limits and capsule radii, batched FK on any device.

    Build with :meth:`from_urdf`. Attributes:

    * ``chain``: the pytorch-kinematics chain the kernel was compiled from.
    * ``dof_names`` (D): the pose vector's order (``chain.get_joint_parameter_names()``).
    * ``joint_names`` (J): the body joints, parents before children; ``parents`` (J) index into them, ``-1``
      for the root.
    * ``lower``, ``upper`` (D,): joint limits (rad or m; +-inf where the URDF gives none).
    * ``dof_joints`` (D): for each DOF, the body joint it moves (the joint at the end of its run).
    * ``bones`` (C): (parent, child) joint indices of the capsules; ``radii`` (C,) in metres.
    """

    def __init__(
        self,
        chain,
        urdf_xml: str,
        joint_names: Sequence[str] | None = None,
        radii: Mapping[str, float] | None = None,
        source: str = "<urdf string>",
    ):
        super().__init__()
        self.chain = chain
        self.source = source
        try:
            root = ET.fromstring(urdf_xml)
        except ET.ParseError as e:
            raise ValueError(f"{source}: invalid URDF XML ({e})") from None
        geometry = _link_geometry(root)
        frames = _flatten_chain(chain)
        self.dof_names: list[str] = list(chain.get_joint_parameter_names())
        lower, upper = chain.get_joint_limits()
        self.register_buffer("lower", torch.tensor(lower, dtype=torch.float64), persistent=False)
        self.register_buffer("upper", torch.tensor(upper, dtype=torch.float64), persistent=False)

        self._cache: dict[tuple, dict] = {}
        body = self._body_frames(frames, geometry, joint_names, source)
        self.joint_names: list[str] = [frames[i].name for i in body]
        # Rows of chain.forward_kinematics_tensor(...) that hold the body joints (for cross-checks).
        self.pk_frame_indices = torch.tensor([chain.frame_to_idx[n] for n in self.joint_names])
        self._compile(frames, body)
        self._build_capsules(geometry, radii or {})

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(
        cls,
        path_or_xml: str | os.PathLike,
        *,
        joint_names: Sequence[str] | None = None,
        radii: Mapping[str, float] | None = None,
    ) -> Skeleton:
        """Load a skeleton from a URDF file path or an XML string.

        Body joints, unless ``joint_names`` lists them explicitly, are all links except *intermediate*
        links: a link with no ``<collision>``/``<visual>``, exactly one child joint, and that joint movable
        with an identity origin (the links inside a ball joint or a floating root); a bare root link above a
        single movable joint (the world of a floating base) is not a body joint either. ``radii`` maps a child
        joint name to the radius (m) of the capsule ending there and overrides the URDF.
        """
        import pytorch_kinematics as pk
        from pytorch_kinematics.urdf_parser_py.xml_reflection import core as xml_core

        xml, source = _read_urdf_text(path_or_xml)
        # The URDF parser prints its complaints to stderr; the optional ``name`` of <collision>/<visual>
        # (URDF spec, used here for capsule radii) is among them. Keep the rest as warnings.
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
                warnings.warn(f"{source}: {msg}", stacklevel=2)
        return cls(chain, xml, joint_names=joint_names, radii=radii, source=source)

    @staticmethod
    def _body_frames(frames, geometry, joint_names, source) -> list[int]:
        if joint_names is not None:
            index = {f.name: i for i, f in enumerate(frames)}
            missing = [n for n in joint_names if n not in index]
            if missing:
                raise ValueError(f"{source}: joint_names not among the URDF links: {missing}")
            chosen = {index[n] for n in joint_names}
        else:
            chosen = set()
            for i, f in enumerate(frames):
                kids = f.children
                # A bare base link above a movable root joint is the world, not a body joint.
                intermediate = (
                    not geometry.get(f.name)
                    and len(kids) == 1
                    and frames[kids[0]].joint_type != "fixed"
                    and (f.parent < 0 or _is_identity(frames[kids[0]].static))
                )
                if not intermediate:
                    chosen.add(i)
        return sorted(chosen)  # depth-first order: parents come first

    def _compile(self, frames: list[_Frame], body: list[int]) -> None:
        """Fuse each body joint's run of single-DOF frames into one local transform; order by depth.

        The local transform of a run, ``S @ M_1(q_1) @ ... @ M_m(q_m)`` (``S`` the static origin), is
        multilinear in per-DOF features: ``(cos q, sin q, 1)`` for a revolute DOF (Rodrigues:
        ``M = cos q (I - a a^T) + sin q [a]_x + a a^T``) and ``(q, 1)`` for a prismatic one. So its 12
        entries (3x4) are one product ``W @ monomials`` with ``W`` precomputed here: a ball joint costs one
        (12 x 27) @ (27 x B) product instead of three rotations and two matrix products.
        """
        body_set = set(body)
        self._consts: dict[str, torch.Tensor] = {}

        # Internal nodes: body joints plus frames that cannot be folded into their single child's run
        # (several children, or a child whose origin is not the identity).
        def foldable(i):
            f = frames[i]
            return i not in body_set and len(f.children) == 1 and _is_identity(frames[f.children[0]].static)

        needed = set(body)
        for i in body:
            j = frames[i].parent
            while j >= 0 and j not in needed:
                if not foldable(j):
                    needed.add(j)
                j = frames[j].parent
        nodes = sorted(needed)
        node_of = {f: n for n, f in enumerate(nodes)}

        parent, runs, statics, depth = [], [], [], []
        for i in nodes:
            run = [i]
            j = frames[i].parent
            while j >= 0 and j not in needed:
                run.append(j)
                j = frames[j].parent
            run.reverse()
            # Every static origin but the first is the identity (that is what made the frames foldable).
            parent.append(node_of[j] if j >= 0 else -1)
            statics.append(frames[run[0]].static)
            runs.append(
                [(frames[k].joint_type, frames[k].axis, frames[k].dof) for k in run if frames[k].dof >= 0]
            )
            depth.append(0 if parent[-1] < 0 else depth[parent[-1]] + 1)

        # Level order: each depth level is a contiguous block of rows.
        order = []
        for d in range(max(depth) + 1):
            # siblings by their parent's rank, so that a level's parents are often one contiguous block
            at_d = [n for n in range(len(nodes)) if depth[n] == d]
            prev_rank = {n: r for r, n in enumerate(order)}
            order += sorted(at_d, key=lambda n: (prev_rank.get(parent[n], -1), n))
        rank = {n: r for r, n in enumerate(order)}
        self._levels = []
        for d in range(max(depth) + 1):
            rows = [r for r, n in enumerate(order) if depth[n] == d]
            # parents index into the previous level's block
            parent_rows = None
            if d > 0:
                parent_rows = torch.tensor([rank[parent[order[r]]] - self._levels[-1][0] for r in rows])
            self._levels.append((rows[0], rows[-1] + 1, parent_rows))

        # Group the nodes by motion signature (e.g. three revolutes for a ball joint).
        groups: dict[tuple[str, ...], list[int]] = {}
        for r, n in enumerate(order):
            groups.setdefault(tuple(t for t, _, _ in runs[n]), []).append(r)
        self._groups = []
        self._axis_pivots: list[bool] = []
        concat = []
        D = len(self.dof_names)
        # Where each DOF's world axis and pivot are found (see :meth:`_world`): its row in the
        # group-concatenated axes, and in the concatenation of the node origins and the computed pivots (a
        # revolute DOF turns about its node's origin unless a prismatic DOF follows it in the run). A DOF in
        # no run (below every body joint) points at an appended zero axis.
        axis_rows, pivot_rows = [-1] * D, [0] * D
        n_axis_rows, n_pivot_rows = 0, len(order)
        for g, (sig, members) in enumerate(groups.items()):
            W = torch.stack([_run_coefficients(statics[order[r]], runs[order[r]]) for r in members])
            dofs = torch.tensor([[dof for _, _, dof in runs[order[r]]] for r in members], dtype=torch.long)
            self._consts[f"W{g}"] = W  # (n, 12, P)
            self._consts[f"dofs{g}"] = dofs.reshape(len(members), len(sig))
            if sig:
                pivots = not all(_pivot_is_origin(runs[order[r]]) for r in members)
                A = torch.stack([_run_axes(statics[order[r]], runs[order[r]], pivots) for r in members])
                self._consts[f"WA{g}"] = torch.cat([W, A], 1)  # (n, 12 + 3m or 12 + 6m, P)
                par = [rank[parent[order[r]]] if parent[order[r]] >= 0 else len(order) for r in members]
                self._consts[f"par{g}"] = torch.tensor(par, dtype=torch.long)
                self._axis_pivots.append(pivots)
                for r, run_dofs in zip(members, dofs.tolist(), strict=True):
                    for dof in run_dofs:
                        axis_rows[dof] = n_axis_rows
                        n_axis_rows += 1
                        pivot_rows[dof] = n_pivot_rows if pivots else r
                        n_pivot_rows += int(pivots)
            else:
                self._axis_pivots.append(False)
            self._groups.append(sig)
            concat.extend(members)
        self._consts["axis_rows"] = torch.tensor(
            [a if a >= 0 else n_axis_rows for a in axis_rows], dtype=torch.long
        )
        self._consts["pivot_rows"] = torch.tensor(pivot_rows, dtype=torch.long)
        revolute = [False] * D
        for f in frames:
            if f.dof >= 0:
                revolute[f.dof] = f.joint_type == _REVOLUTE
        self._dof_revolute = torch.tensor(revolute)
        # Node structure in level order (the articulated-body solve of torchpf.ik reads it): each internal
        # node's parent row (-1 for a root) and the DOFs of its run, root first.
        self._node_parent = [rank[parent[n]] if parent[n] >= 0 else -1 for n in order]
        self._node_dofs = [[dof for _, _, dof in runs[n]] for n in order]
        kinds = {k for sig in self._groups for k in sig}
        self._has_revolute, self._has_prismatic = _REVOLUTE in kinds, _PRISMATIC in kinds
        # Rows of the group-concatenated tensor, in level order.
        self._reorder = None if concat == sorted(concat) else torch.argsort(torch.tensor(concat))

        self._body_rows = torch.tensor([rank[node_of[i]] for i in body], dtype=torch.long)
        self._body_rows_identity = bool(torch.equal(self._body_rows, torch.arange(len(order))))
        self.parents: list[int] = []
        self._bone_has_prismatic: list[bool] = []
        # dof_joints[d]: the body joint whose run (the URDF joints between it and its parent joint) holds d
        self.dof_joints: list[int] = [-1] * len(self.dof_names)
        for b, i in enumerate(body):
            j, kinds = i, set()
            while True:
                kinds.add(frames[j].joint_type)
                if frames[j].dof >= 0:
                    self.dof_joints[frames[j].dof] = b
                j = frames[j].parent
                if j < 0 or j in body_set:
                    break
            self.parents.append(body.index(j) if j >= 0 else -1)
            self._bone_has_prismatic.append(_PRISMATIC in kinds)

    def _build_capsules(self, geometry, radii: Mapping[str, float]) -> None:
        rest = self.fk(torch.zeros(len(self.dof_names), dtype=torch.float64))
        bones, r = [], []
        for c, p in enumerate(self.parents):
            if p < 0:
                continue
            length = float((rest[c] - rest[p]).norm())
            if length < 1e-9 and not self._bone_has_prismatic[c]:
                continue
            child, parent = self.joint_names[c], self.joint_names[p]
            radius = radii.get(child)
            if radius is None:
                entries = geometry.get(parent, [])
                named = [rad for name, rad in entries if name == child and rad is not None]
                if named:
                    radius = named[0]
                else:
                    n_bones = sum(
                        1
                        for k, q in enumerate(self.parents)
                        if q == p and float((rest[k] - rest[p]).norm()) >= 1e-9
                    )
                    unnamed = [rad for name, rad in entries if rad is not None]
                    if n_bones == 1 and len(unnamed) == 1:
                        radius = unnamed[0]
            if radius is None:
                radius = 0.15 * length
            bones.append((p, c))
            r.append(float(radius))
        self.bones: list[tuple[int, int]] = bones
        self.register_buffer("radii", torch.tensor(r, dtype=torch.float64), persistent=False)
        self.register_buffer(
            "_bone_index", torch.tensor(bones, dtype=torch.long).reshape(-1, 2), persistent=False
        )

    # ------------------------------------------------------------------ kernel
    def _constants(self, dtype: torch.dtype, device: torch.device) -> dict:
        key = (dtype, device)
        consts = self._cache.get(key)
        if consts is None:
            consts = {
                k: v.to(device=device, dtype=dtype if v.is_floating_point() else v.dtype)
                for k, v in self._consts.items()
            }
            consts["levels"] = [(s, e, _as_slice_or(p, device)) for s, e, p in self._levels]
            consts["reorder"] = None if self._reorder is None else self._reorder.to(device)
            consts["body_rows"] = self._body_rows.to(device)
            consts["eye34"] = torch.eye(3, 4, dtype=dtype, device=device)[None, :, :, None]
            consts["col3"] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype, device=device).reshape(
                1, 1, 4, 1
            )
            self._cache[key] = consts
        return consts

    def _world(self, theta: torch.Tensor, axes: bool = False):
        """World 3x4 transforms (M, 3, 4, B) of every internal node, level order; ``theta`` is (B, D).

        Batch-last layout: every elementwise product below runs over contiguous B-long rows, which on a CPU
        is several times faster than batched 3x3 ``bmm``. With ``axes=True`` also returns every DOF's world
        axis and pivot, each ``(D, 3, B)`` (see :meth:`dof_axes`): the same monomial products give the axes
        (and the pivots that are not a node's origin) in the run's parent frame (rows ``WA``), one rotation
        takes them to the world.
        """
        c = self._constants(theta.dtype, theta.device)
        q = theta.t().contiguous()  # (D, B): batch last, see above
        one = torch.ones_like(q)
        feats = {}
        if self._has_revolute:
            feats[_REVOLUTE] = torch.stack([torch.cos(q), torch.sin(q), one], 1)  # (D, 3, B)
        if self._has_prismatic:
            feats[_PRISMATIC] = torch.stack([q, one], 1)  # (D, 2, B)
        B = theta.shape[0]
        local = []
        run_axes = []  # per group with DOFs: (n, 3m or 6m, B) axes (and pivots) in the parent frame
        for g, sig in enumerate(self._groups):
            W = c[f"W{g}"]
            if not sig:
                local.append(W.expand(-1, -1, B))  # fixed joint: the static transform
                continue
            dofs = c[f"dofs{g}"]
            mono = None
            for k, kind in enumerate(sig):
                f = feats[kind].index_select(0, dofs[:, k])  # (n, F, B)
                mono = f if mono is None else (mono[:, :, None] * f[:, None]).flatten(1, 2)
            if axes:
                out = torch.bmm(c[f"WA{g}"], mono)
                local.append(out[:, :12])
                run_axes.append((g, out[:, 12:]))
            else:
                local.append(torch.bmm(W, mono))  # (n, 12, B)
        loc = torch.cat(local, 0) if len(local) > 1 else local[0]
        if c["reorder"] is not None:
            loc = loc.index_select(0, c["reorder"])
        loc = loc.view(-1, 3, 4, B)
        world = []
        col3 = c["col3"]
        for start, end, parent_rows in c["levels"]:
            L = loc[start:end]
            if parent_rows is not None:
                prev = world[-1]
                P = prev[parent_rows] if isinstance(parent_rows, slice) else prev.index_select(0, parent_rows)
                # [R_p | t_p] @ [[R_l, t_l], [0, 1]] = [R_p R_l | R_p t_l + t_p]
                T = torch.addcmul(P * col3, P[:, :, 0:1], L[:, 0:1])
                T = torch.addcmul(T, P[:, :, 1:2], L[:, 1:2])
                L = torch.addcmul(T, P[:, :, 2:3], L[:, 2:3])
            world.append(L)
        if not axes:
            return torch.cat(world, 0) if len(world) > 1 else world[0]
        # the parent frames of the runs, a root's being the identity (an appended row)
        ext = torch.cat([*world, c["eye34"].expand(1, 3, 4, B)], 0)
        world = ext[:-1]
        axis_parts, pivot_parts = [], [world[:, :, 3]]
        for g, v in run_axes:
            P = ext.index_select(0, c[f"par{g}"])  # (n, 3, 4, B)
            n, m = v.shape[0], len(self._groups[g])
            v = v.view(n, -1, 3, B)  # (n, m or 2m, 3, B)
            w = P[:, None, :, 0] * v[:, :, 0:1]
            w = torch.addcmul(w, P[:, None, :, 1], v[:, :, 1:2])
            w = torch.addcmul(w, P[:, None, :, 2], v[:, :, 2:3])
            axis_parts.append(w[:, :m].reshape(n * m, 3, B))
            if self._axis_pivots[g]:
                pivot_parts.append((w[:, m:] + P[:, None, :, 3]).reshape(n * m, 3, B))  # points: translate
        axis_parts.append(world.new_zeros(1, 3, B))
        dof_axes = torch.cat(axis_parts, 0).index_select(0, c["axis_rows"])
        pivots = pivot_parts[0] if len(pivot_parts) == 1 else torch.cat(pivot_parts, 0)
        return world, dof_axes, pivots.index_select(0, c["pivot_rows"])

    def _flat(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Size]:
        if not isinstance(theta, torch.Tensor):
            theta = torch.as_tensor(theta, dtype=torch.get_default_dtype())
        if not theta.is_floating_point():
            theta = theta.to(torch.get_default_dtype())
        if theta.ndim == 0 or theta.shape[-1] != len(self.dof_names):
            raise ValueError(
                f"theta must have shape (..., {len(self.dof_names)}) in dof_names order, "
                f"got {tuple(theta.shape)}"
            )
        return theta.reshape(-1, theta.shape[-1]), theta.shape[:-1]

    # ------------------------------------------------------------------ public API
    def fk(self, theta: torch.Tensor) -> torch.Tensor:
        """World positions (m) of the body joints.

        Args:
            theta: (..., D) pose in ``dof_names`` order (rad for revolute, m for prismatic DOFs).

        Returns:
            (..., J, 3) joint positions in ``joint_names`` order; dtype and device of ``theta``;
            differentiable with respect to ``theta``.
        """
        flat, batch = self._flat(theta)
        t = self._body(self._world(flat)[:, :, 3], flat)  # (J, 3, B)
        return t.permute(2, 0, 1).reshape(*batch, len(self.joint_names), 3)

    def _body(self, nodes: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:
        if self._body_rows_identity:
            return nodes
        return nodes.index_select(0, self._constants(flat.dtype, flat.device)["body_rows"])

    def forward(self, theta: torch.Tensor) -> torch.Tensor:
        """Same as :meth:`fk`, so that a skeleton composes as a module."""
        return self.fk(theta)

    def transforms(self, theta: torch.Tensor) -> torch.Tensor:
        """Homogeneous world transforms (..., J, 4, 4) of the body-joint frames (rotation, translation m)."""
        flat, batch = self._flat(theta)
        T = self._body(self._world(flat), flat).permute(3, 0, 1, 2)  # (B, J, 3, 4)
        bottom = flat.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*T.shape[:2], 1, 4)
        return torch.cat([T, bottom], -2).reshape(*batch, len(self.joint_names), 4, 4)

    def dof_axes(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World axis and pivot of every DOF: the columns of the kinematic Jacobian.

        Args:
            theta: (..., D) pose.

        Returns:
            ``axes`` (..., D, 3) world direction of each DOF's axis (as long as the URDF axis is), and
            ``pivots`` (..., D, 3) a point on it (m): the origin of the frame right above the DOF. A
            revolute DOF moves a point ``y`` below it with velocity ``axis x (y - pivot)`` per rad, a
            prismatic one with ``axis`` per metre (its pivot is then only some point of its run); a DOF
            below every body joint gets a zero axis.
        """
        flat, batch = self._flat(theta)
        _, axes, pivots = self._world(flat, axes=True)
        D = len(self.dof_names)
        return axes.permute(2, 0, 1).reshape(*batch, D, 3), pivots.permute(2, 0, 1).reshape(*batch, D, 3)

    @property
    def dof_revolute(self) -> torch.Tensor:
        """(D,) bool: True for a revolute DOF (radians), False for a prismatic one (metres), from the URDF
        joint types (never from names)."""
        return self._dof_revolute.clone()

    def clamp(self, theta: torch.Tensor) -> torch.Tensor:
        """``theta`` (..., D) clamped into ``[lower, upper]`` per DOF (differentiable inside the limits)."""
        lo = self.lower.to(device=theta.device, dtype=theta.dtype)
        hi = self.upper.to(device=theta.device, dtype=theta.dtype)
        return torch.maximum(torch.minimum(theta, hi), lo)

    def within_limits(self, theta: torch.Tensor) -> torch.Tensor:
        """(...,) bool: every DOF of ``theta`` (..., D) within ``[lower, upper]``."""
        lo = self.lower.to(device=theta.device, dtype=theta.dtype)
        hi = self.upper.to(device=theta.device, dtype=theta.dtype)
        return ((theta >= lo) & (theta <= hi)).all(-1)

    def capsules(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Capsule body model (Hauberg §5): one capsule per bone.

        Args:
            theta: (..., D) pose.

        Returns:
            ends: (..., C, 2, 3) world positions (m) of each bone's parent and child joint.
            radii: (C,) radii (m), dtype and device of ``theta``.
        """
        joints = self.fk(theta)
        idx = self._bone_index.to(joints.device)
        ends = joints[..., idx, :]  # (..., C, 2, 3)
        return ends, self.radii.to(device=joints.device, dtype=joints.dtype)

    def extra_repr(self) -> str:
        return (
            f"source={self.source!r}, D={len(self.dof_names)}, J={len(self.joint_names)}, C={len(self.bones)}"
        )
