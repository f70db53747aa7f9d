"""Articulated skeletons from URDF with a fused, level-batched forward-kinematics kernel.

A :class:`Skeleton` is built from a URDF through pytorch-kinematics (``skel.chain``) and then compiled into a
kernel that is much faster than ``chain.forward_kinematics_tensor``: it is the innermost loop of every
particle filter step, IK iteration and annealing layer.

* The body joints are the links whose origin is an anatomical joint. pytorch-kinematics has no ball or
  floating joint, so a ball joint is a run of revolute URDF joints joined by intermediate links; those are
  recognised and hidden (see :meth:`Skeleton.from_urdf`).
* Consecutive single-DOF motions between two body joints are fused into one rotation and translation per
  body joint, static offsets are precomputed, and the tree is traversed one depth level at a time (one
  batched product per level, no Python loop over joints at call time); for a few poses (a gradient
  refinement's), where the number of operations is the cost, by pointer jumping instead (every node
  composed with its ancestor 2^k levels up in round k: ceil(log2(depth)) rounds). On a CPU without
  autograd the same arithmetic runs as one fused numba kernel, node by node
  (:mod:`torchpf.kinematics._fk_cpu`): 5-8x fewer microseconds for a refinement's few poses.
* Transforms are carried as rotation ``(..., 3, 3)`` and translation ``(..., 3)`` instead of 4x4 matrices.
* The topology (body joints, nodes and their runs, depth levels, revolute mask, bones, partition) is a public
  :class:`~torchpf.kinematics.tree.KinematicTree`, ``skel.tree``, which the IK Jacobian and the
  articulated-body solve (:mod:`torchpf.kinematics`) read too; this module adds the geometry (the fused
  run coefficients, the capsule radii) and the kernel. URDF reading is :mod:`torchpf.kinematics.urdf`.

Conventions (those of URDF and pytorch-kinematics): column vectors, ``p_world = R @ p_local + t``; a link's
frame is ``T_parent @ T_origin @ M(q)`` with ``M`` a rotation of ``q`` rad about (revolute) or a translation
of ``q`` m along (prismatic) the joint axis.

Capsule geometry (Hauberg §5): one capsule per bone (parent body joint -> child body joint) whose radius is
read from the URDF ``<collision>``/``<visual>`` cylinder or capsule of the parent link (``name`` = child),
else from a radii table, else ``0.15 x`` bone length (0.01 m for a bone of zero rest length).

Example::

    skel = Skeleton.from_urdf(torchpf.assets.path("human.urdf"))
    theta = skel.clamp(torch.randn(1000, len(skel.dof_names)))
    joints = skel.fk(theta)                      # (1000, J, 3) metres
    ends, radii = skel.capsules(theta)           # (1000, C, 2, 3), (C,)
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence

import torch
from torch import nn

from torchpf.distributions import flatten_batch, unflatten_batch
from torchpf.kinematics import _fk_cpu
from torchpf.kinematics.tree import KinematicTree, partition_labels
from torchpf.kinematics.urdf import (
    Frame,
    build_chain,
    flatten_chain,
    is_identity,
    link_geometry,
    parse_urdf_xml,
    read_urdf_text,
    rebody_urdf,
    relimit_urdf,
)

_REVOLUTE, _PRISMATIC = "revolute", "prismatic"

#: batch x nodes up to which FK composes the tree by pointer jumping instead of level by level (measured:
#: the crossover on a CPU lies near 60 poses of a 38-node body)
_JUMP_MAX_ROWS = 2048


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
    * ``tree``: the :class:`~torchpf.kinematics.tree.KinematicTree` (index tensors of the topology) that
      the FK kernel, the IK Jacobian and the articulated-body solve share.
    * ``dof_names`` (D): the pose vector's order (``chain.get_joint_parameter_names()``).
    * ``joint_names`` (J): the body joints, parents before children; ``parents`` (J) index into them, ``-1``
      for the root (``tree.parents`` as a list).
    * ``lower``, ``upper`` (D,): joint limits (rad or m; +-inf where the URDF gives none).
    * ``dof_joints`` (D): for each DOF, the body joint it moves (the joint at the end of its run;
      ``tree.dof_joint`` as a list).
    * ``bones`` (C): (parent, child) joint indices of the capsules (``tree.bones``); ``radii`` (C,) in metres.
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
        bad = {k: v for k, v in (radii or {}).items() if not (math.isfinite(float(v)) and float(v) > 0)}
        if bad:
            raise ValueError(f"{source}: capsule radii must be finite and > 0, got {bad}")
        self.urdf_xml = urdf_xml  # what with_body / save_urdf rewrite
        geometry = link_geometry(parse_urdf_xml(urdf_xml, source))
        frames = flatten_chain(chain)
        self.dof_names: list[str] = list(chain.get_joint_parameter_names())
        lower, upper = chain.get_joint_limits()
        self.register_buffer("lower", torch.tensor(lower, dtype=torch.float64), persistent=False)
        self.register_buffer("upper", torch.tensor(upper, dtype=torch.float64), persistent=False)

        body = self._body_frames(frames, geometry, joint_names, source)
        self.joint_names: list[str] = [frames[i].name for i in body]
        # Rows of chain.forward_kinematics_tensor(...) that hold the body joints (for cross-checks).
        self.pk_frame_indices = torch.tensor([chain.frame_to_idx[n] for n in self.joint_names])
        # bones and the partition need the rest pose, i.e. the compiled kernel: set once it is
        self.tree = KinematicTree.from_frames(frames, body, len(self.dof_names))
        self.parents: list[int] = self.tree.parents.tolist()
        self.dof_joints: list[int] = self.tree.dof_joint.tolist()
        self._compile(frames)
        rest = self.rest_joints()
        self._build_capsules(frames, body, rest, geometry, radii or {})
        self.tree = self.tree.replace(
            bones=torch.tensor(self.bones, dtype=torch.long).reshape(-1, 2),
            joint_part=partition_labels(self.parents, rest),
        )

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
        xml, source = read_urdf_text(path_or_xml)
        chain = build_chain(xml, source)
        return cls(chain, xml, joint_names=joint_names, radii=radii, source=source)

    @staticmethod
    def _body_frames(frames: list[Frame], geometry, joint_names, source) -> list[int]:
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
                    and (f.parent < 0 or is_identity(frames[kids[0]].static))
                )
                if not intermediate:
                    chosen.add(i)
        return sorted(chosen)  # depth-first order: parents come first

    def _compile(self, frames: list[Frame]) -> None:
        """Fuse each node's run of single-DOF frames into one local transform, grouped by motion signature.

        The local transform of a run, ``S @ M_1(q_1) @ ... @ M_m(q_m)`` (``S`` the static origin), is
        multilinear in per-DOF features: ``(cos q, sin q, 1)`` for a revolute DOF (Rodrigues:
        ``M = cos q (I - a a^T) + sin q [a]_x + a a^T``) and ``(q, 1)`` for a prismatic one. So its 12
        entries (3x4) are one product ``W @ monomials`` with ``W`` precomputed here: a ball joint costs one
        (12 x 27) @ (27 x B) product instead of three rotations and two matrix products. The nodes, their
        runs and their level order are the tree's (:meth:`KinematicTree.from_frames`).
        """
        tree = self.tree
        node_frame, node_parent = tree.node_frame.tolist(), tree.node_parent.tolist()
        M = len(node_frame)
        statics, runs = [], []
        for r in range(M):
            stop = node_frame[node_parent[r]] if node_parent[r] >= 0 else -1
            run, j = [], node_frame[r]
            while j != stop:
                run.append(j)
                j = frames[j].parent
            run.reverse()
            # Every static origin but the first is the identity (that is what made the frames foldable).
            statics.append(frames[run[0]].static)
            runs.append(
                [(frames[k].joint_type, frames[k].axis, frames[k].dof) for k in run if frames[k].dof >= 0]
            )

        # Group the nodes by motion signature (e.g. three revolutes for a ball joint).
        groups: dict[tuple[str, ...], list[int]] = {}
        for r in range(M):
            groups.setdefault(tuple(t for t, _, _ in runs[r]), []).append(r)
        self._groups: list[tuple[str, ...]] = []
        self._axis_pivots: list[bool] = []
        # float64 coefficients per group, (W (n, 12, P), WA (n, 12 + 3m or 12 + 6m, P) or None): cast to the
        # compute dtype in the tree's cache (plain attributes: module.to(dtype) must not round them)
        self._coefficients: list[tuple[torch.Tensor, torch.Tensor | None]] = []
        concat = []
        D = len(self.dof_names)
        # Where each DOF's world axis and pivot are found (see :meth:`_world`): its row in the
        # group-concatenated axes, and in the concatenation of the node origins and the computed pivots (a
        # revolute DOF turns about its node's origin unless a prismatic DOF follows it in the run). A DOF in
        # no run (below every body joint) points at an appended zero axis.
        axis_rows, pivot_rows = [-1] * D, [0] * D
        n_axis_rows, n_pivot_rows = 0, M
        for g, (sig, members) in enumerate(groups.items()):
            W = torch.stack([_run_coefficients(statics[r], runs[r]) for r in members])
            dofs = torch.tensor([[dof for _, _, dof in runs[r]] for r in members], dtype=torch.long)
            self.register_buffer(f"_fk_dofs{g}", dofs.reshape(len(members), len(sig)), persistent=False)
            WA = None
            if sig:
                pivots = not all(_pivot_is_origin(runs[r]) for r in members)
                A = torch.stack([_run_axes(statics[r], runs[r], pivots) for r in members])
                WA = torch.cat([W, A], 1)
                par = [node_parent[r] if node_parent[r] >= 0 else M for r in members]
                self.register_buffer(f"_fk_par{g}", torch.tensor(par, dtype=torch.long), persistent=False)
                self._axis_pivots.append(pivots)
                for r, run_dofs in zip(members, dofs.tolist(), strict=True):
                    for dof in run_dofs:
                        axis_rows[dof] = n_axis_rows
                        n_axis_rows += 1
                        pivot_rows[dof] = n_pivot_rows if pivots else r
                        n_pivot_rows += int(pivots)
            else:
                self._axis_pivots.append(False)
            self._coefficients.append((W, WA))
            self._groups.append(sig)
            concat.extend(members)
        self.register_buffer(
            "_fk_axis_rows",
            torch.tensor([a if a >= 0 else n_axis_rows for a in axis_rows], dtype=torch.long),
            persistent=False,
        )
        self.register_buffer("_fk_pivot_rows", torch.tensor(pivot_rows, dtype=torch.long), persistent=False)
        kinds = {k for sig in self._groups for k in sig}
        self._has_revolute, self._has_prismatic = _REVOLUTE in kinds, _PRISMATIC in kinds
        # Rows of the group-concatenated tensor, in level order.
        reorder = None if concat == sorted(concat) else torch.argsort(torch.tensor(concat))
        self.register_buffer("_fk_reorder", reorder, persistent=False)
        self._body_rows_identity = bool(torch.equal(tree.joint_node, torch.arange(M)))

    def _build_capsules(self, frames, body, rest, geometry, radii: Mapping[str, float]) -> None:
        body_set = set(body)
        has_prismatic = []  # per body joint: a prismatic URDF joint between it and its parent joint
        for i in body:
            j, kinds = i, set()
            while True:
                kinds.add(frames[j].joint_type)
                j = frames[j].parent
                if j < 0 or j in body_set:
                    break
            has_prismatic.append(_PRISMATIC in kinds)
        bones, r = [], []
        for c, p in enumerate(self.parents):
            if p < 0:
                continue
            length = float((rest[c] - rest[p]).norm())
            if length < 1e-9 and not has_prismatic[c]:
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
                # a bone of zero rest length (a prismatic one) still needs a positive radius: URDF refuses 0
                radius = 0.15 * length if length > 1e-9 else 0.01
            bones.append((p, c))
            r.append(float(radius))
        self.bones: list[tuple[int, int]] = bones
        self.register_buffer("radii", torch.tensor(r, dtype=torch.float64), persistent=False)

    # ------------------------------------------------------------------ kernel
    def _constants(self, dtype: torch.dtype, device: torch.device) -> dict:
        """The kernel's constants in ``dtype`` on ``device``, built once (the tree's cache)."""
        return self.tree.cached(("fk", device, dtype), lambda: self._build_constants(dtype, device))

    def _build_constants(self, dtype: torch.dtype, device: torch.device) -> dict:
        c: dict = {}
        for g, (W, WA) in enumerate(self._coefficients):
            c[f"W{g}"] = W.to(device=device, dtype=dtype)
            c[f"dofs{g}"] = getattr(self, f"_fk_dofs{g}").to(device)
            if WA is not None:
                c[f"WA{g}"] = WA.to(device=device, dtype=dtype)
                c[f"par{g}"] = getattr(self, f"_fk_par{g}").to(device)
        c["axis_rows"] = self._fk_axis_rows.to(device)
        c["pivot_rows"] = self._fk_pivot_rows.to(device)
        c["reorder"] = None if self._fk_reorder is None else self._fk_reorder.to(device)
        c["body_rows"] = self.tree.joint_node.to(device)
        # each level's parents, as rows of the level above: a slice where they are contiguous
        node_parent = self.tree.node_parent.cpu()
        levels = []
        prev = None
        for start, end in self.tree.levels():
            rows = None if prev is None else node_parent[start:end] - prev
            levels.append((start, end, _as_slice_or(rows, device)))
            prev = start
        c["levels"] = levels
        # Pointer jumping (a parallel prefix product over the tree): round k composes every node with the
        # ancestor 2^k edges up, so ceil(log2(depth)) rounds replace one round per level. It does more
        # arithmetic (every node, every round), so it is used for small batches only, where the cost is the
        # number of operations, not their size (see :meth:`_world`). Row M is the identity, every node's
        # ancestor beyond its root, and its own.
        M = self.tree.n_nodes
        anc = torch.cat([torch.where(node_parent >= 0, node_parent, M), torch.tensor([M])])
        jumps = []
        while bool((anc[:M] < M).any()):
            jumps.append(anc.to(device))
            anc = anc[anc]
        c["jumps"] = jumps
        c["eye34"] = torch.eye(3, 4, dtype=dtype, device=device)[None, :, :, None]
        c["col3"] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype, device=device).reshape(1, 1, 4, 1)
        return c

    def _fused_structure(self, dtype: torch.dtype):
        """The fused CPU kernel's arrays (:mod:`torchpf.kinematics._fk_cpu`) in ``dtype``, built once."""

        def build():
            M = self.tree.n_nodes
            kmax = max(1, max(len(sig) for sig in self._groups))
            P = max(W.shape[2] for W, _ in self._coefficients)
            coef = torch.zeros(M, 12 + 6 * kmax, P, dtype=torch.float64)
            dofs = torch.full((M, kmax), -1, dtype=torch.long)
            kinds = torch.zeros(M, kmax, dtype=torch.long)
            pivots = torch.zeros(M, dtype=torch.bool)
            # the groups' nodes, concatenated in group order: the inverse of the level-order permutation
            concat = torch.arange(M) if self._fk_reorder is None else torch.argsort(self._fk_reorder.cpu())
            start = 0
            for g, ((W, WA), sig) in enumerate(zip(self._coefficients, self._groups, strict=True)):
                members = concat[start : start + W.shape[0]]
                start += W.shape[0]
                rows = W if WA is None else WA
                coef[members, : rows.shape[1], : rows.shape[2]] = rows
                if sig:
                    dofs[members, : len(sig)] = getattr(self, f"_fk_dofs{g}").cpu()
                    kinds[members, : len(sig)] = torch.tensor([int(k == _PRISMATIC) for k in sig])
                pivots[members] = self._axis_pivots[g]
            coef = coef.to(dtype)  # the coefficients' rounding of the tensor version (cast once, as it does)
            parent = self.tree.node_parent.cpu()
            return _fk_cpu.Structure(
                parent.numpy(),
                dofs.numpy(),
                kinds.numpy(),
                coef.numpy(),
                pivots.numpy(),
                len(self.dof_names),
                dtype,
            )

        return self.tree.cached(("fk_fused", dtype), build)

    def _world(self, theta: torch.Tensor, axes: bool = False):
        """World 3x4 transforms (M, 3, 4, B) of every internal node, level order; ``theta`` is (B, D).

        Batch-last layout: every elementwise product below runs over contiguous B-long rows, which on a CPU
        is several times faster than batched 3x3 ``bmm``. With ``axes=True`` also returns every DOF's world
        axis and pivot, each ``(D, 3, B)`` (see :meth:`dof_axes`): the same monomial products give the axes
        (and the pivots that are not a node's origin) in the run's parent frame (rows ``WA``), one rotation
        takes them to the world. Where autograd does not track ``theta`` on a CPU the fused kernel
        (:mod:`torchpf.kinematics._fk_cpu`) computes the same, equal to rounding.
        """
        if _fk_cpu.applies(theta):  # no autograd on a CPU: one fused kernel instead of ~130 operations
            return _fk_cpu.world(self._fused_structure(theta.dtype), theta, axes)
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
        loc = loc.view(loc.shape[0], 3, 4, B)  # explicit sizes: B may be 0 (an empty batch)
        col3 = c["col3"]

        def compose(P, L):  # [R_p | t_p] @ [[R_l, t_l], [0, 1]] = [R_p R_l | R_p t_l + t_p]
            T = torch.addcmul(P * col3, P[:, :, 0:1], L[:, 0:1])
            T = torch.addcmul(T, P[:, :, 1:2], L[:, 1:2])
            return torch.addcmul(T, P[:, :, 2:3], L[:, 2:3])

        def compose_few(P, L):  # the same in fewer, larger operations (small batches)
            return torch.addcmul((P[:, :, :3].unsqueeze(3) * L.unsqueeze(1)).sum(2), P, col3)

        few = B * loc.shape[0] <= _JUMP_MAX_ROWS
        if few and len(c["jumps"]) < len(c["levels"]) - 1:
            # few poses: the operations' count is the cost, pointer jumping takes fewer rounds (constants)
            ext = torch.cat([loc, c["eye34"].expand(1, 3, 4, B)], 0)
            for anc in c["jumps"]:
                ext = compose_few(ext.index_select(0, anc), ext)
            world = ext[:-1]
            if not axes:
                return world
        else:
            levels = []
            for start, end, parent_rows in c["levels"]:
                L = loc[start:end]
                if parent_rows is not None:
                    prev = levels[-1]
                    P = (
                        prev[parent_rows]
                        if isinstance(parent_rows, slice)
                        else prev.index_select(0, parent_rows)
                    )
                    L = compose(P, L)
                levels.append(L)
            if not axes:
                return torch.cat(levels, 0) if len(levels) > 1 else levels[0]
            # the parent frames of the runs, a root's being the identity (an appended row)
            ext = torch.cat([*levels, c["eye34"].expand(1, 3, 4, B)], 0)
            world = ext[:-1]
        axis_parts, pivot_parts = [], [world[:, :, 3]]
        for g, v in run_axes:
            P = ext.index_select(0, c[f"par{g}"])  # (n, 3, 4, B)
            n, m = v.shape[0], len(self._groups[g])
            v = v.view(n, v.shape[1] // 3, 3, B)  # (n, m or 2m, 3, B)
            if few:  # the rotation as one product and one sum (fewer operations, a larger temporary)
                w = (P[:, None, :, :3] * v.unsqueeze(2)).sum(3)
            else:
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
        return flatten_batch(theta, 1)

    # ------------------------------------------------------------------ public API
    def rest_joints(self) -> torch.Tensor:
        """(J, 3) world positions (m) of the body joints in the rest pose (every DOF at 0), float64, detached:
        what the structure-derived parts of the library (the partition, mirror limbs, arms, collision
        pairs) read the body's layout from."""
        with torch.no_grad():
            return self.fk(torch.zeros(len(self.dof_names), dtype=torch.float64))

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
        return unflatten_batch(t.permute(2, 0, 1), batch)

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
        return unflatten_batch(torch.cat([T, bottom], -2), batch)

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
        return unflatten_batch(axes.permute(2, 0, 1), batch), unflatten_batch(pivots.permute(2, 0, 1), batch)

    def fk_with_axes(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Joint positions and DOF axes in one FK pass, *batch last*: what a solver linearises.

        The layout of the IK solver and the tree Jacobian (:mod:`torchpf.kinematics.jacobian`), whose small
        3-vector algebra runs over contiguous ``B``-long rows.

        Args:
            theta: (B, D) poses.

        Returns:
            ``axes`` (D, 3, B) and ``pivots`` (D, 3, B) as in :meth:`dof_axes`, and ``joints`` (J, 3, B) the
            body-joint positions (m) of :meth:`fk`.
        """
        flat, _ = self._flat(theta)
        world, axes, pivots = self._world(flat, axes=True)
        return axes, pivots, self._body(world[:, :, 3], flat)

    @property
    def dof_revolute(self) -> torch.Tensor:
        """(D,) bool: True for a revolute DOF (radians), False for a prismatic one (metres), from the URDF
        joint types (never from names): ``tree.dof_revolute``."""
        return self.tree.dof_revolute.clone()

    @property
    def posture_dofs(self) -> torch.Tensor:
        """(D,) bool: the revolute DOFs that are not the root joint's (the root's place where the person is
        and which way they face; these shape the body), from the tree (never from names)."""
        joint = self.tree.dof_joint
        root = (joint >= 0) & (self.tree.parents[joint.clamp_min(0)] < 0)  # -1: a DOF below every joint
        return self.dof_revolute & ~root

    def free_rotations(self, full_turn: float = 1.9 * math.pi) -> list[str]:
        """Names of the :attr:`posture_dofs` whose limits span at least ``full_turn`` rad (or are absent):
        a skeleton converted from BVH has only those (BVH has no limits; ``python -m training fit-limits``
        learns them from mocap)."""
        span = (self.upper - self.lower).cpu()
        free = self.posture_dofs.cpu() & ~(span < full_turn)
        return [self.dof_names[d] for d in torch.nonzero(free).flatten().tolist()]

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
        idx = self.tree.bones.to(joints.device)
        ends = joints[..., idx, :]  # (..., C, 2, 3)
        return ends, self.radii.to(device=joints.device, dtype=joints.dtype)

    # ------------------------------------------------------------------ body shape
    def _body_xml(self, radii=None, scale: float = 1.0, lengths=None) -> str:
        """URDF text of this skeleton with capsule radii ``radii`` (C,) m before ``scale``, global ``scale``
        and per-joint bone-length factors ``lengths`` (J,); see :meth:`with_body`."""
        scale = float(scale)
        r = self.radii if radii is None else self._per_bone(radii)
        l_joint = torch.ones(len(self.joint_names), dtype=torch.float64)
        if lengths is not None:
            if isinstance(lengths, Mapping):
                unknown = sorted(set(lengths) - set(self.joint_names))
                if unknown:
                    raise ValueError(f"with_body: lengths names no body joint: {unknown}")
                for name, f in lengths.items():
                    l_joint[self.joint_names.index(name)] = float(f)
            else:
                l_joint = torch.as_tensor(lengths, dtype=torch.float64).reshape(-1)
                if l_joint.shape != (len(self.joint_names),):
                    raise ValueError(f"with_body: lengths must have shape ({len(self.joint_names)},)")
        if not scale > 0 or not bool((l_joint > 0).all()) or not bool((r > 0).all()):
            raise ValueError("with_body: scale, lengths and radii must be > 0")
        root = parse_urdf_xml(self.urdf_xml, self.source)
        joint_above = {j.find("child").get("link"): j.get("name") for j in root.iter("joint")}
        frames = flatten_chain(self.chain)
        frame_of = {f.name: i for i, f in enumerate(frames)}
        joint_scales = {}
        for c, p in enumerate(self.parents):
            if p < 0 or float(l_joint[c]) == 1.0:
                continue
            # the URDF joints of the run between the parent body joint and this one carry the offset
            i, stop = frame_of[self.joint_names[c]], frame_of[self.joint_names[p]]
            while i != stop:
                joint_scales[joint_above[frames[i].name]] = float(l_joint[c])
                i = frames[i].parent
        T = self.transforms(torch.zeros(len(self.dof_names), dtype=torch.float64))
        capsules: dict[str, list] = {}
        for (p, c), radius in zip(self.bones, r.tolist(), strict=True):
            offset = T[p, :3, :3].t() @ (T[c, :3, 3] - T[p, :3, 3]) * scale * float(l_joint[c])
            capsules.setdefault(self.joint_names[p], []).append(
                (self.joint_names[c], offset.tolist(), radius * scale)
            )
        return rebody_urdf(
            self.urdf_xml, scale=scale, joint_scales=joint_scales, capsules=capsules, source=self.source
        )

    def _per_bone(self, radii) -> torch.Tensor:
        if isinstance(radii, Mapping):
            children = [self.joint_names[c] for _, c in self.bones]
            unknown = sorted(set(radii) - set(children))
            if unknown:
                raise ValueError(f"with_body: radii names no bone (child joint): {unknown}")
            current = self.radii.tolist()
            return torch.tensor([float(radii.get(n, r)) for n, r in zip(children, current, strict=True)])
        r = torch.as_tensor(radii, dtype=torch.float64).detach().cpu().reshape(-1)
        if r.shape != (len(self.bones),):
            raise ValueError(f"with_body: radii must have shape ({len(self.bones)},) in bones order")
        return r

    def with_body(self, *, radii=None, scale: float = 1.0, lengths=None) -> Skeleton:
        """A new skeleton with the same DOFs and joints and another body shape.

        Args:
            radii: capsule radii (m) before ``scale``: (C,) in ``bones`` order, or a mapping child body
                joint name -> radius (the bones not named keep theirs); None keeps ``self.radii``.
            scale: global factor (> 0) on every bone offset (so every bone length) and on the radii. Pose
                vectors keep their meaning: ``with_body(scale=s).fk(theta) == s * fk(theta')`` with the
                prismatic DOFs of ``theta'`` divided by ``s``.
            lengths: bone-length factors (> 0): (J,) per body joint (the bone ending there) or a mapping
                body joint name -> factor; the root's is ignored.

        The new skeleton is built from this one's URDF rewritten by
        :func:`~torchpf.kinematics.urdf.rebody_urdf` (its ``urdf_xml``), so :meth:`save_urdf` and
        :meth:`from_urdf` give it back as it is.
        """
        return self._rebuilt(self._body_xml(radii, scale, lengths))

    def with_limits(self, lower=None, upper=None) -> Skeleton:
        """A new skeleton with the same body and other joint limits: ``lower``, ``upper`` (D,) tensors in
        :attr:`dof_names` order (rad or m; ``+-inf`` or NaN entries keep this skeleton's limit), or None to
        keep them all. Written into the URDF (:func:`~torchpf.kinematics.urdf.relimit_urdf`), so
        :meth:`save_urdf` keeps them; :func:`training.limits.fit_limits` learns them from mocap."""
        D = len(self.dof_names)
        new = {}
        for name, given, own in (("lower", lower, self.lower), ("upper", upper, self.upper)):
            given = own if given is None else torch.as_tensor(given, dtype=torch.float64).reshape(-1).cpu()
            if given.shape != (D,):
                raise ValueError(f"with_limits: {name} must have shape ({D},), got {tuple(given.shape)}")
            new[name] = torch.where(torch.isfinite(given), given, own.cpu())
        bad = [self.dof_names[d] for d in torch.nonzero(new["lower"] > new["upper"]).flatten().tolist()]
        if bad:
            raise ValueError(f"with_limits: lower > upper for {bad[:5]}")
        changed = (new["lower"] != self.lower.cpu()) | (new["upper"] != self.upper.cpu())
        finite = torch.isfinite(new["lower"]) & torch.isfinite(new["upper"])
        limits = {
            self.dof_names[d]: (float(new["lower"][d]), float(new["upper"][d]))
            for d in torch.nonzero(changed & finite).flatten().tolist()
        }
        if bool((changed & ~finite).any()):
            raise ValueError("with_limits: a DOF given a limit needs finite limits on both sides")
        return self._rebuilt(relimit_urdf(self._body_xml(), limits, source=self.source))

    def _rebuilt(self, xml: str) -> Skeleton:
        """A skeleton read from ``xml``, a rewrite of this one's URDF (same joints, same source)."""
        return Skeleton(build_chain(xml, self.source), xml, joint_names=self.joint_names, source=self.source)

    def save_urdf(self, path: str | os.PathLike) -> None:
        """Write this skeleton as URDF, atomically: the URDF it was read from with one ``<collision
        name="CHILD">`` cylinder per bone holding the current radius, so that :meth:`from_urdf` reloads the
        same DOFs, limits, FK and radii (whatever the radii came from: URDF, a ``radii`` table, the
        ``0.15 x`` length default or :meth:`with_body`)."""
        from torchpf.io import write_text_atomic

        write_text_atomic(path, self._body_xml())

    def extra_repr(self) -> str:
        return (
            f"source={self.source!r}, D={len(self.dof_names)}, J={len(self.joint_names)}, C={len(self.bones)}"
        )
