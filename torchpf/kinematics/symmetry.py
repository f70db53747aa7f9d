"""Mirror-image limbs from the skeleton's structure, and the move that swaps them.

Silhouettes do not tell the left leg from the right one: a walker seen with the legs swapped (the left leg
where the right one is, mirrored) casts nearly the same masks, and a tracker that takes the wrong pair keeps
it for a stride or more. In the lost tracks of foreign renders with mask defects that was the failure
(BENCHMARKS.md, "Swapped limbs"): each foot 0.4-0.9 m off its own truth and within 0.05-0.15 m of the other
foot's (CMU 07_01, 35_02, 35_24, 16_21), and in 35_02 later the hands. :func:`limb_swaps` gives the swap
of each mirror pair as a map on the DOFs, so that a filter can try the swapped hypothesis
(:class:`~torchpf.filters.HybridParticleFilter`'s ``swaps``).

Everything comes from the tree and the rest pose, never from joint names:

* :func:`mirror_limbs` pairs the limbs that hang off the torso (:func:`~torchpf.kinematics.body_partition`)
  with the same tree shape whose rest-pose joints are mirror images across the plane half-way between them.
* :func:`limb_swaps` maps each DOF of one limb to the DOF of its mirror at the corresponding joint and place
  in the joint's chain. A reflection ``M`` turns a rotation by ``q`` about axis ``a`` into a rotation by
  ``-q`` about ``M a`` (it reverses handedness), so where the mirror DOF's rest axis is ``s M a``
  (``s = +-1``), the mirrored angle is ``-s q``; a prismatic DOF keeps its sign: ``s q``. Composed down the
  limb's chain this reproduces the reflected limb exactly when the rest pose is symmetric.

Example::

    from torchpf.kinematics.symmetry import limb_swaps
    swaps = limb_swaps(skel)             # e.g. [legs, arms] of a humanoid
    swapped = swaps[0](theta)            # (..., D): the two legs exchanged, mirrored
"""

from __future__ import annotations

import torch
from torch import nn

from torchpf.kinematics.tree import body_partition, children_of

__all__ = ["LimbSwap", "limb_swaps", "mirror_limbs"]


def _shape(j: int, kids) -> str:
    """Canonical string of the subtree's topology (children sorted), the same for a limb and its mirror."""
    return "(" + "".join(sorted(_shape(c, kids) for c in kids[j])) + ")"


def _canonical(j: int, kids, rest: torch.Tensor) -> list[int]:
    """The joints of the subtree of ``j`` depth-first, siblings ordered by shape then bone length: an order
    in which a limb and its mirror list corresponding joints at the same positions."""
    order = [j]
    key = lambda c: (_shape(c, kids), round(float((rest[c] - rest[j]).norm()), 3))  # noqa: E731
    for c in sorted(kids[j], key=key):
        order += _canonical(c, kids, rest)
    return order


def _mirror_normal(a: list[int], b: list[int], rest: torch.Tensor, kids, tol: float) -> torch.Tensor | None:
    """Unit normal (3,) of the plane across which limb ``a`` (canonical joint order) reflected lands on limb
    ``b`` in the rest pose within ``tol`` x the limb's size, or None: the plane half-way between the limbs'
    centroids."""
    if len(a) != len(b) or _shape(a[0], kids) != _shape(b[0], kids):
        return None
    pa, pb = rest[a], rest[b]
    size = float((pa - pa[0]).norm(dim=-1).max()) + 1e-6
    normal = pb.mean(0) - pa.mean(0)
    if float(normal.norm()) < 1e-6:
        return None
    normal = normal / normal.norm()
    mid = 0.5 * (pa.mean(0) + pb.mean(0))
    reflected = pa - 2 * ((pa - mid) @ normal)[:, None] * normal
    if float((reflected - pb).norm(dim=-1).max()) > tol * size:
        return None
    return normal


