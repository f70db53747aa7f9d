"""Duck-typed interfaces between the filters and the models they run.

The filters never subclass or wrap a model: anything with the right methods works (an ``nn.Module`` in
practice, so that ``.to(device)`` moves its buffers). Shapes: ``x (..., N, D)``, log-densities ``(..., N)``.

* :class:`Dynamics` -- the motion prior ``p(x_t | x_{t-1})``: ``sample(x, generator)`` and
  ``log_prob(x_new, x_old)``. Optional ``sample_from_noise(x, eps)`` (with an optional ``noise_dim``
  attribute, default ``D``) maps standard-normal noise ``eps (..., N, noise_dim)`` to a sample;
  quasi-Monte-Carlo sampling (``sampling="qrs"``, Fontmarty Table 4) needs it.
* :class:`StatefulDynamics` -- dynamics whose prediction depends on per-particle extras (a velocity for a
  constant-velocity prior, Rius eq. 3). A dynamics opts in by defining ``update_extras``; the filters then
  pass the particles' extras to ``sample``, ``log_prob`` and ``sample_from_noise`` as the keyword ``extras``
  (the extras of ``x_old``) and, once a frame's particles are final -- after a proposal, annealing layers,
  partition stages or HMC moves have moved them -- call ``update_extras(x_new, x_old, extras)`` with each
  particle's frame-start parent ``x_old`` to get the new extras (e.g. ``v = (x_new - x_old) / dt``). An
  optional ``init_extras(x0)`` supplies the extras for ``filter.init(x0)``.
* :class:`Likelihood` -- ``likelihood(x, obs) -> (..., N)`` log-likelihood ``log p(z_t | x_t)``.
* :class:`Proposal` -- an importance distribution ``q(x_t | x_{t-1}, z_t)``: ``sample(state, obs, generator)``
  returns new particles ``(..., N, D)`` and ``log_q (..., N)``; ``state`` holds the (resampled) parents.
  The filter adds ``log p(x_t | x_{t-1}) - log q`` to the weights (Hauberg eq. 2; Brubaker eq. 17).

The helper functions below call a dynamics the right way whether it is stateful or not.

Example::

    class RandomWalk(torch.nn.Module):
        def sample(self, x, generator=None): return x + 0.1 * torch.randn(x.shape, generator=generator)
        def log_prob(self, x_new, x_old): return Normal(x_old, 0.1).log_prob(x_new).sum(-1)
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor


@runtime_checkable
class Dynamics(Protocol):
    """Motion prior ``p(x_t | x_{t-1})`` over ``(..., N, D)`` particles."""

    def sample(self, x: Tensor, generator: torch.Generator | None) -> Tensor: ...

    def log_prob(self, x_new: Tensor, x_old: Tensor) -> Tensor: ...


@runtime_checkable
class StatefulDynamics(Protocol):
    """Dynamics that read and update per-particle extras (see the module docstring)."""

    def sample(
        self, x: Tensor, generator: torch.Generator | None, *, extras: Mapping[str, Tensor]
    ) -> Tensor: ...

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras: Mapping[str, Tensor]) -> Tensor: ...

    def update_extras(
        self, x_new: Tensor, x_old: Tensor, extras: Mapping[str, Tensor]
    ) -> Mapping[str, Tensor]: ...


@runtime_checkable
class Likelihood(Protocol):
    """Observation model: ``(x (..., N, D), obs) -> log p(obs | x) (..., N)``."""

    def __call__(self, x: Tensor, obs: Any) -> Tensor: ...


@runtime_checkable
class Proposal(Protocol):
    """Importance distribution: ``sample(state, obs, generator) -> (x (..., N, D), log_q (..., N))``."""

    def sample(self, state: Any, obs: Any, generator: torch.Generator | None) -> tuple[Tensor, Tensor]: ...


def is_stateful(dynamics: Any) -> bool:
    """True when ``dynamics`` follows :class:`StatefulDynamics` (it defines ``update_extras``)."""
    return hasattr(dynamics, "update_extras")


def dynamics_sample(
    dynamics: Any, x: Tensor, extras: Mapping[str, Tensor], generator: torch.Generator | None
) -> Tensor:
    """Draw ``x_t ~ p(. | x)``: ``(..., N, D) -> (..., N, D)``."""
    if is_stateful(dynamics):
        return dynamics.sample(x, generator, extras=extras)
    return dynamics.sample(x, generator)


def dynamics_log_prob(dynamics: Any, x_new: Tensor, x_old: Tensor, extras: Mapping[str, Tensor]) -> Tensor:
    """``log p(x_new | x_old)``: ``(..., N, D), (..., N, D) -> (..., N)``, in the particles' dtype."""
    if is_stateful(dynamics):
        out = dynamics.log_prob(x_new, x_old, extras=extras)
    else:
        out = dynamics.log_prob(x_new, x_old)
    return out.to(x_new.dtype)


def dynamics_from_noise(dynamics: Any, x: Tensor, eps: Tensor, extras: Mapping[str, Tensor]) -> Tensor:
    """Deterministic map of standard-normal noise ``eps (..., N, noise_dim)`` to ``x_t (..., N, D)``."""
    if not hasattr(dynamics, "sample_from_noise"):
        raise TypeError(f"{type(dynamics).__name__} has no sample_from_noise(x, eps); QRS sampling needs it")
    if is_stateful(dynamics):
        return dynamics.sample_from_noise(x, eps, extras=extras)
    return dynamics.sample_from_noise(x, eps)


def noise_dim(dynamics: Any, state_dim: int) -> int:
    """Dimension of the standard-normal noise that ``sample_from_noise`` expects (default ``D``)."""
    return int(getattr(dynamics, "noise_dim", None) or state_dim)


def update_extras(
    dynamics: Any, x_new: Tensor, x_old: Tensor, extras: Mapping[str, Tensor]
) -> Mapping[str, Tensor]:
    """New per-particle extras once the frame's particles are final (unchanged for plain dynamics)."""
    if is_stateful(dynamics):
        return dict(dynamics.update_extras(x_new, x_old, extras))
    return extras
