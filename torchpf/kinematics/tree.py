"""The kinematic tree of a skeleton as public index tensors, shared by FK, the IK Jacobian and the ABA.

A URDF chain (:func:`torchpf.kinematics.urdf.flatten_chain`) is flattened once into a
:class:`KinematicTree`: who is whose parent, which DOFs move which node, the depth levels the FK kernel
walks, the revolute mask, the capsule bones, which body joint owns each DOF and the torso/limb partition.
:class:`torchpf.skeleton.Skeleton` builds it (``skel.tree``); the fused FK kernel, the tree Jacobian
(:mod:`torchpf.kinematics.jacobian`), the articulated-body solve (:mod:`torchpf.kinematics.aba`), the IK loop
and the partitioned filters read it instead of reaching into the skeleton. The same idea as
pytorch-kinematics' ``Chain`` (a tree flattened into index tensors that its Jacobian and IK consume), with
the body joints, the fused runs of single-DOF URDF joints and the depth levels made explicit.

Two index spaces:

* **body joints** ``J``: the links whose origin is an anatomical joint (``Skeleton.joint_names``);
* **nodes** ``M``: the body joints plus the frames that branch (several children, or a child with an
  offset), each with the run of single-DOF URDF joints between it and its parent node. Nodes are in *level
  order*: depth by depth, so that each depth is one contiguous block of rows (the FK kernel multiplies one
  block at a time) and every parent row comes before its children.

Example::

    tree = skel.tree
    tree.parents                                  # (J,) parent body joint, -1 for the root
    moved_by = tree.dof_moves[:, j]               # (D,) the DOFs that move body joint j
    groups = body_partition(skel, per_limb=True)  # DOF indices: torso, then each limb
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from typing import TypeVar

import torch
from torch import Tensor, nn

from torchpf.kinematics.urdf import is_identity

T = TypeVar("T")


class KinematicTree(nn.Module):
    """A skeleton's tree topology as index tensors (buffers: ``.to(device)`` moves them); frozen.

    Fields (``J`` body joints, ``M`` nodes in level order, ``D`` DOFs, ``C`` bones, ``L`` depth levels,
    ``K`` the longest run of DOFs above a node; all ``long`` unless said otherwise):

    * ``parents`` (J,): parent body joint, -1 for a root; parents come before children.
    * ``joint_node`` (J,): the node row of each body joint.
    * ``bones`` (C, 2): (parent, child) body joints of each capsule (zero-length bones left out).
    * ``joint_part`` (J,): the body partition (Fontmarty Table 2): 0 for the torso chain, ``k >= 1`` for the
      ``k``-th limb hanging off it (in the order met from the root up), -1 for a joint in neither (another
      root's tree); see :func:`body_partition`.
    * ``node_parent`` (M,): parent node row, -1 for a root.
    * ``node_frame`` (M,): the frame of each node in :func:`~torchpf.kinematics.urdf.flatten_chain` order.
    * ``node_dofs`` (M, K): the DOFs of the run of URDF joints above each node, root side first, padded
      with -1 (a node without DOFs is all -1).
    * ``level_starts`` (L + 1,): depth ``l`` is the node rows ``level_starts[l]:level_starts[l + 1]``.
    * ``dof_node`` (D,): the node whose run holds each DOF, -1 for a DOF below every body joint.
    * ``dof_joint`` (D,): the body joint each DOF moves first (the joint at the end of its run), -1 as above.
    * ``dof_revolute`` (D,) bool: revolute (radians) or prismatic (metres), from the URDF joint types.
    * ``dof_moves`` (D, J) bool: DOF ``d`` moves body joint ``j`` (``j`` lies below ``d``): the sparsity
      pattern of the Jacobian ``d fk / d theta``.

    Derived constants (a tensor in a compute dtype, an index on another device, a structure built from the
    fields) are memoised with :meth:`cached`, the one cache the kinematics code keeps.
    """

    parents: Tensor
    joint_node: Tensor
    bones: Tensor
    joint_part: Tensor
    node_parent: Tensor
    node_frame: Tensor
    node_dofs: Tensor
    level_starts: Tensor
    dof_node: Tensor
    dof_joint: Tensor
    dof_revolute: Tensor
    dof_moves: Tensor

    FIELDS = (
        "parents",
        "joint_node",
        "bones",
        "joint_part",
        "node_parent",
        "node_frame",
        "node_dofs",
        "level_starts",
        "dof_node",
        "dof_joint",
        "dof_revolute",
        "dof_moves",
    )

    def __init__(self, **fields: Tensor):
        super().__init__()
        missing = set(self.FIELDS) - set(fields)
        unknown = set(fields) - set(self.FIELDS)
        if missing or unknown:
            raise TypeError(f"KinematicTree: missing fields {sorted(missing)}, unknown {sorted(unknown)}")
        for name in self.FIELDS:
            self.register_buffer(name, torch.as_tensor(fields[name]), persistent=False)
        J, D, M = len(self.parents), len(self.dof_revolute), len(self.node_parent)
        shapes = {
            "joint_node": (J,),
            "joint_part": (J,),
            "node_frame": (M,),
            "dof_node": (D,),
            "dof_joint": (D,),
            "dof_moves": (D, J),
        }
        for name, shape in shapes.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"KinematicTree.{name}: shape {tuple(getattr(self, name).shape)} != {shape}")
        self._cache: dict = {}
        self._frozen = True

    def __setattr__(self, name, value):
        # nn.Module sets ``training`` (train/eval) and private bookkeeping; the fields stay as built
        if getattr(self, "_frozen", False) and not (name == "training" or name.startswith("_")):
            raise AttributeError(f"KinematicTree is frozen: use .replace({name}=...) for a modified copy")
        super().__setattr__(name, value)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_frames(cls, frames: Sequence, body: Sequence[int], n_dofs: int) -> KinematicTree:
        """The tree of the body joints ``body`` (frame indices, depth-first) over a flattened chain.

        ``frames``: :class:`~torchpf.kinematics.urdf.Frame` records, parents before children. Nodes are the
        body joints plus the frames that cannot be folded into their single child's run (several children,
        or a child whose origin is not the identity). ``bones`` and ``joint_part`` need the rest pose: they
        start empty (no bones, every joint in no part) and :meth:`replace` sets them.
        """
        body_set = set(body)

        def foldable(i):
            f = frames[i]
            return i not in body_set and len(f.children) == 1 and is_identity(frames[f.children[0]].static)

        needed = set(body)
        for i in body:
            j = frames[i].parent
            while j >= 0 and j not in needed:
                if not foldable(j):
                    needed.add(j)
                j = frames[j].parent
        nodes = sorted(needed)
        node_of = {f: n for n, f in enumerate(nodes)}
        parent, runs, depth = [], [], []
        for i in nodes:
            j = frames[i].parent
            run = [i]
            while j >= 0 and j not in needed:
                run.append(j)
                j = frames[j].parent
            parent.append(node_of[j] if j >= 0 else -1)
            runs.append([frames[k].dof for k in reversed(run) if frames[k].dof >= 0])
            depth.append(0 if parent[-1] < 0 else depth[parent[-1]] + 1)

        # Level order: siblings by their parent's rank, so that a level's parents are often one contiguous
        # block (a slice, no gather, in the FK kernel).
        order: list[int] = []
        starts = [0]
        for d in range(max(depth) + 1):
            at_d = [n for n in range(len(nodes)) if depth[n] == d]
            prev_rank = {n: r for r, n in enumerate(order)}
            order += sorted(at_d, key=lambda n: (prev_rank.get(parent[n], -1), n))
            starts.append(len(order))
        rank = {n: r for r, n in enumerate(order)}

        kmax = max((len(r) for r in runs), default=0)
        node_dofs = torch.full((len(order), kmax), -1, dtype=torch.long)
        dof_node = torch.full((n_dofs,), -1, dtype=torch.long)
        for r, n in enumerate(order):
            node_dofs[r, : len(runs[n])] = torch.tensor(runs[n], dtype=torch.long)
            dof_node[runs[n]] = r
        node_parent = [rank[parent[n]] if parent[n] >= 0 else -1 for n in order]

        revolute = [False] * n_dofs
        for f in frames:
            if f.dof >= 0:
                revolute[f.dof] = f.joint_type == "revolute"

        # dof_joint[d]: the body joint whose run (the URDF joints between it and its parent joint) holds d
        parents, dof_joint = [], [-1] * n_dofs
        for b, i in enumerate(body):
            j = i
            while True:
                if frames[j].dof >= 0:
                    dof_joint[frames[j].dof] = b
                j = frames[j].parent
                if j < 0 or j in body_set:
                    break
            parents.append(body.index(j) if j >= 0 else -1)

        joint_node = torch.tensor([rank[node_of[i]] for i in body], dtype=torch.long)
        # desc[a, b]: node b lies in the subtree of node a (a included)
        M = len(order)
        desc = torch.zeros(M, M, dtype=torch.bool)
        for b in range(M):
            a = b
            while a >= 0:
                desc[a, b] = True
                a = node_parent[a]
        dof_moves = desc[dof_node.clamp(min=0)][:, joint_node] & (dof_node >= 0)[:, None]
        return cls(
            parents=torch.tensor(parents, dtype=torch.long),
            joint_node=joint_node,
            bones=torch.zeros(0, 2, dtype=torch.long),
            joint_part=torch.full((len(body),), -1, dtype=torch.long),
            node_parent=torch.tensor(node_parent, dtype=torch.long),
            node_frame=torch.tensor([nodes[n] for n in order], dtype=torch.long),
            node_dofs=node_dofs,
            level_starts=torch.tensor(starts, dtype=torch.long),
            dof_node=dof_node,
            dof_joint=torch.tensor(dof_joint, dtype=torch.long),
            dof_revolute=torch.tensor(revolute, dtype=torch.bool),
            dof_moves=dof_moves,
        )

    def replace(self, **changes: Tensor) -> KinematicTree:
        """A copy with some fields replaced (the others shared); its cache starts empty."""
        return type(self)(**{name: changes.get(name, getattr(self, name)) for name in self.FIELDS})

    # ------------------------------------------------------------------ sizes and views
    @property
    def n_joints(self) -> int:
        """``J``, the number of body joints."""
        return len(self.parents)

    @property
    def n_dofs(self) -> int:
        """``D``, the number of DOFs."""
        return len(self.dof_revolute)

    @property
    def n_nodes(self) -> int:
        """``M``, the number of nodes."""
        return len(self.node_parent)

    def node_runs(self) -> list[list[int]]:
        """The DOFs of each node's run (``node_dofs`` without the padding), root side first."""
        return [[d for d in row if d >= 0] for row in self.node_dofs.tolist()]

    def levels(self) -> list[tuple[int, int]]:
        """``(start, end)`` node rows of each depth level."""
        s = self.level_starts.tolist()
        return list(zip(s[:-1], s[1:], strict=True))

    # ------------------------------------------------------------------ the one cache
    def cached(self, key: Hashable, build: Callable[[], T]) -> T:
        """``build()``, computed once per ``key`` and kept: the one cache of derived constants.

        The kinematics code keys it by purpose, dtype and device (e.g. ``("fk", torch.float32, device)``)
        so that a kernel's constants are converted once, not per call. The tree is frozen, so an entry
        never goes stale.
        """
        value = self._cache.get(key)
        if value is None:
            value = build()
            self._cache[key] = value
        return value

    def extra_repr(self) -> str:
        return (
            f"J={self.n_joints}, D={self.n_dofs}, M={self.n_nodes}, C={len(self.bones)}, "
            f"levels={len(self.level_starts) - 1}"
        )


