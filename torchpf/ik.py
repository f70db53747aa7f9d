"""Inverse kinematics: project joint positions onto the pose manifold (Hauberg eq. 7).

Every joint gets a goal, and the pose is the bound-constrained, damped least-squares fit

    θ̂ = argmin_{θ ∈ [lower, upper]}  Σ_l w_l ||F_l(θ) - x̂_l||²  +  μ ||θ - θ_init||²          (Hauberg eq. 7)

solved for a whole batch of poses ``(..., N)`` at once by projected, damped Gauss-Newton
(Levenberg-Marquardt) started at ``θ_init`` (the previous frame's pose ``θ_{t-1}``: a warm start, as in the
paper). This is the projection ``proj_M`` of the projected prior (Hauberg eq. 6) and of the data-driven
proposals (eq. 12-14).

How it is solved:

* **Jacobian.** ``method="tree"`` (default) builds it from the kinematic tree: the FK kernel gives every
  DOF's world axis ``a_d`` and pivot ``p_d`` with the joint positions (:meth:`Skeleton.dof_axes`: the same
  monomial products, one rotation more); the column of DOF ``d`` is ``a_d x (x_j - p_d)`` (revolute) or
  ``a_d`` (prismatic) for the joints ``j`` below it. ``method="autograd"``
  takes the Jacobian ``(B, 3J, D)`` of ``skeleton.fk`` by forward-mode autograd (``torch.func.jacfwd`` under
  ``vmap``) and works for any skeleton; the two agree to rounding (tested). The tree Jacobian costs about
  one FK; the autograd one about ``D`` FKs, which is why it is not the default.
* **Linear solve.** The Gauss-Newton matrix ``JᵀWJ + (μ + λ) I`` of a kinematic tree is the joint-space
  inertia matrix of point masses ``w_l`` sitting at the joints, with ``μ + λ`` as joint armature, so
  ``method="tree"`` solves it exactly in ``O(J)`` per pose with the articulated-body recursion
  (Featherstone's ABA, world-frame spatial vectors, zero velocities): no ``(B, D, D)`` matrix is formed or
  factorised. ``method="autograd"`` forms ``JᵀWJ`` and uses a batched Cholesky solve. On a CPU, without
  autograd, the recursion runs as one fused kernel (:mod:`torchpf._aba_cpu`, numba): 4-25x faster than
  the same recursion as tensor operations (``TORCHPF_FUSED=0`` selects those, as CUDA and autograd do).
* **Damping / well-posedness.** ``μ`` (``reg``) keeps DOFs that no joint position constrains (the twist of
  an end segment such as the head or a finger tip) at ``θ_init`` instead of leaving the system singular;
  ``λ`` is the Levenberg-Marquardt damping, adapted per pose (×0.3 after a full step that lowered the cost,
  up otherwise). A step that raises the cost is halved along the projection arc (up to twice, one FK each
  for the poses concerned) before it is given up. DOFs can also be frozen outright (``free``).
* **Joint limits** by projection with an active set (projected Newton): ``θ_init`` is clamped into the
  limits, a DOF at a bound whose descent direction points outward is held for that iteration, a DOF the
  step would push through a bound is pinned at the bound while the others are re-solved (up to twice),
  and every trial point is clamped. Every iterate is therefore feasible; no barrier term distorts the
  objective.
* **Per pose.** Each pose has its own λ, step acceptance and convergence flag; a converged pose leaves the
  working set, and the loop stops when every pose has converged (``max |δθ| < tol``, a relative cost
  decrease below ``ftol``, or joints met to ~1 µm) or after ``iters`` iterations. The defaults stop at a
  0.1 % relative cost decrease (the RMS residual is then within ~0.05 % of its minimum, 6 µm at a 12 mm
  noise floor): the weakly determined DOFs (head or finger twists) may still creep, the joint positions
  no longer move measurably; pass ``ftol=0`` and a small ``tol`` for a tight solve.
* **Cost.** Per iteration one FK with the DOF axes at the trial point (the accepted one is the next
  linearisation point), the twists and body inertias, and the ``O(J)`` solve (two more for the poses
  whose step crosses a bound). On a CPU one intra-op thread is often faster than several for batches
  below ~10^4 poses.
* **Gradients.** The iterations run without autograd. When ``targets``, ``theta_init`` or the weights
  require grad, one extra differentiable Gauss-Newton step at the solution gives ``θ̂`` the implicit-function
  derivative in its Gauss-Newton form, ``dθ̂/dx̂ = (JᵀWJ + μI)⁻¹ JᵀW`` (zero for frozen / bound-active DOFs):
  exact when the targets lie on the manifold, first-order in the residual otherwise (the second-derivative
  term ``Σ r·∇²F`` is left out). Poses never mix: the gradient of one pose with respect to another pose's
  targets is exactly zero.

Example::

    skel = Skeleton.from_urdf(torchpf.assets.path("human.urdf"))
    noisy = skel.fk(theta) + 0.01 * torch.randn(*theta.shape[:-1], len(skel.joint_names), 3)
    theta_hat = ik.project(skel, noisy, theta_init=theta)          # (..., D), within the joint limits
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

_METHODS = ("tree", "autograd")


@dataclass(frozen=True)
class IKResult:
    """What :func:`project` returns with ``return_result=True``. Shapes: ``...`` are the pose batch dims.

    Attributes:
        theta: ``(..., D)`` solution, within the joint limits.
        converged: ``(...)`` bool, the pose met the stopping rule before ``iters`` ran out.
        residual: ``(...)`` root-mean-square joint-position error ``sqrt(mean_l ||F_l(θ) - x̂_l||²)`` (m),
            unweighted, over all ``J`` joints.
        errors: ``(..., J)`` per-joint distance ``||F_l(θ) - x̂_l||`` (m).
        cost: ``(...)`` the objective ``Σ w_l ||F_l - x̂_l||² + μ ||θ - θ_init||²``.
        iterations: ``(...)`` int, iterations the pose took until it converged (``iters`` if it did not).
    """

    theta: Tensor
    converged: Tensor
    residual: Tensor
    errors: Tensor
    cost: Tensor
    iterations: Tensor


# ---------------------------------------------------------------------------------------------- structure


class _Tree:
    """Kinematic structure of a skeleton for the tree Jacobian and the articulated-body solve.

    Built once per skeleton (cached on it) from the nodes of its FK kernel (body joints and branching
    frames, each with the run of single-DOF URDF joints above it): any skeleton that
    :meth:`Skeleton.from_urdf` accepts.
    """

    def __init__(self, skeleton):
        J, D = len(skeleton.joint_names), len(skeleton.dof_names)
        parent = list(skeleton._node_parent)
        runs = [list(r) for r in skeleton._node_dofs]
        node_of_joint = skeleton._body_rows.tolist()
        M = len(parent)
        self.J, self.D = J, D
        # desc[a, b]: node b lies in the subtree of node a (a included); parents come first in level order
        desc = torch.zeros(M, M, dtype=torch.bool)
        for b in range(M):
            a = b
            while a >= 0:
                desc[a, b] = True
                a = parent[a]
        dof_node = torch.full((D,), -1, dtype=torch.long)
        for n, run in enumerate(runs):
            for d in run:
                dof_node[d] = n
        # (D, J): the joints each DOF moves; a DOF below every body joint moves none
        self.dof_mask = desc[dof_node.clamp(min=0)][:, node_of_joint] & (dof_node >= 0)[:, None]
        self.revolute = skeleton._dof_revolute.clone()

        # Bodies of the articulated-body recursion: the nodes that own DOFs. A joint at a node without DOFs
        # (an end site) is a point mass on the body of its nearest ancestor that has some (``point_body``;
        # -1: moved by no DOF, dropped). Bodies are grouped by depth, each body's DOFs padded to the level's
        # widest run (index D = a dummy DOF with zero twist), each parent given as a position in the level
        # above; ``delta_gather`` picks every real DOF out of the levels' concatenated solutions.
        bodies = [n for n in range(M) if runs[n]]
        body_pos = {n: i for i, n in enumerate(bodies)}

        def body_above(n):
            while n >= 0 and n not in body_pos:
                n = parent[n]
            return body_pos.get(n, -1)

        self.point_body = torch.tensor([body_above(n) for n in node_of_joint], dtype=torch.long)
        self.point_body_np = self.point_body.numpy().astype("int64")
        body_parent = [body_above(parent[n]) for n in bodies]
        depth: list[int] = []
        for i in range(len(bodies)):  # parents come first (level order)
            depth.append(0 if body_parent[i] < 0 else depth[body_parent[i]] + 1)
        self.n_bodies = len(bodies)
        self.levels = []
        self.n_bodies_at: list[int] = []
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
            self.levels.append(
                (torch.tensor(members, dtype=torch.long), dofs.reshape(-1), k, parent_pos, d > 0)
            )
            self.n_bodies_at.append(len(members))
        self.body_runs = [runs[n] for n in bodies]
        self.body_parent = body_parent
        self._kernel_structure = None
        where = {dof: i for i, dof in enumerate(flat) if dof < D}
        # a DOF in no body's run solves to 0: it points at the zero row appended after the levels' solutions
        self.delta_gather = torch.tensor([where.get(dof, len(flat)) for dof in range(D)], dtype=torch.long)
        self._device_cache: dict = {}

    def kernel_structure(self):
        """The tree for the fused CPU kernel (:mod:`torchpf._aba_cpu`), built on first use."""
        if self._kernel_structure is None:
            from torchpf import _aba_cpu

            self._kernel_structure = _aba_cpu.Structure(self.body_runs, self.body_parent)
        return self._kernel_structure

    def on(self, device, dtype) -> dict:
        """The index and constant tensors on ``device`` (floats in ``dtype``), cached."""
        key = (device, dtype)
        c = self._device_cache.get(key)
        if c is None:
            levels = []
            for li, (members, dofs, k, parent_pos, has) in enumerate(self.levels):
                valid = (dofs < self.D).to(dtype)
                # parent matrix: child contributions are summed into the level above with one product
                P = None
                if has:
                    P = torch.zeros(self.n_bodies_at[li - 1], len(members), dtype=dtype)
                    P[parent_pos, torch.arange(len(members))] = 1.0
                    P = P.to(device)
                levels.append(
                    (
                        members.to(device),
                        dofs.clamp(max=self.D - 1).to(device),
                        valid.to(device),
                        k,
                        P,
                        parent_pos.to(device),
                    )
                )
            dof_mask = self.dof_mask.to(device=device, dtype=dtype)
            c = {
                "levels": levels,
                "dof_mask": dof_mask,  # (D, J)
                "anc_mask": dof_mask.t().contiguous(),  # (J, D)
                "revolute": self.revolute.to(device)[:, None, None],
                "revf": self.revolute.to(device=device, dtype=dtype)[:, None, None],
                "delta_gather": self.delta_gather.to(device),
                # (n_bodies + 1, J) 0/1: which body carries each joint's point mass (points moved by no DOF go
                # to the extra last row, which no level reads); a product with it sums points per body
                "point_body": torch.zeros(self.n_bodies + 1, self.J, dtype=dtype)
                .index_put_(
                    (torch.where(self.point_body < 0, self.n_bodies, self.point_body), torch.arange(self.J)),
                    torch.ones(self.J, dtype=dtype),
                )
                .to(device),
                "inertia_index": _inertia_index().to(device),
            }
            self._device_cache[key] = c
        return c


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


def _tree(skeleton) -> _Tree:
    tree = getattr(skeleton, "_ik_tree", None)
    if tree is None:
        tree = _Tree(skeleton)
        # The skeleton is an nn.Module: a plain attribute (not a buffer or submodule) is fine for a cache.
        object.__setattr__(skeleton, "_ik_tree", tree)
    return tree


# ------------------------------------------------------------------------------------------------- layout
#
# Inside the solver every per-pose quantity is stored *batch last*: ``(D, B)``, ``(J, 3, B)``,
# ``(n, 6, 6, B)``.
# The small-matrix algebra (3x3 rotations, 6x6 spatial inertias) is then written as broadcast products over
# contiguous B-long rows, which on a CPU is far faster than batched tiny ``bmm``/LAPACK calls (the same
# choice as the FK kernel in :mod:`torchpf.skeleton`).


def _frames(skeleton, th: Tensor) -> tuple[Tensor, Tensor]:
    """DOF axes and pivots ``(D, 2, 3, B)`` and joint positions ``(J, 3, B)`` at ``th (B, D)``."""
    world, axes, pivots = skeleton._world(th, axes=True)
    return torch.stack([axes, pivots], 1), skeleton._body(world[:, :, 3], th)


def _twists(tree: _Tree, ap: Tensor, centre: Tensor) -> Tensor:
    """World twists ``(D, 6, B)`` = (ω, v) of every DOF about a per-pose ``centre (3, B)``.

    A point at ``y`` (relative to the centre) moved by DOF ``d`` has velocity ``v_d + ω_d x y`` per unit
    ``δθ_d``: revolute ``ω = a``, ``v = p x a`` (axis ``a``, pivot ``p`` relative to the centre), prismatic
    ``ω = 0``, ``v = a``.
    """
    c = tree.on(ap.device, ap.dtype)
    a = ap[:, 0]
    v = torch.where(c["revolute"], _cross(ap[:, 1] - centre, a), a)
    return torch.cat([a * c["revf"], v], 1)


def _cross(a: Tensor, b: Tensor, dim: int = 1) -> Tensor:
    """Cross product along ``dim`` (size 3), broadcasting; several times faster than ``torch.linalg.cross``
    on batch-last layouts on a CPU."""
    a0, a1, a2 = a.unbind(dim)
    b0, b1, b2 = b.unbind(dim)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim)


def _dot(a: Tensor, b: Tensor, dim: int) -> Tensor:
    """``Σ_j a_j b_j`` over ``dim`` (a short dim, the same size in both), with broadcasting.

    Accumulated with ``addcmul`` one slice at a time: no temporary the size of the broadcast product, which
    is what bounds the speed of these small contractions on a CPU.
    """
    if math.prod(torch.broadcast_shapes(a.shape, b.shape)) < _SMALL:
        return (a * b).sum(dim)  # small batch: fewer operations beat smaller temporaries
    pairs = zip(a.unbind(dim), b.unbind(dim), strict=True)
    x, y = next(pairs)
    out = x * y
    for x, y in pairs:
        out = torch.addcmul(out, x, y)
    return out


_SMALL = 1 << 13


def _point_velocities(tw: Tensor, rel: Tensor, anc_mask: Tensor, delta: Tensor) -> Tensor:
    """``J δ``: joint displacements ``(J, 3, B)`` for a step ``delta (D, B)`` (linearised)."""
    D, _, B = tw.shape
    V = (anc_mask @ (tw * delta[:, None]).reshape(D, 6 * B)).reshape(-1, 6, B)  # summed twist per joint
    return V[:, 3:] + _cross(V[:, :3], rel)


def _wrenches(rel: Tensor, w: Tensor, r: Tensor) -> Tensor:
    """Spatial forces ``(J, 6, B)`` = (moment, force) of the forces ``w_l r_l`` at the joints ``rel``."""
    wr = w[:, None] * r
    return torch.cat([_cross(rel, wr), wr], 1)


def _gradient(tw: Tensor, wrench: Tensor, dof_mask: Tensor) -> Tensor:
    """``Jᵀ W r`` ``(D, B)``: per DOF, its twist dotted with the wrenches (:func:`_wrenches`) below it."""
    J, _, B = wrench.shape
    sub = (dof_mask @ wrench.reshape(J, 6 * B)).reshape(-1, 6, B)
    return _dot(tw, sub, 1)


# Symmetric 3x3 inverse by cofactors, on the row-major entries m0..m8: cofactor c_ij = m[p] m[q] - m[r] m[s]
# (rows ``_COF``), determinant = row 0 of M dotted with row 0 of the cofactors.
_COF = torch.tensor(
    [[4, 8, 5, 7], [5, 6, 3, 8], [3, 7, 4, 6], [2, 7, 1, 8], [0, 8, 2, 6], [1, 6, 0, 7], [1, 5, 2, 4],
     [2, 3, 0, 5], [0, 4, 1, 3]]
).t().contiguous()  # fmt: skip


def _inv_small(M: Tensor) -> Tensor:
    """Inverse of SPD matrices ``M (n, k, k, B)``: closed form for k <= 3, batched LAPACK otherwise."""
    n, k, _, B = M.shape
    if k == 1:
        return 1.0 / M
    if k == 3:
        flat = M.reshape(n, 9, B)
        idx = _COF.to(M.device)
        cof = flat.index_select(1, idx[0]) * flat.index_select(1, idx[1])
        cof = cof - flat.index_select(1, idx[2]) * flat.index_select(1, idx[3])  # (n, 9, B) row-major
        det = _dot(flat[:, :3], cof[:, :3], 1)
        # adj(M) = cofactorsᵀ = cofactors for a symmetric M
        return (cof / det[:, None]).view(n, 3, 3, B)
    if k == 2:
        a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
        det = a * d - b * c
        return torch.stack([torch.stack([d, -b], 1), torch.stack([-c, a], 1)], 1) / det[:, None, None]
    # wider runs (a floating root): batched LAPACK on (n B, k, k); few such bodies per tree
    inv = torch.linalg.inv_ex(M.permute(0, 3, 1, 2).reshape(n * B, k, k))[0]
    return inv.reshape(n, B, k, k).permute(0, 2, 3, 1)


def _body_inertia(tree: _Tree, rel: Tensor, w: Tensor) -> Tensor:
    """Spatial inertias ``(n_bodies + 1, 6, 6, B)`` of the joints as point masses ``w`` at ``rel``, per body.

    Summed as moments ``(Σ w, Σ w y, Σ w y yᵀ)`` per body, then arranged (:func:`_inertia_index`) as
    ``[[tr(S) I - S, [h]x], [-[h]x, m I]]``. The last row collects points that no DOF moves.
    """
    c = tree.on(rel.device, rel.dtype)
    J, B = rel.shape[0], rel.shape[-1]
    wy = w[:, None] * rel
    moments = torch.cat([w[:, None], wy, wy * rel, wy[:, [0, 0, 1]] * rel[:, [1, 2, 2]]], 1)  # (J, 10, B)
    M = (c["point_body"] @ moments.reshape(J, 10 * B)).view(-1, 10, B)
    S = M[:, 4:7]
    diag = S.sum(1, keepdim=True) - S  # tr(S) - S_ii
    table = torch.cat([M, -M, torch.zeros_like(M[:, :1]), diag], 1)
    return table.index_select(1, c["inertia_index"]).view(-1, 6, 6, B)


def _aba_solve(
    tree: _Tree,
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
    ``arm (D, B)`` diagonal, ``free (D, B)`` bool; ``inertia`` from :func:`_body_inertia` and ``wrench``
    from :func:`_wrenches` (computed when not given). Returns ``δ (D, B)``.

    ``JᵀWJ + diag(arm)`` is the joint-space inertia matrix of point masses ``w_l`` at the joints with
    armature ``arm``, and ``JᵀW r`` the joint torque of the forces ``w_l r_l`` applied at the joints. So ``δ``
    is that system's joint acceleration from rest: Featherstone's articulated-body algorithm, with world-frame
    spatial vectors (no coordinate transforms between bodies), one level of the tree at a time.
    """
    c = tree.on(tw.device, tw.dtype)
    D, _, B = tw.shape
    freef = free.to(tw.dtype)
    if _fused_kernel_applies(tw, rel, w, r, tau, arm):
        from torchpf import _aba_cpu

        return _aba_cpu.aba_solve(tree.kernel_structure(), tw, rel, w, r, tau, arm, freef, tree.point_body_np)
    if inertia is None:
        inertia = _body_inertia(tree, rel, w)
    if wrench is None:
        wrench = _wrenches(rel, w, r)
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
        Ut = _dot(Ia[:, None], St[:, :, None], 3)  # (I S)ᵀ: (n, k, 6, B)
        Dm = _dot(St[:, :, None], Ut[:, None], 3)  # Sᵀ I S: (n, k, k, B)
        arm_k = torch.where(on > 0, arm.index_select(0, dofs).reshape(n, k, B), torch.ones_like(on))
        Dm.diagonal(0, 1, 2).add_(arm_k.transpose(1, 2))
        u = tau.index_select(0, dofs).reshape(n, k, B) * on - _dot(St, pa[:, None], 2)
        Dinv = _inv_small(Dm)
        Dinv_u = _dot(Dinv, u[:, None], 2)  # (n, k, B)
        Dinv_Ut = _dot(Dinv[:, :, :, None], Ut[:, None], 2)  # (n, k, 6, B)
        saved[li] = (St, Dinv_u, Dinv_Ut)
        if P is not None:
            Ic = Ia - _dot(Ut[:, :, :, None], Dinv_Ut[:, :, None], 1)
            pc = pa + _dot(Ut, Dinv_u[:, :, None], 1)
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
            qdd = Dinv_u - _dot(Dinv_Ut, a_par[:, None], 2)
            acc = a_par + _dot(St, qdd[:, :, None], 1)
        else:
            qdd = Dinv_u
            acc = _dot(St, qdd[:, :, None], 1)
        out.append(qdd.reshape(-1, B))
    out.append(tw.new_zeros(1, B))
    return torch.cat(out, 0).index_select(0, c["delta_gather"]) * freef


