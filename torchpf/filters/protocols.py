"""Interfaces between the filters and the models they run.

Shapes: ``x (..., N, D)``, log-densities ``(..., N)``.

* Dynamics -- the motion prior ``p(x_t | x_{t-1})``: the base class :class:`torchpf.distributions.Dynamics`
  (re-exported here), with ``sample(x, generator, *, extras)``, ``log_prob(x_new, x_old, *, extras)``,
  optionally ``sample_from_noise(x, eps, *, extras)`` (quasi-Monte-Carlo sampling, Fontmarty Table 4) and the
  per-particle extras hooks ``init_extras`` / ``update_extras`` (no-ops in the base). Filters take any object
  with ``sample(x, generator)`` (and ``log_prob(x_new, x_old)``) too:
  :func:`torchpf.distributions.as_dynamics` adapts it once, at construction, so every call inside a filter is
  the same. A duck-typed model that defines ``update_extras`` is called with ``extras=`` (the extras of
  ``x_old``); once a frame's particles are final -- after a proposal, annealing layers, partition stages or
  HMC moves have moved them -- the filter calls ``update_extras(x_new, x_old, extras)`` with each particle's
  frame-start parent ``x_old``.
* :class:`Likelihood` -- ``likelihood(x, obs) -> (..., N)`` log-likelihood ``log p(z_t | x_t)``.
* :class:`Proposal` -- an importance distribution ``q(x_t | x_{t-1}, z_t)``: ``sample(state, obs, generator)``
  returns new particles ``(..., N, D)`` and ``log_q (..., N)``; ``state`` holds the (resampled) parents.
  The filter adds ``log p(x_t | x_{t-1}) - log q`` to the weights (Hauberg eq. 2; Brubaker eq. 17).

Example::

    class RandomWalk(torchpf.distributions.Dynamics):
        def sample(self, x, generator=None, *, extras=None):
            return x + 0.1 * torch.randn(x.shape, generator=generator)

        def log_prob(self, x_new, x_old, *, extras=None):
            return diag_normal_log_prob(x_new, x_old, 0.1)
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from torchpf.distributions import Dynamics

__all__ = ["Dynamics", "Likelihood", "Proposal"]


@runtime_checkable
class Likelihood(Protocol):
    """Observation model: ``(x (..., N, D), obs) -> log p(obs | x) (..., N)``."""

    def __call__(self, x: Tensor, obs: Any) -> Tensor: ...


@runtime_checkable
class Proposal(Protocol):
    """Importance distribution: ``sample(state, obs, generator) -> (x (..., N, D), log_q (..., N))``."""

    def sample(self, state: Any, obs: Any, generator: torch.Generator | None) -> tuple[Tensor, Tensor]: ...
