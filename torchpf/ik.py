"""Inverse kinematics: project joint positions onto the pose manifold (Hauberg eq. 7).

Every joint gets a goal, and the pose is the bound-constrained, damped least-squares fit

    θ̂ = argmin_{θ ∈ [lower, upper]}  Σ_l w_l ||F_l(θ) - x̂_l||²  +  μ ||θ - θ_init||²          (Hauberg eq. 7)

solved for a whole batch of poses ``(..., N)`` at once by projected, damped Gauss-Newton
(Levenberg-Marquardt) started at ``θ_init`` (the previous frame's pose ``θ_{t-1}``: a warm start, as in the
paper). This is the projection ``proj_M`` of the projected prior (Hauberg eq. 6) and of the data-driven
proposals (eq. 12-14).

How it is solved:

* **Jacobian.** ``method="tree"`` (default) builds it from the kinematic tree: one ``skeleton.transforms``
  call gives each body joint's world frame, and walking back through each ball joint's run of single-DOF
  frames gives every DOF's world axis ``a_d`` and pivot ``p_d``; the column of DOF ``d`` is
  ``a_d x (x_j - p_d)`` (revolute) or ``a_d`` (prismatic) for the joints ``j`` below it. ``method="autograd"``
  takes the Jacobian ``(B, 3J, D)`` of ``skeleton.fk`` by forward-mode autograd (``torch.func.jacfwd`` under
  ``vmap``) and works for any skeleton; the two agree to rounding (tested). The tree Jacobian costs about
  one FK; the autograd one about ``D`` FKs, which is why it is not the default.
* **Linear solve.** The Gauss-Newton matrix ``JᵀWJ + (μ + λ) I`` of a kinematic tree is the joint-space
  inertia matrix of point masses ``w_l`` sitting at the joints, with ``μ + λ`` as joint armature, so
  ``method="tree"`` solves it exactly in ``O(J)`` per pose with the articulated-body recursion
  (Featherstone's ABA, world-frame spatial vectors, zero velocities): no ``(B, D, D)`` matrix is formed or
  factorised. ``method="autograd"`` forms ``JᵀWJ`` and uses a batched Cholesky solve.
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
  0.01 % relative cost decrease: the weakly determined DOFs (head or finger twists) may still creep, the
  joint positions no longer move measurably; pass ``ftol=0`` and a small ``tol`` for a tight solve.
* **Cost.** Per iteration about one FK for the frames, one for the trial point, the twists and the
  ``O(J)`` solve. On a CPU the small-tensor bookkeeping dominates; one intra-op thread is often faster
  than several for batches below ~10^4 poses.
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


def _is_identity(t) -> bool:
    if t is None:
        return True
    m = t.get_matrix().reshape(4, 4).to(torch.float64)
    return bool(torch.allclose(m, torch.eye(4, dtype=torch.float64), atol=1e-12, rtol=0))


class _Tree:
    """Kinematic structure of a skeleton for the tree Jacobian and the articulated-body solve.

    Built once per skeleton (cached on it). ``ok`` is False when the URDF does not fit the assumptions (each
    body joint preceded by a run of single-DOF frames whose origins are the identity except the first);
    :func:`project` then falls back to ``method="autograd"``.
    """

    def __init__(self, skeleton):
        names = list(skeleton.joint_names)
        J, D = len(names), len(skeleton.dof_names)
        body = {n: i for i, n in enumerate(names)}
        self._names = set(names)
        dof_index = {n: i for i, n in enumerate(skeleton.dof_names)}
        self.ok = True
        runs: list[list[tuple[int, bool, list[float]]]] = [[] for _ in range(J)]  # chain order, root first
        owner = [-1] * D

        def walk(frame):
            """DFS; collect each body joint's run by walking up from it."""
            name = frame.name.strip("\n")
            if name in body:
                self._collect(frame, body[name], runs, owner, dof_index, parents_of)
            for child in frame.children:
                walk(child)

        parents_of: dict[int, object] = {}

        def index_parents(frame, parent):
            parents_of[id(frame)] = parent
            for child in frame.children:
                index_parents(child, frame)

        index_parents(skeleton.chain._root, None)
        walk(skeleton.chain._root)
        if any(o < 0 for o in owner):
            self.ok = False  # a DOF outside every run (e.g. below a non-body branching frame)

        self.J, self.D = J, D
        self.parents = list(skeleton.parents)
        self.runs = runs
        owner_t = torch.tensor(owner, dtype=torch.long)
        self.owner = owner_t
        # desc[c, j]: body joint j lies in the subtree of body joint c (c included).
        desc = torch.zeros(J, J, dtype=torch.bool)
        for j in range(J):
            c = j
            while c >= 0:
                desc[c, j] = True
                c = self.parents[c]
        self.desc = desc
        self.dof_mask = desc[owner_t.clamp(min=0)] if self.ok else None  # (D, J): joints moved by each DOF

        # Walk-back steps: step s handles, for every body joint with more than s DOFs, the s-th DOF from the
        # end of its run (the body joint's own frame first). Step s's nodes are a subset of step s-1's:
        # ``sub`` gives their positions there, so the running rotations are narrowed, never scattered.
        self.steps = []
        prev: list[int] = []
        order: list[int] = []  # DOFs in the order the steps produce their twists
        for s in range(max((len(r) for r in runs), default=0)):
            nodes = [c for c in range(J) if len(runs[c]) > s]
            sub = [prev.index(c) for c in nodes] if s else nodes
            dofs = [runs[c][-1 - s][0] for c in nodes]
            rev = [runs[c][-1 - s][1] for c in nodes]
            axes = [runs[c][-1 - s][2] for c in nodes]
            order += dofs
            self.steps.append(
                (
                    torch.tensor(sub, dtype=torch.long),
                    torch.tensor(dofs, dtype=torch.long),
                    torch.tensor(rev, dtype=torch.bool),
                    torch.tensor(axes, dtype=torch.float64),
                )
            )
            prev = nodes
        if self.ok and sorted(order) != list(range(D)):
            self.ok = False
        self.twist_gather = torch.argsort(torch.tensor(order, dtype=torch.long)) if self.ok else None

        # Levels for the articulated-body recursion. Its bodies are the body joints that own DOFs; a joint
        # without DOFs (an end site) is a point mass on the body of its nearest ancestor that has some
        # (``point_body``; -1: moved by no DOF, dropped). Bodies are grouped by depth, each body's DOFs padded
        # to the level's widest run (index D = a dummy DOF with zero twist), each parent given as a position
        # in the level above; ``delta_gather`` picks every real DOF out of the levels' concatenated solutions.
        bodies = [j for j in range(J) if runs[j]]
        body_pos = {j: i for i, j in enumerate(bodies)}

        def body_above(j):
            while j >= 0 and j not in body_pos:
                j = self.parents[j]
            return body_pos.get(j, -1)

        self.point_body = torch.tensor([body_above(j) for j in range(J)], dtype=torch.long)
        body_parent = [body_above(self.parents[j]) if self.parents[j] >= 0 else -1 for j in bodies]
        depth: list[int] = []
        for i in range(len(bodies)):  # parents come first (joint_names order)
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
                for col, (dof, _, _) in enumerate(runs[bodies[i]]):
                    dofs[p, col] = dof
            flat += dofs.reshape(-1).tolist()
            parent_pos = torch.tensor(
                [pos_in_level.get(body_parent[i], 0) for i in members], dtype=torch.long
            )
            self.levels.append(
                (torch.tensor(members, dtype=torch.long), dofs.reshape(-1), k, parent_pos, d > 0)
            )
            self.n_bodies_at.append(len(members))
        if self.ok:
            where = {dof: i for i, dof in enumerate(flat) if dof < D}
            self.delta_gather = torch.tensor([where[dof] for dof in range(D)], dtype=torch.long)
        self._device_cache: dict = {}

    def _collect(self, frame, c, runs, owner, dof_index, parents_of):
        """Run of DOFs above body joint ``c``: walk up until the parent body joint (or the root)."""
        run = []
        f = frame
        while f is not None:
            joint = f.joint
            if joint.joint_type in ("revolute", "prismatic"):
                d = dof_index[joint.name]
                run.append(
                    (d, joint.joint_type == "revolute", joint.axis.detach().double().reshape(3).tolist())
                )
                owner[d] = c
            parent = parents_of[id(f)]
            if parent is None or parent.name.strip("\n") in self._names:
                break
            # Stepping past this frame's origin to its parent: only exact when the origin is the identity.
            if not (_is_identity(joint.offset) and _is_identity(f.link.offset)):
                if any(jt in ("revolute", "prismatic") for jt in self._movable_above(parent, parents_of)):
                    self.ok = False
            f = parent
        run.reverse()
        runs[c] = run

    def _movable_above(self, frame, parents_of):
        """Joint types from ``frame`` up to (excluding) the next body joint."""
        out = []
        f = frame
        while f is not None and f.name.strip("\n") not in self._names:
            out.append(f.joint.joint_type)
            f = parents_of[id(f)]
        return out

    def on(self, device, dtype) -> dict:
        """The index and constant tensors on ``device`` (floats in ``dtype``), cached."""
        key = (device, dtype)
        c = self._device_cache.get(key)
        if c is None:
            steps = []
            for sub, dofs, rev, axes in self.steps:
                a = axes.to(device=device, dtype=dtype)
                K = _skew(a, dim=-1)
                steps.append((sub.to(device), dofs.to(device), rev.to(device), a, K, K @ K))
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
                "steps": steps,
                "levels": levels,
                "dof_mask": dof_mask,  # (D, J)
                "anc_mask": dof_mask.t().contiguous(),  # (J, D)
                "twist_gather": self.twist_gather.to(device),
                "delta_gather": self.delta_gather.to(device),
                # (n_bodies + 1, J) 0/1: which body carries each joint's point mass (points moved by no DOF go
                # to the extra last row, which no level reads); a product with it sums points per body
                "point_body": torch.zeros(self.n_bodies + 1, self.J, dtype=dtype)
                .index_put_(
                    (torch.where(self.point_body < 0, self.n_bodies, self.point_body), torch.arange(self.J)),
                    torch.ones(self.J, dtype=dtype),
                )
                .to(device),
                "step0_nodes": torch.tensor(
                    [c for c in range(self.J) if self.runs[c]], dtype=torch.long, device=device
                ),
            }
            self._device_cache[key] = c
        return c


