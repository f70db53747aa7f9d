"""Densities, randomness and the motion-model base that every filter, prior and proposal shares.

* :func:`diag_normal_log_prob` -- the one diagonal-Gaussian log-density (a ``σ = 0`` DOF is a Dirac).
* :func:`wrap_angle` -- angles to ``[-π, π)``.
* :func:`as_generator` -- a seed or a generator -> a ``torch.Generator`` on the particles' device.
* :func:`flatten_batch` / :func:`unflatten_batch` -- free leading dims ``...`` to one and back.
* :data:`DYNAMICS` / :func:`make_dynamics` -- motion priors by name.
* :class:`Dynamics` -- base of motion models ``p(x_t | x_{t-1})`` with no-op hooks for per-particle extras,
  so that filters call every model the same way; :func:`as_dynamics` adapts a duck-typed object once.

Example::

    from torchpf.distributions import Dynamics, diag_normal_log_prob

    class Walk(Dynamics):
        def __init__(self, std):
            super().__init__()
            self.register_buffer("std", torch.as_tensor(std))

        def sample(self, x, generator=None, *, extras=None):
            return x + self.std * torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)

        def log_prob(self, x_new, x_old, *, extras=None):
            return diag_normal_log_prob(x_new, x_old, self.std)
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping

import torch
from torch import Tensor, nn

from torchpf.registry import Registry

LOG_2PI = math.log(2 * math.pi)


# ------------------------------------------------------------------------------------------ densities
def diag_normal_log_prob(x: Tensor, mean: Tensor | float, std: Tensor | float) -> Tensor:
    """``log N(x; mean, diag std²)`` summed over the last dim: ``(..., D) -> (...)``, in nats.

    ``mean`` and ``std`` broadcast against ``x`` (``std`` scalar, ``(D,)`` or full shape). A DOF with
    ``std = 0`` is deterministic (a Dirac): it is left out of the sum, i.e. the density is taken with respect
    to the Lebesgue measure of the DOFs that move. That keeps frozen DOFs (fingers, a fixed root) from turning
    every weight into ``±inf``; ``x`` is assumed to equal ``mean`` there. Used by the random walks (Hauberg
    eq. 3; Brubaker eq. 11-13) and the proposal corrections (Hauberg eq. 2).
    """
    std = torch.as_tensor(std).to(x)
    mean = torch.as_tensor(mean).to(x)
    free = std > 0
    safe = torch.where(free, std, torch.ones_like(std))
    z = (x - mean) / safe
    per_dof = -0.5 * z.square() - torch.log(safe) - 0.5 * LOG_2PI
    return torch.where(free, per_dof, torch.zeros_like(per_dof)).sum(-1)


def wrap_angle(x: Tensor) -> Tensor:
    """Angles (rad) wrapped to ``[-π, π)``, elementwise, any shape."""
    return torch.remainder(x + math.pi, 2.0 * math.pi) - math.pi


# ------------------------------------------------------------------------------------------ randomness
def as_generator(
    seed_or_generator: int | torch.Generator | None, device: torch.device | str | None = None
) -> torch.Generator | None:
    """A ``torch.Generator`` on ``device`` (the particles' device) from a seed or a generator.

    ``None`` stays ``None`` (torch's global generator). A seed gives a new generator on ``device`` seeded
    with it. A generator on ``device`` is returned as is; a generator on another device cannot be used by
    ``torch.randn(..., device=device)``, so a new generator on ``device`` is derived from it (seeded with one
    draw of it, so the result is still reproducible from the given generator's state).
    """
    device = torch.device("cpu" if device is None else device)
    if seed_or_generator is None:
        return None
    if isinstance(seed_or_generator, torch.Generator):
        if seed_or_generator.device.type == device.type:
            return seed_or_generator
        seed = int(torch.randint(0, 2**62, (), generator=seed_or_generator, device=seed_or_generator.device))
        return torch.Generator(device=device).manual_seed(seed)
    if isinstance(seed_or_generator, bool) or not isinstance(seed_or_generator, int):
        raise TypeError(f"seed must be an int or a torch.Generator, got {type(seed_or_generator).__name__}")
    return torch.Generator(device=device).manual_seed(int(seed_or_generator))


def randn_like(x: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Standard-normal noise of ``x``'s shape, dtype and device drawn from ``generator``."""
    return torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)


# ------------------------------------------------------------------------------------------ batch dims
def flatten_batch(x: Tensor, event_dims: int) -> tuple[Tensor, torch.Size]:
    """``(..., *event)`` -> ``(B, *event)`` and the batch shape ``...`` for :func:`unflatten_batch`.

    ``event_dims`` trailing dims are kept; ``B`` is the product of the rest (1 for none).
    """
    batch = x.shape[: x.ndim - event_dims]
    return x.reshape(-1, *x.shape[x.ndim - event_dims :]), batch


def unflatten_batch(x: Tensor, batch: torch.Size) -> Tensor:
    """``(B, *event)`` -> ``(*batch, *event)``: the inverse of :func:`flatten_batch`."""
    return x.reshape(*batch, *x.shape[1:])


# ------------------------------------------------------------------------------------------ dynamics
class Dynamics(nn.Module):
    """Base of motion models ``p(x_t | x_{t-1})`` over particles ``x (..., N, D)``.

    Every filter calls a dynamics the same way; the hooks for per-particle extras (a velocity riding along
    with each particle, Rius eq. 3) are no-ops here, so a plain model implements only :meth:`sample` and,
    where tractable, :meth:`log_prob`:

    * ``sample(x, generator, *, extras)`` -> ``x_t (..., N, D)``.
    * ``log_prob(x_new, x_old, *, extras)`` -> ``(..., N)`` log-density in nats.
    * ``sample_from_noise(x, eps, *, extras)``: the deterministic map of standard-normal noise
      ``eps (..., N, noise_dim)`` to a sample, for quasi-Monte-Carlo sampling (Fontmarty Table 4).
    * ``init_extras(x0)`` -> the extras of the initial particles; ``update_extras(x_new, x_old, extras)`` ->
      the extras once a frame's particles are final (``x_old`` is each particle's frame-start parent);
      ``frame_stats(x, log_weights, extras)`` -> per-frame diagnostics for ``Track.stats``.

    ``extras`` is the mapping of the parents' extras (empty for a model that keeps none).
    """

    #: dimension of the noise that :meth:`sample_from_noise` maps (``None``: the state dimension ``D``)
    noise_dim: int | None = None

    def sample(self, x: Tensor, generator: torch.Generator | None = None, *, extras=None) -> Tensor:
        raise NotImplementedError(f"{type(self).__name__} does not implement sample")

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras=None) -> Tensor:
        raise NotImplementedError(f"{type(self).__name__} has no tractable log_prob")

    def sample_from_noise(self, x: Tensor, eps: Tensor, *, extras=None) -> Tensor:
        raise TypeError(f"{type(self).__name__} has no sample_from_noise(x, eps); QRS sampling needs it")

    def has_noise_map(self) -> bool:
        """Whether :meth:`sample_from_noise` is implemented (quasi-Monte-Carlo sampling needs it)."""
        return type(self).sample_from_noise is not Dynamics.sample_from_noise

    def init_extras(self, x0: Tensor) -> dict[str, Tensor]:
        return {}

    def update_extras(self, x_new: Tensor, x_old: Tensor, extras: Mapping[str, Tensor]) -> dict[str, Tensor]:
        return dict(extras)

    def frame_stats(self, x: Tensor, log_weights: Tensor, extras: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """Per-frame diagnostics ``{name: (...)}`` from a frame's final particles ``x (..., N, D)``, weights
        ``(..., N)`` and extras; the filters add them to ``state.info`` (and ``Track.stats``). None here."""
        return {}

    def noise_size(self, state_dim: int) -> int:
        """Dimension of the noise :meth:`sample_from_noise` expects (``noise_dim``, default ``D``)."""
        return int(self.noise_dim or state_dim)


class _DuckDynamics(Dynamics):
    """A duck-typed dynamics object (``sample(x, generator)`` / ``log_prob(new, old)``, optionally with
    ``extras=`` keywords and the hooks) seen through the :class:`Dynamics` interface."""

    def __init__(self, inner):
        super().__init__()
        self.inner = inner
        # a model that defines update_extras takes ``extras=`` in sample / log_prob
        self._stateful = callable(getattr(inner, "update_extras", None))
        self.noise_dim = getattr(inner, "noise_dim", None)

    def _kw(self, extras):
        return {"extras": extras if extras is not None else {}} if self._stateful else {}

    def sample(self, x, generator=None, *, extras=None):
        return self.inner.sample(x, generator, **self._kw(extras))

    def log_prob(self, x_new, x_old, *, extras=None):
        return self.inner.log_prob(x_new, x_old, **self._kw(extras))

    def sample_from_noise(self, x, eps, *, extras=None):
        fn = getattr(self.inner, "sample_from_noise", None)
        if fn is None:
            return super().sample_from_noise(x, eps)
        return fn(x, eps, **self._kw(extras))

    def has_noise_map(self):
        return callable(getattr(self.inner, "sample_from_noise", None))

    def init_extras(self, x0):
        fn = getattr(self.inner, "init_extras", None)
        return dict(fn(x0)) if fn is not None else {}

    def update_extras(self, x_new, x_old, extras):
        return dict(self.inner.update_extras(x_new, x_old, extras)) if self._stateful else dict(extras)

    def frame_stats(self, x, log_weights, extras):
        fn = getattr(self.inner, "frame_stats", None)
        return dict(fn(x, log_weights, extras)) if fn is not None else {}

    def __getattr__(self, name):
        try:
            return super().__getattr__(name)
        except AttributeError:
            # attributes of the adapted model (``std``, ``sigma``, ...) read through; while the module is
            # being built or unpickled there is no inner model yet, and the lookup must fail as usual
            inner = self.__dict__.get("inner", self.__dict__.get("_modules", {}).get("inner"))
            if inner is None:
                raise
            return getattr(inner, name)


def as_dynamics(model) -> Dynamics:
    """``model`` as a :class:`Dynamics`: subclasses pass through, a duck-typed object with ``sample`` (and
    ``log_prob``) is adapted once here instead of being probed at every call."""
    if isinstance(model, Dynamics):
        return model
    if not callable(getattr(model, "sample", None)):
        raise TypeError(f"dynamics must have a sample(x, generator) method, got {type(model).__name__}")
    return _DuckDynamics(model)


#: Motion priors by name: factories ``factory(skeleton, **options) -> Dynamics``. The ``priors``
#: package registers ``random_walk``, ``constant_velocity``, ``damped`` and ``action`` through the
#: ``torchpf.dynamics`` entry-point group (so torchpf never imports priors); ``DYNAMICS.register(name,
#: factory)`` adds one at run time.
DYNAMICS: Registry = Registry("dynamics", entry_point_group="torchpf.dynamics")


def make_dynamics(name: str, skeleton, **options) -> Dynamics:
    """Build the motion prior registered as ``name`` for ``skeleton``: ``DYNAMICS.get(name)(skeleton,
    **options)`` (an unknown name raises a ``ValueError`` listing the registered ones; options the factory
    does not take, or a required one missing, a ``TypeError`` naming the prior and what it takes)."""
    factory = DYNAMICS.get(name)
    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):  # a builtin or C callable: let the call itself complain
        signature = None
    if signature is not None:
        try:
            signature.bind(skeleton, **options)
        except TypeError as e:
            takes = [
                f"{p.name}{'' if p.default is inspect.Parameter.empty else '=...'}"
                for p in list(signature.parameters.values())[1:]
                if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
            ]
            raise TypeError(
                f"dynamics {name!r}: {e} (given {sorted(options) or 'no options'}; "
                f"it takes {', '.join(takes)})"
            ) from None
    return factory(skeleton, **options)
