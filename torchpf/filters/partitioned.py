"""Partitioned sampling (MacCormick & Isard), Fontmarty Table 2 / §2.3.2, and PARTITIONED QRS.

The state is split into ``M`` groups of dimensions (e.g. the 6 torso DOFs first, then the limbs) such that the
dynamics and the likelihood factorise::

    p(x_t | x_{t-1}) = prod_m p_m(x_t^m | x_{t-1}^m),     p(z_t | x_t) = prod_m l_m(z_t | x_t^1, ..., x_t^m)

Stage ``m`` diffuses only group ``m`` (from each particle's frame-start parent), weights by the partial
likelihood ``tau_m = tau_{m-1} l_m`` and, if ``m < M``, resamples, so the cloud is refined group by group; the
cost is linear in ``M`` instead of exponential in the dimension. Group ``m`` is drawn by sampling the full
dynamics from the parent and keeping the group's coordinates, which is exact for factorised dynamics (and the
usual approximation otherwise); coordinates of later groups hold the parent's values until their stage.

This is a proper SMC sampler over the intermediate targets ``prod_{j<=m} l_j p``, so the product over the
stages of ``sum_i tau_{m-1}^i l_m(x^i)`` is an unbiased estimate of ``p(z_t|z_{1:t-1})``; its log is added to
``state.log_evidence`` (the same quantity the SIR accumulates). Equal budget (Fontmarty §3.3.2): ``M`` stages
of ``N`` particles evaluate ``M N`` (partial) likelihoods per frame; compare with an SIR of ``M N`` particles.

With ``sampling="qrs"`` each stage's children of a resampled parent get randomised Sobol noise
(:mod:`torchpf.filters.qmc`), Fontmarty's PARTITIONED QRS.

Example::

    ppf = PartitionedParticleFilter(dynamics, [torso_lik, limbs_lik], groups=[range(6), range(6, 22)],
                                    n_particles=250, sampling="qrs", progress=False)
    track = ppf.run(observations, x0, generator=g)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from torchpf.filters.base import ParticleFilter
from torchpf.filters.state import ParticleState, gather_particles
from torchpf.filters.weights import reweight


class PartitionedParticleFilter(ParticleFilter):
    """Partitioned particle filter (Fontmarty Table 2). See the module docstring.

    Args:
        dynamics: motion prior (factorised over the groups); for ``sampling="qrs"`` it needs
            ``sample_from_noise``.
        likelihoods: ``M`` partial log-likelihoods ``l_m(x (..., N, D), obs) -> (..., N)``, one per group.
        groups: ``M`` sequences of state indices, disjoint and together covering ``range(D)``.
        n_particles: ``N`` particles per stage.
        resampler, ess_threshold, sampling, progress: as :class:`~torchpf.filters.ParticleFilter`; the
            threshold applies at the start of a frame, stages always resample in between.
    """

    def __init__(
        self,
        dynamics: Any,
        likelihoods: Sequence[Any],
        groups: Sequence[Sequence[int]],
        *,
        n_particles: int | None = None,
        resampler: Any = "systematic",
        ess_threshold: float = 0.5,
        sampling: str = "mc",
        progress: bool = True,
    ):
        likelihoods = list(likelihoods)
        groups = [sorted(int(i) for i in g) for g in groups]
        if len(likelihoods) != len(groups) or not groups:
            raise ValueError(
                f"need one partial likelihood per group, got {len(likelihoods)} and {len(groups)}"
            )
        flat = [i for g in groups for i in g]
        if len(set(flat)) != len(flat) or any(not g for g in groups):
            raise ValueError("groups must be non-empty and disjoint")
        super().__init__(
            dynamics,
            likelihoods[0],
            None,
            n_particles=n_particles,
            resampler=resampler,
            ess_threshold=ess_threshold,
            sampling=sampling,
            progress=progress,
        )
        # a ModuleList moves the stage likelihoods with .to(device) when they are modules
        self.likelihoods = (
            nn.ModuleList(likelihoods)
            if all(isinstance(lik, nn.Module) for lik in likelihoods)
            else likelihoods
        )
        self.groups = groups

    @classmethod
    def evaluations_per_particle(cls, **options: Any) -> int:
        """``M``, the number of groups (a partial likelihood per stage; Fontmarty §3.3.2: ``N / M`` per
        stage). ``options["groups"]`` is required: the cost depends on the partition."""
        if "groups" not in options:
            raise ValueError("the partitioned filter's budget depends on its groups: pass groups=")
        return len(options["groups"])

    def budget_options(self) -> dict[str, Any]:
        return {"groups": self.groups}

    def _check_groups(self, dim: int) -> None:
        if sorted(i for g in self.groups for i in g) != list(range(dim)):
            raise ValueError(f"groups must partition range({dim}) (the state dimension), got {self.groups}")

    def step(self, state: ParticleState, obs: Any, generator: torch.Generator | None = None) -> ParticleState:
        """One frame of Table 2: ``M`` stages of diffuse-weight(-resample)."""
        self._check_groups(state.particles.shape[-1])
        state, ancestors, resampled = self._maybe_resample(state, generator)
        x_prev, extras_prev = state.particles, state.extras
        x = x_prev.clone()
        log_w = state.log_weights
        inc = log_w.new_zeros(log_w.shape[:-1])
        failed = torch.zeros_like(resampled)
        for m, (group, likelihood) in enumerate(zip(self.groups, self.likelihoods, strict=True)):
            if m > 0:
                ancestors = self.resampler(log_w, generator)
                x, x_prev = self._gather(ancestors, x, x_prev)
                extras_prev = {k: gather_particles(v, ancestors) for k, v in extras_prev.items()}
                log_w = torch.full_like(log_w, -math.log(log_w.shape[-1]))
            idx = torch.as_tensor(group, device=x.device)
            draw = self._sample_dynamics(x_prev, extras_prev, ancestors, generator)
            x = x.index_copy(-1, idx, draw.index_select(-1, idx))
            log_w, lse, failed_m = reweight(log_w, self._loglik(likelihood, x, obs))
            inc = inc + torch.where(failed_m, torch.zeros_like(lse), lse)
            failed = failed | failed_m
        # A frame that failed at any stage adds nothing to the evidence (its partial sum means nothing).
        return self._end_frame(state, x, log_w, inc, failed, resampled, x_prev, extras_prev)
