"""Motion priors ``p(θ_t | θ_{t-1})`` for articulated tracking: the dynamics a particle filter samples from.

Every prior is a :class:`torchpf.distributions.Dynamics` (an ``nn.Module``) with the one signature
``sample(x, generator=None, *, extras=None)`` that draws ``x_t`` for every particle,
``log_prob(x_new, x_old, *, extras=None)`` -> ``log p(x_new | x_old)`` ``(..., N)`` where it is tractable,
``sample_from_noise(x, eps, *, extras=None)`` for QRS sampling, and the extras hooks ``init_extras`` /
``update_extras`` (no-ops for the priors that keep no per-particle state). Particles are ``(..., N, D)`` pose
vectors in ``Skeleton.dof_names`` order (radians / metres).

* :class:`ConstantVelocity` -- Rius eq. 3: ``φ_t = φ_{t-1} + V + N(0, σ_φ²)`` with a per-particle
  velocity ``V_t = α V_{t-1} + (1-α)(φ_{t-1} - φ_{t-2})`` carried as the extra ``"velocity"``.
* :class:`DampedSecondOrder` -- Brubaker eq. 13: ``s_{t+1} = s_t + κ (s_t - s_{t-1}) + η``.
* :class:`AngularRandomWalk` -- Hauberg eq. 3: ``p(θ_t | θ_{t-1}) ∝ N(θ_t | θ_{t-1}, diag σ²) U_Θ(θ_t)``,
  the Gaussian random walk in joint angles truncated to the joint limits, with per-DOF σ defaulting to the
  structural stds of :mod:`priors.diffusion` (Fontmarty Table 5 on request).
* :class:`ProjectedGaussian` -- Hauberg eq. 6-7: joint *positions* drawn from ``N(F(θ_{t-1}), Σ)`` with
  per-joint blocks ``Σ_l`` and projected onto the pose manifold by :func:`torchpf.ik.project`. Its spatial
  spread is the same for every joint, where the angular walk's grows along each kinematic chain (hands
  spread more than shoulders, Hauberg §1.2).

Example::

    walk = AngularRandomWalk.from_skeleton(skel, fps=30)      # structural σ, exact truncation at the limits
    x1 = walk.sample(x0, generator)                           # (..., N, D) -> (..., N, D)
    lp = walk.log_prob(x1, x0)                                # (..., N)
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from priors.diffusion import diffusion_sigma
from priors.table5 import TABLE5_FPS
from torchpf import ik
from torchpf.distributions import LOG_2PI, Dynamics, diag_normal_log_prob, randn_like


def _as_buffer(value, name: str) -> Tensor:
    """Float64 tensor (scalar or ``(D,)``) from a float / sequence / tensor, checked non-negative."""
    t = torch.as_tensor(value, dtype=torch.float64).clone()
    if t.ndim > 1:
        raise ValueError(f"{name} must be a scalar or a (D,) vector, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all() or (t < 0).any():
        raise ValueError(f"{name} must be finite and >= 0")
    return t


class _VelocityDynamics(Dynamics):
    """Gaussian diffusion around ``x + dt * gain * v`` with a per-particle velocity extra ``"velocity"``."""

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
        return self.sample_from_noise(x, randn_like(x, generator), extras=extras)

    def sample_from_noise(
        self, x: Tensor, eps: Tensor, *, extras: Mapping[str, Tensor] | None = None
    ) -> Tensor:
        """Deterministic map of standard-normal ``eps (..., N, D)`` to a sample (QRS sampling uses it)."""
        return self.predict(x, extras) + self._scale(x) * eps.to(x)

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras: Mapping[str, Tensor] | None = None) -> Tensor:
        """``log N(x_new; predict(x_old, v), diag σ²)`` ``(..., N)``; σ = 0 DOFs are left out (Dirac)."""
        return diag_normal_log_prob(x_new, self.predict(x_old, extras), self._scale(x_new))

    def update_extras(
        self, x_new: Tensor, x_old: Tensor, extras: Mapping[str, Tensor] | None = None
    ) -> dict[str, Tensor]:
        """New velocity once the frame is final: ``v' = a v + (1 - a) (x_new - x_old) / dt``, ``(..., N, D)``.

        ``x_old`` is each particle's frame-start parent, so the velocity is that particle's own history.
        Other extras are passed through unchanged.
        """
        a = self._blend()
        v = self._velocity(x_old, extras)
        a = a.to(v) if isinstance(a, Tensor) else a
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
        alpha: learning coefficient α in [0, 1] (Rius uses 0.5), a float or ``(D,)`` per DOF: 0 keeps only
            the last difference, 1 never updates the velocity.
        dt: time unit of the velocity. With the default 1.0 the velocity is in state units *per frame*; with
            ``dt = 1 / fps`` it is in units per second (same predictions, the velocity is just rescaled).

    Example::

        cv = ConstantVelocity(torch.full((D,), 0.05), alpha=0.5)
        state = ParticleFilter(cv, likelihood, n_particles=500).init(x0)    # extras from cv.init_extras
    """

    def __init__(self, sigma, *, alpha: float | Tensor = 0.5, dt: float = 1.0):
        super().__init__(sigma, dt=dt)
        a = torch.as_tensor(alpha, dtype=torch.float64)
        if a.ndim > 1 or not ((a >= 0.0) & (a <= 1.0)).all():
            raise ValueError(f"alpha must be in [0, 1] (a float or one per DOF), got {alpha}")
        self.alpha = float(a) if a.ndim == 0 else a.clone()  # per DOF: Rius §3.1 fitted per DOF

    def _blend(self) -> float | Tensor:
        return self.alpha

    def extra_repr(self) -> str:
        a = self.alpha
        return f"{super().extra_repr()}, alpha={a if isinstance(a, float) else f'(D={a.shape[0]})'}"


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


