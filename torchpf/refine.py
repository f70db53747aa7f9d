"""Local optimisation of poses on a differentiable image cue: the "local optimisation" layer of a hybrid
tracker (Gall, Rosenhahn, Brox, Seidel, IJCV 2010, "Optimization and filtering for human motion capture":
a global stochastic search, then gradient refinement of its best hypotheses).

:class:`Refiner` minimises, for a batch of poses ``x (..., K, D)`` independently::

    E(x) = -log p_cue(z | x) - log p(x)

where ``p_cue`` is a differentiable likelihood (default the two-sided distance-transform silhouette cue,
:class:`~torchpf.likelihoods.SilhouetteDistanceLikelihood`, whose gradient is informative away from the
silhouette's boundary; any likelihood of :mod:`torchpf.likelihoods` works) and ``log p(x)`` an optional
log-prior passed per call (a filter passes its motion prior ``log p(x | x_{t-1})`` given each particle's
parent, so the refinement climbs the filtering posterior): silhouettes leave some rotations free (a
forearm's roll, a finger), and without a prior the optimiser moves those at random.

The optimiser is Adam (Kingma & Ba 2015) run elementwise, so every pose of the batch takes its own steps
(batch-independent: one pose's loss never scales another's step), with a learning rate per DOF kind
(radians for revolute DOFs, metres for prismatic ones) decayed linearly to 10 %, a projection onto the joint
limits after every step (projected gradient descent), frozen DOFs (fixed by their limits, or given), and
keep-best: each pose returns the best iterate it visited, so refinement never makes a pose worse on ``E``.

**Damping.** Adam divides each DOF's step by the size of its own gradient, so a DOF the cue barely sees (a
finger inside the silhouette, a forearm's roll, a limb a mask defect pulls at) takes full steps driven by
tiny gradients, rounding noise included: two float32 runs of one refinement, whose cue values differed by
1e-6, ended 0.1-0.27 rad apart in such DOFs. ``damping`` raises Adam's ``eps`` to a share of the pose's
largest gradient (each scaled by its DOF's step), so such a DOF moves in proportion to its gradient (as in
plain gradient descent) while the DOFs the cue sees keep Adam's steps; with 0.1 the two runs agree to 3e-7.
On the foreign renders of the 11 CMU clips (``track``'s defaults, 2 runs; BENCHMARKS.md) 0.1 took clean
masks from 38 to 37-38 mm and noisy ones from 108 to 99 mm over three draws of their defects; 0.3 gave 94 mm
noisy but 40-42 mm clean, and 1.0 47 mm clean.

**Refining in other coordinates.** ``space`` (per call; :class:`RefineSpace`) lets the optimiser move other
coordinates ``y`` of the poses, ``x = clamp(decode(y))``, with the gradient pulled back through ``decode``
(``dE/dy = J^T dE/dx``, ``J = d decode / dy``): e.g. an action model's aSpace (Rius eq. 1), so a refined
posture stays in the action's principal subspace (:class:`priors.action.ActionSubspace`) instead of moving
the DOFs the silhouettes leave free. Without one the poses' own DOFs are the coordinates.

Cost: one step is one forward and one backward pass of the cue for the ``K`` poses, about
:attr:`Refiner.cost_per_step` likelihood evaluations each (forward + backward ~ 3 forwards, the usual
reverse-mode ratio; ``python -m benchmarks.refine`` measures it); :meth:`Refiner.evaluations` counts them
for the equal-budget comparisons of :mod:`torchpf.filters.registry`.

Example::

    from torchpf.refine import Refiner
    refiner = Refiner(skel, cameras, steps=20)
    out = refiner(poses, Silhouettes(masks))              # poses (K, D) -> out.x (K, D), out.loss (K,)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor, nn

__all__ = ["RefineResult", "RefineSpace", "Refiner"]


def descent_setup(
    skeleton, cameras, cue, cue_options, steps: int, lr_rotation: float, lr_translation: float, damping: float
) -> tuple[nn.Module, Tensor]:
    """The checked arguments of a descent on a cue (:class:`Refiner`,
    :class:`~torchpf.smooth.TrajectorySmoother`): the cue module (a name of
    :data:`~torchpf.likelihoods.LIKELIHOODS` built with ``cue_options``) and the per-DOF Adam step ``(D,)``
    float64, ``lr_rotation`` (rad) for revolute DOFs, ``lr_translation`` (m) for prismatic ones, 0 for a DOF
    fixed by its limits."""
    if isinstance(cue, str):
        from torchpf.likelihoods import LIKELIHOODS

        cue = LIKELIHOODS.get(cue)(skeleton, cameras, **dict(cue_options or {}))
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if not (lr_rotation > 0 and lr_translation > 0):
        raise ValueError("lr_rotation and lr_translation must be positive")
    if not damping >= 0:
        raise ValueError(f"damping must be >= 0, got {damping}")
    lr = torch.where(skeleton.dof_revolute, lr_rotation, lr_translation).double()
    return cue, torch.where(skeleton.lower >= skeleton.upper, 0.0, lr)


def damping_factor(damping: float, lr: Tensor) -> Tensor | None:
    """The damping's per-coordinate factor ``damping / lr_d`` (None for plain Adam), once per descent: the
    damped ``eps`` of :func:`damped_adam_step` is ``damping max_j(lr_j rms_j) / lr_d``."""
    return damping / torch.where(lr > 0, lr, 1.0) if damping > 0 else None


def damped_adam_step(
    cur: Tensor, grad: Tensor, m: Tensor, v: Tensor, lr: Tensor, damp: Tensor | None, step: int, steps: int
) -> Tensor:
    """One projected-Adam step of :class:`Refiner` (Kingma & Ba 2015, with bias correction and the
    refiner's damping), elementwise over ``cur (..., E)``: updates the moments ``m``, ``v`` in place and
    returns ``cur - decay lr m_hat / (sqrt(v_hat) + eps_d)``, the step size ``lr (E,)`` decayed linearly to
    10 % over ``steps``; ``eps_d = damp_d max_j(lr_j sqrt(v_hat_j))`` over the last axis
    (:func:`damping_factor`; ``damp`` None: plain Adam's 1e-8). In few in-place operations: each costs
    microseconds at a refinement's sizes."""
    b1, b2, eps = 0.9, 0.999, 1e-8
    k = step + 1
    decay = 1.0 - 0.9 * step / max(1, steps - 1)
    m.mul_(b1).add_(grad, alpha=1 - b1)
    v.mul_(b2).addcmul_(grad, grad, value=1 - b2)
    denom = v.mul(1.0 / (1 - b2**k)).sqrt_()
    if damp is not None:
        denom = denom.addcmul_((denom * lr).amax(-1, keepdim=True), damp)
    denom = denom.add_(eps)
    return cur.addcmul(lr, m.div(denom), value=-decay / (1 - b1**k))


@runtime_checkable
class RefineSpace(Protocol):
    """Coordinates ``y (..., E)`` in which :class:`Refiner` moves poses ``x (..., D)`` (module docstring).

    ``encode(x)`` gives the start ``y`` of poses ``x``; ``decode(y)`` the poses (the refiner clamps them to
    the joint limits); ``pullback(y, grad_x)`` the gradient ``J^T grad_x (..., E)`` of ``decode`` at ``y``;
    ``step_sizes(lr)`` the Adam step per coordinate ``(E,)`` from the refiner's per-DOF steps ``lr (D,)``
    (0 freezes a coordinate).
    """

    def encode(self, x: Tensor) -> Tensor: ...

    def decode(self, y: Tensor) -> Tensor: ...

    def pullback(self, y: Tensor, grad_x: Tensor) -> Tensor: ...

    def step_sizes(self, lr: Tensor) -> Tensor: ...


@dataclass
class RefineResult:
    """What :meth:`Refiner.forward` returns: ``x (..., K, D)`` the refined poses (the best iterate of each),
    ``loss_before``, ``loss`` ``(..., K)`` the objective ``E`` at the start and at ``x``, ``steps`` taken."""

    x: Tensor
    loss_before: Tensor
    loss: Tensor
    steps: int


class Refiner(nn.Module):
    """Projected Adam on ``E(x) = -log p_cue(z | x) - log p(x)`` (module docstring), batched over poses.

    Args:
        skeleton: the body model (its limits, revolute mask).
        cameras: a :class:`~torchpf.camera.CameraRig` or list of cameras; used to build the default cue.
        cue: a likelihood module ``(x (..., K, D), obs) -> (..., K)``, or a name of
            :data:`~torchpf.likelihoods.LIKELIHOODS` (default ``"silhouette_distance"``).
        cue_options: keywords of a named cue.
        steps: gradient steps per call.
        lr_rotation: Adam step (radians) for revolute DOFs; ``lr_translation`` (metres) for prismatic ones.
        frozen: ``(D,)`` bool of DOFs never moved; DOFs with ``lower == upper`` are always frozen.
        damping: Adam's ``eps`` relative to each pose's largest step-scaled gradient (module docstring):
            DOF ``d`` takes ``lr_d m_d / (sqrt(v_d) + damping max_j(lr_j sqrt(v_j)) / lr_d)``, a full
            Adam step where the cue sees it and a step in proportion to its gradient where it barely does.
            0 is plain Adam.
    """

    #: likelihood evaluations one gradient step costs per pose (forward + backward ~ 3 forwards)
    cost_per_step: float = 3.0

    def __init__(
        self,
        skeleton,
        cameras=None,
        *,
        cue="silhouette_distance",
        cue_options=None,
        steps: int = 20,
        lr_rotation: float = 0.03,
        lr_translation: float = 0.01,
        frozen=None,
        damping: float = 0.1,
    ):
        super().__init__()
        self.cue, lr = descent_setup(
            skeleton, cameras, cue, cue_options, steps, lr_rotation, lr_translation, damping
        )
        self.damping = float(damping)
        self.skeleton = skeleton
        self.steps = int(steps)
        fixed = lr == 0
        if frozen is not None:
            frozen = torch.as_tensor(frozen, dtype=torch.bool)
            if frozen.shape != fixed.shape:
                raise ValueError(f"frozen must have shape {tuple(fixed.shape)}, got {tuple(frozen.shape)}")
            fixed = fixed | frozen.to(fixed.device)
        self.register_buffer("lr", torch.where(fixed.to(lr.device), 0.0, lr))

    @classmethod
    def cost(cls, n_poses: int, steps: int) -> int:
        """Likelihood-evaluation equivalents of refining ``n_poses`` poses with ``steps`` gradient steps
        (:attr:`cost_per_step` each, plus the final look at the last iterate)."""
        return int(math.ceil(n_poses * (steps * cls.cost_per_step + 1)))

    def evaluations(self, n_poses: int) -> int:
        """:meth:`cost` of refining ``n_poses`` poses once with this refiner's ``steps``."""
        return self.cost(n_poses, self.steps)

    def clamp(self, x: Tensor) -> Tensor:
        """Poses ``x (..., D)`` projected onto the skeleton's joint limits (:meth:`Skeleton.clamp`)."""
        return self.skeleton.clamp(x)

    def objective(self, x: Tensor, obs, log_prior=None) -> Tensor:
        """``E(x) (..., K)`` for poses ``x (..., K, D)``; ``log_prior``: ``x -> (..., K)`` or None."""
        loss = -self.cue(x, obs)
        if log_prior is not None:
            loss = loss - log_prior(x).to(loss)
        return loss

    def objective_and_grad(self, x: Tensor, obs, log_prior=None) -> tuple[Tensor, Tensor]:
        """``E(x) (..., K)`` and its gradient ``(..., K, D)``, detached. A cue with
        ``log_likelihood_and_grad`` (every :class:`~torchpf.likelihoods.Likelihood`) gives its gradient
        without back-propagating through forward kinematics (the tree's vector-Jacobian product, most of
        the backward pass for a few poses); the prior's goes through autograd."""
        if hasattr(self.cue, "log_likelihood_and_grad"):
            loglik, grad = self.cue.log_likelihood_and_grad(x, obs)
            loss, grad = -loglik, -grad.to(x)
            if log_prior is not None:
                with torch.enable_grad():
                    xr = x.detach().requires_grad_(True)
                    lp = log_prior(xr).to(loss)
                    (g,) = torch.autograd.grad(lp.sum(), xr)
                loss, grad = loss - lp.detach(), grad - g
            return loss, grad
        with torch.enable_grad():
            xr = x.detach().requires_grad_(True)
            loss = self.objective(xr, obs, log_prior)
            (grad,) = torch.autograd.grad(loss.sum(), xr)
        return loss.detach(), grad

    def forward(self, x: Tensor, obs, log_prior=None, space: RefineSpace | None = None) -> RefineResult:
        """Refine poses ``x (..., K, D)`` on observation ``obs``; returns a :class:`RefineResult`.

        ``log_prior``: optional differentiable ``x (..., K, D) -> (..., K)`` log-prior added to the cue.
        ``space``: optional :class:`RefineSpace` whose coordinates the optimiser moves (default the DOFs);
        its ``decode(encode(x))`` is the first iterate, so a space that is a subset of poses (a subspace)
        starts from ``x``'s image there.

        Computes its gradients whatever the caller's grad mode (a filter calls it under ``no_grad``); the
        result is detached. A pose whose objective is not finite is left where it is.
        """
        # A non-finite pose is not refined (and must not reach the cue's backward pass: grid_sample's
        # gradient at a NaN coordinate reads out of bounds); a finite stand-in runs in its place.
        finite = torch.isfinite(x).all(-1, keepdim=True)
        x0 = torch.where(finite, x.detach(), self.clamp(torch.zeros_like(x)))
        # the limits once in the poses' dtype (what self.clamp does, without its per-call conversions)
        lo = self.skeleton.lower.to(x0)
        hi = self.skeleton.upper.to(x0)

        def limited(z):
            return torch.maximum(torch.minimum(z, hi), lo)

        if space is None:  # the DOFs themselves, each iterate projected onto the limits
            cur, lr = x0.clone(), self.lr.to(x0)

            def decode(y):
                return y

        else:  # the space's coordinates, left free; the poses they decode to are projected
            cur, lr = space.encode(x0), space.step_sizes(self.lr.to(x0)).to(x0)

            def decode(y):
                return limited(space.decode(y))

        damp = damping_factor(self.damping, lr)
        m = torch.zeros_like(cur)
        v = torch.zeros_like(cur)
        best = decode(cur)
        best_loss = torch.full(cur.shape[:-1], math.inf, dtype=cur.dtype, device=cur.device)
        first = None
        for step in range(self.steps):
            pose = decode(cur)
            loss, grad = self.objective_and_grad(pose, obs, log_prior)
            if first is None:
                first = loss
            better = loss < best_loss  # NaN compares False: a non-finite iterate is never kept
            best = torch.where(better.unsqueeze(-1), pose, best)
            best_loss = torch.where(better, loss, best_loss)
            grad = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)
            if space is not None:
                grad = space.pullback(cur, grad)
            cur = damped_adam_step(cur, grad, m, v, lr, damp, step, self.steps)
            if space is None:
                cur = limited(cur)
        pose = decode(cur)
        with torch.no_grad():
            last = self.objective(pose, obs, log_prior)
        if first is None:
            first = last
        better = last < best_loss
        best = torch.where(better.unsqueeze(-1), pose, best)
        best_loss = torch.where(better, last, best_loss)
        stuck = ~torch.isfinite(best_loss).unsqueeze(-1) | ~finite  # never finite: keep the start pose
        best = torch.where(stuck, x.detach(), best)
        best_loss = torch.where(finite.squeeze(-1), best_loss, math.nan)
        first = torch.where(finite.squeeze(-1), first, math.nan)
        return RefineResult(x=best, loss_before=first, loss=best_loss, steps=self.steps)