def _tree(skeleton) -> _Tree:
    tree = getattr(skeleton, "_ik_tree", None)
    if tree is None:
        tree = _Tree(skeleton)
        # The skeleton is an nn.Module: a plain attribute (not a buffer or submodule) is fine for a cache.
        object.__setattr__(skeleton, "_ik_tree", tree)
    return tree


def _skew(a: Tensor, dim: int = 1) -> Tensor:
    """Cross-product matrices of the 3-vectors along ``dim``; the 3x3 replaces that dim (``dim, dim+1``)."""
    dim = dim % a.ndim
    x, y, z = a.unbind(dim)
    o = torch.zeros_like(x)
    m = torch.stack([o, -z, y, z, o, -x, -y, x, o], dim)
    shape = list(a.shape)
    shape[dim : dim + 1] = [3, 3]
    return m.reshape(shape)


# ------------------------------------------------------------------------------------------------- layout
#
# Inside the solver every per-pose quantity is stored *batch last*: ``(D, B)``, ``(J, 3, B)``,
# ``(n, 6, 6, B)``.
# The small-matrix algebra (3x3 rotations, 6x6 spatial inertias) is then written as broadcast products over
# contiguous B-long rows, which on a CPU is far faster than batched tiny ``bmm``/LAPACK calls (the same
# choice as the FK kernel in :mod:`torchpf.skeleton`).