def children_of(parents: Sequence[int]) -> dict[int, list[int]]:
    """``{j: [children of j]}`` for every joint of a parent list (``-1`` for a root), children in index
    order."""
    children: dict[int, list[int]] = {j: [] for j in range(len(parents))}
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    return children


def subtree_of(children: dict[int, list[int]], j: int) -> list[int]:
    """Joint ``j`` and every joint below it (depth first), from a :func:`children_of` map."""
    out = [j]
    for c in children[j]:
        out += subtree_of(children, c)
    return out


def partition_labels(parents: Sequence[int], rest: Tensor) -> Tensor:
    """``joint_part`` (J,) of :class:`KinematicTree`: 0 torso, ``k`` the ``k``-th limb, -1 neither.

    The torso is the chain from the (first) root towards the highest joint in the rest pose (pelvis, spine,
    neck, head): at each torso joint it continues along the child whose subtree reaches highest (largest
    ``z``); every other child's subtree is a limb (legs, arms), numbered in the order met from the root up.
    ``rest`` (J, 3): body-joint positions (m) in the rest pose.
    """
    parents = list(parents)
    J = len(parents)
    children = children_of(parents)

    def subtree(j):
        return subtree_of(children, j)

    labels = [-1] * J
    if -1 not in parents:
        return torch.tensor(labels, dtype=torch.long)
    j, limb = parents.index(-1), 0
    while True:
        labels[j] = 0
        if not children[j]:
            break
        best = max(children[j], key=lambda c: float(rest[subtree(c), 2].max()))
        for c in children[j]:
            if c != best:
                limb += 1
                for k in subtree(c):
                    labels[k] = limb
        j = best
    return torch.tensor(labels, dtype=torch.long)


