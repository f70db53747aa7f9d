"""MCMC filtering with hybrid Monte Carlo moves, Brubaker Alg. 3-4 and eq. 21-22.

After the usual SIR propagation and weighting, the particles are resampled (``j`` with probability ``w_j``)
and each becomes the start of a Markov chain whose stationary distribution is the frame's posterior given its
parent, ``P(q) ∝ p(z_t | q) p(q | x_{t-1}^j)`` (Alg. 3). ``R`` hybrid Monte Carlo moves (Alg. 4) are made per
particle; the weights are then uniform. Since every move leaves ``P`` invariant (eq. 21), the moves only
rejuvenate the particle set: they spread duplicated particles over the posterior without changing what the set
represents, so the log-evidence estimate is the SIR one.

One HMC move (Alg. 4) with energy ``E(q) = -log P(q)``, momentum ``p_0 ~ N(0, I)`` and diagonal step
``Delta`` runs ``L`` leapfrog steps::

    p <- p - Delta/2 dE/dq(q);   q <- q + Delta p;   p <- p - Delta/2 dE/dq(q)

and accepts ``q_L`` with probability ``min(1, exp(-c))``, ``c = H(q_L, p_L) - H(q_0, p_0)``,
``H(q, p) = E(q) + |p|^2 / 2``. (The text of eq. 22 prints ``p_0`` and ``p_L`` swapped; the Hamiltonian
difference above is the standard, detailed-balance-preserving form.) Gradients come from autograd through the
likelihood and ``dynamics.log_prob``, so both must be differentiable in ``x``.

Step size: ``Delta = step_size * step_scale`` with a per-sequence ``step_size (...)``. During the first
``burn_in`` frames it is tuned after every move towards ``target_acceptance`` (Brubaker's rule of thumb: ~75%)
by a Robbins-Monro recursion on its log, ``log step += 0.5 k^-0.75 clip(logit(a_k) - logit(target), +-3)``,
where ``a_k`` is the acceptance probability averaged over the ``N`` chains of the sequence (a low-noise
signal) and the logit makes the first corrections large when the step is off by orders of magnitude;
afterwards the step is kept fixed, so the chains are proper MCMC (the caveat under eq. 22). The adaptation
state lives in ``state.aux``. ``info["acceptance"] (...)`` is the fraction of accepted moves of the frame and
``info["step_size"] (...)`` the step used.

Example::

    mpf = MCMCParticleFilter(dynamics, likelihood, n_particles=500, n_moves=2, n_leapfrog=5, progress=False)
    track = mpf.run(observations, x0, generator=g)
    track.stats["acceptance"]                                  # (..., T)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor

from torchpf.filters.base import ParticleFilter
from torchpf.filters.state import ParticleState, gather_particles


def _value_and_grad(log_target: Callable[[Tensor], Tensor], q: Tensor) -> tuple[Tensor, Tensor]:
    with torch.enable_grad():
        q = q.detach().requires_grad_(True)
        value = log_target(q)
        if not value.requires_grad:  # a target that does not depend on q (e.g. masked out): zero force
            return value.detach(), torch.zeros_like(q)
        (grad,) = torch.autograd.grad(value.sum(), q)
    return value.detach(), grad


def hmc_move(
    q: Tensor,
    log_target: Callable[[Tensor], Tensor],
    step_size: Tensor | float,
    n_leapfrog: int = 5,
    generator: torch.Generator | None = None,
    step_scale: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """One hybrid Monte Carlo move per particle (Brubaker Alg. 4), leaving ``exp(log_target)`` invariant.

    Args:
        q: ``(..., N, D)`` current states (each particle is an independent chain).
        log_target: ``(..., N, D) -> (..., N)`` unnormalised log density ``log P(q) = -E(q)``; differentiable,
            and particle ``i``'s value must depend on ``q[..., i, :]`` only.
        step_size: scalar or ``(...)`` leapfrog step (state units).
        n_leapfrog: ``L`` leapfrog steps.
        generator: randomness for the momenta and the Metropolis test.
        step_scale: optional ``(D,)`` per-dimension multiplier of the step (the diagonal of ``Delta``).

    Returns:
        ``(q_new (..., N, D), accept_prob (..., N), accepted (..., N) bool)``. Non-finite energies are
        rejected.
    """
    q = q.detach()
    step = torch.as_tensor(step_size, device=q.device, dtype=q.dtype)
    step = step.reshape(step.shape + (1, 1))
    if step_scale is not None:
        step = step * torch.as_tensor(step_scale, device=q.device, dtype=q.dtype)
    p0 = torch.randn(q.shape, generator=generator, device=q.device, dtype=q.dtype)
    log_p0, grad = _value_and_grad(log_target, q)
    # grad is d log P / dq = -dE/dq, hence the plus signs.
    p = p0 + 0.5 * step * grad
    q_new = q
    for i in range(n_leapfrog):
        q_new = q_new + step * p
        log_p, grad = _value_and_grad(log_target, q_new)
        p = p + (step if i < n_leapfrog - 1 else 0.5 * step) * grad
    h0 = -log_p0 + 0.5 * (p0 * p0).sum(-1)
    h1 = -log_p + 0.5 * (p * p).sum(-1)
    log_accept = torch.nan_to_num(torch.clamp(h0 - h1, max=0.0), nan=-math.inf)
    u = torch.rand(log_accept.shape, generator=generator, device=q.device, dtype=q.dtype)
    accepted = torch.log(u) < log_accept
    q_out = torch.where(accepted.unsqueeze(-1), q_new, q)
    return q_out, torch.exp(log_accept), accepted


class MCMCParticleFilter(ParticleFilter):
    """Particle filter with HMC rejuvenation moves (Brubaker Alg. 3-4). See the module docstring.

    Args:
        dynamics, likelihood, proposal, n_particles, resampler, ess_threshold, sampling, progress: as
            :class:`~torchpf.filters.ParticleFilter`; ``resampler`` also picks the chains' starting points.
        n_moves: ``R`` HMC moves per particle and frame.
        n_leapfrog: ``L`` leapfrog steps per move.
        step_size: initial leapfrog step (state units).
        step_scale: optional ``(D,)`` per-dimension step multipliers (diagonal of Brubaker's ``Delta``).
        target_acceptance: acceptance rate the burn-in adaptation aims at (0.75).
        burn_in: number of frames during which the step size is adapted; fixed afterwards (0: never adapt).
    """

    def __init__(
        self,
        dynamics: Any,
        likelihood: Any,
        proposal: Any = None,
        *,
        n_particles: int | None = None,
        n_moves: int = 2,
        n_leapfrog: int = 5,
        step_size: float = 0.1,
        step_scale: Tensor | None = None,
        target_acceptance: float = 0.75,
        burn_in: int = 10,
        resampler: Any = "systematic",
        ess_threshold: float = 0.5,
        sampling: str = "mc",
        progress: bool = True,
    ):
        super().__init__(
            dynamics,
            likelihood,
            proposal,
            n_particles=n_particles,
            resampler=resampler,
            ess_threshold=ess_threshold,
            sampling=sampling,
            progress=progress,
        )
        if n_moves < 0 or n_leapfrog < 1 or step_size <= 0:
            raise ValueError("need n_moves >= 0, n_leapfrog >= 1 and step_size > 0")
        if not 0.0 < target_acceptance < 1.0:
            raise ValueError(f"target_acceptance must be in (0, 1), got {target_acceptance}")
        self.n_moves = n_moves
        self.n_leapfrog = n_leapfrog
        self.step_size = float(step_size)
        self.step_scale = step_scale
        self.target_acceptance = target_acceptance
        self.burn_in = burn_in

    @classmethod
    def evaluations_per_particle(cls, **options: Any) -> int:
        """``1 + R (L + 1)``: the SIR weight, then per HMC move ``L + 1`` likelihood gradients (Brubaker
        Alg. 4; a gradient counted as one evaluation)."""
        return 1 + int(options.get("n_moves", 2)) * (int(options.get("n_leapfrog", 5)) + 1)

    def budget_options(self) -> dict[str, Any]:
        return {"n_moves": self.n_moves, "n_leapfrog": self.n_leapfrog}

    # Robbins-Monro gain 0.5 k^-0.75 on a logit error clipped to +-3 (tuned on Gaussian targets: reaches
    # ~75% within ~15 updates from steps 1000x too small or 30x too large).
    _GAIN, _DECAY, _CLIP = 0.5, 0.75, 3.0

    def _init_aux(self, x0: Tensor) -> dict[str, Tensor]:
        batch = x0.shape[:-2]
        return {
            "hmc_log_step": x0.new_full(batch, math.log(self.step_size)),
            "hmc_updates": x0.new_zeros(batch),  # number of adaptation updates so far
            "hmc_frames": torch.zeros(batch, dtype=torch.long, device=x0.device),
        }

    def _adapt(self, aux: dict[str, Tensor], accept_prob: Tensor, active: Tensor) -> None:
        """One update of ``aux["hmc_log_step"] (...)`` from the mean acceptance probability ``(...)``."""
        k = aux["hmc_updates"] + 1
        a = accept_prob.clamp(1e-4, 1 - 1e-4)
        t = self.target_acceptance
        error = (torch.log(a / (1 - a)) - math.log(t / (1 - t))).clamp(-self._CLIP, self._CLIP)
        log_step = aux["hmc_log_step"] + self._GAIN * k ** (-self._DECAY) * error
        aux["hmc_updates"] = torch.where(active, k, aux["hmc_updates"])
        aux["hmc_log_step"] = torch.where(active, log_step, aux["hmc_log_step"])

    def _log_target(self, obs: Any, x_prev: Tensor, extras_prev: Mapping[str, Tensor]) -> Callable:
        def log_target(q: Tensor) -> Tensor:
            lik = self._loglik(self.likelihood, q, obs)
            return lik + self.dynamics.log_prob(q, x_prev, extras=extras_prev).to(q.dtype)

        return log_target

    def step(self, state: ParticleState, obs: Any, generator: torch.Generator | None = None) -> ParticleState:
        """One frame of Alg. 3; ``info`` adds ``"ess"`` (of the importance weights, before the moves),
        ``"acceptance"`` and ``"step_size"`` (each ``(...)``)."""
        aux = {**self._init_aux(state.particles), **state.aux}
        weighted, x_prev, extras_prev = self._sir_step(state, obs, generator)
        failed = weighted.info["failed"]
        ancestors = self.resampler(weighted.log_weights, generator)
        chosen = weighted.select(ancestors)
        x_prev = gather_particles(x_prev, ancestors)
        extras_prev = {k: gather_particles(v, ancestors) for k, v in extras_prev.items()}

        adapting = (aux["hmc_frames"] < self.burn_in) & ~failed
        log_target = self._log_target(obs, x_prev, extras_prev)
        q = chosen.particles
        n_accepted = torch.zeros_like(weighted.log_evidence)
        step_used = torch.zeros_like(n_accepted)
        for _ in range(self.n_moves):
            step = torch.exp(aux["hmc_log_step"])
            q, accept_prob, accepted = hmc_move(
                q, log_target, step, self.n_leapfrog, generator, step_scale=self.step_scale
            )
            n_accepted = n_accepted + accepted.to(step.dtype).mean(-1)
            step_used = step_used + step / self.n_moves
            # The acceptance probability averaged over N chains is a low-noise signal for the adaptation.
            self._adapt(aux, accept_prob.mean(-1), adapting)
        # A failed frame has no posterior to move towards: keep the predicted particles.
        q = torch.where(failed[..., None, None], chosen.particles, q)
        acceptance = n_accepted / max(self.n_moves, 1)
        aux["hmc_frames"] = aux["hmc_frames"] + 1
        info = weighted.info
        return self._end_frame(
            state,
            q,
            chosen.log_weights,
            info["log_evidence_increment"],
            failed,
            info["resampled"],
            x_prev,
            extras_prev,
            aux=aux,
            ess=weighted.ess(),
            nonfinite=info["nonfinite"],
            acceptance=acceptance,
            step_size=step_used,
        )