def mirror_limbs(
    skeleton, *, tol: float = 0.1
) -> list[tuple[list[int], list[int] | None, torch.Tensor | None]]:
    """Each limb hanging off the torso with its mirror image, if it has one.

    Args:
        skeleton: a :class:`~torchpf.skeleton.Skeleton` (its tree, the torso/limb partition and ``fk``).
        tol: a limb reflected across the plane half-way between its centroid and its mirror's must land on
            the mirror's joints within ``tol`` x the limb's size (rest pose, all DOFs 0).

    Returns:
        One ``(joints, mirror_joints, normal)`` per limb, in the partition's order: the limb's joint indices
        in canonical order (corresponding joints at the same positions), its mirror's the same way (each
        pair listed once, at its first limb), and the mirror plane's unit normal (3,) in the rest pose
        (float64); a limb without a mirror has ``None`` for both.
    """
    tree = skeleton.tree
    parents = tree.parents.tolist()
    kids = children_of(parents)
    rest = skeleton.rest_joints().cpu()
    limbs = body_partition(tree, per_limb=True, joints=True)[1:]
    orders = []
    for limb in limbs:  # a limb's root is its joint whose parent is outside it (on the torso)
        members = set(limb)
        roots = [j for j in limb if parents[j] not in members]
        orders.append([j for r in roots for j in _canonical(r, kids, rest)])
    out, paired = [], set()
    for i, a in enumerate(orders):
        if i in paired:
            continue
        paired.add(i)
        found = None
        for k in range(i + 1, len(orders)):
            normal = None if k in paired else _mirror_normal(a, orders[k], rest, kids, tol)
            if normal is not None:
                paired.add(k)
                found = (orders[k], normal)
                break
        out.append((a, *found) if found else (a, None, None))
    return out


class LimbSwap(nn.Module):
    """Exchange of two mirror limbs on poses: ``x'[b] = sign x[a]`` and ``x'[a] = sign x[b]``, other DOFs
    unchanged (module docstring). A module, so that its index buffers follow the particles' device.

    Args:
        a, b: ``(k,)`` DOF indices of the two limbs, corresponding DOFs at the same positions.
        sign: ``(k,)`` ``-s`` for a revolute DOF and ``s`` for a prismatic one, ``s = +-1`` the orientation of
            the mirror DOF's axis relative to the reflected one.
    """

    def __init__(self, a, b, sign):
        super().__init__()
        self.register_buffer("a", torch.as_tensor(a, dtype=torch.long).reshape(-1))
        self.register_buffer("b", torch.as_tensor(b, dtype=torch.long).reshape(-1))
        self.register_buffer("sign", torch.as_tensor(sign, dtype=torch.float64).reshape(-1))
        if not (self.a.shape == self.b.shape == self.sign.shape):
            raise ValueError("a, b and sign must have the same length")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Poses ``x (..., D)`` with the two limbs exchanged (a new tensor, ``x``'s dtype and device)."""
        a, b = self.a.to(x.device), self.b.to(x.device)
        sign = self.sign.to(x)
        out = x.clone()
        out[..., b] = sign * x[..., a]
        out[..., a] = sign * x[..., b]
        return out


def limb_swaps(skeleton, *, tol: float = 0.1, axis_tol: float = 0.95) -> list[LimbSwap]:
    """The :class:`LimbSwap` of every mirror pair of :func:`mirror_limbs` whose DOFs correspond.

    Corresponding joints must carry as many DOFs, of the same kinds, whose rest-pose world axes are the
    reflected ones up to sign (``|cos| >= axis_tol``); a pair where one does not is left out (its swap would
    not be a mirror image). A pair without DOFs is left out too.

    Returns:
        The swaps, in the order of :func:`mirror_limbs` (for a humanoid: legs and arms, as the partition
        lists them).
    """
    rest = torch.zeros(len(skeleton.dof_names), dtype=torch.float64)
    axes, _ = skeleton.dof_axes(rest)
    axes = axes.detach().cpu().to(torch.float64)
    revolute = skeleton.dof_revolute.cpu()
    owner = list(skeleton.dof_joints)
    dofs_of: dict[int, list[int]] = {}
    for d, j in enumerate(owner):
        dofs_of.setdefault(int(j), []).append(d)
    swaps = []
    for joints, mirror, normal in mirror_limbs(skeleton, tol=tol):
        if mirror is None:
            continue
        reflect = torch.eye(3, dtype=torch.float64) - 2 * torch.outer(normal, normal)
        pa, pb, signs, ok = [], [], [], True
        for ja, jb in zip(joints, mirror, strict=True):
            da, db = dofs_of.get(ja, []), dofs_of.get(jb, [])
            if len(da) != len(db):
                ok = False
                break
            for u, v in zip(da, db, strict=True):
                cos = float(axes[v] @ (reflect @ axes[u]))
                if bool(revolute[u]) != bool(revolute[v]) or abs(cos) < axis_tol:
                    ok = False
                    break
                s = 1.0 if cos > 0 else -1.0
                pa.append(u)
                pb.append(v)
                signs.append(-s if bool(revolute[u]) else s)
            if not ok:
                break
        if ok and pa:
            swaps.append(LimbSwap(pa, pb, signs))
    return swaps
