"""Immutable containers passed in and out of the filters: :class:`ParticleState` and :class:`Track`.

A filter never stores its state on itself: ``step`` takes a :class:`ParticleState` and returns a new one, and
``run`` returns a :class:`Track` of per-frame summaries. Several independent sequences are tracked at once by
giving every tensor the same leading batch dims ``...``.

Example::

    state = pf.init(x0)                    # x0: (..., N, D)
    state = pf.step(state, obs)
    state.mean(), state.map(), state.ess() # (..., D), (..., D), (...,)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchpf.filters import weights


def gather_particles(values: Tensor, ancestors: Tensor) -> Tensor:
    """Per-particle rows: ``values (..., N, *rest)``, ``ancestors (..., M)`` -> ``(..., M, *rest)``."""
    dim = ancestors.ndim - 1
    rest = values.shape[dim + 1 :]
    index = ancestors.reshape(ancestors.shape + (1,) * len(rest)).expand(ancestors.shape + rest)
    return values.gather(dim, index)


@dataclass(frozen=True)
class ParticleState:
    """Weighted particle approximation of the filtering posterior ``p(x_t | z_{1:t})`` (Fontmarty eq. 1).

    Attributes:
        particles: ``(..., N, D)`` particle states (units of the state vector: metres / radians for a pose).
        log_weights: ``(..., N)`` normalised log-weights (``logsumexp`` over ``N`` is 0 after every step).
        log_evidence: ``(...)`` running estimate of ``log p(z_{1:t})`` in nats (0 at ``init``).
        extras: per-particle tensors ``(..., N, *k)`` that ride along with the particles (a velocity, a
            phase, an action label); every resampling gathers them with the particles. See
            :class:`torchpf.distributions.Dynamics` for how dynamics read and update them.
        aux: per-sequence filter bookkeeping carried from step to step (e.g. the HMC step size ``(...)``).
        info: diagnostics of the step that produced this state, each ``(..., *k)``: ``"failed"`` (bool, all
            weights were ``-inf``/NaN), ``"resampled"`` (bool), ``"log_evidence_increment"`` and
            filter-specific entries such as ``"acceptance"`` or ``"betas"``. ``run`` stacks them over time.

    Treat the dicts as read-only; make a modified copy with :meth:`replace`.
    """

    particles: Tensor
    log_weights: Tensor
    log_evidence: Tensor
    extras: Mapping[str, Tensor] = field(default_factory=dict)
    aux: Mapping[str, Tensor] = field(default_factory=dict)
    info: Mapping[str, Tensor] = field(default_factory=dict)

    @property
    def n_particles(self) -> int:
        return self.particles.shape[-2]

    @property
    def batch_shape(self) -> torch.Size:
        return self.particles.shape[:-2]

    def replace(self, **changes) -> ParticleState:
        """A copy with some fields replaced (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)

    def weights(self) -> Tensor:
        """Normalised weights ``(..., N)`` (computed from the log-weights with a softmax)."""
        return weights.probabilities(self.log_weights)

    def ess(self) -> Tensor:
        """Effective sample size ``(...)``, ``1 / sum_i w_i^2`` (Brubaker eq. 18), in ``[1, N]`` (0 when every
        weight is ``-inf``; :func:`torchpf.filters.weights.ess`)."""
        return weights.ess(self.log_weights)

    def mean(self) -> Tensor:
        """MMSE estimate ``sum_i w_i x_i``: ``(..., D)`` (Brubaker eq. 16 with ``f(x) = x``); a particle of
        weight 0 does not enter it, even when its coordinates are NaN/inf."""
        w = self.weights()
        return (w.unsqueeze(-2) @ self._weighted_only(w)).squeeze(-2)

    def _weighted_only(self, w: Tensor) -> Tensor:
        # 0 * NaN is NaN: zero-weight particles are zeroed before the weighted sums
        return torch.where((w > 0).unsqueeze(-1), self.particles, torch.zeros_like(self.particles))

    def cov(self) -> Tensor:
        """Weighted covariance of the particles ``(..., D, D)``."""
        w = self.weights()
        centred = self._weighted_only(w) - self.mean().unsqueeze(-2)
        return (centred * w.unsqueeze(-1)).transpose(-1, -2) @ centred

    def map(self) -> Tensor:
        """The highest-weight particle ``(..., D)`` (the MAP among the samples)."""
        best = torch.nan_to_num(self.log_weights, nan=-math.inf).argmax(-1, keepdim=True)
        return gather_particles(self.particles, best).squeeze(-2)

    def select(self, ancestors: Tensor) -> ParticleState:
        """Resampled copy: particles and extras gathered by ``ancestors (..., N)``, weights uniform."""
        n = ancestors.shape[-1]
        return self.replace(
            particles=gather_particles(self.particles, ancestors),
            log_weights=self.log_weights.new_full(ancestors.shape, -math.log(n)),
            extras={k: gather_particles(v, ancestors) for k, v in self.extras.items()},
        )


@dataclass(frozen=True)
class Track:
    """Per-frame output of ``ParticleFilter.run`` over ``T`` frames.

    Attributes:
        estimates: ``(..., T, D)`` MMSE estimates ``E[x_t | z_{1:t}]``.
        map_estimates: ``(..., T, D)`` highest-weight particle of each frame.
        ess: ``(..., T)`` effective sample size of each frame's importance weights (before any MCMC move).
        log_evidence: ``(...)`` estimate of ``log p(z_{1:T})`` in nats (see each filter for its meaning).
        log_evidence_increments: ``(..., T)`` per-frame ``log p(z_t | z_{1:t-1})`` estimates (0 on failed
            frames).
        failed: ``(..., T)`` bool, frames where every weight was ``-inf``/NaN (uniform weights were kept).
        resampled: ``(..., T)`` bool, frames that started with an (ESS-triggered) resampling.
        stats: filter-specific per-frame diagnostics, each ``(..., T, *k)`` (``"acceptance"``,
            ``"betas"``, ...).
        final_state: the state after the last frame (continue with ``filter.step(track.final_state, obs)``).
    """

    estimates: Tensor
    map_estimates: Tensor
    ess: Tensor
    log_evidence: Tensor
    log_evidence_increments: Tensor
    failed: Tensor
    resampled: Tensor
    stats: Mapping[str, Tensor]
    final_state: ParticleState

    @property
    def failure_rate(self) -> Tensor:
        """Fraction of failed frames per sequence ``(...)``."""
        return self.failed.to(self.estimates.dtype).mean(-1)
