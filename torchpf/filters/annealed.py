"""Annealed particle filter (APF; Deutscher & Reid), Brubaker Alg. 2 / Fontmarty Table 3.

Each frame runs ``L`` layers that progressively sharpen both the exploration and the likelihood. Layer 1
draws from the proposal (the dynamics by default) and weights by ``w_{t-1} p(z|x)^{beta_1} p/q``; every
later layer ``l`` resamples, diffuses each particle with a Gaussian ``N(x, c_l Sigma)`` (Brubaker eq. 19) and
weights it by the annealed target (Brubaker eq. 20)::

    W_l(x) = (p(z_t | x) p(x | x_{t-1}))^{beta_l}      (layer_prior=True, Brubaker eq. 20)
    W_l(x) =  p(z_t | x)^{beta_l}                      (layer_prior=False, Fontmarty Table 3)

where ``x_{t-1}`` is the particle's frame-start parent (tracked through the layer resamplings). The last
``beta_L`` is 1. Diffusion scales ``c_l``:

* Fontmarty's parameterisation (default): ``alphas = (1, 4, 4)`` are exponents on the dynamics density,
  ``p(x_t|x_{t-1})^{alpha_l}``; for a Gaussian random walk that is ``N(x, Sigma / alpha_l)``, so ``c_l = 1 /
  alpha_l``. ``alpha_1`` is the proposal layer and must be 1. With ``betas = (0.1, 0.4, 1)`` this is the
  schedule of Fontmarty §3.3.2.
* Brubaker's/Deutscher's annealing rate ``annealing_rate = a`` in ``(0, 1)``: ``c_l = a^{l-1}``, i.e.
  ``a^ell Sigma`` for the ``ell``-th diffusion after the proposal layer (eq. 19).

``Sigma = diag(diffusion_std^2)``; ``diffusion_std`` defaults to ``dynamics.std`` (the random-walk std).

``betas="adaptive"`` chooses ``beta_l`` per frame and per sequence so that the particle survival rate
``ESS / N`` equals ``survival_rate`` (Deutscher's ``alpha = 0.5``), by bisection on ``beta`` in
``[beta_{l-1}, 1]`` (batched, fixed iteration count, no host sync); ``beta_L = 1``. The chosen betas are
reported in ``info["betas"] (..., L)``.

The APF is **not** a proper Bayesian filter (Brubaker §5.2; Fontmarty §2.3.3): the Gaussian diffusion is not
invariant for the annealed targets, so the final weighted set does not represent ``p(x_t | z_{1:t})``
exactly and its mean is a mode-seeking estimate. Consequently ``state.log_evidence`` accumulates the
standard SIR estimate of ``log p(z_t | z_{1:t-1})`` computed from the layer-1 particles at full likelihood
(``log sum_i w_{t-1}^i p(z_t|x^i) p/q``), i.e. relative to the APF's own (approximate) predictive
distribution; it costs no extra likelihood evaluation but is only as good as that approximation. Equal
budget (Fontmarty §3.3.2): an APF with ``N`` particles and ``L`` layers evaluates the likelihood ``L N``
times per frame; compare it with an SIR of ``L N`` particles.

Example::

    apf = AnnealedParticleFilter(dynamics, likelihood, n_particles=200, betas=(0.1, 0.4, 1.0),
                                 alphas=(1.0, 4.0, 4.0), diffusion_std=0.05, progress=False)
    track = apf.run(observations, x0, generator=g)          # track.stats["betas"]: (..., T, 3)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchpf.filters.base import ParticleFilter
from torchpf.filters.state import ParticleState, gather_particles
from torchpf.filters.weights import reweight, survival_fraction, temper


def anneal_beta(
    base: Tensor, energy: Tensor, survival_rate: float, lower: Tensor, iterations: int = 30
) -> Tensor:
    """``beta`` in ``[lower, 1]`` where ``ESS(base + beta * energy) / N`` falls to ``survival_rate``.

    Deutscher's adaptive annealing by bisection (30 halvings, batched over sequences, no host sync); the
    survival fraction usually decreases with ``beta``, and the bisection keeps the side that still meets the
    target. ``base, energy (..., N)``, ``lower (...)`` -> ``beta (...)``. Returns 1 when even ``beta = 1``
    keeps enough survivors and ``lower`` when even ``beta = lower`` does not.
    """
    one = torch.ones_like(lower)
    ok_at_one = survival_fraction(base + temper(one, energy)) >= survival_rate
    lo, hi = lower, one
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        good = survival_fraction(base + temper(mid, energy)) >= survival_rate
        lo = torch.where(good, mid, lo)
        hi = torch.where(good, hi, mid)
    return torch.where(ok_at_one, one, lo)


class AnnealedParticleFilter(ParticleFilter):
    """Annealed particle filter (Brubaker Alg. 2, eq. 19-20; Fontmarty Table 3). See the module docstring.

    Args:
        dynamics, likelihood, proposal: as :class:`~torchpf.filters.ParticleFilter` (the proposal is used
            by layer 1 only).
        n_particles: ``N`` particles *per layer*.
        betas: ``L`` likelihood exponents ``beta_1 < ... < beta_L = 1`` (default Fontmarty's
            ``(0.1, 0.4, 1.0)``), or ``"adaptive"`` (per-frame bisection on the survival rate).
        n_layers: ``L`` for ``betas="adaptive"`` (default: ``len(alphas)`` or 3).
        alphas: Fontmarty's per-layer dynamics exponents (diffusion covariance ``Sigma / alpha_l``); the first
            must be 1. Default ``(1, 4, 4)``, or all ones past the third layer.
        annealing_rate: Brubaker's ``alpha`` in ``(0, 1)`` (covariance ``alpha^ell Sigma``); excludes
            ``alphas``.
        diffusion_std: ``(D,)`` or scalar std of ``Sigma`` (state units); defaults to ``dynamics.std``.
        survival_rate: target ``ESS / N`` for ``betas="adaptive"`` (Deutscher: 0.5).
        layer_prior: include ``p(x | x_{t-1})`` in the layer weights (eq. 20) or not (Fontmarty Table 3).
        resampler, ess_threshold, sampling, progress: as :class:`~torchpf.filters.ParticleFilter`; the
            threshold applies at the start of a frame, layers always resample; ``sampling="qrs"`` applies to
            the layer-1 draws from the dynamics (the layer diffusions are i.i.d.).
    """

    def __init__(
        self,
        dynamics: Any,
        likelihood: Any,
        proposal: Any = None,
        *,
        n_particles: int | None = None,
        betas: Sequence[float] | str = (0.1, 0.4, 1.0),
        n_layers: int | None = None,
        alphas: Sequence[float] | None = None,
        annealing_rate: float | None = None,
        diffusion_std: Any = None,
        survival_rate: float = 0.5,
        layer_prior: bool = True,
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
        adaptive = isinstance(betas, str)
        n_layers = self._layers(betas, n_layers, alphas)
        if not adaptive:
            betas = tuple(float(b) for b in betas)
            if any(not 0.0 < b <= 1.0 for b in betas) or betas[-1] != 1.0:
                raise ValueError(f"betas must lie in (0, 1] and end with 1, got {betas}")
        if annealing_rate is not None:
            if alphas is not None:
                raise ValueError("give either alphas (Fontmarty) or annealing_rate (Brubaker), not both")
            if not 0.0 < annealing_rate <= 1.0:
                raise ValueError(f"annealing_rate must be in (0, 1], got {annealing_rate}")
            scales = [annealing_rate**ell for ell in range(n_layers)]
        else:
            if alphas is None:
                alphas = (1.0, 4.0, 4.0)[:n_layers] + (4.0,) * max(0, n_layers - 3)
            alphas = tuple(float(a) for a in alphas)
            if len(alphas) != n_layers:
                raise ValueError(f"{len(alphas)} alphas for {n_layers} layers")
            if alphas[0] != 1.0 or any(a <= 0 for a in alphas):
                raise ValueError(
                    f"alphas must be positive with alphas[0] == 1 (the proposal layer), got {alphas}"
                )
            scales = [1.0 / a for a in alphas]
        if diffusion_std is None and n_layers > 1:
            diffusion_std = getattr(dynamics, "std", None)
            if diffusion_std is None:
                raise ValueError("give diffusion_std (the layer diffusion std) or use dynamics with a .std")
        if not 0.0 < survival_rate < 1.0:
            raise ValueError(f"survival_rate must be in (0, 1), got {survival_rate}")
        self.adaptive = adaptive
        self.betas = None if adaptive else betas
        self.n_layers = n_layers
        self.diffusion_scales = tuple(scales)
        self.diffusion_std = diffusion_std
        self.survival_rate = survival_rate
        self.layer_prior = layer_prior

    @staticmethod
    def _layers(betas: Sequence[float] | str, n_layers: int | None, alphas: Sequence[float] | None) -> int:
        """``L``: ``len(betas)``, or for ``betas="adaptive"`` ``n_layers`` / ``len(alphas)`` / 3."""
        if isinstance(betas, str):
            if betas != "adaptive":
                raise ValueError(f"betas must be a sequence of floats or 'adaptive', got {betas!r}")
            n_layers = n_layers or (len(alphas) if alphas is not None else 3)
        else:
            if n_layers is not None and n_layers != len(betas):
                raise ValueError(f"n_layers={n_layers} but {len(betas)} betas were given")
            n_layers = len(betas)
        if n_layers < 1:
            raise ValueError("an APF needs at least one layer")
        return n_layers

    @classmethod
    def evaluations_per_particle(cls, **options: Any) -> int:
        """``L``: every layer weights all ``N`` particles (Fontmarty §3.3.2: APF at ``N / 3`` per layer)."""
        return cls._layers(
            options.get("betas", (0.1, 0.4, 1.0)), options.get("n_layers"), options.get("alphas")
        )

    def budget_options(self) -> dict[str, Any]:
        return {"betas": "adaptive" if self.adaptive else self.betas, "n_layers": self.n_layers}

    def _beta(self, layer: int, base: Tensor, energy: Tensor, lower: Tensor) -> Tensor:
        if not self.adaptive:
            return torch.full_like(lower, self.betas[layer])
        if layer == self.n_layers - 1:
            return torch.ones_like(lower)
        return anneal_beta(base, energy, self.survival_rate, lower)

    def step(self, state: ParticleState, obs: Any, generator: torch.Generator | None = None) -> ParticleState:
        """One APF frame; ``info`` adds ``"betas" (..., L)`` to the SIR diagnostics."""
        *frame, info = self._anneal(state, obs, generator)
        return self._end_frame(*frame, **info)

    def _anneal(self, state: ParticleState, obs: Any, generator: torch.Generator | None) -> tuple:
        """The layers of one frame: the positional arguments of :meth:`_end_frame` (the frame's particles,
        weights, evidence increment, failure flags, and each particle's frame-start parent and its extras)
        followed by its info keywords (a dict), for subclasses that add a move before the frame ends."""
        state, ancestors, resampled = self._maybe_resample(state, generator)
        x_prev, extras_prev = state.particles, state.extras
        x, log_corr = self._propose(state, ancestors, obs, generator)
        loglik = self._loglik(self.likelihood, x, obs)
        base = state.log_weights if log_corr is None else state.log_weights + log_corr

        # Evidence from layer 1 at full temperature: a proper SIR estimate w.r.t. the predictive particles.
        _, lse, failed_ev = reweight(base, loglik)
        inc = torch.where(failed_ev, torch.zeros_like(lse), lse)

        lower = loglik.new_zeros(loglik.shape[:-1])
        beta = self._beta(0, base, loglik, lower)
        log_w, _, failed = reweight(base, temper(beta, loglik))
        betas = [beta]
        if self.n_layers > 1:
            std = torch.as_tensor(self.diffusion_std, device=x.device, dtype=x.dtype)
        uniform = torch.full_like(log_w, -math.log(log_w.shape[-1]))
        for layer in range(1, self.n_layers):
            anc = self.resampler(log_w, generator)
            x, x_prev = self._gather(anc, x, x_prev)
            extras_prev = {k: gather_particles(v, anc) for k, v in extras_prev.items()}
            noise = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
            x = x + math.sqrt(self.diffusion_scales[layer]) * std * noise
            energy = self._loglik(self.likelihood, x, obs)
            if self.layer_prior:
                energy = energy + self.dynamics.log_prob(x, x_prev, extras=extras_prev).to(x.dtype)
            beta = self._beta(layer, uniform, energy, beta)
            log_w, _, failed_l = reweight(uniform, temper(beta, energy))
            failed = failed | failed_l
            betas.append(beta)
        failed = failed | failed_ev
        return state, x, log_w, inc, failed, resampled, x_prev, extras_prev, {"betas": torch.stack(betas, -1)}