def _fused_kernel_applies(*tensors: Tensor) -> bool:
    """Whether :func:`_aba_solve` may run the fused CPU kernel: CPU float tensors, no autograd through them,
    numba installed (``TORCHPF_FUSED=0`` in the environment turns it off)."""
    t0 = tensors[0]
    if t0.device.type != "cpu" or t0.dtype not in (torch.float32, torch.float64):
        return False
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return False
    if os.environ.get("TORCHPF_FUSED", "1") == "0":
        return False
    from torchpf import _aba_cpu

    return _aba_cpu.AVAILABLE


def _dense_solve(Jac: Tensor, w: Tensor, r: Tensor, tau: Tensor, arm: Tensor, free: Tensor) -> Tensor:
    """The system of :func:`_aba_solve` from an explicit Jacobian ``(B, J, 3, D)`` (batch first): Cholesky.

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


# ------------------------------------------------------------------------------------------ Jacobians


def tree_jacobian(skeleton, theta: Tensor) -> Tensor:
    """Jacobian of :meth:`Skeleton.fk` from the kinematic tree: ``(..., D) -> (..., J, 3, D)``.

    Column ``d`` is ``a_d x (x_j - p_d)`` (revolute) or ``a_d`` (prismatic) for the joints ``j`` below DOF
    ``d`` and zero elsewhere (world axis ``a_d``, pivot ``p_d``, see :meth:`Skeleton.dof_axes`).
    """
    tree = _tree(skeleton)
    flat = theta.reshape(-1, theta.shape[-1])
    ap, x = _frames(skeleton, flat)
    rel = x - x[:1]
    tw = _twists(tree, ap, x[0])  # (D, 6, B)
    mask = tree.on(flat.device, flat.dtype)["dof_mask"]  # (D, J)
    cols = tw[:, None, 3:] + _cross(tw[:, None, :3], rel[None], dim=2)
    cols = cols * mask[:, :, None, None]  # (D, J, 3, B)
    return cols.permute(3, 1, 2, 0).reshape(*theta.shape[:-1], rel.shape[0], 3, flat.shape[-1])


def autograd_jacobian(skeleton, theta: Tensor) -> Tensor:
    """Jacobian of :meth:`Skeleton.fk` by forward-mode autograd: ``(..., D) -> (..., J, 3, D)``.

    ``torch.func.jacfwd`` under ``vmap`` over the flattened poses, so each pose's Jacobian depends on that
    pose only. Costs about ``D`` forward kinematics; works for any skeleton.
    """
    flat = theta.reshape(-1, theta.shape[-1])

    def one(th):
        return skeleton.fk(th[None])[0]

    Jac = torch.func.vmap(torch.func.jacfwd(one))(flat)  # (B, J, 3, D)
    return Jac.reshape(*theta.shape[:-1], *Jac.shape[1:])


# -------------------------------------------------------------------------------------------- the solver


def _free_mask(skeleton, free, D: int, device) -> Tensor:
    if free is None:
        return torch.ones(D, dtype=torch.bool, device=device)
    if isinstance(free, Tensor):
        if free.dtype != torch.bool or free.shape != (D,):
            raise ValueError(f"free must be a (D={D},) bool mask or a list of DOF names")
        return free.to(device)
    names = list(free)
    unknown = [n for n in names if n not in skeleton.dof_names]
    if unknown:
        raise ValueError(f"free: unknown DOF names {unknown}")
    mask = torch.zeros(D, dtype=torch.bool, device=device)
    mask[[skeleton.dof_names.index(n) for n in names]] = True
    return mask


def frozen_mask(skeleton, patterns: Sequence[str]) -> Tensor:
    """``(D,)`` bool mask, False for the DOFs whose name contains any of ``patterns`` (True = free).

    Example: ``free = ik.frozen_mask(skel, ["Finger", "Thumb", "HandIndex"])`` freezes the finger DOFs of
    ``human.urdf``, which the hand's few joint positions barely constrain.
    """
    return torch.tensor([not any(p in n for p in patterns) for n in skeleton.dof_names], dtype=torch.bool)


class _Problem:
    """One batch of IK problems in batch-last layout, with the step computation for either method."""

    def __init__(self, skeleton, tree, g, th0, w, lo, hi, free_d, reg):
        self.skeleton, self.tree = skeleton, tree
        self.g, self.th0, self.w = g, th0, w  # (J, 3, B), (D, B), (J, B)
        self.lo, self.hi, self.free_d, self.reg = lo, hi, free_d, reg  # (D, 1) (D, 1) (D, 1) float

    def subset(self, rows: Tensor) -> _Problem:
        """The same problem for the poses ``rows`` only."""
        return _Problem(
            self.skeleton,
            self.tree,
            self.g.index_select(-1, rows),
            self.th0.index_select(-1, rows),
            self.w.index_select(-1, rows),
            self.lo,
            self.hi,
            self.free_d,
            self.reg,
        )

    def evaluate(self, q: Tensor):
        """DOF axes ``(D, 2, 3, B)``, positions and residual ``(J, 3, B)``, cost ``(B,)`` at ``q (D, B)``."""
        ap, x = _frames(self.skeleton, q.t())
        r = self.g - x
        cost = (self.w * r.square().sum(1)).sum(0) + self.reg * (q - self.th0).square().sum(0)
        return ap, x, r, cost

    def linearise(self, q, ap, x):
        """What :meth:`solve` needs at ``q``: twists and body inertias (tree) or the Jacobian (autograd)."""
        if self.tree is not None:
            centre = x[0].detach()
            rel = x - centre
            tw = _twists(self.tree, ap, centre)
            # the fused CPU kernel sums the body inertias itself
            inertia = None if _fused_kernel_applies(tw, rel) else _body_inertia(self.tree, rel, self.w)
            return ("tree", tw, rel, inertia)
        return ("dense", autograd_jacobian(self.skeleton, q.t()))

    @staticmethod
    def subset_lin(lin, rows):
        """The linearisation of the poses ``rows`` only."""
        if lin[0] == "tree":
            return ("tree", *(None if t is None else t.index_select(-1, rows) for t in lin[1:]))
        return ("dense", lin[1].index_select(0, rows))

    def gradient(self, lin, r, q, wrench=None) -> Tensor:
        """Descent direction of the cost, ``JᵀW r - μ (q - θ_init)``: ``(D, B)``."""
        if lin[0] == "tree":
            dof_mask = self.tree.on(q.device, q.dtype)["dof_mask"]
            g = _gradient(lin[1], _wrenches(lin[2], self.w, r) if wrench is None else wrench, dof_mask)
        else:
            g = torch.einsum("bjkd,jkb->db", lin[1], self.w[:, None] * r)
        return g - self.reg * (q - self.th0)

    def solve(self, lin, w, r, tau, arm, free, wrench=None) -> Tensor:
        """``(JᵀWJ + diag(arm)) δ = JᵀW r + tau`` over ``free``: ``δ (D, B)``."""
        if lin[0] == "tree":
            return _aba_solve(self.tree, lin[1], lin[2], w, r, tau, arm, free, inertia=lin[3], wrench=wrench)
        return _dense_solve(lin[1], w.t(), r.permute(2, 0, 1), tau.t(), arm.t(), free.t()).t()

    def displacement(self, lin, delta) -> Tensor:
        """``J δ`` ``(J, 3, B)``."""
        if lin[0] == "tree":
            anc = self.tree.on(delta.device, delta.dtype)["anc_mask"]
            return _point_velocities(lin[1], lin[2], anc, delta)
        return torch.einsum("bjkd,db->jkb", lin[1], delta)

    def step(self, q, ap, x, r, lam, refine: int = 2):
        """Projected LM step ``δ (D, B)`` with an active set for the joint limits.

        Held: the user's frozen DOFs and those at a bound whose descent direction points outward. Then, up
        to ``refine`` times and only for the poses concerned, DOFs the step would push through a bound are
        pinned *at* that bound and the others re-solved against the linearised residual this leaves, so
        that the remaining DOFs compensate instead of the step simply being cut.
        """
        lin = self.linearise(q, ap, x)
        lo, hi = self.lo, self.hi
        eps = 1e-9
        wrench = _wrenches(lin[2], self.w, r) if lin[0] == "tree" else None
        grad = self.gradient(lin, r, q, wrench)
        hold = ((q <= lo + eps) & (grad <= 0)) | ((q >= hi - eps) & (grad >= 0))
        free = self.free_d & ~hold
        free0 = free
        arm = (self.reg + lam)[None].expand_as(q)
        tau = -self.reg * (q - self.th0)
        delta = self.solve(lin, self.w, r, tau, arm, free, wrench)
        fixed = torch.zeros_like(q)  # prescribed moves of DOFs pinned at a bound
        for _ in range(refine):
            target = q + fixed + delta
            out = free & ((target < lo) | (target > hi))
            rows = out.any(0).nonzero().flatten()
            if rows.numel() == 0:
                break
            if 2 * rows.numel() > q.shape[-1]:
                # most poses concerned: re-solving all is cheaper than gathering them (the others solve
                # to the same step again: same free set, same right-hand side)
                rows = None

            def sub(t, rows=rows):
                return t if rows is None else t.index_select(-1, rows)

            def put(t, t_s, rows=rows):
                return t_s if rows is None else t.index_copy(-1, rows, t_s)

            q_s, out_s, target_s = sub(q), sub(out), sub(target)
            fixed_s = sub(fixed) + torch.where(
                out_s,
                torch.maximum(torch.minimum(target_s, hi), lo) - q_s - sub(fixed),
                torch.zeros_like(q_s),
            )
            free_s = sub(free) & ~out_s
            lin_s = lin if rows is None else self.subset_lin(lin, rows)
            r_lin = sub(r) - self.displacement(lin_s, fixed_s)
            tau_s = -self.reg * (q_s + fixed_s - sub(self.th0))
            delta_s = self.solve(lin_s, sub(self.w), r_lin, tau_s, sub(arm), free_s)
            delta, fixed, free = put(delta, delta_s), put(fixed, fixed_s), put(free, free_s)
        # first-order optimality of the current point: the descent direction over the DOFs not held
        stationarity = torch.where(free0, grad, torch.zeros_like(grad)).abs().amax(0)
        return fixed + delta, stationarity


def project(
    skeleton,
    targets: Tensor,
    theta_init: Tensor,
    joint_weights: Tensor | None = None,
    *,
    iters: int = 30,
    tol: float = 1e-4,
    ftol: float = 1e-3,
    reg: float = 1e-5,
    damping: float = 1e-3,
    free: Tensor | Sequence[str] | None = None,
    method: str = "tree",
    return_result: bool = False,
) -> Tensor | IKResult:
    """Least-squares pose for joint-position goals, within the joint limits (Hauberg eq. 7).

    Minimises ``Σ_l w_l ||F_l(θ) - x̂_l||² + reg ||θ - θ_init||²`` over ``θ ∈ [lower, upper]`` by projected
    Levenberg-Marquardt from ``θ_init`` (see the module docstring for the method).

    Args:
        skeleton: a :class:`torchpf.skeleton.Skeleton`.
        targets: ``(..., J, 3)`` goal positions ``x̂`` (m) of all body joints, ``joint_names`` order.
        theta_init: ``(..., D)`` start and regularisation anchor (typically ``θ_{t-1}``); broadcast against
            the targets' batch dims. Clamped into the limits first.
        joint_weights: ``(J,)`` or ``(..., J)`` weights ``w_l >= 0`` (default 1); 0 ignores a joint.
        iters: maximum Levenberg-Marquardt iterations.
        tol: a pose has converged when an accepted step has ``max |δθ| < tol`` (rad or m) ...
        ftol: ... or decreased the cost by less than ``ftol`` relative.
        reg: ``μ`` (m² per rad²), the damping toward ``θ_init`` that keeps unconstrained DOFs put. The
            default 1e-5 weighs a 0.1 rad change like a 0.3 mm joint error.
        damping: initial Levenberg-Marquardt ``λ`` (same units as ``reg``).
        free: DOFs to optimise, a ``(D,)`` bool mask or a list of DOF names; the others stay at ``θ_init``
            (clamped). Default: all.
        method: ``"tree"`` (kinematic-tree Jacobian + articulated-body solve, fast) or ``"autograd"``
            (autograd Jacobian + dense Cholesky; a cross-check, ~100x slower).
        return_result: return an :class:`IKResult` (flags, residuals) instead of ``θ`` alone.

    Returns:
        ``θ̂ (..., D)`` in the inputs' dtype and device, or an :class:`IKResult`.
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if iters < 1:
        raise ValueError(f"iters must be >= 1, got {iters}")
    J, D = len(skeleton.joint_names), len(skeleton.dof_names)
    if targets.shape[-2:] != (J, 3):
        raise ValueError(f"targets must have shape (..., {J}, 3), got {tuple(targets.shape)}")
    if theta_init.shape[-1] != D:
        raise ValueError(f"theta_init must have shape (..., {D}), got {tuple(theta_init.shape)}")
    dtype = torch.promote_types(targets.dtype, theta_init.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    device = targets.device
    batch = torch.broadcast_shapes(targets.shape[:-2], theta_init.shape[:-1])
    g = targets.to(dtype).expand(*batch, J, 3).reshape(-1, J, 3)
    th0 = theta_init.to(device=device, dtype=dtype).expand(*batch, D).reshape(-1, D)
    B = g.shape[0]
    if joint_weights is None:
        w = g.new_ones(B, J)
    else:
        w = joint_weights.to(dtype=dtype, device=device).expand(*batch, J).reshape(-1, J)
    lo = skeleton.lower.to(device=device, dtype=dtype)[:, None]
    hi = skeleton.upper.to(device=device, dtype=dtype)[:, None]
    free_d = _free_mask(skeleton, free, D, device)[:, None]

    tree = _tree(skeleton) if method == "tree" else None

    # batch-last copies for the solver
    g_bl, th0_bl, w_bl = g.permute(1, 2, 0), th0.t(), w.t()
    with torch.no_grad():
        prob = _Problem(skeleton, tree, g_bl.detach(), th0_bl.detach(), w_bl.detach(), lo, hi, free_d, reg)
        q = torch.maximum(torch.minimum(prob.th0, hi), lo)
        ap, x, r, cost = prob.evaluate(q)
        lam = torch.full((B,), float(damping), dtype=dtype, device=device)
        converged = torch.zeros(B, dtype=torch.bool, device=device)
        n_iter = torch.full((B,), iters, dtype=torch.long, device=device)
        tiny_cost = J * 1e-12
        eps_rel = torch.finfo(dtype).eps ** 0.5
        # Results for all poses, written as poses finish; the loop works on a compact working set (the
        # columns ``rows`` of the batch) that shrinks as poses converge.
        q_out, x_out, cost_out = q.clone(), x.clone(), cost.clone()
        rows = torch.arange(B, device=device)
        P = prob
        for it in range(iters):
            delta, stationarity = P.step(q, ap, x, r, lam)
            # Full step first; then a line search on the projection arc clamp(q + α δ), α = 1/2, 1/4, for
            # the poses whose cost went up (each halving costs one FK of those poses only).
            q_t = torch.maximum(torch.minimum(q + delta, hi), lo)
            ap_t, x_t, r_t, c_t = P.evaluate(q_t)
            full = c_t <= cost
            rel_dec = (cost - c_t) / cost.clamp_min(torch.finfo(dtype).tiny)
            # the trial point becomes the state, the rejected poses keep theirs (usually few: copy those)
            rej = (~full).nonzero().flatten()
            if rej.numel():
                for new, old in ((q_t, q), (ap_t, ap), (x_t, x), (r_t, r), (c_t, cost)):
                    new.index_copy_(-1, rej, old.index_select(-1, rej))
            q, ap, x, r, cost = q_t, ap_t, x_t, r_t, c_t
            accepted = full.clone()
            alpha = 0.5
            for _ in range(2):
                sub = (~accepted).nonzero().flatten()
                if sub.numel() == 0:
                    break
                q_t = torch.maximum(torch.minimum(q[:, sub] + alpha * delta[:, sub], hi), lo)
                ap_t, x_t, r_t, c_t = P.subset(sub).evaluate(q_t)
                ok = c_t <= cost[sub]
                put, take = sub[ok], ok.nonzero().flatten()
                q[:, put] = q_t[:, take]
                ap[..., put] = ap_t[..., take]
                x[..., put] = x_t[..., take]
                r[..., put] = r_t[..., take]
                cost[put] = c_t[take]
                accepted[put] = True
                alpha *= 0.5
            small = delta.abs().amax(0) < tol
            # No descent even with a gradient-descent-sized step: converged if that is rounding, i.e. the
            # projected gradient (m² per rad) is nil next to sqrt(eps) x the residual norm x a 1 m lever.
            stuck = ~accepted & (lam >= 1e6)
            stationary = stationarity <= eps_rel * cost.clamp_min(tiny_cost).sqrt()
            exact = cost <= tiny_cost  # targets on the manifold, met to ~1 µm per joint
            done = (full & (small | (rel_dec < ftol))) | stuck | exact
            lam = torch.where(full, (lam * 0.3).clamp_min(1e-7), lam * torch.where(accepted, 3.0, 30.0))
            fin = done.nonzero().flatten()
            if fin.numel() == 0:
                continue
            idx = rows.index_select(0, fin)
            converged[idx[(~stuck | stationary)[fin]]] = True
            n_iter[idx] = it + 1
            q_out[:, idx] = q.index_select(-1, fin)
            x_out[..., idx] = x.index_select(-1, fin)
            cost_out[idx] = cost.index_select(0, fin)
            keep = (~done).nonzero().flatten()
            rows = rows.index_select(0, keep)
            if rows.numel() == 0:
                break
            P = P.subset(keep)
            q, ap, x, r, cost, lam = (t.index_select(-1, keep) for t in (q, ap, x, r, cost, lam))
        if rows.numel():  # out of iterations
            q_out[:, rows], x_out[..., rows], cost_out[rows] = q, x, cost
        q, x, cost = q_out, x_out, cost_out

    if torch.is_grad_enabled() and (
        targets.requires_grad or theta_init.requires_grad or _needs(joint_weights)
    ):
        # One differentiable Gauss-Newton step at the solution: the value moves by ~0 at convergence, and the
        # derivative is that of the fixed point, (JᵀWJ + μI)⁻¹ JᵀW for the targets (implicit function).
        prob_g = _Problem(skeleton, tree, g_bl, th0_bl, w_bl, lo, hi, free_d, reg)
        q_fix = q.detach()
        ap_g, x_g = _frames(skeleton, q_fix.t())
        r_g = g_bl - x_g
        delta = prob_g.step(q_fix, ap_g, x_g, r_g, torch.zeros_like(lam), refine=0)[0]
        q = q_fix + delta - delta.detach()

    theta = q.t().reshape(*batch, D)
    if not return_result:
        return theta
    with torch.no_grad():
        err = (x - prob.g).norm(dim=1).t()  # (B, J)
    return IKResult(
        theta=theta,
        converged=converged.reshape(batch),
        residual=err.square().mean(-1).sqrt().reshape(batch),
        errors=err.reshape(*batch, J),
        cost=cost.reshape(batch),
        iterations=n_iter.reshape(batch),
    )


def _needs(t) -> bool:
    return isinstance(t, Tensor) and t.requires_grad