def _mv(M: Tensor, v: Tensor) -> Tensor:
    """``(..., i, j, B) @ (..., j, B) -> (..., i, B)``."""
    return (M * v.unsqueeze(-3)).sum(-2)


def _frames(skeleton, th: Tensor) -> tuple[Tensor, Tensor]:
    """World rotations ``(J, 3, 3, B)`` and positions ``(J, 3, B)`` of the body joints at ``th (B, D)``."""
    T = skeleton.transforms(th)  # (B, J, 4, 4)
    return T[..., :3, :3].permute(1, 2, 3, 0), T[..., :3, 3].permute(1, 2, 0)


def _twists(tree: _Tree, q: Tensor, R: Tensor, rel: Tensor) -> Tensor:
    """World twists ``(D, 6, B)`` = (ω, v) of every DOF, about a per-pose centre.

    A point at ``y`` (relative to the centre) moved by DOF ``d`` has velocity ``v_d + ω_d x y`` per unit
    ``δθ_d``. ``q (D, B)`` pose, ``R (J, 3, 3, B)`` body-joint rotations, ``rel (J, 3, B)`` body-joint
    positions relative to the centre.

    Each body joint's run of single-DOF frames is walked back from the body joint's own frame: the world axis
    of a DOF is ``R a_local`` with ``R`` the rotation of the frame right below that DOF (rotating about an
    axis leaves it fixed), its pivot is that frame's origin; then ``R <- R Rot(a_local, -q)`` (revolute) or
    ``t <- t - a q`` (prismatic) gives the frame above.
    """
    c = tree.on(q.device, q.dtype)
    idx = c["step0_nodes"]
    Rc, tc = R.index_select(0, idx), rel.index_select(0, idx)
    eye = torch.eye(3, dtype=q.dtype, device=q.device)[None, :, :, None]
    parts = []
    for s, (sub, dofs, rev, a_loc, K, K2) in enumerate(c["steps"]):
        if s:
            Rc, tc = Rc.index_select(0, sub), tc.index_select(0, sub)
        a = (Rc * a_loc[:, None, :, None]).sum(2)  # (n, 3, B) = R @ a_local
        qs = q.index_select(0, dofs)  # (n, B)
        revf = rev.to(q.dtype)[:, None, None]
        # revolute: ω = a, v = p x a (p the pivot); prismatic: ω = 0, v = a
        v = torch.where(rev[:, None, None], torch.linalg.cross(tc, a, dim=1), a)
        parts.append(torch.cat([a * revf, v], 1))
        if s + 1 < len(c["steps"]):
            # Rot(a_local, -q) = I - sin(q) K + (1 - cos(q)) K²; identity for a prismatic DOF
            sn = torch.where(rev[:, None], torch.sin(qs), torch.zeros_like(qs))[:, None, None]
            cm = torch.where(rev[:, None], 1 - torch.cos(qs), torch.zeros_like(qs))[:, None, None]
            back = eye - sn * K[..., None] + cm * K2[..., None]  # (n, 3, 3, B)
            Rc = (Rc[:, :, :, None] * back[:, None]).sum(2)
            tc = torch.where(rev[:, None, None], tc, tc - a * qs[:, None])
    return torch.cat(parts, 0).index_select(0, c["twist_gather"])


