"""Sequential importance resampling (SIR) particle filter, Brubaker Alg. 1 / Fontmarty Table 1.

One frame: if the effective sample size (Brubaker eq. 18) is below ``ess_threshold * N``, resample; then move
every particle with the proposal (the dynamics by default) and multiply its weight by the likelihood and the
importance correction (Brubaker eq. 17, Hauberg eq. 1-2)::

    log w_t^i = log w_{t-1}^i + log p(z_t | x_t^i) + log p(x_t^i | x_{t-1}^i) - log q(x_t^i | x_{t-1}^i, z_t)

The last two terms cancel for the bootstrap proposal (``proposal=None``) and are not computed. The
normaliser ``sum_i w_{t-1}^i p(z_t|x_t^i) p/q`` (normalised ``w_{t-1}``) is an unbiased estimate of
``p(z_t | z_{1:t-1})``; its log is accumulated in ``state.log_evidence`` (an estimate of ``log p(z_{1:t})``,
biased low by about half its variance, as every log of an unbiased estimate).

A frame where every weight is ``-inf`` or NaN (the likelihood rejected every particle) keeps the predicted
particles with uniform weights, adds nothing to the log-evidence and sets ``info["failed"]``.

Example::

    pf = ParticleFilter(dynamics, likelihood, n_particles=500, progress=False)
    track = pf.run(observations, x0, generator=torch.Generator().manual_seed(0))
    track.estimates, track.ess, track.log_evidence        # (..., T, D), (..., T), (...)
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from torchpf.distributions import as_dynamics, as_generator
from torchpf.filters.qmc import qrs_normal
from torchpf.filters.state import ParticleState, Track, gather_particles
from torchpf.filters.weights import normalise, reweight
from torchpf.resampling import RESAMPLERS

_STANDARD_INFO = ("failed", "resampled", "log_evidence_increment", "ess", "estimate")


def frame_summary(state: ParticleState) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
    """What a :class:`~torchpf.filters.state.Track` keeps of one frame: the per-frame values of its fields
    (``estimates``, ``map_estimates``, ``ess``, ``log_evidence_increments``, ``failed``, ``resampled``, each
    ``(..., *k)``) and the filter-specific statistics of ``state.info``."""
    info = state.info
    fields = {
        # a filter whose estimate is not the weighted mean (a refined one) reports it in info
        "estimates": info["estimate"] if "estimate" in info else state.mean(),
        "map_estimates": state.map(),
        "ess": info["ess"] if "ess" in info else state.ess(),
        "log_evidence_increments": info["log_evidence_increment"],
        "failed": info["failed"],
        "resampled": info["resampled"],
    }
    return fields, {key: value for key, value in info.items() if key not in _STANDARD_INFO}


class ParticleFilter(nn.Module):
    """SIR particle filter with ESS-triggered resampling (Brubaker Alg. 1).

    Args:
        dynamics: motion prior, see :class:`~torchpf.distributions.Dynamics` (or a duck-typed
            object, adapted by :func:`~torchpf.distributions.as_dynamics`).
        likelihood: ``(x (..., N, D), obs) -> (..., N)`` log-likelihood.
        proposal: importance distribution with ``sample(state, obs, generator) -> (x, log_q)``; ``None``
            is the bootstrap filter (proposal = dynamics, no correction).
        n_particles: ``N``; ``None`` takes it from ``x0`` at ``init``. An ``x0`` with a single particle is
            copied ``N`` times.
        resampler: a name registered in :mod:`torchpf.resampling` or a callable
            ``(log_weights (..., N), generator) -> ancestors (..., N)``.
        ess_threshold: resample at the start of a frame when ``ESS < ess_threshold * N``; ``1.0`` resamples
            every frame, ``0.0`` never.
        sampling: ``"mc"`` (i.i.d. draws) or ``"qrs"`` (randomised Sobol noise per resampled parent,
            Fontmarty Table 4; needs ``dynamics.sample_from_noise`` and no proposal).
        progress: show a tqdm bar in :meth:`run`.

    The filter holds no state between calls: ``init`` / ``step`` / ``run`` take and return
    :class:`~torchpf.filters.state.ParticleState`. It is an ``nn.Module`` so that ``.to(device)`` moves the
    dynamics, likelihood and proposal when they are modules. Device and dtype follow ``x0``.
    """

    def __init__(
        self,
        dynamics: Any,
        likelihood: Any,
        proposal: Any = None,
        *,
        n_particles: int | None = None,
        resampler: Any = "systematic",
        ess_threshold: float = 0.5,
        sampling: str = "mc",
        progress: bool = True,
    ):
        super().__init__()
        if not 0.0 <= ess_threshold <= 1.0:
            raise ValueError(f"ess_threshold must be in [0, 1], got {ess_threshold}")
        if n_particles is not None and n_particles < 1:
            raise ValueError(f"n_particles must be positive, got {n_particles}")
        if sampling not in ("mc", "qrs"):
            raise ValueError(f"sampling must be 'mc' or 'qrs', got {sampling!r}")
        if sampling == "qrs":
            if proposal is not None:
                raise ValueError(
                    "sampling='qrs' draws from the dynamics; it cannot be combined with a proposal"
                )
        dynamics = as_dynamics(dynamics)
        if sampling == "qrs" and not dynamics.has_noise_map():
            raise ValueError(
                f"sampling='qrs' (filters 'qrs', 'partitioned_qrs') needs a motion prior that maps noise to "
                f"a sample (dynamics.sample_from_noise(x, eps)); {type(dynamics).__name__} has none: use the "
                f"Monte Carlo filters ('sir', 'partitioned', 'apf', 'hybrid') with it"
            )
        self.dynamics = dynamics
        self.likelihood = likelihood
        self.proposal = proposal
        self.n_particles = n_particles
        self.resampler = RESAMPLERS.resolve(resampler)
        self.ess_threshold = float(ess_threshold)
        self.sampling = sampling
        self.progress = progress

    # ------------------------------------------------------------------ equal likelihood budget

    @classmethod
    def evaluations_per_particle(cls, **options: Any) -> int:
        """Likelihood evaluations per particle and frame of this filter built with ``options`` (its
        constructor keywords; defaults where absent). 1 for the SIR."""
        return 1

    @classmethod
    def for_budget(cls, budget: int, **options: Any) -> int:
        """Particles ``N`` such that this filter, built with ``options``, evaluates the likelihood at most
        ``budget`` times per frame (Fontmarty §3.3.2: every filter compared at equal likelihood evaluations;
        an SIR gets ``budget``, an APF of ``L`` layers ``budget // L``, ...). At least 1."""
        if int(budget) < 1:
            raise ValueError(f"the likelihood budget must be >= 1, got {budget}")
        return max(1, int(budget) // cls.evaluations_per_particle(**options))

    def budget_options(self) -> dict[str, Any]:
        """The constructor keywords that :meth:`evaluations_per_particle` reads, as this filter was built."""
        return {}

    @property
    def likelihood_evaluations(self) -> int | None:
        """Likelihood evaluations per frame (``None`` while ``n_particles`` is taken from ``x0``)."""
        if self.n_particles is None:
            return None
        return self.n_particles * self.evaluations_per_particle(**self.budget_options())

    # ------------------------------------------------------------------ public API

    def init(self, x0: Tensor, extras: Mapping[str, Tensor] | None = None) -> ParticleState:
        """Initial state from particles ``x0 (..., N, D)`` (or ``(..., 1, D)``), uniform weights.

        ``extras`` (per-particle ``(..., N, *k)`` tensors) default to ``dynamics.init_extras(x0)``.
        """
        if x0.ndim < 2 or not x0.is_floating_point():
            raise ValueError(f"x0 must be a floating tensor (..., N, D), got shape {tuple(x0.shape)}")
        n = self.n_particles or x0.shape[-2]
        if x0.shape[-2] == 1 and n > 1:
            x0 = x0.expand(*x0.shape[:-2], n, x0.shape[-1]).clone()
        elif x0.shape[-2] != n:
            raise ValueError(f"x0 has {x0.shape[-2]} particles, the filter was built for {n}")
        if extras is None:
            extras = self.dynamics.init_extras(x0)
        extras = dict(extras)
        for key, value in extras.items():
            if value.shape[: x0.ndim - 1] != x0.shape[:-1]:
                if value.shape[: x0.ndim - 1] == x0.shape[:-2] + (1,):
                    extras[key] = value.expand(*x0.shape[:-1], *value.shape[x0.ndim - 1 :]).clone()
                else:
                    raise ValueError(
                        f"extras[{key!r}] has shape {tuple(value.shape)}, expected (..., {n}, ...)"
                    )
        batch = x0.shape[:-2]
        return ParticleState(
            particles=x0,
            log_weights=x0.new_full(batch + (n,), -math.log(n)),
            log_evidence=x0.new_zeros(batch),
            extras=extras,
            aux=self._init_aux(x0),
        )

    def forward(
        self, state: ParticleState, obs: Any, generator: torch.Generator | None = None
    ) -> ParticleState:
        """Same as :meth:`step` (so the filter can sit in an ``nn.Sequential``-style pipeline)."""
        return self.step(state, obs, generator)

    def step(self, state: ParticleState, obs: Any, generator: torch.Generator | None = None) -> ParticleState:
        """One frame of Brubaker Alg. 1: ESS-triggered resampling, propagation, weighting.

        Args:
            state: the filtering state at ``t-1``.
            obs: the observation ``z_t`` passed unchanged to the likelihood (and proposal).
            generator: randomness (on the particles' device); same generator state, same result.

        Returns:
            the state at ``t``, with ``info`` = ``failed``, ``resampled``, ``log_evidence_increment`` (each
            ``(...)``). Gradients flow as the caller's grad mode says (:meth:`run`: ``grad=False``).
        """
        new, _, _ = self._sir_step(state, obs, generator)
        return new

    def run(
        self,
        observations: Iterable[Any],
        x0: Tensor,
        generator: torch.Generator | int | None = None,
        *,
        extras: Mapping[str, Tensor] | None = None,
        grad: bool = False,
        hook: Any = None,
    ) -> Track:
        """Filter a whole sequence: ``init(x0)`` then one :meth:`step` per observation.

        Args:
            observations: iterable over frames (a list, or a tensor whose first dim is ``T``); each item is
                one ``obs`` for :meth:`step`. For a batch of sequences stored as ``(B, T, ...)`` pass
                ``obs.transpose(0, 1)``.
            x0: ``(..., N, D)`` initial particles.
            generator: randomness, a generator or a seed; the same seed gives the same track. A generator on
                another device than ``x0`` seeds one there (:func:`torchpf.distributions.as_generator`).
            extras: initial per-particle extras (see :meth:`init`).
            grad: keep the autograd graph (default: run under ``no_grad``). The track's tensors are then
                differentiable in the likelihood's and the dynamics' parameters (and ``x0``) with the
                random numbers and the resampling indices held fixed: ``log_evidence.backward()`` gives the
                gradient of ``log p_hat(z_{1:T})`` along this realisation, where the weights carried
                through a frame without resampling keep their dependence and a resampling resets it (the
                ancestor indices are not differentiated; no differentiable resampling). Without
                resampling (``ess_threshold=0``) it is the exact gradient of the importance-sampling
                estimate; with it, a biased but low-variance estimate of the score, good enough to fit
                a few scale parameters (Poyiadjis et al. 2011 discuss the bias). The filters' MCMC moves
                and annealing schedules are computed without gradient.
            hook: ``hook(state, obs, generator) -> state`` called after every step, before the frame's
                estimate is taken: where a tracker mixes in re-detected particles (track recovery).

        Returns:
            a :class:`~torchpf.filters.state.Track`.
        """
        fields: dict[str, list[Tensor]] = {}
        stats: dict[str, list[Tensor]] = {}
        state = None
        for state in self.iterate(observations, x0, generator, extras=extras, grad=grad, hook=hook):
            frame, frame_stats = frame_summary(state)
            for out, values in ((fields, frame), (stats, frame_stats)):
                for key, value in values.items():
                    out.setdefault(key, []).append(value)
        if state is None:
            raise ValueError("observations is empty")
        nb = state.particles.ndim - 2  # time goes right after the batch dims

        def stack(values: list[Tensor]) -> Tensor:
            return torch.stack(values, dim=nb)

        return Track(
            **{key: stack(values) for key, values in fields.items()},
            log_evidence=state.log_evidence,
            stats={key: stack(values) for key, values in stats.items()},
            final_state=state,
        )

    def iterate(
        self,
        observations: Iterable[Any],
        x0: Tensor,
        generator: torch.Generator | int | None = None,
        *,
        extras: Mapping[str, Tensor] | None = None,
        grad: bool = False,
        hook: Any = None,
    ) -> Iterator[ParticleState]:
        """:meth:`run` one frame at a time: ``init(x0)``, then yields the state after each :meth:`step`
        (under ``no_grad`` unless ``grad``) and keeps nothing, so a consumer that writes each frame out runs
        in memory that does not grow with the sequence (``observations`` may be a lazy iterable). Arguments
        as :meth:`run`.
        """
        total = len(observations) if hasattr(observations, "__len__") else None
        generator = as_generator(generator, x0.device)
        with torch.set_grad_enabled(grad):
            state = self.init(x0, extras)
        for obs in tqdm(observations, total=total, desc=type(self).__name__, disable=not self.progress):
            with torch.set_grad_enabled(grad):
                state = self.step(state, obs, generator)
                if hook is not None:
                    state = hook(state, obs, generator)
            yield state

    # ------------------------------------------------------------------ building blocks for subclasses

    def _init_aux(self, x0: Tensor) -> dict[str, Tensor]:
        return {}

    def _loglik(self, likelihood: Any, x: Tensor, obs: Any) -> Tensor:
        out = likelihood(x, obs)
        if out.shape != x.shape[:-1]:
            raise ValueError(f"likelihood returned shape {tuple(out.shape)}, expected {tuple(x.shape[:-1])}")
        # a particle with a NaN/inf coordinate is impossible, whatever the likelihood made of it
        return torch.where(torch.isfinite(x).all(-1), out.to(x.dtype), -math.inf)

    def _maybe_resample(
        self, state: ParticleState, generator: torch.Generator | None
    ) -> tuple[ParticleState, Tensor, Tensor]:
        """ESS-triggered resampling (Brubaker Alg. 1): ``(state, ancestors (..., N), resampled (...))``."""
        log_w = normalise(state.log_weights)
        state = state.replace(log_weights=log_w)
        n = state.n_particles
        identity = torch.arange(n, device=log_w.device).expand(log_w.shape)
        if self.ess_threshold <= 0.0:
            return state, identity, torch.zeros(log_w.shape[:-1], dtype=torch.bool, device=log_w.device)
        if self.ess_threshold >= 1.0:
            need = torch.ones(log_w.shape[:-1], dtype=torch.bool, device=log_w.device)
        else:
            need = state.ess() < self.ess_threshold * n
        # All sequences are resampled in one batched call and the ones above threshold keep the identity:
        # deciding per sequence on the host would need a device sync.
        ancestors = torch.where(need.unsqueeze(-1), self.resampler(log_w, generator), identity)
        log_w = torch.where(need.unsqueeze(-1), torch.full_like(log_w, -math.log(n)), log_w)
        resampled = state.select(ancestors).replace(log_weights=log_w)
        return resampled, ancestors, need

    def _sample_dynamics(
        self,
        x: Tensor,
        extras: Mapping[str, Tensor],
        ancestors: Tensor,
        generator: torch.Generator | None,
    ) -> Tensor:
        """Draw from the dynamics, i.i.d. (``"mc"``) or with per-parent Sobol noise (``"qrs"``)."""
        if self.sampling == "qrs":
            eps = qrs_normal(ancestors, self.dynamics.noise_size(x.shape[-1]), generator, x.dtype)
            return self.dynamics.sample_from_noise(x, eps, extras=extras)
        return self.dynamics.sample(x, generator, extras=extras)

    def _propose(
        self, state: ParticleState, ancestors: Tensor, obs: Any, generator: torch.Generator | None
    ) -> tuple[Tensor, Tensor | None]:
        """New particles and ``log p(x|x_prev) - log q`` (``None`` for the bootstrap proposal)."""
        if self.proposal is None:
            return self._sample_dynamics(state.particles, state.extras, ancestors, generator), None
        x, log_q = self.proposal.sample(state, obs, generator)
        log_p = self.dynamics.log_prob(x, state.particles, extras=state.extras).to(x.dtype)
        return x, log_p - log_q.to(x.dtype)

    def _sir_step(
        self, state: ParticleState, obs: Any, generator: torch.Generator | None
    ) -> tuple[ParticleState, Tensor, Mapping[str, Tensor]]:
        """Alg. 1 for one frame; also returns each particle's parent ``x_{t-1}`` and its extras."""
        state, ancestors, resampled = self._maybe_resample(state, generator)
        x, log_corr = self._propose(state, ancestors, obs, generator)
        increment = self._loglik(self.likelihood, x, obs)
        if log_corr is not None:
            increment = increment + log_corr
        log_w, lse, failed = reweight(state.log_weights, increment)
        new = self._end_frame(state, x, log_w, lse, failed, resampled, state.particles, state.extras)
        return new, state.particles, state.extras

    def _end_frame(
        self,
        state: ParticleState,
        x: Tensor,
        log_w: Tensor,
        increment: Tensor,
        failed: Tensor,
        resampled: Tensor,
        x_prev: Tensor,
        extras_prev: Mapping[str, Tensor],
        aux: Mapping[str, Tensor] | None = None,
        **info: Tensor,
    ) -> ParticleState:
        """The state at the end of a frame, the same for every filter.

        ``x (..., N, D)`` and ``log_w (..., N)`` are the frame's final particles and weights, ``increment
        (...)`` its log-evidence increment (dropped where ``failed``: a failed frame adds nothing), ``x_prev``
        and ``extras_prev`` each particle's frame-start parent and its extras (the dynamics' extras are
        updated from them once, here); ``info`` adds filter-specific diagnostics.
        """
        inc = torch.where(failed, torch.zeros_like(increment), increment)
        # A particle that left the reals (a NaN/inf from the dynamics, a move or a proposal) is dropped: it
        # falls back to its frame-start parent with zero weight (uniform weights stay on a failed frame), so
        # the estimates stay finite; info["nonfinite"] counts them.
        bad = ~torch.isfinite(x).all(-1)
        x = torch.where(bad.unsqueeze(-1), x_prev, x)
        dropped, _, _ = reweight(log_w, torch.where(bad & ~failed.unsqueeze(-1), -math.inf, 0.0))
        log_w = torch.where(bad.any(-1, keepdim=True), dropped, log_w)  # rows without one: untouched
        info = {**info, "nonfinite": bad.sum(-1) + info.get("nonfinite", 0)}  # plus earlier stages' drops
        extras = self.dynamics.update_extras(x, x_prev, extras_prev)
        info.update(self.dynamics.frame_stats(x, log_w, extras))  # e.g. an action prior's acceptance
        return ParticleState(
            particles=x,
            log_weights=log_w,
            log_evidence=state.log_evidence + inc,
            extras=extras,
            aux=state.aux if aux is None else aux,
            info={"failed": failed, "resampled": resampled, "log_evidence_increment": inc, **info},
        )

    @staticmethod
    def _gather(ancestors: Tensor, *tensors: Tensor) -> list[Tensor]:
        return [gather_particles(t, ancestors) for t in tensors]
