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
  ``a_d`` (prismatic) for the joints ``j`` below it (:mod:`torchpf.kinematics.jacobian`, on
  ``skeleton.tree``). ``method="autograd"``
  takes the Jacobian ``(B, 3J, D)`` of ``skeleton.fk`` by forward-mode autograd (``torch.func.jacfwd`` under
  ``vmap``) and works for any skeleton; the two agree to rounding (tested). The tree Jacobian costs about
  one FK; the autograd one about ``D`` FKs, which is why it is not the default.
* **Linear solve.** The Gauss-Newton matrix ``JᵀWJ + (μ + λ) I`` of a kinematic tree is the joint-space
  inertia matrix of point masses ``w_l`` sitting at the joints, with ``μ + λ`` as joint armature, so
  ``method="tree"`` solves it exactly in ``O(J)`` per pose with the articulated-body recursion
  (Featherstone's ABA, world-frame spatial vectors, zero velocities; :mod:`torchpf.kinematics.aba`): no
  ``(B, D, D)`` matrix is formed or factorised. ``method="autograd"`` forms ``JᵀWJ`` and uses a batched
  Cholesky solve. On a CPU, without autograd, the recursion runs as one fused kernel
  (:mod:`torchpf.kinematics._aba_cpu`, numba): 4-25x faster than the same recursion as tensor operations
  (``TORCHPF_FUSED=0`` selects those, as CUDA and autograd do).
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

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torchpf.distributions import flatten_batch, unflatten_batch
from torchpf.kinematics.aba import aba_solve, body_inertia, dense_solve, fused_kernel_applies
from torchpf.kinematics.jacobian import (
    autograd_jacobian,
    dof_frames,
    joint_torques,
    point_velocities,
    twists,
    wrenches,
)

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
        ap, x = dof_frames(self.skeleton, q.t())
        r = self.g - x
        cost = (self.w * r.square().sum(1)).sum(0) + self.reg * (q - self.th0).square().sum(0)
        return ap, x, r, cost

    def linearise(self, q, ap, x):
        """What :meth:`solve` needs at ``q``: twists and body inertias (tree) or the Jacobian (autograd)."""
        if self.tree is not None:
            centre = x[0].detach()
            rel = x - centre
            tw = twists(self.tree, ap, centre)
            # the fused CPU kernel sums the body inertias itself
            inertia = None if fused_kernel_applies(tw, rel) else body_inertia(self.tree, rel, self.w)
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
            g = joint_torques(self.tree, lin[1], wrenches(lin[2], self.w, r) if wrench is None else wrench)
        else:
            g = torch.einsum("bjkd,jkb->db", lin[1], self.w[:, None] * r)
        return g - self.reg * (q - self.th0)

    def solve(self, lin, w, r, tau, arm, free, wrench=None) -> Tensor:
        """``(JᵀWJ + diag(arm)) δ = JᵀW r + tau`` over ``free``: ``δ (D, B)``."""
        if lin[0] == "tree":
            return aba_solve(self.tree, lin[1], lin[2], w, r, tau, arm, free, inertia=lin[3], wrench=wrench)
        return dense_solve(lin[1], w.t(), r.permute(2, 0, 1), tau.t(), arm.t(), free.t()).t()

    def displacement(self, lin, delta) -> Tensor:
        """``J δ`` ``(J, 3, B)``."""
        if lin[0] == "tree":
            return point_velocities(self.tree, lin[1], lin[2], delta)
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
        wrench = wrenches(lin[2], self.w, r) if lin[0] == "tree" else None
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
    g, _ = flatten_batch(targets.to(dtype).expand(*batch, J, 3), 2)
    th0, _ = flatten_batch(theta_init.to(device=device, dtype=dtype).expand(*batch, D), 1)
    B = g.shape[0]
    if joint_weights is None:
        w = g.new_ones(B, J)
    else:
        w, _ = flatten_batch(joint_weights.to(dtype=dtype, device=device).expand(*batch, J), 1)
    lo = skeleton.lower.to(device=device, dtype=dtype)[:, None]
    hi = skeleton.upper.to(device=device, dtype=dtype)[:, None]
    free_d = _free_mask(skeleton, free, D, device)[:, None]

    tree = skeleton.tree if method == "tree" else None

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
        ap_g, x_g = dof_frames(skeleton, q_fix.t())
        r_g = g_bl - x_g
        delta = prob_g.step(q_fix, ap_g, x_g, r_g, torch.zeros_like(lam), refine=0)[0]
        q = q_fix + delta - delta.detach()

    theta = unflatten_batch(q.t(), batch)
    if not return_result:
        return theta
    with torch.no_grad():
        err = (x - prob.g).norm(dim=1).t()  # (B, J)
    return IKResult(
        theta=theta,
        converged=unflatten_batch(converged, batch),
        residual=unflatten_batch(err.square().mean(-1).sqrt(), batch),
        errors=unflatten_batch(err, batch),
        cost=unflatten_batch(cost, batch),
        iterations=unflatten_batch(n_iter, batch),
    )


def _needs(t) -> bool:
    return isinstance(t, Tensor) and t.requires_grad