def _point_velocities(tw: Tensor, rel: Tensor, anc_mask: Tensor, delta: Tensor) -> Tensor:
    """``J δ``: joint displacements ``(J, 3, B)`` for a step ``delta (D, B)`` (linearised)."""
    D, _, B = tw.shape
    V = (anc_mask @ (tw * delta[:, None]).reshape(D, 6 * B)).reshape(-1, 6, B)  # summed twist per joint
    return V[:, 3:] + torch.linalg.cross(V[:, :3], rel, dim=1)


def _gradient(tw: Tensor, rel: Tensor, w: Tensor, r: Tensor, dof_mask: Tensor) -> Tensor:
    """``Jᵀ W r`` ``(D, B)``: per DOF, its twist dotted with the wrench of the joints below it."""
    J, _, B = rel.shape
    wr = w[:, None] * r
    wrench = torch.cat([torch.linalg.cross(rel, wr, dim=1), wr], 1)  # (J, 6, B)
    sub = (dof_mask @ wrench.reshape(J, 6 * B)).reshape(-1, 6, B)
    return (tw * sub).sum(1)


def _inv_small(M: Tensor) -> Tensor:
    """Inverse of SPD matrices ``M (n, k, k, B)``: closed form for k <= 3, batched LAPACK otherwise."""
    k = M.shape[1]
    if k == 1:
        return 1.0 / M
    if k == 2:
        a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
        det = a * d - b * c
        return torch.stack([torch.stack([d, -b], 1), torch.stack([-c, a], 1)], 1) / det[:, None, None]
    if k == 3:
        # adjugate from cross products of the rows: row i of adj(M)ᵀ is r_{i+1} x r_{i+2}
        r1, r2 = M.roll(-1, 1), M.roll(-2, 1)
        cof = torch.linalg.cross(r1, r2, dim=2)  # (n, 3, 3, B) cofactor rows
        det = (M[:, 0] * cof[:, 0]).sum(1)
        return cof.transpose(1, 2) / det[:, None, None]
    # wider runs (a floating root): batched LAPACK on (n B, k, k); few such bodies per tree
    n, _, _, B = M.shape
    inv = torch.linalg.inv_ex(M.permute(0, 3, 1, 2).reshape(n * B, k, k))[0]
    return inv.reshape(n, B, k, k).permute(0, 2, 3, 1)


