"""Motion priors ``p(θ_t | θ_{t-1})`` for articulated tracking: the dynamics a particle filter samples from.

Every prior is an ``nn.Module`` following the duck-typed dynamics protocol of
:mod:`torchpf.filters.protocols`: ``sample(x, generator)`` draws ``x_t`` for every particle and
``log_prob(x_new, x_old)`` returns ``log p(x_new | x_old)`` ``(..., N)`` where it is tractable. Particles are
``(..., N, D)`` pose vectors in ``Skeleton.dof_names`` order (radians / metres).

* :class:`ConstantVelocity` -- Rius eq. 3: ``φ_t = φ_{t-1} + V + N(0, σ_φ²)`` with a per-particle
  velocity ``V_t = α V_{t-1} + (1-α)(φ_{t-1} - φ_{t-2})`` carried as the extra ``"velocity"``.
* :class:`DampedSecondOrder` -- Brubaker eq. 13: ``s_{t+1} = s_t + κ (s_t - s_{t-1}) + η``.

Example::

    cv = ConstantVelocity(0.05, alpha=0.5)
    extras = cv.init_extras(x0)                               # {"velocity": zeros (..., N, D)}
    x1 = cv.sample(x0, generator, extras=extras); extras = cv.update_extras(x1, x0, extras)
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor, nn

_LOG_2PI = math.log(2.0 * math.pi)


def _as_buffer(value, name: str) -> Tensor:
    """Float64 tensor (scalar or ``(D,)``) from a float / sequence / tensor, checked non-negative."""
    t = torch.as_tensor(value, dtype=torch.float64).clone()
    if t.ndim > 1:
        raise ValueError(f"{name} must be a scalar or a (D,) vector, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all() or (t < 0).any():
        raise ValueError(f"{name} must be finite and >= 0")
    return t


def _randn_like(x: Tensor, generator: torch.Generator | None) -> Tensor:
    return torch.randn(x.shape, generator=generator, dtype=x.dtype, device=x.device)


def _diag_normal_log_prob(x: Tensor, mean: Tensor, sigma: Tensor) -> Tensor:
    """``log N(x; mean, diag σ²)`` summed over the last dim, ``(..., D) -> (...)``.

    DOFs with ``σ = 0`` are deterministic (a Dirac): they are left out of the sum, i.e. the density is taken
    with respect to the Lebesgue measure of the DOFs that do move. That keeps frozen DOFs (fingers, a fixed
    root) from turning every weight into ``-inf``/``+inf``; ``x`` is assumed to equal ``mean`` there.
    """
    sigma = sigma.to(x)
    free = sigma > 0
    safe = torch.where(free, sigma, torch.ones_like(sigma))
    z = (x - mean) / safe
    per_dof = -0.5 * z.square() - torch.log(safe) - 0.5 * _LOG_2PI
    return torch.where(free, per_dof, torch.zeros_like(per_dof)).sum(-1)


class _VelocityDynamics(nn.Module):
    """Gaussian diffusion around ``x + dt * gain * v`` with a per-particle velocity extra ``"velocity"``."""

    noise_dim = None  # standard-normal noise has the state's dimension D (protocol default)

    def __init__(self, sigma, *, dt: float = 1.0):
        super().__init__()
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        self.register_buffer("sigma", _as_buffer(sigma, "sigma"))
        self.dt = float(dt)

    # -- to be specialised -------------------------------------------------------------------------------
    def _gain(self) -> float:
        return 1.0

    def _blend(self) -> float:
        """Weight of the old velocity in the update ``v_new = a v + (1 - a) (x_new - x_old) / dt``."""
        return 0.0

    # -- protocol ------------------------------------------------------------------------------------------
    def _velocity(self, x: Tensor, extras: Mapping[str, Tensor] | None) -> Tensor:
        if extras is None or "velocity" not in extras:
            return torch.zeros_like(x)
        v = extras["velocity"]
        if v.shape[-1] != x.shape[-1]:
            raise ValueError(f"extras['velocity'] has D={v.shape[-1]}, particles have D={x.shape[-1]}")
        return v.to(x)

    def init_extras(self, x0: Tensor) -> dict[str, Tensor]:
        """Zero velocity per particle: ``{"velocity": (..., N, D)}`` (the first frame is a random walk)."""
        return {"velocity": torch.zeros_like(x0)}

    def predict(self, x: Tensor, extras: Mapping[str, Tensor] | None = None) -> Tensor:
        """Mean of ``p(x_t | x_{t-1}, v)``: ``x + dt * gain * v``, ``(..., N, D)``."""
        return x + (self.dt * self._gain()) * self._velocity(x, extras)

    def _scale(self, x: Tensor) -> Tensor:
        sigma = self.sigma.to(x)
        if sigma.ndim == 1 and sigma.shape[0] != x.shape[-1]:
            raise ValueError(f"sigma has {sigma.shape[0]} entries, particles have D={x.shape[-1]}")
        return sigma

    def sample(
        self,
        x: Tensor,
        generator: torch.Generator | None = None,
        *,
        extras: Mapping[str, Tensor] | None = None,
    ) -> Tensor:
        """Draw ``x_t = predict(x, v) + σ ε``, ``ε ~ N(0, I)``: ``(..., N, D) -> (..., N, D)``."""
        return self.sample_from_noise(x, _randn_like(x, generator), extras=extras)

    def sample_from_noise(
        self, x: Tensor, eps: Tensor, *, extras: Mapping[str, Tensor] | None = None
    ) -> Tensor:
        """Deterministic map of standard-normal ``eps (..., N, D)`` to a sample (QRS sampling uses it)."""
        return self.predict(x, extras) + self._scale(x) * eps.to(x)

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras: Mapping[str, Tensor] | None = None) -> Tensor:
        """``log N(x_new; predict(x_old, v), diag σ²)`` ``(..., N)``; σ = 0 DOFs are left out (Dirac)."""
        return _diag_normal_log_prob(x_new, self.predict(x_old, extras), self._scale(x_new))

    def update_extras(
        self, x_new: Tensor, x_old: Tensor, extras: Mapping[str, Tensor] | None = None
    ) -> dict[str, Tensor]:
        """New velocity once the frame is final: ``v' = a v + (1 - a) (x_new - x_old) / dt``, ``(..., N, D)``.

        ``x_old`` is each particle's frame-start parent, so the velocity is that particle's own history.
        Other extras are passed through unchanged.
        """
        a = self._blend()
        v = self._velocity(x_old, extras)
        out = dict(extras or {})
        out["velocity"] = a * v + (1.0 - a) * (x_new - x_old) / self.dt
        return out

    def extra_repr(self) -> str:
        s = self.sigma
        sig = f"{s.item():.4g}" if s.ndim == 0 else f"(D={s.shape[0]})"
        return f"sigma={sig}, dt={self.dt}"


class ConstantVelocity(_VelocityDynamics):
    """Constant-velocity prior with an exponentially smoothed velocity (Rius eq. 3).

    ``φ_t = φ_{t-1} + dt · V + N(0, diag σ_φ²)``, and once the frame's particles are final
    ``V ← α V + (1 - α)(φ_t - φ_{t-1}) / dt`` (:meth:`update_extras`), per particle.

    Indexing: Rius writes the update as ``V_t = α V_{t-1} + (1-α)(φ_{t-1} - φ_{t-2})`` and predicts with it
    at the next frame; we use the freshest difference ``φ_{t-1} - φ_{t-2}`` in the prediction of ``φ_t``
    (no extra frame of lag), which is what the filters' ``update_extras`` hook gives. Rius smooths the
    velocity of the *estimated* state; here every particle carries its own velocity (extra ``"velocity"``
    ``(..., N, D)``, gathered by resampling), which reduces to Rius' when the particles agree. To use the
    estimate's velocity instead, overwrite ``state.extras["velocity"]`` between steps.

    Args:
        sigma: diffusion std σ_φ per frame step, scalar or ``(D,)`` (radians / metres). It does *not* scale
            with ``dt``. DOFs with σ = 0 move deterministically and are left out of :meth:`log_prob`.
        alpha: learning coefficient α in [0, 1] (Rius uses 0.5): 0 keeps only the last difference, 1 never
            updates the velocity.
        dt: time unit of the velocity. With the default 1.0 the velocity is in state units *per frame*; with
            ``dt = 1 / fps`` it is in units per second (same predictions, the velocity is just rescaled).

    Example::

        cv = ConstantVelocity(torch.full((D,), 0.05), alpha=0.5)
        state = ParticleFilter(cv, likelihood, n_particles=500).init(x0)    # extras from cv.init_extras
    """

    def __init__(self, sigma, *, alpha: float = 0.5, dt: float = 1.0):
        super().__init__(sigma, dt=dt)
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {alpha}")
        self.alpha = float(alpha)

    def _blend(self) -> float:
        return self.alpha

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, alpha={self.alpha}"


class DampedSecondOrder(_VelocityDynamics):
    """Damped second-order linear prior (Brubaker eq. 13): ``s_{t+1} = s_t + κ (s_t - s_{t-1}) + η``.

    ``η ~ N(0, diag σ²)``; the last difference ``(s_t - s_{t-1}) / dt`` rides along per particle as the extra
    ``"velocity"`` ``(..., N, D)`` (set by :meth:`update_extras`, zero at :meth:`init_extras`), so the
    transition is the exact Gaussian ``G(s_{t+1}; s_t + κ (s_t - s_{t-1}), Σ)`` and :meth:`log_prob` is exact.
    κ = 0 is the first-order random walk of Brubaker eq. 11-12.

    Args:
        sigma: process-noise std per step, scalar or ``(D,)``; σ = 0 DOFs are deterministic.
        kappa: damping constant κ, typically in [0, 1].
        dt: time unit of the stored velocity (1.0: per frame); the prediction does not depend on it.

    Example::

        dyn = DampedSecondOrder(0.03, kappa=0.8)
        x1 = dyn.sample(x0, g, extras=dyn.init_extras(x0))
    """

    def __init__(self, sigma, *, kappa: float = 0.8, dt: float = 1.0):
        super().__init__(sigma, dt=dt)
        if not math.isfinite(kappa):
            raise ValueError("kappa must be finite")
        self.kappa = float(kappa)

    def _gain(self) -> float:
        return self.kappa

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, kappa={self.kappa}"
