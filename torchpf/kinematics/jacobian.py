"""The Jacobian of forward kinematics from the kinematic tree, and its products, batch last.

Every DOF ``d`` has a world axis ``a_d`` and a pivot ``p_d`` on it (:meth:`Skeleton.dof_axes`; the fused FK
kernel computes them with the joint positions in one pass, :meth:`Skeleton.fk_with_axes`). Its *twist*
about a centre ``c`` is ``(ω, v) = (a, (p - c) x a)`` (revolute) or ``(0, a)`` (prismatic): a point ``y``
(relative to ``c``) below the DOF moves with velocity ``v + ω x y`` per unit ``δθ_d``, and not at all if it
is not below (``tree.dof_moves``). So the Jacobian column of DOF ``d`` at joint ``j`` is
``a_d x (x_j - p_d)`` or ``a_d``, and its products with a step (``J δ``) or with forces (``Jᵀ W r``) sum
twists or wrenches over the tree instead of forming the ``(3J, D)`` matrix. :mod:`torchpf.ik` (Hauberg
eq. 7) and :mod:`torchpf.kinematics.aba` build on these.

Layout: per-pose quantities are *batch last*, ``(D, 6, B)``, ``(J, 3, B)``: the small-vector algebra is then
broadcast products over contiguous ``B``-long rows, which on a CPU is far faster than batched tiny
``bmm``/LAPACK calls (the same choice as the FK kernel).

Example::

    Jac = tree_jacobian(skel, theta)              # (..., J, 3, D), equal to autograd_jacobian to rounding
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchpf.distributions import flatten_batch, unflatten_batch
from torchpf.kinematics.tree import KinematicTree

#: below this many elements a contraction is one broadcast product (fewer operations beat smaller temporaries)
_SMALL = 1 << 13


def tree_constants(tree: KinematicTree, device, dtype) -> dict:
    """The tree's masks on ``device`` in ``dtype`` (cached on the tree): ``dof_mask`` (D, J) and its
    transpose ``anc_mask`` (J, D) as 0/1 floats, ``revolute`` (D, 1, 1) bool and ``revf`` its 0/1 float."""

    def build():
        dof_mask = tree.dof_moves.to(device=device, dtype=dtype)
        revolute = tree.dof_revolute.to(device)
        return {
            "dof_mask": dof_mask,
            "anc_mask": dof_mask.t().contiguous(),
            "revolute": revolute[:, None, None],
            "revf": revolute.to(dtype)[:, None, None],
        }

    return tree.cached(("jacobian", device, dtype), build)


def dof_frames(skeleton, theta: Tensor) -> tuple[Tensor, Tensor]:
    """DOF axes and pivots ``(D, 2, 3, B)`` and joint positions ``(J, 3, B)`` at ``theta (B, D)``, one FK."""
    axes, pivots, joints = skeleton.fk_with_axes(theta)
    return torch.stack([axes, pivots], 1), joints


def twists(tree: KinematicTree, ap: Tensor, centre: Tensor) -> Tensor:
    """World twists ``(D, 6, B)`` = (ω, v) of every DOF about a per-pose ``centre (3, B)``.

    A point at ``y`` (relative to the centre) moved by DOF ``d`` has velocity ``v_d + ω_d x y`` per unit
    ``δθ_d``: revolute ``ω = a``, ``v = p x a`` (axis ``a``, pivot ``p`` relative to the centre), prismatic
    ``ω = 0``, ``v = a``. ``ap (D, 2, 3, B)``: axes and pivots from :func:`dof_frames`.
    """
    c = tree_constants(tree, ap.device, ap.dtype)
    a = ap[:, 0]
    v = torch.where(c["revolute"], cross(ap[:, 1] - centre, a), a)
    return torch.cat([a * c["revf"], v], 1)


def cross(a: Tensor, b: Tensor, dim: int = 1) -> Tensor:
    """Cross product along ``dim`` (size 3), broadcasting; several times faster than ``torch.linalg.cross``
    on batch-last layouts on a CPU."""
    a0, a1, a2 = a.unbind(dim)
    b0, b1, b2 = b.unbind(dim)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim)


def dot(a: Tensor, b: Tensor, dim: int) -> Tensor:
    """``Σ_j a_j b_j`` over ``dim`` (a short dim, the same size in both), with broadcasting.

    Accumulated with ``addcmul`` one slice at a time: no temporary the size of the broadcast product, which
    is what bounds the speed of these small contractions on a CPU.
    """
    if max(a.numel(), b.numel()) < _SMALL:  # (torch.broadcast_shapes costs more than a small product)
        return (a * b).sum(dim)  # small batch: fewer operations beat smaller temporaries
    pairs = zip(a.unbind(dim), b.unbind(dim), strict=True)
    x, y = next(pairs)
    out = x * y
    for x, y in pairs:
        out = torch.addcmul(out, x, y)
    return out


def point_velocities(tree: KinematicTree, tw: Tensor, rel: Tensor, delta: Tensor) -> Tensor:
    """``J δ``: joint displacements ``(J, 3, B)`` for a step ``delta (D, B)`` (linearised).

    ``tw (D, 6, B)`` twists about a centre, ``rel (J, 3, B)`` joint positions relative to it.
    """
    anc_mask = tree_constants(tree, delta.device, delta.dtype)["anc_mask"]
    D, _, B = tw.shape
    V = (anc_mask @ (tw * delta[:, None]).reshape(D, 6 * B)).reshape(-1, 6, B)  # summed twist per joint
    return V[:, 3:] + cross(V[:, :3], rel)


def wrenches(rel: Tensor, w: Tensor, r: Tensor) -> Tensor:
    """Spatial forces ``(J, 6, B)`` = (moment, force) of the forces ``w_l r_l`` at the joints ``rel``.

    ``rel (J, 3, B)`` joint positions about the twists' centre, ``w (J, B)`` weights, ``r (J, 3, B)``.
    """
    wr = w[:, None] * r
    return torch.cat([cross(rel, wr), wr], 1)


def joint_torques(tree: KinematicTree, tw: Tensor, wrench: Tensor) -> Tensor:
    """``Jᵀ W r`` ``(D, B)``: per DOF, its twist dotted with the wrenches (:func:`wrenches`) below it."""
    dof_mask = tree_constants(tree, tw.device, tw.dtype)["dof_mask"]
    J, _, B = wrench.shape
    sub = (dof_mask @ wrench.reshape(J, 6 * B)).reshape(-1, 6, B)
    return dot(tw, sub, 1)


def pose_gradient(tree: KinematicTree, ap: Tensor, joints: Tensor, grad: Tensor) -> Tensor:
    """``Jᵀ g``: the gradient ``(D, B)`` in the pose of a function of the joint positions, from its gradient
    ``grad (J, 3, B)`` in them (the vector-Jacobian product of forward kinematics, summed over the tree by
    :func:`joint_torques` instead of back-propagated through the FK kernel: a few products for any depth).

    ``ap (D, 2, 3, B)`` and ``joints (J, 3, B)``: :func:`dof_frames` at the pose. Equals autograd through
    :meth:`Skeleton.fk` to rounding.
    """
    rel = joints - joints[:1]
    return joint_torques(tree, twists(tree, ap, joints[0]), torch.cat([cross(rel, grad), grad], 1))


def tree_jacobian(skeleton, theta: Tensor) -> Tensor:
    """Jacobian of :meth:`Skeleton.fk` from the kinematic tree: ``(..., D) -> (..., J, 3, D)``.

    Column ``d`` is ``a_d x (x_j - p_d)`` (revolute) or ``a_d`` (prismatic) for the joints ``j`` below DOF
    ``d`` and zero elsewhere (world axis ``a_d``, pivot ``p_d``, see :meth:`Skeleton.dof_axes`).
    """
    tree = skeleton.tree
    flat, batch = flatten_batch(theta, 1)
    ap, x = dof_frames(skeleton, flat)
    rel = x - x[:1]
    tw = twists(tree, ap, x[0])  # (D, 6, B)
    mask = tree_constants(tree, flat.device, flat.dtype)["dof_mask"]  # (D, J)
    cols = tw[:, None, 3:] + cross(tw[:, None, :3], rel[None], dim=2)
    cols = cols * mask[:, :, None, None]  # (D, J, 3, B)
    return unflatten_batch(cols.permute(3, 1, 2, 0), batch)


def autograd_jacobian(skeleton, theta: Tensor) -> Tensor:
    """Jacobian of :meth:`Skeleton.fk` by forward-mode autograd: ``(..., D) -> (..., J, 3, D)``.

    ``torch.func.jacfwd`` under ``vmap`` over the flattened poses, so each pose's Jacobian depends on that
    pose only. Costs about ``D`` forward kinematics; works for any skeleton.
    """
    flat, batch = flatten_batch(theta, 1)

    def one(th):
        return skeleton.fk(th[None])[0]

    return unflatten_batch(torch.func.vmap(torch.func.jacfwd(one))(flat), batch)  # (..., J, 3, D)