# ------------------------------------------------------------------------------------- angular random walk


def _log_ndtr_interval(a: Tensor, b: Tensor) -> Tensor:
    """``log(Φ(b) - Φ(a))`` for ``a <= b``, stable in both tails (and for infinite bounds)."""
    # In the upper tail use the mirror image: Φ(b) - Φ(a) = Φ(-a) - Φ(-b).
    flip = a > 0
    lo = torch.where(flip, -b, a)
    hi = torch.where(flip, -a, b)
    log_hi = torch.special.log_ndtr(hi)
    log_lo = torch.special.log_ndtr(lo)
    return log_hi + torch.log1p(-torch.exp((log_lo - log_hi).clamp(max=0.0)).clamp(max=1.0 - 1e-16))


def _truncnorm_icdf(mu: Tensor, sigma: Tensor, lo: Tensor, hi: Tensor, eps: Tensor) -> Tensor:
    """Exact truncated-normal sample from standard-normal ``eps`` by the inverse CDF (a deterministic map)."""
    a, b = (lo - mu) / sigma, (hi - mu) / sigma
    flip = a > 0  # work in the lower tail for accuracy, mirror back
    a2, b2 = torch.where(flip, -b, a), torch.where(flip, -a, b)
    u = torch.special.ndtr(torch.where(flip, -eps, eps))
    pa, pb = torch.special.ndtr(a2), torch.special.ndtr(b2)
    p = (pa + u * (pb - pa)).clamp(torch.finfo(mu.dtype).tiny, 1 - torch.finfo(mu.dtype).eps)
    z = torch.special.ndtri(p).clamp(a2, b2)
    return mu + sigma * torch.where(flip, -z, z)


