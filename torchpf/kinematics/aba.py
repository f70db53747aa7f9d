"""The articulated-body solve of the Gauss-Newton system of a kinematic tree, in ``O(J)`` per pose.

The Gauss-Newton matrix ``JᵀWJ + diag(arm)`` of joint-position goals on a tree (:mod:`torchpf.ik`, Hauberg
eq. 7) is the joint-space inertia matrix of point masses ``w_l`` sitting at the joints, with ``arm`` as
joint armature, and ``JᵀW r`` is the joint torque of the forces ``w_l r_l`` applied at the joints. So the
step ``δ`` is that system's joint acceleration from rest: Featherstone's articulated-body algorithm (ABA),
here with world-frame spatial vectors (no coordinate transforms between bodies, the twists of
:mod:`torchpf.kinematics.jacobian`) and zero velocities. No ``(B, D, D)`` matrix is formed or factorised.

Two implementations of the same recursion: tensor operations one tree level at a time (any device,
autograd), and on a CPU without autograd one fused numba kernel (:mod:`torchpf.kinematics._aba_cpu`):
4-25x faster (``TORCHPF_FUSED=0`` in the environment selects the tensor one). :func:`dense_solve` solves the
same system from an explicit Jacobian (Cholesky), as a reference and for the autograd IK method.

The *bodies* of the recursion are the tree's nodes that own DOFs (``tree.node_dofs``); a joint at a node
without DOFs (an end site) is a point mass on the body of its nearest ancestor that has some.

Example::

    tw = twists(skel.tree, ap, x[0])                      # (D, 6, B)
    delta = aba_solve(skel.tree, tw, x - x[:1], w, r, tau, arm, free)   # (D, B)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchpf.devices import fused_cpu
from torchpf.kinematics.jacobian import dot, wrenches
from torchpf.kinematics.tree import KinematicTree


@dataclass(frozen=True)
class _Bodies:
    """The tree as the articulated-body recursion walks it (derived once from the tree, device-free).

    Bodies are grouped by depth, each body's DOFs padded to the level's widest run (index D = a dummy DOF
    with zero twist), each parent given as a position in the level above; ``delta_gather`` picks every real
    DOF out of the levels' concatenated solutions (a DOF in no body's run points at a zero row appended
    after them). ``point_body`` (J,): the body carrying each joint's point mass (-1: moved by no DOF,
    dropped).
    """

    n_bodies: int
    point_body: Tensor
    point_body_np: np.ndarray
    levels: list  # per depth: (members (n,), dofs (n k,), k, parent_pos (n,), has_parent)
    n_bodies_at: list[int]
    body_runs: list[list[int]]
    body_parent: list[int]
    delta_gather: Tensor

    @classmethod
    def of(cls, tree: KinematicTree) -> _Bodies:
        return tree.cached("aba", lambda: cls._build(tree))

    @classmethod
    def _build(cls, tree: KinematicTree) -> _Bodies:
        D = tree.n_dofs
        parent = tree.node_parent.tolist()
        runs = tree.node_runs()
        bodies = [n for n in range(len(parent)) if runs[n]]
        body_pos = {n: i for i, n in enumerate(bodies)}

        def body_above(n):
            while n >= 0 and n not in body_pos:
                n = parent[n]
            return body_pos.get(n, -1)

        point_body = torch.tensor([body_above(n) for n in tree.joint_node.tolist()], dtype=torch.long)
        body_parent = [body_above(parent[n]) for n in bodies]
        depth: list[int] = []
        for i in range(len(bodies)):  # parents come first (level order)
            depth.append(0 if body_parent[i] < 0 else depth[body_parent[i]] + 1)
        levels, n_bodies_at = [], []
        pos_in_level: dict[int, int] = {}
        flat: list[int] = []
        for d in range(max(depth) + 1 if depth else 0):
            members = [i for i in range(len(bodies)) if depth[i] == d]
            for p, i in enumerate(members):
                pos_in_level[i] = p
            k = max(len(runs[bodies[i]]) for i in members)
            dofs = torch.full((len(members), k), D, dtype=torch.long)
            for p, i in enumerate(members):
                dofs[p, : len(runs[bodies[i]])] = torch.tensor(runs[bodies[i]])
            flat += dofs.reshape(-1).tolist()
            parent_pos = torch.tensor(
                [pos_in_level.get(body_parent[i], 0) for i in members], dtype=torch.long
            )
            levels.append((torch.tensor(members, dtype=torch.long), dofs.reshape(-1), k, parent_pos, d > 0))
            n_bodies_at.append(len(members))
        where = {dof: i for i, dof in enumerate(flat) if dof < D}
        return cls(
            n_bodies=len(bodies),
            point_body=point_body,
            point_body_np=point_body.numpy().astype("int64"),
            levels=levels,
            n_bodies_at=n_bodies_at,
            body_runs=[runs[n] for n in bodies],
            body_parent=body_parent,
            delta_gather=torch.tensor([where.get(dof, len(flat)) for dof in range(D)], dtype=torch.long),
        )

    def kernel_structure(self, tree: KinematicTree):
        """The tree for the fused CPU kernel (:mod:`torchpf.kinematics._aba_cpu`), cached on the tree."""

        def build():
            from torchpf.kinematics import _aba_cpu

            return _aba_cpu.Structure(self.body_runs, self.body_parent)

        return tree.cached(("aba", "kernel"), build)

    def constants(self, device, dtype) -> dict:
        """The index and constant tensors on ``device`` (floats in ``dtype``)."""
        D, J = len(self.delta_gather), len(self.point_body)
        levels = []
        for li, (members, dofs, k, parent_pos, has) in enumerate(self.levels):
            valid = (dofs < D).to(dtype)
            # parent matrix: child contributions are summed into the level above with one product
            P = None
            if has:
                P = torch.zeros(self.n_bodies_at[li - 1], len(members), dtype=dtype)
                P[parent_pos, torch.arange(len(members))] = 1.0
                P = P.to(device)
            levels.append(
                (
                    members.to(device),
                    dofs.clamp(max=D - 1).to(device),
                    valid.to(device),
                    k,
                    P,
                    parent_pos.to(device),
                )
            )
        return {
            "levels": levels,
            "delta_gather": self.delta_gather.to(device),
            # (n_bodies + 1, J) 0/1: which body carries each joint's point mass (points moved by no DOF go
            # to the extra last row, which no level reads); a product with it sums points per body
            "point_body": torch.zeros(self.n_bodies + 1, J, dtype=dtype)
            .index_put_(
                (torch.where(self.point_body < 0, self.n_bodies, self.point_body), torch.arange(J)),
                torch.ones(J, dtype=dtype),
            )
            .to(device),
            "inertia_index": _inertia_index().to(device),
        }


def _constants(tree: KinematicTree, device, dtype) -> dict:
    """:meth:`_Bodies.constants` of ``tree``, cached on the tree."""
    return tree.cached(("aba", device, dtype), lambda: _Bodies.of(tree).constants(device, dtype))


def _inertia_index() -> Tensor:
    """(36,) rows of the 6x6 spatial inertia (row-major) in ``[M, -M, 0, Syy+Szz, Sxx+Szz, Sxx+Syy]``.

    ``M`` = the point-mass moments ``(m, hx, hy, hz, Sxx, Syy, Szz, Sxy, Sxz, Syz)`` (``m = Σ w``,
    ``h = Σ w y``, ``S = Σ w y yᵀ``); the inertia is ``[[tr(S) I - S, [h]x], [-[h]x, m I]]`` (the sum of
    ``w [[-[y]x², [y]x], [-[y]x, I]]``).
    """
    pos = {"m": 0, "hx": 1, "hy": 2, "hz": 3, "Sxy": 7, "Sxz": 8, "Syz": 9}
    zero, diag = 20, (21, 22, 23)

    def at(name, sign=1):
        return pos[name] + (10 if sign < 0 else 0)

    rows = [
        [diag[0], at("Sxy", -1), at("Sxz", -1), zero, at("hz", -1), at("hy")],
        [at("Sxy", -1), diag[1], at("Syz", -1), at("hz"), zero, at("hx", -1)],
        [at("Sxz", -1), at("Syz", -1), diag[2], at("hy", -1), at("hx"), zero],
        [zero, at("hz"), at("hy", -1), at("m"), zero, zero],
        [at("hz", -1), zero, at("hx"), zero, at("m"), zero],
        [at("hy"), at("hx", -1), zero, zero, zero, at("m")],
    ]
    return torch.tensor(rows, dtype=torch.long).reshape(36)


# Symmetric 3x3 inverse by cofactors, on the row-major entries m0..m8: cofactor c_ij = m[p] m[q] - m[r] m[s]
# (rows ``_COF``), determinant = row 0 of M dotted with row 0 of the cofactors.
_COF = torch.tensor(
    [[4, 8, 5, 7], [5, 6, 3, 8], [3, 7, 4, 6], [2, 7, 1, 8], [0, 8, 2, 6], [1, 6, 0, 7], [1, 5, 2, 4],
     [2, 3, 0, 5], [0, 4, 1, 3]]
).t().contiguous()  # fmt: skip


def inv_small(M: Tensor) -> Tensor:
    """Inverse of SPD matrices ``M (n, k, k, B)``: closed form for k <= 3, batched LAPACK otherwise."""
    n, k, _, B = M.shape
    if k == 1:
        return 1.0 / M
    if k == 3:
        flat = M.reshape(n, 9, B)
        idx = _COF.to(M.device)
        cof = flat.index_select(1, idx[0]) * flat.index_select(1, idx[1])
        cof = cof - flat.index_select(1, idx[2]) * flat.index_select(1, idx[3])  # (n, 9, B) row-major
        det = dot(flat[:, :3], cof[:, :3], 1)
        # adj(M) = cofactorsᵀ = cofactors for a symmetric M
        return (cof / det[:, None]).view(n, 3, 3, B)
    if k == 2:
        a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
        det = a * d - b * c
        return torch.stack([torch.stack([d, -b], 1), torch.stack([-c, a], 1)], 1) / det[:, None, None]
    # wider runs (a floating root): batched LAPACK on (n B, k, k); few such bodies per tree
    inv = torch.linalg.inv_ex(M.permute(0, 3, 1, 2).reshape(n * B, k, k))[0]
    return inv.reshape(n, B, k, k).permute(0, 2, 3, 1)


def body_inertia(tree: KinematicTree, rel: Tensor, w: Tensor) -> Tensor:
    """Spatial inertias ``(n_bodies + 1, 6, 6, B)`` of the joints as point masses ``w`` at ``rel``, per body.

    Summed as moments ``(Σ w, Σ w y, Σ w y yᵀ)`` per body, then arranged (:func:`_inertia_index`) as
    ``[[tr(S) I - S, [h]x], [-[h]x, m I]]``. The last row collects points that no DOF moves.
    """
    c = _constants(tree, rel.device, rel.dtype)
    J, B = rel.shape[0], rel.shape[-1]
    wy = w[:, None] * rel
    moments = torch.cat([w[:, None], wy, wy * rel, wy[:, [0, 0, 1]] * rel[:, [1, 2, 2]]], 1)  # (J, 10, B)
    M = (c["point_body"] @ moments.reshape(J, 10 * B)).view(-1, 10, B)
    S = M[:, 4:7]
    diag = S.sum(1, keepdim=True) - S  # tr(S) - S_ii
    table = torch.cat([M, -M, torch.zeros_like(M[:, :1]), diag], 1)
    return table.index_select(1, c["inertia_index"]).view(-1, 6, 6, B)


def aba_solve(
    tree: KinematicTree,
    tw: Tensor,
    rel: Tensor,
    w: Tensor,
    r: Tensor,
    tau: Tensor,
    arm: Tensor,
    free: Tensor,
    inertia: Tensor | None = None,
    wrench: Tensor | None = None,
) -> Tensor:
    """Solve ``(JᵀWJ + diag(arm)) δ = JᵀW r + tau`` over the ``free`` DOFs (others get ``δ = 0``), ``O(J)``.

    Batch-last arguments: ``tw (D, 6, B)`` twists, ``rel (J, 3, B)`` joint positions about the centre,
    ``w (J, B)`` weights, ``r (J, 3, B)`` residuals (target - position), ``tau (D, B)`` extra right-hand side,
    ``arm (D, B)`` diagonal, ``free (D, B)`` bool; ``inertia`` from :func:`body_inertia` and ``wrench``
    from :func:`~torchpf.kinematics.jacobian.wrenches` (computed when not given). Returns ``δ (D, B)``.

    ``JᵀWJ + diag(arm)`` is the joint-space inertia matrix of point masses ``w_l`` at the joints with
    armature ``arm``, and ``JᵀW r`` the joint torque of the forces ``w_l r_l`` applied at the joints. So ``δ``
    is that system's joint acceleration from rest: Featherstone's articulated-body algorithm, with world-frame
    spatial vectors (no coordinate transforms between bodies), one level of the tree at a time.
    """
    c = _constants(tree, tw.device, tw.dtype)
    D, _, B = tw.shape
    freef = free.to(tw.dtype)
    if fused_kernel_applies(tw, rel, w, r, tau, arm):
        from torchpf.kinematics import _aba_cpu

        bodies = _Bodies.of(tree)
        structure = bodies.kernel_structure(tree)
        return _aba_cpu.aba_solve(structure, tw, rel, w, r, tau, arm, freef, bodies.point_body_np)
    if inertia is None:
        inertia = body_inertia(tree, rel, w)
    if wrench is None:
        wrench = wrenches(rel, w, r)
    force = (c["point_body"] @ wrench.reshape(-1, 6 * B)).view(-1, 6, B)

    levels = c["levels"]
    saved = [None] * len(levels)
    child = [None] * len(levels)
    for li in range(len(levels) - 1, -1, -1):
        members, dofs, valid, k, P, _ = levels[li]
        n = members.shape[0]
        Ia = inertia.index_select(0, members)  # articulated inertia (n, 6, 6, B)
        pa = force.index_select(0, members).neg()  # articulated bias force (n, 6, B)
        if child[li] is not None:
            Ia = Ia + child[li][0]
            pa = pa + child[li][1]
        # a level's runs are padded to k DOFs: a padding or frozen DOF gets a zero twist, armature 1 and a
        # zero right-hand side, so it solves to 0
        on = (freef.index_select(0, dofs) * valid[:, None]).reshape(n, k, B)
        St = tw.index_select(0, dofs).reshape(n, k, 6, B) * on[:, :, None]  # motion subspace, row per DOF
        Ut = dot(Ia[:, None], St[:, :, None], 3)  # (I S)ᵀ: (n, k, 6, B)
        Dm = dot(St[:, :, None], Ut[:, None], 3)  # Sᵀ I S: (n, k, k, B)
        arm_k = torch.where(on > 0, arm.index_select(0, dofs).reshape(n, k, B), torch.ones_like(on))
        Dm.diagonal(0, 1, 2).add_(arm_k.transpose(1, 2))
        u = tau.index_select(0, dofs).reshape(n, k, B) * on - dot(St, pa[:, None], 2)
        Dinv = inv_small(Dm)
        Dinv_u = dot(Dinv, u[:, None], 2)  # (n, k, B)
        Dinv_Ut = dot(Dinv[:, :, :, None], Ut[:, None], 2)  # (n, k, 6, B)
        saved[li] = (St, Dinv_u, Dinv_Ut)
        if P is not None:
            Ic = Ia - dot(Ut[:, :, :, None], Dinv_Ut[:, :, None], 1)
            pc = pa + dot(Ut, Dinv_u[:, :, None], 1)
            child[li - 1] = (
                (P @ Ic.reshape(n, -1)).view(-1, 6, 6, B),
                (P @ pc.reshape(n, -1)).view(-1, 6, B),
            )

    out = []
    acc = None
    for li, (_, _, _, _, P, parent_pos) in enumerate(levels):
        St, Dinv_u, Dinv_Ut = saved[li]
        if P is not None:
            a_par = acc.index_select(0, parent_pos)  # (n, 6, B) spatial acceleration of the parent
            qdd = Dinv_u - dot(Dinv_Ut, a_par[:, None], 2)
            acc = a_par + dot(St, qdd[:, :, None], 1)
        else:
            qdd = Dinv_u
            acc = dot(St, qdd[:, :, None], 1)
        out.append(qdd.reshape(-1, B))
    out.append(tw.new_zeros(1, B))
    return torch.cat(out, 0).index_select(0, c["delta_gather"]) * freef


def fused_kernel_applies(*tensors: Tensor) -> bool:
    """Whether :func:`aba_solve` may run the fused CPU kernel: no autograd through any of ``tensors``,
    numba installed and :func:`torchpf.devices.fused_cpu` of the first (a CPU float tensor,
    ``TORCHPF_FUSED=0`` in the environment not set)."""
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return False
    from torchpf.kinematics import _aba_cpu

    return _aba_cpu.AVAILABLE and fused_cpu(tensors[0])


def dense_solve(Jac: Tensor, w: Tensor, r: Tensor, tau: Tensor, arm: Tensor, free: Tensor) -> Tensor:
    """The system of :func:`aba_solve` from an explicit Jacobian ``(B, J, 3, D)`` (batch first): Cholesky.

    ``w (B, J)``, ``r (B, J, 3)``, ``tau``, ``arm``, ``free`` ``(B, D)``. Returns ``δ (B, D)``.
    """
    B, J, _, D = Jac.shape
    freef = free.to(Jac.dtype)
    Jf = (Jac * freef[:, None, None, :]).reshape(B, 3 * J, D)
    ww = w.repeat_interleave(3, dim=1)  # (B, 3J)
    H = Jf.transpose(1, 2) @ (Jf * ww[..., None])
    H = H + torch.diag_embed(torch.where(free, arm, torch.ones_like(arm)))
    g = (Jf.transpose(1, 2) @ (ww * r.reshape(B, 3 * J))[..., None])[..., 0] + tau * freef
    Lc, info = torch.linalg.cholesky_ex(H)
    delta = torch.cholesky_solve(g[..., None], Lc)[..., 0]
    return torch.where((info == 0)[:, None], delta, torch.zeros_like(delta)) * freef