def body_partition(skeleton, *, per_limb: bool = False, joints: bool = False) -> list[list[int]]:
    """Index groups for partitioned sampling (Fontmarty Table 2): the torso first, then the limbs.

    The torso is the chain from the root towards the highest joint in the rest pose (pelvis, spine, neck,
    head), with the root's DOFs; each subtree hanging off that chain (legs, arms) is a limb
    (:func:`partition_labels`, stored as ``skeleton.tree.joint_part``). Fontmarty §3.3.2 uses two
    partitions: the torso, then all the limbs together (``per_limb=False``); ``per_limb=True`` gives one
    partition per limb.

    Args:
        skeleton: a :class:`~torchpf.skeleton.Skeleton` or its :class:`KinematicTree`.

    Returns:
        DOF indices per partition (ascending; every DOF that moves a body joint of the root's tree exactly
        once), or body-joint indices with ``joints=True``. Empty groups are left out.
    """
    tree = skeleton if isinstance(skeleton, KinematicTree) else skeleton.tree
    part = tree.joint_part.tolist()
    n_limbs = max(part, default=0)
    torso = [j for j, p in enumerate(part) if p == 0]
    limbs = [[j for j, p in enumerate(part) if p == k] for k in range(1, n_limbs + 1)]
    joint_groups = [torso] + (limbs if per_limb else [[j for limb in limbs for j in limb]])
    if joints:
        return [g for g in joint_groups if g]
    owner = tree.dof_joint.tolist()
    groups = [[d for d, j in enumerate(owner) if j >= 0 and part[j] == k] for k in range(n_limbs + 1)]
    if not per_limb:
        groups = [groups[0], [d for d, j in enumerate(owner) if j >= 0 and part[j] > 0]]
    return [g for g in groups if g]