class AngularRandomWalk(Dynamics):
    """Gaussian random walk in joint angles, restricted to the joint limits (Hauberg eq. 3).

    ``p(θ_t | θ_{t-1}) ∝ N(θ_t | θ_{t-1}, diag σ²) U_Θ(θ_t)`` with ``Θ = [lower, upper]`` a box. How the
    limits are imposed (``limits``), and what :meth:`log_prob` then returns:

    * ``"reject"`` (default, exact): each DOF is redrawn while it lies outside its limits (vectorised over all
      particles and DOFs, at most ``max_tries`` rounds; the few left then come from the exact inverse-CDF
      sampler). A box and a diagonal covariance make eq. 3 a product of per-DOF truncated normals, so
      rejecting per DOF samples exactly the same law as whole-pose rejection, much faster. ``log_prob`` is
      the exact truncated density ``Σ_d log N(θ_d; μ_d, σ_d) - log(Φ(b_d) - Φ(a_d))``, ``-inf`` outside.
    * ``"reflect"``: out-of-limit draws are folded back into the box. ``log_prob`` is the exact density of
      the folded normal (sum over the mirror images, two periods each way).
    * ``"clamp"``: out-of-limit draws are clamped to the bound, which puts point masses on the bounds.
      ``log_prob`` mixes measures: density inside, log-*probability* ``log Φ`` of the mass at a bound.
    * ``"none"``: the plain Gaussian (limits ignored).

    ``sample_from_noise`` maps standard-normal noise deterministically (inverse CDF for ``"reject"``), so
    QRS sampling works. DOFs with σ = 0 stay put and are left out of ``log_prob``.

    Args:
        sigma: per-DOF std ``(D,)`` or scalar (rad or m per frame).
        lower, upper: ``(D,)`` limits (default ±inf).
        limits: ``"reject"``, ``"reflect"``, ``"clamp"`` or ``"none"``.
        max_tries: rejection rounds before the inverse-CDF fallback.

    Example::

        walk = AngularRandomWalk.from_skeleton(skel, fps=30.0)
        x1 = walk.sample(x0, torch.Generator().manual_seed(0))
    """

    _LIMITS = ("reject", "reflect", "clamp", "none")

    def __init__(self, sigma, lower=None, upper=None, *, limits: str = "reject", max_tries: int = 50):
        super().__init__()
        if limits not in self._LIMITS:
            raise ValueError(f"limits must be one of {self._LIMITS}, got {limits!r}")
        if max_tries < 0:
            raise ValueError("max_tries must be >= 0")
        sigma = _as_buffer(sigma, "sigma")
        self.register_buffer("sigma", sigma)
        inf = torch.tensor(math.inf, dtype=torch.float64)
        lo = -inf if lower is None else torch.as_tensor(lower, dtype=torch.float64).clone()
        hi = inf if upper is None else torch.as_tensor(upper, dtype=torch.float64).clone()
        if bool((lo > hi).any()):
            raise ValueError("lower must be <= upper")
        self.register_buffer("lower", lo)
        self.register_buffer("upper", hi)
        self.limits = limits
        self.max_tries = int(max_tries)

    @classmethod
    def from_skeleton(
        cls,
        skeleton,
        sigma="structural",
        *,
        fps: float | None = TABLE5_FPS,
        scale: float = 1.0,
        speeds=None,
        limits: str = "reject",
        max_tries: int = 50,
    ) -> AngularRandomWalk:
        """Walk on ``skeleton``'s DOFs and limits; ``sigma`` is ``"structural"`` (default: from the kinematic
        tree and capsules, :func:`priors.diffusion.structural_sigma`), ``"table5"`` or ``(D,)`` values, at
        ``fps`` (Hz; ``None`` warns and takes 5 Hz) times ``scale`` (:func:`priors.diffusion.diffusion_sigma`,
        which logs a summary)."""
        sigma = diffusion_sigma(skeleton, sigma, fps=fps, scale=scale, speeds=speeds)
        return cls(sigma, skeleton.lower, skeleton.upper, limits=limits, max_tries=max_tries)

    @property
    def std(self) -> Tensor:
        """The step std ``(D,)``: the layer diffusion an annealed filter reads (Brubaker eq. 19)."""
        return self.sigma

    def _params(self, x: Tensor):
        sig, lo, hi = (t.to(device=x.device, dtype=x.dtype) for t in (self.sigma, self.lower, self.upper))
        if sig.ndim == 1 and sig.shape[0] != x.shape[-1]:
            raise ValueError(f"sigma has {sig.shape[0]} entries, particles have D={x.shape[-1]}")
        return sig.expand(x.shape[-1:]), lo.expand(x.shape[-1:]), hi.expand(x.shape[-1:])

    def _fold(self, y: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        both = torch.isfinite(lo) & torch.isfinite(hi)
        width = torch.where(both, hi - lo, torch.ones_like(lo))
        z = torch.remainder(y - lo, 2 * width)
        folded = lo + torch.where(z > width, 2 * width - z, z)
        only_lo = torch.isfinite(lo) & ~torch.isfinite(hi)
        only_hi = ~torch.isfinite(lo) & torch.isfinite(hi)
        out = torch.where(both, folded, y)
        out = torch.where(only_lo, lo + (y - lo).abs(), out)
        return torch.where(only_hi, hi - (hi - y).abs(), out)

    def sample(self, x: Tensor, generator: torch.Generator | None = None, *, extras=None) -> Tensor:
        """Draw ``θ_t ~ p(· | θ_{t-1} = x)``: ``(..., N, D) -> (..., N, D)`` (keeps no extras)."""
        if self.limits != "reject":
            return self.sample_from_noise(x, randn_like(x, generator))
        sig, lo, hi = self._params(x)
        y = x + sig * randn_like(x, generator)
        moving = sig > 0
        bad = ((y < lo) | (y > hi)) & moving
        for _ in range(self.max_tries):
            n_bad = int(bad.sum())
            if n_bad == 0:
                return y
            redraw = torch.randn(n_bad, generator=generator, dtype=x.dtype, device=x.device)
            y = y.masked_scatter(bad, x[bad] + sig.expand_as(x)[bad] * redraw)
            bad = ((y < lo) | (y > hi)) & moving
        if bool(bad.any()):  # rare: far-out parents; finish with the exact inverse-CDF sampler
            exact = _truncnorm_icdf(
                x, sig.where(moving, torch.ones_like(sig)), lo, hi, randn_like(x, generator)
            )
            y = torch.where(bad, exact, y)
        return y

    def sample_from_noise(self, x: Tensor, eps: Tensor, *, extras=None) -> Tensor:
        """Deterministic map of standard-normal ``eps (..., N, D)`` to a draw (QRS sampling)."""
        sig, lo, hi = self._params(x)
        eps = eps.to(x)
        if self.limits == "reject":
            moving = sig > 0
            y = _truncnorm_icdf(x, torch.where(moving, sig, torch.ones_like(sig)), lo, hi, eps)
            return torch.where(moving, y, x)
        y = x + sig * eps
        if self.limits == "reflect":
            return self._fold(y, lo, hi)
        if self.limits == "clamp":
            return torch.maximum(torch.minimum(y, hi), lo)
        return y

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras=None) -> Tensor:
        """``log p(x_new | x_old)`` ``(..., N)`` under the chosen limit handling (class docstring)."""
        sig, lo, hi = self._params(x_new)
        moving = sig > 0
        s = torch.where(moving, sig, torch.ones_like(sig))
        if self.limits == "none":
            return diag_normal_log_prob(x_new, x_old, sig)
        if self.limits == "reflect":
            per = self._reflect_log_density(x_new, x_old, s, lo, hi)
        else:
            z = (x_new - x_old) / s
            per = -0.5 * z.square() - torch.log(s) - 0.5 * LOG_2PI
            if self.limits == "reject":
                per = per - _log_ndtr_interval((lo - x_old) / s, (hi - x_old) / s)
            else:  # clamp: probability masses at the bounds
                at_lo, at_hi = x_new <= lo, x_new >= hi
                per = torch.where(at_lo, torch.special.log_ndtr((lo - x_old) / s), per)
                per = torch.where(at_hi, torch.special.log_ndtr((x_old - hi) / s), per)
        outside = (x_new < lo) | (x_new > hi)
        per = torch.where(outside, torch.full_like(per, -math.inf), per)
        return torch.where(moving, per, torch.zeros_like(per)).sum(-1)

    def _reflect_log_density(self, x: Tensor, mu: Tensor, s: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
        """Log-density of the folded normal: the normal summed over the mirror images of ``x``."""
        both = torch.isfinite(lo) & torch.isfinite(hi)
        width = torch.where(both, hi - lo, torch.zeros_like(lo))
        lo_f = torch.where(torch.isfinite(lo), lo, torch.zeros_like(lo))
        hi_f = torch.where(torch.isfinite(hi), hi, torch.zeros_like(hi))
        images, valid = [x], [torch.ones_like(x, dtype=torch.bool)]
        for k in (-2, -1, 1, 2):  # periodic images (box finite on both sides)
            images.append(x + 2 * k * width)
            valid.append(both.expand_as(x))
        for k in (-2, -1, 0, 1, 2):  # mirror images
            images.append(2 * lo_f - x + 2 * k * width)
            valid.append((torch.isfinite(lo) & (both | (k == 0))).expand_as(x))
        # a box open below: the only mirror is about ``hi``
        images.append(2 * hi_f - x)
        valid.append((torch.isfinite(hi) & ~torch.isfinite(lo)).expand_as(x))
        y = torch.stack(images)
        z = (y - mu) / s
        lp = -0.5 * z.square() - torch.log(s) - 0.5 * LOG_2PI
        lp = torch.where(torch.stack(valid), lp, torch.full_like(lp, -math.inf))
        return torch.logsumexp(lp, 0)

    def extra_repr(self) -> str:
        return f"D={self.sigma.numel()}, limits={self.limits!r}, max_tries={self.max_tries}"


# ----------------------------------------------------------------------------------- projected Gaussian


def _joint_scale(joint_sigma, J: int) -> Tensor:
    """Per-joint Cholesky factors ``(J, 3, 3)`` (float64) from a scalar, ``(J,)`` stds or ``(J, 3, 3)``."""
    t = torch.as_tensor(joint_sigma, dtype=torch.float64)
    if t.ndim == 0 or (t.ndim == 1 and t.shape[0] == J):
        std = t.expand(J).clone()
        if (std < 0).any():
            raise ValueError("joint_sigma must be >= 0")
        return torch.eye(3, dtype=torch.float64) * std[:, None, None]
    if t.shape == (J, 3, 3):
        return torch.linalg.cholesky(t)
    raise ValueError(f"joint_sigma must be a scalar, (J,) stds or (J, 3, 3) covariances with J={J}")


class ProjectedGaussian(Dynamics):
    """Projected prior (Hauberg eq. 6-7): a Gaussian on joint positions, projected onto the pose manifold.

    ``x̂_t ~ N(F(θ_{t-1}), Σ)`` with ``Σ = blockdiag(Σ_1 .. Σ_J)`` (one 3x3 block per joint), then
    ``θ_t = argmin_{θ ∈ Θ} ||x̂_t - F(θ)||²`` by :func:`torchpf.ik.project` warm-started at ``θ_{t-1}``.

    Its spatial variance is set per joint directly, so a hand moves no more than a shoulder unless asked
    to, unlike :class:`AngularRandomWalk` whose joint-position variance accumulates along each chain.

    Density: the law of ``θ_t`` on the manifold has no closed form (Hauberg only samples from it).
    :meth:`log_prob` returns the **embedding-space surrogate** ``log N(F(θ_t); F(θ_{t-1}), Σ)``, the
    Gaussian density at the projected point. It is what the data-driven proposals of
    :mod:`priors.proposals` report as ``log_q`` under the paper's approximation, so that the correction
    factor of Hauberg eq. 2 cancels (is treated as constant) when this prior is the filter's dynamics.

    Args:
        skeleton: the :class:`torchpf.Skeleton`.
        joint_sigma: isotropic std per joint (scalar or ``(J,)``, m) or blocks ``Σ_l`` ``(J, 3, 3)`` (m²).
        ik_options: keyword arguments for :func:`torchpf.ik.project` (``iters``, ``reg``, ``free`` ...).
            Default ``{"iters": 3}``: a sample needs the projection to a small fraction of Σ, not to full
            convergence. Measured on CMU walk poses with 3 cm per joint: 3 iterations leave the joints a
            median 2.9 mm (90 %: 6 mm) from the converged projection, 10 iterations 0.3 mm, at 2.3x the
            time; tracking error and effective sample size do not change (``benchmarks/importance.py
            --ik-iters``). Override for a tighter solve.

    Example::

        prior = ProjectedGaussian(skel, joint_sigma=0.03)
        x1 = prior.sample(x0, torch.Generator().manual_seed(0))      # (..., N, D), within the limits
    """

    def __init__(self, skeleton, joint_sigma=0.03, *, ik_options: Mapping | None = None):
        super().__init__()
        self.skeleton = skeleton
        J = len(skeleton.joint_names)
        self.register_buffer("scale_tril", _joint_scale(joint_sigma, J))
        self.ik_options = {"iters": 3, **dict(ik_options or {})}
        self.noise_dim = 3 * J

    def mean_joints(self, x: Tensor) -> Tensor:
        """``F(θ_{t-1})``: ``(..., N, D) -> (..., N, J, 3)``."""
        return self.skeleton.fk(x)

    def sample_joints(self, x: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Embedding-space draw ``x̂ ~ N(F(x), Σ)`` ``(..., N, J, 3)`` (before projection)."""
        mu = self.mean_joints(x)
        return self.joints_from_noise(mu, randn_like(mu, generator))

    def joints_from_noise(self, mu: Tensor, eps: Tensor) -> Tensor:
        """``μ + L_l ε_l`` per joint: ``(..., J, 3), (..., J, 3) -> (..., J, 3)``."""
        L = self.scale_tril.to(mu)
        return mu + (L @ eps.to(mu)[..., None])[..., 0]

    def project(self, joints: Tensor, x_old: Tensor) -> Tensor:
        """Eq. 7: joint positions ``(..., N, J, 3)`` -> poses ``(..., N, D)`` by IK from ``x_old``."""
        return ik.project(self.skeleton, joints, x_old, **self.ik_options)

    def sample(self, x: Tensor, generator: torch.Generator | None = None, *, extras=None) -> Tensor:
        """Draw ``θ_t``: ``(..., N, D) -> (..., N, D)`` (within the joint limits)."""
        return self.project(self.sample_joints(x, generator), x)

    def sample_from_noise(self, x: Tensor, eps: Tensor, *, extras=None) -> Tensor:
        """Deterministic map of standard-normal ``eps (..., N, 3J)`` to a draw (QRS sampling)."""
        mu = self.mean_joints(x)
        return self.project(self.joints_from_noise(mu, eps.reshape(mu.shape)), x)

    def log_prob_joints(self, joints: Tensor, x_old: Tensor) -> Tensor:
        """Exact ``log N(joints; F(x_old), Σ)`` of embedding-space points: ``(..., N, J, 3) -> (..., N)``."""
        mu = self.mean_joints(x_old)
        L = self.scale_tril.to(mu)
        diag = torch.diagonal(L, dim1=-2, dim2=-1)
        moving = diag > 0  # a zero-variance axis is a Dirac: left out, like the angular priors
        safe = torch.where(moving.all(-1)[:, None, None], L, torch.eye(3, dtype=mu.dtype, device=mu.device))
        z = torch.linalg.solve_triangular(safe, (joints - mu)[..., None], upper=False)[..., 0]
        per = -0.5 * z.square() - torch.log(torch.diagonal(safe, dim1=-2, dim2=-1)) - 0.5 * LOG_2PI
        per = torch.where(moving.all(-1)[:, None], per, torch.zeros_like(per))
        return per.sum((-1, -2))

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras=None) -> Tensor:
        """Embedding-space surrogate ``log N(F(x_new); F(x_old), Σ)``, ``(..., N)`` (class docstring)."""
        return self.log_prob_joints(self.skeleton.fk(x_new), x_old)

    def extra_repr(self) -> str:
        return f"J={self.scale_tril.shape[0]}, ik_options={self.ik_options}"
