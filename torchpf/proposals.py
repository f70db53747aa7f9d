"""Generic proposals (importance distributions) and Gaussian dynamics for the particle filters.

A proposal draws the new particles from ``q(x_t | x_{t-1}, z_t)`` instead of the dynamics, so that they land
where the current observation says the state is; the filter then corrects the weights by
``p(x_t | x_{t-1}) / q(x_t | x_{t-1}, z_t)`` (Hauberg eq. 2; Brubaker eq. 17). The protocol is
``sample(state, obs, generator) -> (x (..., N, D), log_q (..., N))`` where ``state.particles`` are the
(resampled) parents ``x_{t-1}``; ``log_q`` must be the exact log-density of the returned samples (up to a
constant shared by all particles of a sequence).

* :class:`BootstrapProposal` -- the dynamics itself, with an explicit ``log_q`` (the correction cancels;
  mostly for testing the correction path; ``proposal=None`` is the fast equivalent).
* :class:`ICondensationProposal` -- Isard & Blake's mixture (Fontmarty §2.2.2)::

      q(x | x_{t-1}^i, z) = alpha pi(x | z) + beta p(x | x_{t-1}^i) + (1 - alpha - beta) p0(x)

  with the exact mixture density in ``log_q`` (each particle's draw may come from any component, so the
  weight uses the full mixture, not the density of the component it was drawn from).

Dynamics and densities usable as models, mixture components and test fixtures:
:class:`GaussianRandomWalk` ``N(x_{t-1}, diag std^2)``, :class:`LinearGaussianDynamics`
``N(A x_{t-1} + b, Q)``, :class:`Gaussian` (a fixed density, e.g. ``p0``), :class:`ObservationGaussian`
(``pi(x | z) = N(f(z), diag std^2)``). All follow the particles' device and dtype; the two dynamics also
provide ``sample_from_noise`` for QRS sampling.

Example::

    q = ICondensationProposal(dynamics, ObservationGaussian(lambda z: z, std=0.1), Gaussian(mu0, std=1.0),
                              alpha=0.3, beta=0.6)
    pf = ParticleFilter(dynamics, likelihood, proposal=q, n_particles=1000)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn

from torchpf.distributions import LOG_2PI, Dynamics, as_dynamics, diag_normal_log_prob, randn_like


def _buffer(value: Tensor | float) -> Tensor:
    """A parameter as a floating tensor: tensors keep their dtype, Python numbers get the default dtype."""
    t = torch.as_tensor(value)
    return t if t.is_floating_point() else t.to(torch.get_default_dtype())


def _like(t: Tensor, x: Tensor) -> Tensor:
    return t.to(device=x.device, dtype=x.dtype)


class GaussianRandomWalk(Dynamics):
    """Random-walk dynamics ``x_t = x_{t-1} + std * eps`` (Fontmarty §3.1, Table 5; Brubaker eq. 11).

    Args:
        std: scalar or ``(D,)`` per-DOF standard deviation (state units per frame).
    """

    def __init__(self, std: Tensor | float):
        super().__init__()
        self.register_buffer("std", _buffer(std))

    def sample(self, x: Tensor, generator: torch.Generator | None = None, *, extras=None) -> Tensor:
        """``(..., N, D) -> (..., N, D)``."""
        return self.sample_from_noise(x, randn_like(x, generator))

    def sample_from_noise(self, x: Tensor, eps: Tensor, *, extras=None) -> Tensor:
        """``x + std * eps`` with ``eps (..., N, D)`` standard normal."""
        return x + _like(self.std, x) * eps

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras=None) -> Tensor:
        """``log N(x_new; x_old, diag std^2)``: ``(..., N, D) -> (..., N)``."""
        return diag_normal_log_prob(x_new, x_old, self.std)


class LinearGaussianDynamics(Dynamics):
    """Linear-Gaussian dynamics ``x_t = A x_{t-1} + b + L eps``, ``Q = L L^T`` (column-vector convention).

    Args:
        transition: ``A (D, D)``.
        cov: ``Q (D, D)`` process-noise covariance (symmetric positive definite).
        offset: optional ``b (D,)``.
    """

    def __init__(self, transition: Tensor, cov: Tensor, offset: Tensor | None = None):
        super().__init__()
        transition = _buffer(transition)
        self.register_buffer("transition", transition)
        self.register_buffer("chol", torch.linalg.cholesky(_buffer(cov).to(transition.dtype)))
        offset = torch.zeros(transition.shape[0]) if offset is None else _buffer(offset)
        self.register_buffer("offset", offset.to(transition.dtype))

    def mean(self, x: Tensor) -> Tensor:
        """Predicted mean ``A x + b``: ``(..., D) -> (..., D)``."""
        return x @ _like(self.transition, x).T + _like(self.offset, x)

    def sample(self, x: Tensor, generator: torch.Generator | None = None, *, extras=None) -> Tensor:
        """``(..., N, D) -> (..., N, D)``."""
        return self.sample_from_noise(x, randn_like(x, generator))

    def sample_from_noise(self, x: Tensor, eps: Tensor, *, extras=None) -> Tensor:
        """``A x + b + L eps`` with ``eps (..., N, D)`` standard normal."""
        return self.mean(x) + eps @ _like(self.chol, x).T

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras=None) -> Tensor:
        """``log N(x_new; A x_old + b, Q)``: ``(..., N, D) -> (..., N)``."""
        chol = _like(self.chol, x_new)
        r = x_new - self.mean(x_old)
        # One triangular solve with all particles as right-hand sides (a batch of tiny solves is far slower).
        z = torch.linalg.solve_triangular(chol, r.reshape(-1, r.shape[-1]).T, upper=False).T.reshape(r.shape)
        logdet = torch.log(torch.diagonal(chol)).sum()
        return -0.5 * (z * z).sum(-1) - logdet - 0.5 * x_new.shape[-1] * LOG_2PI


class Gaussian(nn.Module):
    """A fixed diagonal Gaussian density ``N(mean, diag std^2)`` over ``(..., D)``, e.g. an initial prior.

    ``sample(like, generator)`` returns a tensor shaped like ``like (..., N, D)``;
    ``log_prob(x) -> (..., N)``.
    ``mean`` may carry batch dims ``(..., D)`` (one per sequence) or be ``(D,)``.
    """

    def __init__(self, mean: Tensor | float, std: Tensor | float = 1.0):
        super().__init__()
        self.register_buffer("mean", _buffer(mean))
        self.register_buffer("std", _buffer(std))

    def _mean(self, x: Tensor) -> Tensor:
        m = _like(self.mean, x)
        return m.unsqueeze(-2) if m.ndim > 1 else m

    def sample(self, like: Tensor, generator: torch.Generator | None = None) -> Tensor:
        return self._mean(like) + _like(self.std, like) * randn_like(like, generator)

    def log_prob(self, x: Tensor) -> Tensor:
        return diag_normal_log_prob(x, self._mean(x), self.std)


class ObservationGaussian(nn.Module):
    """Observation-driven importance density ``pi(x | z) = N(x; f(z), diag std^2)``.

    Args:
        mean_fn: ``f(obs) -> (..., D)`` state suggested by the observation (a detector, an IK solution...).
        std: scalar or ``(D,)`` spread around it (state units).
    """

    def __init__(self, mean_fn: Callable[[Any], Tensor], std: Tensor | float):
        super().__init__()
        self.mean_fn = mean_fn
        self.register_buffer("std", _buffer(std))

    def sample(self, obs: Any, like: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Draws shaped like ``like (..., N, D)``."""
        return _like(self.mean_fn(obs), like).unsqueeze(-2) + _like(self.std, like) * randn_like(
            like, generator
        )

    def log_prob(self, x: Tensor, obs: Any) -> Tensor:
        """``(..., N, D) -> (..., N)``."""
        return diag_normal_log_prob(x, _like(self.mean_fn(obs), x).unsqueeze(-2), self.std)