def _body_inertia(tree: _Tree, rel: Tensor, w: Tensor) -> Tensor:
    """Spatial inertias ``(n_bodies + 1, 6, 6, B)`` of the joints as point masses, summed per body.

    A point mass ``w`` at ``y``: ``w GᵀG`` with ``G = [-[y]_x, I]`` (so that ``ẏ = G (ω, v)``), i.e.
    ``w [[-[y]², [y]], [-[y], I]]``. The last row collects points that no DOF moves.
    """
    c = tree.on(rel.device, rel.dtype)
    X = _skew(rel, dim=1)  # (J, 3, 3, B)
    XX = (X[:, :, :, None] * X[:, None, :, :]).sum(2)
    eye = torch.eye(3, dtype=rel.dtype, device=rel.device)[None, :, :, None].expand_as(X)
    point = torch.cat([torch.cat([-XX, X], 2), torch.cat([-X, eye], 2)], 1) * w[:, None, None]
    J, B = rel.shape[0], rel.shape[-1]
    return (c["point_body"] @ point.reshape(J, 36 * B)).view(-1, 6, 6, B)


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
) -> Tensor:
    """Solve ``(JᵀWJ + diag(arm)) δ = JᵀW r + tau`` over the ``free`` DOFs (others get ``δ = 0``), ``O(J)``.

    Batch-last arguments: ``tw (D, 6, B)`` twists, ``rel (J, 3, B)`` joint positions about the centre,
    ``w (J, B)`` weights, ``r (J, 3, B)`` residuals (target - position), ``tau (D, B)`` extra right-hand side,
    ``arm (D, B)`` diagonal, ``free (D, B)`` bool; ``inertia`` from :func:`_body_inertia` (computed when not
    given). Returns ``δ (D, B)``.

    ``JᵀWJ + diag(arm)`` is the joint-space inertia matrix of point masses ``w_l`` at the joints with
    armature ``arm``, and ``JᵀW r`` the joint torque of the forces ``w_l r_l`` applied at the joints. So ``δ``
    is that system's joint acceleration from rest: Featherstone's articulated-body algorithm, with world-frame
    spatial vectors (no coordinate transforms between bodies), one level of the tree at a time.
    """
    c = tree.on(tw.device, tw.dtype)
    D, _, B = tw.shape
    if inertia is None:
        inertia = _body_inertia(tree, rel, w)
    freef = free.to(tw.dtype)
    point_force = torch.cat([torch.linalg.cross(rel, r, dim=1), r], 1) * w[:, None]  # (J, 6, B)
    force = (c["point_body"] @ point_force.reshape(-1, 6 * B)).view(-1, 6, B)

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
        Ut = (Ia[:, None] * St[:, :, None]).sum(3)  # (I S)ᵀ: (n, k, 6, B)
        Dm = (St[:, :, None] * Ut[:, None]).sum(3)  # Sᵀ I S: (n, k, k, B)
        arm_k = torch.where(on > 0, arm.index_select(0, dofs).reshape(n, k, B), torch.ones_like(on))
        eye_k = torch.eye(k, dtype=tw.dtype, device=tw.device)[None, :, :, None]
        Dm = Dm + eye_k * arm_k[:, :, None]
        u = tau.index_select(0, dofs).reshape(n, k, B) * on - (St * pa[:, None]).sum(2)
        Dinv = _inv_small(Dm)
        Dinv_u = (Dinv * u[:, None]).sum(2)  # (n, k, B)
        Dinv_Ut = (Dinv[:, :, :, None] * Ut[:, None]).sum(2)  # (n, k, 6, B)
        saved[li] = (St, Dinv_u, Dinv_Ut)
        if P is not None:
            Ic = Ia - (Ut[:, :, :, None] * Dinv_Ut[:, :, None]).sum(1)
            pc = pa + (Ut * Dinv_u[:, :, None]).sum(1)
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
            qdd = Dinv_u - (Dinv_Ut * a_par[:, None]).sum(2)
            acc = a_par + (St * qdd[:, :, None]).sum(1)
        else:
            qdd = Dinv_u
            acc = (St * qdd[:, :, None]).sum(1)
        out.append(qdd.reshape(-1, B))
    return torch.cat(out, 0).index_select(0, c["delta_gather"]) * freef


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
    ``d`` and zero elsewhere (world axis ``a_d``, pivot ``p_d``). Raises ``ValueError`` for a skeleton whose
    structure it cannot read; :func:`autograd_jacobian` works for any.
    """
    tree = _tree(skeleton)
    if not tree.ok:
        raise ValueError("tree_jacobian: unsupported skeleton structure; use autograd_jacobian")
    flat = theta.reshape(-1, theta.shape[-1])
    R, x = _frames(skeleton, flat)
    rel = x - x[:1]
    tw = _twists(tree, flat.t(), R, rel)  # (D, 6, B)
    mask = tree.on(flat.device, flat.dtype)["dof_mask"]  # (D, J)
    cols = tw[:, None, 3:] + torch.linalg.cross(
        tw[:, None, :3].expand(-1, rel.shape[0], -1, -1), rel[None], dim=2
    )
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
        """Frames, residual ``(J, 3, B)`` and cost ``(B,)`` at ``q (D, B)``."""
        R, x = _frames(self.skeleton, q.t())
        r = self.g - x
        cost = (self.w * r.square().sum(1)).sum(0) + self.reg * (q - self.th0).square().sum(0)
        return R, x, r, cost

    def linearise(self, q, R, x):
        """What :meth:`solve` needs at ``q``: twists and body inertias (tree) or the Jacobian (autograd)."""
        if self.tree is not None:
            rel = x - x[:1].detach()
            tw = _twists(self.tree, q, R, rel)
            return ("tree", tw, rel, _body_inertia(self.tree, rel, self.w))
        return ("dense", autograd_jacobian(self.skeleton, q.t()))

    @staticmethod
    def subset_lin(lin, rows):
        """The linearisation of the poses ``rows`` only."""
        if lin[0] == "tree":
            return ("tree", *(t.index_select(-1, rows) for t in lin[1:]))
        return ("dense", lin[1].index_select(0, rows))

    def gradient(self, lin, r, q) -> Tensor:
        """Descent direction of the cost, ``JᵀW r - μ (q - θ_init)``: ``(D, B)``."""
        if lin[0] == "tree":
            dof_mask = self.tree.on(q.device, q.dtype)["dof_mask"]
            g = _gradient(lin[1], lin[2], self.w, r, dof_mask)
        else:
            g = torch.einsum("bjkd,jkb->db", lin[1], self.w[:, None] * r)
        return g - self.reg * (q - self.th0)

    def solve(self, lin, w, r, tau, arm, free) -> Tensor:
        """``(JᵀWJ + diag(arm)) δ = JᵀW r + tau`` over ``free``: ``δ (D, B)``."""
        if lin[0] == "tree":
            return _aba_solve(self.tree, lin[1], lin[2], w, r, tau, arm, free, inertia=lin[3])
        return _dense_solve(lin[1], w.t(), r.permute(2, 0, 1), tau.t(), arm.t(), free.t()).t()

    def displacement(self, lin, delta) -> Tensor:
        """``J δ`` ``(J, 3, B)``."""
        if lin[0] == "tree":
            anc = self.tree.on(delta.device, delta.dtype)["anc_mask"]
            return _point_velocities(lin[1], lin[2], anc, delta)
        return torch.einsum("bjkd,db->jkb", lin[1], delta)

    def step(self, q, R, x, r, lam, refine: int = 2):
        """Projected LM step ``δ (D, B)`` with an active set for the joint limits.

        Held: the user's frozen DOFs and those at a bound whose descent direction points outward. Then, up
        to ``refine`` times and only for the poses concerned, DOFs the step would push through a bound are
        pinned *at* that bound and the others re-solved against the linearised residual this leaves, so
        that the remaining DOFs compensate instead of the step simply being cut.
        """
        lin = self.linearise(q, R, x)
        lo, hi = self.lo, self.hi
        eps = 1e-9
        grad = self.gradient(lin, r, q)
        hold = ((q <= lo + eps) & (grad <= 0)) | ((q >= hi - eps) & (grad >= 0))
        free = self.free_d & ~hold
        arm = (self.reg + lam)[None].expand_as(q)
        tau = -self.reg * (q - self.th0)
        delta = self.solve(lin, self.w, r, tau, arm, free)
        fixed = torch.zeros_like(q)  # prescribed moves of DOFs pinned at a bound
        for _ in range(refine):
            target = q + fixed + delta
            out = free & ((target < lo) | (target > hi))
            rows = out.any(0).nonzero().flatten()
            if rows.numel() == 0:
                break

            def sub(t, rows=rows):
                return t.index_select(-1, rows)

            q_s, out_s, target_s = sub(q), sub(out), sub(target)
            fixed_s = sub(fixed) + torch.where(
                out_s,
                torch.maximum(torch.minimum(target_s, hi), lo) - q_s - sub(fixed),
                torch.zeros_like(q_s),
            )
            free_s = sub(free) & ~out_s
            lin_s = self.subset_lin(lin, rows)
            r_lin = sub(r) - self.displacement(lin_s, fixed_s)
            tau_s = -self.reg * (q_s + fixed_s - sub(self.th0))
            delta_s = self.solve(lin_s, sub(self.w), r_lin, tau_s, sub(arm), free_s)
            delta = delta.index_copy(-1, rows, delta_s)
            fixed = fixed.index_copy(-1, rows, fixed_s)
            free = free.index_copy(-1, rows, free_s)
        return fixed + delta


def project(
    skeleton,
    targets: Tensor,
    theta_init: Tensor,
    joint_weights: Tensor | None = None,
    *,
    iters: int = 30,
    tol: float = 1e-4,
    ftol: float = 1e-4,
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
            (autograd Jacobian + dense Cholesky, general). ``"tree"`` falls back to ``"autograd"`` for a
            skeleton whose structure it cannot read.
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
    if tree is not None and not tree.ok:
        tree = None

    # batch-last copies for the solver
    g_bl, th0_bl, w_bl = g.permute(1, 2, 0), th0.t(), w.t()
    with torch.no_grad():
        prob = _Problem(skeleton, tree, g_bl.detach(), th0_bl.detach(), w_bl.detach(), lo, hi, free_d, reg)
        q = torch.maximum(torch.minimum(prob.th0, hi), lo)
        R, x, r, cost = prob.evaluate(q)
        lam = torch.full((B,), float(damping), dtype=dtype, device=device)
        active = torch.ones(B, dtype=torch.bool, device=device)
        converged = torch.zeros(B, dtype=torch.bool, device=device)
        n_iter = torch.full((B,), iters, dtype=torch.long, device=device)
        tiny_cost = J * 1e-12
        rows = None  # poses still iterating (None: all); converged poses drop out of the work
        for it in range(iters):
            P = prob if rows is None else prob.subset(rows)

            def pick(t, rows=rows):
                return t if rows is None else t.index_select(-1, rows)

            q_a, R_a, x_a, r_a, cost_a, lam_a = (pick(t) for t in (q, R, x, r, cost, lam))
            delta = P.step(q_a, R_a, x_a, r_a, lam_a)
            # Full step first; then a line search on the projection arc clamp(q + α δ), α = 1/2, 1/4, for
            # the poses whose cost went up (each halving costs one FK of those poses only).
            q_t = torch.maximum(torch.minimum(q_a + delta, hi), lo)
            R_t, x_t, r_t, c_t = P.evaluate(q_t)
            full = c_t <= cost_a
            rel_dec = (cost_a - c_t) / cost_a.clamp_min(torch.finfo(dtype).tiny)
            q_a = torch.where(full, q_t, q_a)
            R_a = torch.where(full, R_t, R_a)
            x_a = torch.where(full, x_t, x_a)
            r_a = torch.where(full, r_t, r_a)
            cost_a = torch.where(full, c_t, cost_a)
            accepted = full.clone()
            alpha = 0.5
            for _ in range(2):
                sub = (~accepted).nonzero().flatten()
                if sub.numel() == 0:
                    break
                q_t = torch.maximum(torch.minimum(q_a[:, sub] + alpha * delta[:, sub], hi), lo)
                R_t, x_t, r_t, c_t = P.subset(sub).evaluate(q_t)
                ok = c_t <= cost_a[sub]
                put, take = sub[ok], ok.nonzero().flatten()
                q_a[:, put] = q_t[:, take]
                R_a[..., put] = R_t[..., take]
                x_a[..., put] = x_t[..., take]
                r_a[..., put] = r_t[..., take]
                cost_a[put] = c_t[take]
                accepted[put] = True
                alpha *= 0.5
            small = delta.abs().amax(0) < tol
            stuck = ~accepted & (lam_a >= 1e6)  # no descent even with a gradient-descent-sized step
            exact = cost_a <= tiny_cost  # targets on the manifold, met to ~1 µm per joint
            done = (full & (small | (rel_dec < ftol))) | stuck | exact
            lam_a = torch.where(full, (lam_a * 0.3).clamp_min(1e-7), lam_a * torch.where(accepted, 3.0, 30.0))
            if rows is None:
                q, R, x, r, cost, lam = q_a, R_a, x_a, r_a, cost_a, lam_a
                idx = torch.arange(B, device=device)
            else:
                idx = rows
                q[:, idx], R[..., idx], x[..., idx], r[..., idx] = q_a, R_a, x_a, r_a
                cost[idx], lam[idx] = cost_a, lam_a
            converged[idx[done & ~stuck]] = True
            n_iter[idx[done]] = it + 1
            active[idx[done]] = False
            rows = active.nonzero().flatten()
            if rows.numel() == 0:
                break

    if torch.is_grad_enabled() and (
        targets.requires_grad or theta_init.requires_grad or _needs(joint_weights)
    ):
        # One differentiable Gauss-Newton step at the solution: the value moves by ~0 at convergence, and the
        # derivative is that of the fixed point, (JᵀWJ + μI)⁻¹ JᵀW for the targets (implicit function).
        prob_g = _Problem(skeleton, tree, g_bl, th0_bl, w_bl, lo, hi, free_d, reg)
        q_fix = q.detach()
        R_g, x_g = _frames(skeleton, q_fix.t())
        r_g = g_bl - x_g
        delta = prob_g.step(q_fix, R_g, x_g, r_g, torch.zeros_like(lam), refine=0)
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