class BootstrapProposal(nn.Module):
    """The dynamics used as a proposal, returning its own ``log_q`` (the filter's correction is then 0)."""

    def __init__(self, dynamics: Any):
        super().__init__()
        self.dynamics = as_dynamics(dynamics)

    def sample(self, state: Any, obs: Any, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        x = self.dynamics.sample(state.particles, generator, extras=state.extras)
        return x, self.dynamics.log_prob(x, state.particles, extras=state.extras).to(x.dtype)


class ICondensationProposal(nn.Module):
    """I-CONDENSATION mixture proposal (Isard & Blake; Fontmarty §2.2.2).

    ``q(x | x_{t-1}^i, z) = alpha pi(x | z) + beta p(x | x_{t-1}^i) + (1 - alpha - beta) p0(x)``.

    Args:
        dynamics: ``p(x_t | x_{t-1})`` (sample / log_prob, stateful dynamics supported).
        importance: ``pi(x | z)`` with ``sample(obs, like, generator)`` and ``log_prob(x, obs)``, e.g.
            :class:`ObservationGaussian`.
        prior: ``p0(x)`` with ``sample(like, generator)`` and ``log_prob(x)``, e.g. :class:`Gaussian`; may be
            ``None`` when ``alpha + beta == 1``.
        alpha, beta: mixture weights, ``alpha, beta >= 0``, ``alpha + beta <= 1``.

    Every component is sampled for every particle and one is kept per particle (three cheap draws instead of a
    data-dependent gather), and ``log_q`` is the log of the full mixture density at the kept sample.
    """

    def __init__(self, dynamics: Any, importance: Any, prior: Any = None, *, alpha: float, beta: float):
        super().__init__()
        rest = 1.0 - alpha - beta
        if alpha < 0 or beta < 0 or rest < -1e-12:
            raise ValueError(f"need alpha, beta >= 0 and alpha + beta <= 1, got {alpha}, {beta}")
        if prior is None and rest > 1e-12:
            raise ValueError("a prior p0 is needed when alpha + beta < 1")
        self.dynamics = as_dynamics(dynamics)
        self.importance = importance
        self.prior = prior
        self.alpha = float(alpha)
        self.beta = float(beta)
        self.rest = max(rest, 0.0)

    def sample(self, state: Any, obs: Any, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """``state.particles (..., N, D)`` parents -> ``(x (..., N, D), log_q (..., N))``."""
        parents, extras = state.particles, state.extras
        x_pi = self.importance.sample(obs, parents, generator)
        x_dyn = self.dynamics.sample(parents, generator, extras=extras)
        u = torch.rand(parents.shape[:-1], generator=generator, device=parents.device, dtype=parents.dtype)
        x = torch.where((u < self.alpha).unsqueeze(-1), x_pi, x_dyn)
        if self.prior is not None and self.rest > 0:
            x_p0 = self.prior.sample(parents, generator)
            x = torch.where((u >= self.alpha + self.beta).unsqueeze(-1), x_p0, x)
        return x, self.log_prob(x, state, obs)

    def log_prob(self, x: Tensor, state: Any, obs: Any) -> Tensor:
        """Mixture log-density ``log q(x | x_{t-1}^i, z)``: ``(..., N, D) -> (..., N)``."""
        terms = []
        if self.alpha > 0:
            terms.append(math.log(self.alpha) + self.importance.log_prob(x, obs).to(x.dtype))
        if self.beta > 0:
            log_p = self.dynamics.log_prob(x, state.particles, extras=state.extras).to(x.dtype)
            terms.append(math.log(self.beta) + log_p)
        if self.rest > 0:
            terms.append(math.log(self.rest) + self.prior.log_prob(x).to(x.dtype))
        return torch.logsumexp(torch.stack(terms), 0)
