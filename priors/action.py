"""Action models Γ = (Ω, ĝ, σ) and action-constrained dynamics (Rius et al., eq. 1-6).

An *action model* says whether a pose is one that occurs while performing a given action (walking,
bending, ...). It is learned from mocap by :mod:`training.fit` and used in the prediction step of a particle
filter to throw away predicted poses that the action never visits, so that fewer particles are wasted.

**The model** (Rius eq. 1): ``Γ = (Ω, ĝ, σ)`` plus the dynamics parameters σ_φ, α and the matching spread Δ.

* Ω, the *aSpace*: a PCA of the action's postures (Brubaker eq. 14, ``ψ ≈ μ + Σ_i u_i c_i``). A pose vector
  θ ``(..., D_full)`` in the skeleton's ``dof_names`` order is reduced to its *posture* DOFs ``(..., P)``
  (root and glitchy hand channels are left out by default, see :mod:`training.fit`) and projected onto
  ``D`` principal components: :meth:`ActionModel.project` ``-> (..., D)``.
* ĝ ``(K, D)``: the synchronised mean performance, ``K`` postures in aSpace coordinates (one gait cycle for
  a cyclic action such as walking, the whole performance otherwise).
* σ ``(K, D)``: the standard deviation of the synchronised training postures around each ĝ_k.
* Δ ``(D,)``: the spread of a posture around the mean posture it matches (RMS over the training frames of
  ``φ̃ - ĝ_{k(φ)}``, ``k(φ)`` the DTW match).
* σ_φ ``(D_full,)`` and α: the diffusion and velocity smoothing of the constant-velocity prior (Rius eq. 3),
  fitted on the training performances at the model's frame rate ``fps``.

**Angle representation.** The aSpace coordinates are raw joint angles (radians, the paper's choice; sin/cos
would double the dimension and bend straight lines of PCA). Angles are periodic, so a pose is first brought
to the branch nearest the action's circular mean ``center`` of each angular posture DOF:
``x = center + wrap(θ - center)``, ``wrap`` into ``[-π, π)``. This is a function of the pose alone (a particle
has no history), it is exactly what the fitter used, and for every DOF that stays within ±π of its mean
during the action it equals the unwrapped (continuous) angle. Which DOFs are angles is the model's
``revolute (D_full,)`` mask, from the skeleton's ``dof_revolute`` (URDF joint types) when the model was fitted
with one; prismatic DOFs are lengths (metres) and never wrapped. Without a skeleton the mask falls back to
the name rule of :func:`guess_revolute` (names ending in ``position`` are prismatic).

**Acceptance test** (Rius eq. 6), :meth:`ActionModel.accepts`: with ``φ̃ = project(θ)``,

1. *match*: draw ``j`` from the Gaussian conditional ``p(j | φ̃) ∝ exp(-½ Σ_d ((φ̃_d - ĝ_{j,d}) / Δ_d)²)``,
   i.e. the posterior over the mean posture under ``φ̃ = ĝ_j + η(Δ)`` with a uniform prior over ``j``;
2. *accept* iff ``|φ̃_d - ĝ_{j,d}| < n_sigma · σ_{j,d}`` for every ``d = 1..D`` (``n_sigma = 2`` in the paper).

The test is random through ``j``; :meth:`ActionModel.accept_probability` is its expectation
``Σ_j p(j | φ̃) 1[φ̃ within n_sigma σ_j of ĝ_j]``. Only the projection is tested, as in the paper: how tight
the filter is depends on ``D``.

**Beyond rejection**: ``ActionConstrained(mode="soft")`` redraws with a soft prior (a Gaussian in aSpace
around the matched posture, :meth:`ActionModel.soft_accept_probability`) instead of eq. 6's 0/1 test, and
:class:`ActionProposal` predicts by phase advance along ĝ, as an importance distribution with its
correction weight.

**Action-constrained dynamics** (Rius eq. 3-5), :class:`ActionConstrained`: predict with the constant-velocity
prior (eq. 3, :class:`priors.motion.ConstantVelocity`), then redraw every prediction the action model rejects
until it is accepted (eq. 6), at most ``max_tries`` times.

**File format** (``.npz``, :meth:`ActionModel.save` / :meth:`ActionModel.load`; no pickles): a JSON string
``metadata`` (``format``, ``version``, ``action``, ``dof_names``, ``posture_dofs``, ``fps``,
``cyclic``, ``n_sigma``, ``training``), the bool array ``revolute (D_full,)`` (since version 2;
a version-1 file falls back to :func:`guess_revolute`, with a warning) and float64 arrays ``center (P,)``,
``pca_mean (P,)``, ``components (D, P)``, ``explained_variance (D,)``, ``explained_variance_ratio (D,)``,
``mean_performance (K, D)``, ``std (K, D)``, ``delta (D,)``, ``sigma_phi (D_full,)``, ``alpha (D_full,)``
(per DOF since version 3; an older file's scalar ``alpha ()`` is broadcast to every DOF); optionally
the training performances for plots: ``train_coords (M, D)`` (aSpace coordinates of all frames, concatenated),
``train_lengths (R,)`` int (frames per performance) and ``train_phase (M,)`` int (matched posture per frame).

Example::

    from priors import ActionModel, ActionConstrained
    model = ActionModel.load("walk.npz", dof_names=skel.dof_names)   # fails clearly on other DOF names
    ok = model.accepts(theta, generator)                               # (..., N, D_full) -> (..., N) bool
    pf = ParticleFilter(ActionConstrained(model), likelihood, n_particles=2000)
"""

from __future__ import annotations

import io
import json
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from priors.diffusion import alpha_summary
from priors.motion import ConstantVelocity
from torchpf.distributions import (
    Dynamics,
    as_dynamics,
    diag_normal_log_prob,
    flatten_batch,
    randn_like,
    unflatten_batch,
    wrap_angle,
)
from torchpf.io import read_versioned_npz, write_atomic

#: ``metadata["format"]`` of an action-model file.
FORMAT = "torchpf-action-model"
#: Current file-format version; files with a higher version are refused. Version 2 added ``revolute``,
#: version 3 stores ``alpha`` per DOF ``(D_full,)`` (older files: one scalar, broadcast on load).
FORMAT_VERSION = 3

_REQUIRED = (
    "center",
    "pca_mean",
    "components",
    "explained_variance",
    "explained_variance_ratio",
    "mean_performance",
    "std",
    "delta",
    "sigma_phi",
)
_TRAINING = ("train_coords", "train_lengths", "train_phase")


class ActionModelFormatError(ValueError):
    """An action-model file that cannot be used; the message starts with the file's path."""


def guess_revolute(dof_names: Sequence[str]) -> list[bool]:
    """``(D,)`` revolute (radians) or prismatic (metres) per DOF *from names alone*: names ending in
    ``position`` (BVH channels) are prismatic.

    Only the fallback where no skeleton is at hand (performances without one, version-1 model files);
    a skeleton's ``dof_revolute`` (URDF joint types) is the answer wherever it is available.
    """
    return [not str(n).lower().endswith("position") for n in dof_names]


def _ndim(value) -> int:
    return value.ndim if isinstance(value, Tensor) else np.ndim(value)


def _f64(value, name: str, ndim: int) -> Tensor:
    t = torch.as_tensor(np.asarray(value, dtype=np.float64) if not isinstance(value, Tensor) else value)
    t = t.detach().to("cpu", torch.float64).clone()
    if t.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite")
    return t


class ActionModel(nn.Module):
    """The action model Γ = (Ω, ĝ, σ) of Rius eq. 1 plus σ_φ, α, Δ (see the module docstring).

    Usually built by :func:`training.fit_action_model` or read with :meth:`load`. All arrays are stored as
    float64 buffers, so ``.to(device)`` moves the model; computations follow the input's dtype and device.

    Args:
        dof_names: ``(D_full,)`` the pose-vector layout the model applies to (a skeleton's ``dof_names``).
        posture_dofs: ``(P,)`` the names of the DOFs that make up a posture (a subset of ``dof_names``).
        center: ``(P,)`` branch centres of the posture DOFs (circular means, radians; see "Angle
            representation" above).
        pca_mean: ``(P,)`` PCA mean μ of the posture vectors.
        components: ``(D, P)`` PCA directions ``u_i`` (orthonormal rows).
        mean_performance: ``(K, D)`` ĝ, the synchronised mean performance in aSpace coordinates.
        std: ``(K, D)`` σ_k, per-posture standard deviation (> 0).
        delta: ``(D,)`` Δ, the matching spread (> 0).
        sigma_phi: ``(D_full,)`` σ_φ, constant-velocity diffusion std per frame (radians / metres).
        alpha: α in [0, 1], velocity smoothing of Rius eq. 3: ``(D_full,)`` per DOF (Rius §3.1), or a float
            for every DOF. Stored as the ``(D_full,)`` buffer ``alpha``.
        fps: frame rate (Hz) at which σ_φ and α apply.
        action: action name, e.g. ``"walk"``.
        cyclic: whether ĝ is one cycle of a periodic action (its last posture precedes its first).
        n_sigma: acceptance half-width in units of σ (Rius: 2).
        revolute: ``(D_full,)`` bool, which DOFs are angles (a skeleton's ``dof_revolute``; default
            :func:`guess_revolute` of ``dof_names``). Its posture entries are the buffer ``angular (P,)``.
        explained_variance: ``(D,)`` PCA variances (rad²); ``explained_variance_ratio`` their fractions.
        training: optional dict for plots: ``coords (M, D)``, ``lengths (R,)``, ``phase (M,)``, and JSON-able
            ``info`` (performance names, fitter configuration).
    """

    def __init__(
        self,
        *,
        dof_names: Sequence[str],
        posture_dofs: Sequence[str],
        center,
        pca_mean,
        components,
        mean_performance,
        std,
        delta,
        sigma_phi,
        alpha: float | Tensor,
        fps: float,
        action: str = "action",
        cyclic: bool = False,
        n_sigma: float = 2.0,
        revolute: Sequence[bool] | Tensor | None = None,
        explained_variance=None,
        explained_variance_ratio=None,
        training: Mapping[str, Any] | None = None,
    ):
        super().__init__()
        self.dof_names = [str(n) for n in dof_names]
        self.posture_dofs = [str(n) for n in posture_dofs]
        if len(set(self.dof_names)) != len(self.dof_names):
            raise ValueError("ActionModel: duplicate names in dof_names")
        index = {n: i for i, n in enumerate(self.dof_names)}
        missing = [n for n in self.posture_dofs if n not in index]
        if missing:
            raise ValueError(f"ActionModel: posture DOFs {missing} are not in dof_names")
        if not self.posture_dofs or len(set(self.posture_dofs)) != len(self.posture_dofs):
            raise ValueError("ActionModel: posture_dofs must be non-empty and without duplicates")
        P, Dfull = len(self.posture_dofs), len(self.dof_names)

        center = _f64(center, "center", 1)
        pca_mean = _f64(pca_mean, "pca_mean", 1)
        components = _f64(components, "components", 2)
        g = _f64(mean_performance, "mean_performance", 2)
        std = _f64(std, "std", 2)
        delta = _f64(delta, "delta", 1)
        sigma_phi = _f64(sigma_phi, "sigma_phi", 1)
        alpha = _f64(alpha, "alpha", _ndim(alpha))
        alpha = alpha.expand(Dfull).clone() if alpha.ndim == 0 else alpha
        D = components.shape[0]
        K = g.shape[0]
        expect = {
            "center": (center, (P,)),
            "pca_mean": (pca_mean, (P,)),
            "components": (components, (D, P)),
            "mean_performance": (g, (K, D)),
            "std": (std, (K, D)),
            "delta": (delta, (D,)),
            "sigma_phi": (sigma_phi, (Dfull,)),
            "alpha": (alpha, (Dfull,)),
        }
        for name, (t, shape) in expect.items():
            if tuple(t.shape) != shape:
                raise ValueError(
                    f"ActionModel: {name} has shape {tuple(t.shape)}, expected {shape} "
                    f"(P={P} posture DOFs, D={D} components, K={K} postures, D_full={Dfull})"
                )
        if D < 1 or K < 1:
            raise ValueError("ActionModel: needs at least one component and one mean posture")
        if (std <= 0).any() or (delta <= 0).any() or (sigma_phi < 0).any():
            raise ValueError("ActionModel: std and delta must be > 0 and sigma_phi >= 0")
        if ((alpha < 0.0) | (alpha > 1.0)).any():
            raise ValueError(f"ActionModel: alpha must be in [0, 1], got {alpha.tolist()}")
        if not (math.isfinite(float(fps)) and float(fps) > 0):
            raise ValueError(f"ActionModel: fps must be > 0, got {fps}")
        if not (math.isfinite(float(n_sigma)) and float(n_sigma) > 0):
            raise ValueError(f"ActionModel: n_sigma must be > 0, got {n_sigma}")
        revolute = guess_revolute(self.dof_names) if revolute is None else revolute
        revolute = torch.as_tensor(
            np.asarray(revolute, dtype=bool) if not isinstance(revolute, Tensor) else revolute
        )
        if tuple(revolute.shape) != (Dfull,):
            raise ValueError(f"ActionModel: revolute has shape {tuple(revolute.shape)}, expected ({Dfull},)")

        self.action = str(action)
        self.fps = float(fps)
        self.cyclic = bool(cyclic)
        self.n_sigma = float(n_sigma)
        self.register_buffer("posture_index", torch.tensor([index[n] for n in self.posture_dofs]))
        self.register_buffer("revolute", revolute.detach().to("cpu", torch.bool).clone())
        self.register_buffer("angular", self.revolute[self.posture_index])
        self.register_buffer("center", center)
        self.register_buffer("pca_mean", pca_mean)
        self.register_buffer("components", components)
        self.register_buffer("mean_performance", g)
        self.register_buffer("std", std)
        self.register_buffer("delta", delta)
        self.register_buffer("sigma_phi", sigma_phi)
        self.register_buffer("alpha", alpha)
        ev = (
            torch.zeros(D)
            if explained_variance is None
            else _f64(explained_variance, "explained_variance", 1)
        )
        evr = (
            torch.zeros(D)
            if explained_variance_ratio is None
            else _f64(explained_variance_ratio, "explained_variance_ratio", 1)
        )
        self.register_buffer("explained_variance", ev.to(torch.float64))
        self.register_buffer("explained_variance_ratio", evr.to(torch.float64))
        self._residual_variance = self._discarded_variance(ev, evr, P)
        self.training_data = _check_training(training, D, K)

    # ------------------------------------------------------------------------------------------ sizes
    @property
    def n_components(self) -> int:
        """D, the aSpace dimension."""
        return self.components.shape[0]

    @property
    def n_postures(self) -> int:
        """K, the number of postures of the mean performance."""
        return self.mean_performance.shape[0]

    # ------------------------------------------------------------------------------------------ aSpace
    def postures(self, theta: Tensor) -> Tensor:
        """Posture vectors on the action's angle branch: ``(..., D_full) -> (..., P)``.

        ``x = center + wrap(θ_p - center)`` for angular DOFs, ``θ_p`` for the others.
        """
        self._check_theta(theta)
        x = theta.index_select(-1, self.posture_index.to(theta.device))
        center = self.center.to(x)
        return torch.where(self.angular.to(x.device), center + wrap_angle(x - center), x)

    def project(self, theta: Tensor) -> Tensor:
        """aSpace coordinates ``φ̃ = U (x - μ)`` of poses: ``(..., D_full) -> (..., D)`` (radians).

        Batched over any leading dims; dtype and device follow ``theta``.
        """
        x = self.postures(theta)
        return (x - self.pca_mean.to(x)) @ self.components.to(x).transpose(0, 1)

    def forward(self, theta: Tensor) -> Tensor:
        """Same as :meth:`project`."""
        return self.project(theta)

    def reconstruct(self, coords: Tensor) -> Tensor:
        """Posture from aSpace coordinates, Brubaker eq. 14 ``μ + Σ_i u_i c_i``: ``(..., D) -> (..., P)``."""
        return self.pca_mean.to(coords) + coords @ self.components.to(coords)

    def pose(self, coords: Tensor, base: Tensor) -> Tensor:
        """Full poses: ``base (..., D_full)`` with the posture DOFs replaced by ``reconstruct(coords)``."""
        self._check_theta(base)
        posture = self.reconstruct(coords.to(base))
        index = self.posture_index.to(base.device).expand(*posture.shape[:-1], -1)
        return base.scatter(-1, index, posture)

    # ------------------------------------------------------------------------------------------ eq. 6
    def _match(self, coords: Tensor) -> tuple[Tensor, Tensor]:
        """``log p(j | φ̃)`` ``(..., K)`` and ``within`` ``(..., K)`` bool for aSpace coords ``(..., D)``."""
        g = self.mean_performance.to(coords)
        diff = coords.unsqueeze(-2) - g  # (..., K, D)
        z = diff / self.delta.to(coords)
        logits = -0.5 * z.square().sum(-1)  # uniform prior over the K postures
        log_p = logits - torch.logsumexp(logits, -1, keepdim=True)
        within = (diff.abs() < self.n_sigma * self.std.to(coords)).all(-1)
        return log_p, within

    def match_probability(self, theta: Tensor) -> Tensor:
        """``p(j | φ̃)``, the Gaussian conditional of eq. 6: ``(..., D_full) -> (..., K)``."""
        log_p, _ = self._match(self.project(theta))
        return log_p.exp()

    def accept_probability(self, theta: Tensor) -> Tensor:
        """P(:meth:`accepts` says yes) ``= Σ_j p(j | φ̃) 1[|φ̃ - ĝ_j| < n_sigma σ_j]``, ``(...)``."""
        log_p, within = self._match(self.project(theta))
        return (log_p.exp() * within).sum(-1)

    def accept_probability_aspace(self, coords: Tensor) -> Tensor:
        """:meth:`accept_probability` for aSpace coordinates ``(..., D) -> (...)`` (e.g. training frames)."""
        log_p, within = self._match(coords)
        return (log_p.exp() * within).sum(-1)

    def _soft_exponent(self, coords: Tensor) -> Tensor:
        """``-½ ||(φ̃ - ĝ_j) / (n_sigma σ_j)||²`` ``(..., K)`` for aSpace coords ``(..., D)``: the soft prior's
        Gaussian around each mean posture, in log space and without its normaliser."""
        z = (coords.unsqueeze(-2) - self.mean_performance.to(coords)) / (self.n_sigma * self.std.to(coords))
        return -0.5 * z.square().sum(-1)

    def _soft(self, coords: Tensor) -> tuple[Tensor, Tensor]:
        """``log p(j | φ̃)`` and the soft acceptance ``exp(-½ ||(φ̃ - ĝ_j) / (n_sigma σ_j)||²)``, each
        ``(..., K)``."""
        log_p, _ = self._match(coords)
        return log_p, self._soft_exponent(coords).exp()

    def soft_accept_probability(self, theta: Tensor) -> Tensor:
        """The soft prior: ``Σ_j p(j | φ̃) exp(-½ Σ_d ((φ̃_d - ĝ_{j,d}) / (n_sigma σ_{j,d}))²)`` ``(...)`` in
        (0, 1]: a Gaussian in aSpace around the matched posture, of std ``n_sigma σ_j``, in place of eq. 6's
        box of half-width ``n_sigma σ_j`` (:meth:`accept_probability`). Never exactly 0."""
        log_p, soft = self._soft(self.project(theta))
        return (log_p.exp() * soft).sum(-1)

    def log_soft_accept_probability(self, theta: Tensor) -> Tensor:
        """``log`` of :meth:`soft_accept_probability` ``(..., D_full) -> (...)``, computed in log space (a
        log-sum-exp over the ``K`` mean postures), so it stays finite and differentiable far from the action
        where the probability itself underflows to 0. A pose ``r`` soft-prior stds (``n_sigma σ``) from its
        matched mean posture scores about ``-r² / 2``."""
        coords = self.project(theta)
        log_p, _ = self._match(coords)
        return torch.logsumexp(log_p + self._soft_exponent(coords), -1)

    @property
    def residual_variance(self) -> float | None:
        """Per-dimension variance of the training postures off the aSpace (rad²): the PCA's discarded
        variance over the ``P - D`` discarded directions (Tipping & Bishop 1999, eq. 8); ``None`` where the
        model does not store its explained variances or keeps every direction. Computed once, on
        construction (:meth:`log_density` reads it every frame of a bank)."""
        return self._residual_variance

    @staticmethod
    def _discarded_variance(ev: Tensor, ratio: Tensor, P: int) -> float | None:
        """:attr:`residual_variance` from the explained variances ``ev`` and their ratios ``ratio``."""
        D = len(ev)
        if P <= D or not bool((ev > 0).all() and (ratio > 0).all()):
            return None
        total = float((ev / ratio).mean())  # each component's variance over its share: the total variance
        return max(total * (1.0 - float(ratio.sum())) / (P - D), 1e-12)

    def log_density(self, theta: Tensor) -> Tensor:
        """``log p(x | action)`` of poses' postures ``(..., D_full) -> (...)``, a normalised density over the
        ``P`` posture DOFs, so that models of different actions (and aSpace dimensions) compare:

        * in the aSpace, a mixture over the ``K`` mean postures (uniform weights) of Gaussians of std
          ``n_sigma σ_k`` around ``ĝ_k``, the soft prior's Gaussians (:meth:`soft_accept_probability`) with
          their normalisers;
        * off it, an isotropic Gaussian of the residual ``x - μ - c U`` with :attr:`residual_variance`
          (probabilistic PCA, Tipping & Bishop 1999); left out where the model has none.

        The soft prior alone is not normalised: a loose model (one performer, few components) would win
        every comparison. Used to tell actions apart (:class:`priors.bank.ActionBank`)."""
        x = self.postures(theta)
        d = x - self.pca_mean.to(x)
        U = self.components.to(x)
        c = d @ U.transpose(0, 1)
        D = self.n_components
        log_norm = (self.n_sigma * self.std.to(x)).log().sum(-1) + 0.5 * D * math.log(2 * math.pi)  # (K,)
        log_k = self._soft_exponent(c) - log_norm
        out = torch.logsumexp(log_k, -1) - math.log(self.n_postures)
        var = self.residual_variance
        if var is not None:
            r = d - c @ U
            n = U.shape[1] - D
            out = out - 0.5 * r.square().sum(-1) / var - 0.5 * n * math.log(2 * math.pi * var)
        return out

    def phase_step(self, theta: Tensor, postures: float) -> Tensor:
        """Posture displacement of phase advance along ĝ: ``(..., D_full) -> (..., D_full)``.

        Each pose is matched to its most likely mean posture ``k = argmax_j p(j | φ̃)`` and moved by the
        mean performance's own change from ``ĝ_k`` to ``ĝ_{k + postures}`` (linear interpolation between
        postures; modulo ``K`` for a cyclic action, clamped at the ends otherwise), mapped back to the pose
        DOFs (``U^T (ĝ_{k+a} - ĝ_k)`` on the posture DOFs, 0 elsewhere). The pose keeps its own offset from
        the mean, so a performer who walks differently is carried along the cycle, not pulled onto ĝ.
        """
        log_p, _ = self._match(self.project(theta))
        k = log_p.argmax(-1).to(theta.dtype)
        K = self.n_postures
        target = k + float(postures)
        g = self.mean_performance.to(theta)
        if self.cyclic:
            target = torch.remainder(target, K)
            lo = target.floor().long() % K
            hi = (lo + 1) % K
        else:
            target = target.clamp(0, K - 1)
            lo = target.floor().long().clamp(0, K - 1)
            hi = (lo + 1).clamp_max(K - 1)
        w = (target - target.floor()).unsqueeze(-1)
        ahead = (1 - w) * g[lo] + w * g[hi]
        step = (ahead - g[k.long()]) @ self.components.to(theta)  # (..., P)
        out = torch.zeros_like(theta)
        return out.index_add(-1, self.posture_index.to(out.device), step)

    def accepts(self, theta: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Rius eq. 6: ``p(φ_t | Γ) ∈ {0, 1}`` per pose, ``(..., D_full) -> (...)`` bool.

        Draws the matched mean posture ``j ~ p(j | φ̃)`` (one uniform per pose, inverse CDF) and accepts
        when ``|φ̃_d - ĝ_{j,d}| < n_sigma σ_{j,d}`` for all ``d``. ``generator`` must live on ``theta``'s
        device.
        """
        log_p, within = self._match(self.project(theta))
        return within.gather(-1, self._draw_match(log_p, generator)).squeeze(-1)

    def accepts_soft(self, theta: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """The soft prior as a random test: draw ``j ~ p(j | φ̃)`` and accept with probability
        ``exp(-½ ||(φ̃ - ĝ_j) / (n_sigma σ_j)||²)``; its expectation is :meth:`soft_accept_probability`, and
        redrawing a prediction until it passes samples ``p(φ_t | φ_{t-1}) · soft(φ_t)``. ``(...)`` bool."""
        log_p, soft = self._soft(self.project(theta))
        keep = soft.gather(-1, self._draw_match(log_p, generator)).squeeze(-1)
        u = torch.rand(keep.shape, generator=generator, dtype=keep.dtype, device=keep.device)
        return u < keep

    @staticmethod
    def _draw_match(log_p: Tensor, generator: torch.Generator | None) -> Tensor:
        """``j ~ p(j | φ̃)`` per pose (one uniform each, inverse CDF): ``(..., 1)`` long."""
        cdf = torch.cumsum(log_p.exp(), -1)
        u = torch.rand(cdf.shape[:-1] + (1,), generator=generator, dtype=cdf.dtype, device=cdf.device)
        return torch.searchsorted(cdf.contiguous(), (u * cdf[..., -1:]).contiguous()).clamp_max(
            cdf.shape[-1] - 1
        )

    def _check_theta(self, theta: Tensor) -> None:
        if theta.ndim < 1 or theta.shape[-1] != len(self.dof_names):
            raise ValueError(
                f"ActionModel({self.action!r}) expects poses (..., {len(self.dof_names)}) in its dof_names "
                f"order, got shape {tuple(theta.shape)}"
            )

    # ------------------------------------------------------------------------------------------ DOF order
    def for_dof_names(self, dof_names: Sequence[str]) -> ActionModel:
        """This model for pose vectors in another order of the same DOFs (``self`` if the order is equal).

        Raises:
            ValueError: ``dof_names`` is not a permutation of the model's DOF names (names what is missing
                and what is extra).
        """
        names = [str(n) for n in dof_names]
        if names == self.dof_names:
            return self
        _check_same_dofs(self.dof_names, names, f"action model {self.action!r}")
        perm = torch.tensor([self.dof_names.index(n) for n in names])
        return ActionModel(
            **{
                **self._init_kwargs(),
                "dof_names": names,
                "sigma_phi": self.sigma_phi[perm],
                "alpha": self.alpha[perm],
                "revolute": self.revolute[perm],
            }
        )

    def renamed(self, name_map: Mapping[str, str]) -> ActionModel:
        """This model with its DOFs renamed: ``name_map`` maps the model's DOF names to the names a user's
        skeleton gives them (a name map file, :func:`read_name_map`); names it leaves out are kept.

        Raises:
            ValueError: the map names DOFs the model does not have, or gives two DOFs one name (lists them).
        """
        name_map = {str(k): str(v) for k, v in name_map.items()}
        unknown = [k for k in name_map if k not in self.dof_names]
        if unknown:
            raise ValueError(
                f"the name map renames DOFs that action model {self.action!r} does not have: {unknown} "
                "(its keys are the model's DOF names, its values the skeleton's)"
            )
        names = [name_map.get(n, n) for n in self.dof_names]
        clashes = sorted({n for n in names if names.count(n) > 1})
        if clashes:
            raise ValueError(f"the name map gives several DOFs of the model the same name: {clashes}")
        lookup = dict(zip(self.dof_names, names, strict=True))
        return ActionModel(
            **{
                **self._init_kwargs(),
                "dof_names": names,
                "posture_dofs": [lookup[n] for n in self.posture_dofs],
            }
        )

    def check_revolute(self, revolute: Tensor) -> ActionModel:
        """``self`` after checking that its angular posture DOFs are those of ``revolute (D_full,)`` bool (a
        skeleton's ``dof_revolute`` in the model's ``dof_names`` order).

        The posture angles were wrapped with the model's own mask when it was fitted, so a model whose mask
        disagrees with the skeleton's joint types projects poses wrongly; it has to be refitted.

        Raises:
            ValueError: the masks differ on a posture DOF (names them).
        """
        want = torch.as_tensor(revolute, dtype=torch.bool).cpu()[self.posture_index.cpu()]
        bad = [
            n
            for n, a, b in zip(self.posture_dofs, self.angular.tolist(), want.tolist(), strict=True)
            if a != b
        ]
        if bad:
            raise ValueError(
                f"action model {self.action!r} disagrees with the skeleton's joint types on whether posture "
                f"DOFs {bad[:5]} are angles; refit the model with the skeleton"
            )
        return self

    def truncated(self, n_components: int, n_sigma: float | None = None) -> ActionModel:
        """This model on its first ``n_components`` aSpace dimensions (``self`` if that is all of them and
        ``n_sigma`` is ``None`` or unchanged), with acceptance half-width ``n_sigma`` if given.

        PCA coordinates are nested, so ĝ, σ_k and Δ of the smaller model are the leading columns of this one's
        (under this model's synchronisation): how model selection scores every ``D`` from one fit.
        """
        d = int(n_components)
        if not 1 <= d <= self.n_components:
            raise ValueError(f"n_components must be in [1, {self.n_components}], got {n_components}")
        n_sigma = self.n_sigma if n_sigma is None else float(n_sigma)
        if d == self.n_components and n_sigma == self.n_sigma:
            return self
        training = self.training_data
        if training is not None:
            training = {**training, "coords": training["coords"][:, :d]}
        return ActionModel(
            **{
                **self._init_kwargs(),
                "components": self.components[:d],
                "mean_performance": self.mean_performance[:, :d],
                "std": self.std[:, :d],
                "delta": self.delta[:d],
                "explained_variance": self.explained_variance[:d],
                "explained_variance_ratio": self.explained_variance_ratio[:d],
                "training": training,
                "n_sigma": n_sigma,
            }
        )

    def at_fps(self, fps: float) -> ActionModel:
        """This model for tracking at another frame rate (``self`` if equal): σ_φ and α rescaled by
        :func:`priors.diffusion.at_rate` (the rule of the learned dynamics). The aSpace, ĝ, σ_k and Δ describe
        postures, not time, and stay; a phase advances ``fps_model / fps`` postures per frame.

        A model fitted at 120 fps and used at 30 fps without this diffuses 4x too little per frame: the
        particles cannot follow the motion and the filter loses the person.
        """
        from priors.diffusion import at_rate

        if math.isclose(float(fps), self.fps, rel_tol=1e-9):
            return self
        sigma_phi, alpha = at_rate(self.sigma_phi, self.alpha, self.fps, float(fps))
        return ActionModel(**{**self._init_kwargs(), "sigma_phi": sigma_phi, "alpha": alpha, "fps": fps})

    def _init_kwargs(self) -> dict[str, Any]:
        return dict(
            dof_names=self.dof_names,
            posture_dofs=self.posture_dofs,
            center=self.center,
            pca_mean=self.pca_mean,
            components=self.components,
            mean_performance=self.mean_performance,
            std=self.std,
            delta=self.delta,
            sigma_phi=self.sigma_phi,
            alpha=self.alpha,
            fps=self.fps,
            action=self.action,
            cyclic=self.cyclic,
            n_sigma=self.n_sigma,
            revolute=self.revolute,
            explained_variance=self.explained_variance,
            explained_variance_ratio=self.explained_variance_ratio,
            training=self.training_data,
        )

    # ------------------------------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike) -> None:
        """Write the model as ``.npz`` (see the module docstring), atomically (temp file + os.replace)."""
        meta = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "action": self.action,
            "dof_names": self.dof_names,
            "posture_dofs": self.posture_dofs,
            "fps": self.fps,
            "cyclic": self.cyclic,
            "n_sigma": self.n_sigma,
            "training": (self.training_data or {}).get("info", {}),
        }
        arrays = {name: getattr(self, name).detach().cpu().numpy() for name in _REQUIRED}
        arrays["alpha"] = self.alpha.cpu().numpy()
        arrays["revolute"] = self.revolute.cpu().numpy()
        if self.training_data is not None:
            arrays["train_coords"] = self.training_data["coords"].numpy()
            arrays["train_lengths"] = self.training_data["lengths"].numpy()
            arrays["train_phase"] = self.training_data["phase"].numpy()
        _savez_atomic(path, metadata=np.array(json.dumps(meta, default=_json_default)), **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike, dof_names: Sequence[str] | None = None) -> ActionModel:
        """Read a model written by :meth:`save`.

        Args:
            path: the ``.npz`` file.
            dof_names: if given, the pose layout the caller will use (e.g. ``skel.dof_names``): the model
                is reordered to it, and a model trained on other DOFs is refused.

        Raises:
            FileNotFoundError: no such file.
            ActionModelFormatError: not an action-model file, a newer format version, missing or malformed
                arrays; the message names the file.
            ValueError: ``dof_names`` differs from the model's DOF names (the message lists the differences).
        """
        path = os.fspath(path)

        def bad(reason: str) -> ActionModelFormatError:
            return ActionModelFormatError(f"{path}: {reason}")

        data, meta, version = read_versioned_npz(
            path, FORMAT, FORMAT_VERSION, "action-model", ActionModelFormatError
        )
        absent = [k for k in (*_REQUIRED, "alpha") if k not in data]
        absent += [k for k in ("dof_names", "posture_dofs", "fps") if k not in meta]
        absent += ["revolute"] if version >= 2 and "revolute" not in data else []
        if absent:
            raise bad(f"missing entries {absent}")
        training = None
        if all(k in data for k in _TRAINING):
            training = {
                "coords": data["train_coords"],
                "lengths": data["train_lengths"],
                "phase": data["train_phase"],
                "info": meta.get("training", {}),
            }
        try:
            revolute = data["revolute"] if version >= 2 else _revolute_v1(meta, path)
            model = cls(
                dof_names=meta["dof_names"],
                posture_dofs=meta["posture_dofs"],
                revolute=revolute,
                center=data["center"],
                pca_mean=data["pca_mean"],
                components=data["components"],
                mean_performance=data["mean_performance"],
                std=data["std"],
                delta=data["delta"],
                sigma_phi=data["sigma_phi"],
                alpha=data["alpha"],  # (D_full,); a scalar before version 3, broadcast
                fps=float(meta["fps"]),
                action=meta.get("action", "action"),
                cyclic=bool(meta.get("cyclic", False)),
                n_sigma=float(meta.get("n_sigma", 2.0)),
                explained_variance=data["explained_variance"],
                explained_variance_ratio=data["explained_variance_ratio"],
                training=training,
            )
        except (ValueError, TypeError) as e:
            raise bad(" ".join(str(e).split())) from None
        if dof_names is not None:
            try:
                model = model.for_dof_names(dof_names)
            except ValueError as e:
                raise ValueError(f"{path}: {e}") from None
        return model

    def extra_repr(self) -> str:
        return (
            f"action={self.action!r}, D_full={len(self.dof_names)}, P={len(self.posture_dofs)}, "
            f"D={self.n_components}, K={self.n_postures}, cyclic={self.cyclic}, fps={self.fps:g}, "
            f"alpha={alpha_summary(self.alpha)}, n_sigma={self.n_sigma:g}"
        )


def _revolute_v1(meta: Mapping[str, Any], path: str) -> list[bool]:
    """The revolute mask of a version-1 file, which stores none: the name rule (what the fitter used then),
    with the posture entries the file's ``angular`` list gives."""
    warnings.warn(
        f"{path}: action-model format version 1 stores no revolute mask; DOFs are taken as revolute unless "
        "their name ends in 'position' (re-save the model to store the mask)",
        stacklevel=3,
    )
    names = [str(n) for n in meta["dof_names"]]
    revolute = guess_revolute(names)
    angular = meta.get("angular")
    if angular is not None:
        posture = [str(n) for n in meta["posture_dofs"]]
        if len(angular) != len(posture):
            raise ValueError(f"angular has {len(angular)} entries, expected {len(posture)}")
        index = {n: i for i, n in enumerate(names)}
        for n, a in zip(posture, angular, strict=True):
            if n in index:
                revolute[index[n]] = bool(a)
    return revolute


def read_name_map(path: str | os.PathLike) -> dict[str, str]:
    """A name map file: YAML (or JSON) ``model DOF name: skeleton DOF name`` lines, e.g.
    ``LeftUpLeg_Xrotation: l_hip_x``; it renames an action model's DOFs for a skeleton that names them
    differently (:meth:`ActionModel.renamed`; ``python -m torchpf track --action M.npz --name-map MAP``).

    Raises:
        ValueError: not a mapping of names to names (says which entry).
    """
    from torchpf.io import load_yaml

    with open(path, encoding="utf-8") as f:
        text = f.read()
    try:
        data = load_yaml(text)
    except Exception as e:  # yaml.YAMLError; the message names the file
        raise ValueError(f"{path}: not a YAML name map ({' '.join(str(e).split())})") from None
    if not isinstance(data, dict) or not data:
        raise ValueError(f"{path}: a name map is a non-empty mapping 'model DOF name: skeleton DOF name'")
    bad = [k for k, v in data.items() if not isinstance(k, str) or not isinstance(v, str)]
    if bad:
        raise ValueError(f"{path}: name map entries must map a name to a name; not {bad[:5]}")
    return dict(data)


def _check_same_dofs(have: Sequence[str], want: Sequence[str], what: str) -> None:
    missing = [n for n in want if n not in set(have)]
    extra = [n for n in have if n not in set(want)]
    if missing or extra or len(want) != len(have):
        raise ValueError(  # the hint first: a CLI clips long messages, and the lists can be long
            f"{what} was trained on other DOFs (if the skeleton only names them differently, map the names "
            "with a name map file of 'model name: skeleton name' lines: python -m torchpf track --name-map "
            f"FILE, or the action prior's name_map option): the pose vector has {len(missing)} DOFs that the "
            f"model lacks {missing}, and the model has {len(extra)} DOFs that the pose vector lacks {extra}"
        )


def _check_training(training: Mapping[str, Any] | None, D: int, K: int) -> dict[str, Any] | None:
    if training is None:
        return None
    coords = _f64(training["coords"], "training coords", 2)
    lengths = torch.as_tensor(np.asarray(training["lengths"]), dtype=torch.int64)
    phase = torch.as_tensor(np.asarray(training["phase"]), dtype=torch.int64)
    if coords.shape[1] != D or lengths.ndim != 1 or phase.shape != (coords.shape[0],):
        raise ValueError("training data: coords (M, D), lengths (R,), phase (M,) do not fit together")
    if int(lengths.sum()) != coords.shape[0] or (lengths < 1).any() or ((phase < 0) | (phase >= K)).any():
        raise ValueError("training data: lengths must sum to M and phases lie in [0, K)")
    return {"coords": coords, "lengths": lengths, "phase": phase, "info": dict(training.get("info", {}))}


def _savez_atomic(path: str | os.PathLike, **arrays) -> None:
    """``np.savez`` written atomically by :func:`torchpf.io.write_atomic` (crash: old file kept)."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_atomic(path, buffer.getvalue())


# ================================================================================================ dynamics
class ActionSubspace:
    """The aSpace as the coordinates of a gradient refinement (:class:`torchpf.refine.RefineSpace`).

    A pose refined on the silhouettes alone moves the DOFs the silhouettes leave free (a forearm's roll, a
    hip's rotation about a limb) and follows the masks' defects. Refined in its action model's aSpace
    (Rius eq. 1, Brubaker eq. 14), a posture stays a combination of the action's ``D`` principal postures:
    ``x_p = μ + Σ_i u_i c_i`` on the posture DOFs, with the ``c`` and the DOFs outside the posture (the root,
    the channels the fitter left out) as the coordinates. On the held-out walk of subject 35 under ``track``'s
    hybrid filter this took the error from 66 to 47 mm (BENCHMARKS.md, "Learned priors ... hybrid").

    Args:
        models: ``M`` :class:`ActionModel` s in the poses' DOF order (one for :class:`ActionConstrained`,
            the bank's for :class:`priors.bank.ActionBank`).
        choice: ``(..., K)`` long, per pose the model whose aSpace it moves in, ``-1`` for none (refined in
            all its DOFs, as without a space); fixed for the refinement.

    Coordinates ``y = (x, c_1, ..., c_M)`` ``(..., D_full + Σ_m D_m)``: ``decode`` keeps ``x`` outside the
    chosen model's posture DOFs and puts ``reconstruct(c_m)`` on them, each angle on the branch nearest the
    pose's own (``x + wrap(μ + c U - x)``), so a decoded pose stays continuous with where it started. The map
    is affine in ``c`` on a branch, so ``pullback`` is exact: ``dE/dc_m = U_m (dE/dx)_p``.
    """

    def __init__(self, models: Sequence[ActionModel], choice: Tensor):
        self.models = list(models)
        if not self.models:
            raise ValueError("ActionSubspace needs at least one action model")
        names = self.models[0].dof_names
        if any(m.dof_names != names for m in self.models[1:]):
            raise ValueError(
                "ActionSubspace: the action models must share one DOF order (ActionModel.for_dof_names)"
            )
        self.choice = choice
        self.n_dofs = len(names)
        sizes = [m.n_components for m in self.models]
        self._slices = [
            slice(self.n_dofs + sum(sizes[:i]), self.n_dofs + sum(sizes[: i + 1])) for i in range(len(sizes))
        ]

    @property
    def active(self) -> Tensor:
        """``(..., K)`` bool, the poses that move in an aSpace."""
        return self.choice >= 0

    @classmethod
    def around(cls, models: Sequence[ActionModel], x: Tensor, radius: float | None) -> ActionSubspace:
        """The space for poses ``x (..., K, D_full)``, each in the aSpace of its likeliest model if within
        ``radius`` soft-prior stds of that model's mean postures (:func:`manifold_choice`)."""
        return cls(models, manifold_choice(models, x, radius))

    def _on(self, i: int, like: Tensor) -> Tensor:
        """``(..., K, 1)`` bool: the poses that move in model ``i``'s aSpace."""
        return (self.choice == i).to(like.device).unsqueeze(-1)

    def encode(self, x: Tensor) -> Tensor:
        """``(x, project_1(x), ..., project_M(x))`` ``(..., D_full + Σ D_m)``."""
        return torch.cat([x, *(m.project(x) for m in self.models)], -1)

    def decode(self, y: Tensor) -> Tensor:
        """Poses ``(..., D_full)``: each chosen model's reconstructed posture on its posture DOFs."""
        x = y[..., : self.n_dofs]
        out = x
        for i, (m, sl) in enumerate(zip(self.models, self._slices, strict=True)):
            index = m.posture_index.to(x.device)
            old = x.index_select(-1, index)
            new = m.reconstruct(y[..., sl])
            new = torch.where(m.angular.to(x.device), old + wrap_angle(new - old), new)
            posed = x.scatter(-1, index.expand(*new.shape[:-1], -1), new)
            out = torch.where(self._on(i, x), posed, out)
        return out

    def pullback(self, y: Tensor, grad_x: Tensor) -> Tensor:
        """``J^T grad_x`` ``(..., D_full + Σ D_m)``: a chosen model's posture DOFs pass their gradient to its
        ``c`` (``grad_p U^T``) and none to ``x``."""
        g_x = grad_x
        parts = []
        for i, m in enumerate(self.models):
            on = self._on(i, grad_x)
            index = m.posture_index.to(grad_x.device)
            g_c = grad_x.index_select(-1, index) @ m.components.to(grad_x).transpose(0, 1)
            parts.append(torch.where(on, g_c, 0.0))
            g_x = torch.where(on, g_x.index_fill(-1, index, 0.0), g_x)
        return torch.cat([g_x, *parts], -1)

    def step_sizes(self, lr: Tensor) -> Tensor:
        """The DOFs keep their steps; a model's ``c`` (radians along unit posture directions) takes the
        largest step of its posture DOFs."""
        steps = [
            lr.index_select(-1, m.posture_index.to(lr.device)).max().expand(m.n_components)
            for m in self.models
        ]
        return torch.cat([lr, *steps], -1)


def manifold_choice(models: Sequence[ActionModel], x: Tensor, radius: float | None) -> Tensor:
    """Per pose ``x (..., D_full)`` the model of ``models`` most likely to have produced it
    (:meth:`ActionModel.log_density`), or ``-1`` where that model's soft prior
    (:meth:`ActionModel.log_soft_accept_probability`) scores it below ``-radius² / 2`` (the pose lies more
    than ``radius`` soft-prior stds from every mean posture: not this action, refine it freely) or ``radius``
    is None. ``(...)`` long."""
    if radius is None:
        return torch.full(x.shape[:-1], -1, dtype=torch.long, device=x.device)
    if len(models) == 1:
        choice = torch.zeros(x.shape[:-1], dtype=torch.long, device=x.device)
        score = models[0].log_soft_accept_probability(x)
    else:
        choice = torch.stack([m.log_density(x) for m in models], -1).argmax(-1)
        soft = torch.stack([m.log_soft_accept_probability(x) for m in models], -1)
        score = soft.gather(-1, choice.unsqueeze(-1)).squeeze(-1)
    return torch.where(score >= -0.5 * float(radius) ** 2, choice, -1)


def _radius(value: float | None) -> float | None:
    if value is not None and not float(value) > 0:
        raise ValueError(f"manifold_radius must be > 0 or None, got {value}")
    return None if value is None else float(value)


class ActionConstrained(Dynamics):
    """Action-constrained first-order dynamics (Rius eq. 3-6), a stateful dynamics for the filters.

    Prediction is a two-step process per particle (Rius §3.1):

    1. ``φ̂_t = φ_{t-1} + V + η(σ_φ)`` (eq. 3, the wrapped ``dynamics``, by default
       ``ConstantVelocity(model.sigma_phi, alpha=model.alpha)``; the velocity is the per-particle extra
       ``"velocity"``, updated by :meth:`update_extras` as ``V ← α V + (1 - α)(φ_t - φ_{t-1})``. Rius smooth
       the velocity of the *estimated* state instead; to do that, overwrite ``state.extras["velocity"]``
       between steps, as ``benchmarks/action_prior.py`` does);
    2. keep ``φ̂_t`` if the action model accepts it (eq. 6, :meth:`ActionModel.accepts`), otherwise draw
       again from eq. 3 for that particle. Only the rejected particles are redrawn (vectorised over them);
       after ``max_tries`` draws a particle keeps its last, unaccepted, draw, so a pose that has left the
       action is still tracked by the likelihood instead of freezing.

    **Never worse than its plain dynamics.** A pose or a frame rate the model has not seen makes eq. 6 reject
    nearly every prediction; redrawing then only burns tries and can pin the particles to the few accepted
    ones. So where fewer than ``min_accept`` of a frame's first draws (per sequence of a batch) are accepted,
    that frame keeps the first draws, i.e. samples the plain eq. 3 dynamics, warns once, and says so in the
    filter's per-frame stats (:meth:`frame_stats`): ``action_accepted`` (share of the frame's particles
    that eq. 6 can accept) and ``action_fallback`` (that share is below ``min_accept``), both ``(...)``,
    stacked over time in ``Track.stats`` / ``TrackResult.stats``. A model fitted at another frame rate is
    rescaled to the tracking rate when ``fps`` is given (:meth:`ActionModel.at_fps`; the ``action`` factory
    passes the tracker's).

    The resulting transition density is ``p(φ_t | φ_{t-1}) p(φ_t | Γ) / Z(φ_{t-1})`` (eq. 5); its normaliser
    ``Z`` is intractable, so :meth:`log_prob` returns ``log p(φ_t | φ_{t-1}) + log P(accept | φ_t)``,
    unnormalised in ``φ_{t-1}`` (fine for ranking, not for importance corrections that need exact densities).
    ``sample_from_noise`` is not provided: rejection sampling uses a random number of draws, so QRS sampling
    does not apply.

    Acceptance is reported functionally, never kept on the module:

    * per particle, riding with the particle state: the extra ``"accepted"`` ``(..., N)`` bool, set by
      :meth:`init_extras` and :meth:`update_extras` once a frame's particles are final: whether eq. 6 can
      accept the particle (``P(accept | φ_t) > 0``, i.e. it lies in the support of eq. 5). The accepted
      fraction of a filter's frame is ``state.extras["accepted"].float().mean(-1)``;
    * per draw: :meth:`sample_with_stats` returns the sampler's own record, ``accepted`` (finally accepted),
      ``accepted_first`` (accepted at the first draw), both ``(..., N)`` bool, and ``tries`` ``(..., N)``.

    Args:
        model: the :class:`ActionModel` (its ``dof_names`` are the particle layout).
        dynamics: eq. 3 dynamics (a :class:`torchpf.distributions.Dynamics`, or a duck-typed object adapted
            once by :func:`torchpf.distributions.as_dynamics`); default built from the model.
        max_tries: at most this many draws per particle and frame (>= 1).
        alpha: overrides the model's α for the default dynamics (Rius tracked with 0.5).
        sigma_scale: multiplies the model's σ_φ for the default dynamics.
        skeleton: the particles' skeleton, if known: the model is put in its ``dof_names`` order and its
            angular posture DOFs are checked against ``skeleton.dof_revolute``
            (:meth:`ActionModel.check_revolute`).
        mode: ``"rius"``: eq. 6's 0/1 test (:meth:`ActionModel.accepts`); ``"soft"``: the soft prior, a
            Gaussian in aSpace around the matched posture (:meth:`ActionModel.accepts_soft`), so that the
            redrawn predictions follow ``p(φ_t | φ_{t-1}) · soft(φ_t)``.
        fps: tracking frame rate (Hz); the model's σ_φ and α are rescaled to it (:meth:`ActionModel.at_fps`).
            ``None``: the model's rate.
        min_accept: below this share of accepted first draws a frame falls back to the plain dynamics
            (0 never falls back).
        manifold_radius: a filter that refines poses by gradient
            (:class:`torchpf.filters.HybridParticleFilter`) refines a pose in the model's aSpace
            (:meth:`refine_space`, :class:`ActionSubspace`) where it lies within this many soft-prior stds
            (``n_sigma σ``) of a mean posture, freely elsewhere (a pose of another action); ``None``: always
            freely.

    Example::

        dyn = ActionConstrained(ActionModel.load("walk.npz"), alpha=0.5, skeleton=skel)
        pf = ParticleFilter(dyn, likelihood, n_particles=2000)
        state = pf.step(pf.init(x0), obs); state.extras["accepted"].float().mean(-1)
    """

    def __init__(
        self,
        model: ActionModel,
        dynamics: Any = None,
        *,
        max_tries: int = 20,
        alpha: float | None = None,
        sigma_scale: float = 1.0,
        skeleton=None,
        fps: float | None = None,
        min_accept: float = 0.01,
        mode: str = "rius",
        manifold_radius: float | None = 4.0,
    ):
        super().__init__()
        self.manifold_radius = _radius(manifold_radius)
        if mode not in ("rius", "soft"):
            raise ValueError(f"mode must be 'rius' (eq. 6's 0/1 test) or 'soft', got {mode!r}")
        self.mode = mode
        if int(max_tries) < 1:
            raise ValueError(f"max_tries must be >= 1, got {max_tries}")
        if not 0.0 <= float(min_accept) < 1.0:
            raise ValueError(f"min_accept must be in [0, 1), got {min_accept}")
        if skeleton is not None:
            model = model.for_dof_names(skeleton.dof_names).check_revolute(skeleton.dof_revolute)
        if fps is not None:
            model = model.at_fps(fps)
        if dynamics is None:
            sigma = model.sigma_phi * float(sigma_scale)
            dynamics = ConstantVelocity(sigma, alpha=model.alpha if alpha is None else float(alpha))
        elif alpha is not None or sigma_scale != 1.0:
            raise ValueError("alpha and sigma_scale configure the default dynamics; not with dynamics=")
        self.model = model
        self.dynamics = as_dynamics(dynamics)
        self.max_tries = int(max_tries)
        self.min_accept = float(min_accept)

    def refine_space(self, x: Tensor) -> ActionSubspace:
        """Coordinates in which a gradient refinement moves poses ``x (..., K, D)``: the model's aSpace for
        the poses within ``manifold_radius`` of the action (:func:`manifold_choice`), their DOFs for the
        others (:class:`ActionSubspace`)."""
        return ActionSubspace.around([self.model], x, self.manifold_radius)

    def _accepted(self, x: Tensor) -> Tensor:
        """``(..., N)`` bool: eq. 6 can accept ``x`` (``P(accept | x) > 0``)."""
        return self.model.accept_probability(x) > 0

    def init_extras(self, x0: Tensor) -> dict[str, Tensor]:
        """The wrapped dynamics' initial extras (zero velocity ``(..., N, D)``) and ``"accepted"``."""
        return {**self.dynamics.init_extras(x0), "accepted": self._accepted(x0)}

    def update_extras(self, x_new: Tensor, x_old: Tensor, extras: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """The wrapped dynamics' update (Rius eq. 3's velocity smoothing) and ``"accepted"`` of ``x_new``."""
        return {**self.dynamics.update_extras(x_new, x_old, extras), "accepted": self._accepted(x_new)}

    def frame_stats(self, x: Tensor, log_weights: Tensor, extras: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """``action_accepted`` (share of the frame's particles eq. 6 can accept) and ``action_fallback``
        (that share below ``min_accept``: the frame ran on the plain dynamics), each ``(...)``."""
        share = extras["accepted"].to(log_weights.dtype).mean(-1)
        return {"action_accepted": share, "action_fallback": share < self.min_accept}

    def sample(
        self,
        x: Tensor,
        generator: torch.Generator | None = None,
        *,
        extras: Mapping[str, Tensor] | None = None,
    ) -> Tensor:
        """Accepted predictions ``(..., N, D) -> (..., N, D)`` (eq. 3 redrawn until eq. 6 accepts)."""
        return self.sample_with_stats(x, generator, extras=extras)[0]

    def sample_with_stats(
        self,
        x: Tensor,
        generator: torch.Generator | None = None,
        *,
        extras: Mapping[str, Tensor] | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Like :meth:`sample`, also returning the sampler's record per particle: ``(x_new (..., N, D),
        {"fallback": (..., N) bool, "accepted": (..., N) bool, "accepted_first": (..., N) bool,
        "tries": (..., N)})`` (``fallback``: the particle's frame fell back to the plain dynamics).

        Host syncs: the fallback check and one "anything left?" per retry round.
        """
        # particles are independent, so all batch dims flatten to one (M, D)
        flat_x, batch = flatten_batch(x, 1)
        flat_extras = {k: flatten_batch(v, v.ndim - len(batch))[0] for k, v in (extras or {}).items()}
        out = self.dynamics.sample(flat_x, generator, extras=flat_extras)
        test = self.model.accepts if self.mode == "rius" else self.model.accepts_soft
        ok = test(out, generator)
        first = ok.clone()
        # a sequence whose first draws eq. 6 all but rejects falls back to them: the plain dynamics
        share = unflatten_batch(ok, batch).to(x.dtype).mean(-1, keepdim=True)
        fallback = (share < self.min_accept).expand(batch).reshape(-1)
        if self.min_accept > 0 and bool(fallback.any()):
            warnings.warn(
                f"action model {self.model.action!r} accepts fewer than {self.min_accept:.0%} of the "
                "predicted poses (an unseen pose or frame rate); those frames use its plain dynamics "
                "(stats 'action_fallback')",
                stacklevel=2,
            )
            ok = ok | fallback
        tries = torch.ones_like(ok, dtype=x.dtype)
        for _ in range(self.max_tries - 1):
            pending = (~ok).nonzero().squeeze(-1)  # one host sync per retry round, not per particle
            if pending.numel() == 0:
                break
            sub_extras = {k: v[pending] for k, v in flat_extras.items()}
            sub = self.dynamics.sample(flat_x[pending], generator, extras=sub_extras)
            acc = test(sub, generator)
            out = out.index_copy(0, pending, sub)
            ok = ok.index_copy(0, pending, acc)
            tries = tries.index_add(0, pending, torch.ones_like(sub[:, 0]))
        ok = ok & ~fallback
        stats = {
            "fallback": unflatten_batch(fallback, batch),
            "accepted": unflatten_batch(ok, batch),
            "accepted_first": unflatten_batch(first, batch),
            "tries": unflatten_batch(tries, batch),
        }
        return unflatten_batch(out, batch), stats

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras: Mapping[str, Tensor] | None = None) -> Tensor:
        """``log p(x_new | x_old) + log(m + (1 - m) P(accept | x_new))`` ``(..., N)`` with ``m = min_accept``,
        unnormalised in x_old (eq. 5 for ``m = 0``).

        The floor ``m`` is the fallback's share in the density: a pose eq. 6 rejects is ``1 / m`` times less
        likely, not impossible (an annealed filter that weights its layers with the prior would otherwise
        fail every frame of a pose the model has not seen).
        """
        base = self.dynamics.log_prob(x_new, x_old, extras=extras)
        p = (
            self.model.accept_probability(x_new)
            if self.mode == "rius"
            else self.model.soft_accept_probability(x_new)
        )
        p = p.to(base)
        return base + torch.log(self.min_accept + (1.0 - self.min_accept) * p)

    def extra_repr(self) -> str:
        return (
            f"mode={self.mode!r}, max_tries={self.max_tries}, min_accept={self.min_accept:g}, "
            f"manifold_radius={self.manifold_radius}"
        )


class ActionProposal(nn.Module):
    """Importance distribution from an action model: phase advance along the synchronised mean performance.

    ĝ is a trajectory, so the model can *predict*: a particle matched to posture ``k`` is moved by the mean
    performance's own change from ``ĝ_k`` to ``ĝ_{k+a}``, ``a = fps_model / fps`` postures per frame
    (:meth:`ActionModel.phase_step`, mapped back to the pose DOFs), plus Gaussian noise of the learned
    per-DOF σ_φ (the constant-velocity residual, at the tracking rate) on the posture DOFs and the
    dynamics' own std on the others (root). With probability ``beta`` a particle is drawn from the
    dynamics instead, so the proposal covers what the model does not predict (another gait, a stop)::

        q(x | x_{t-1}) = beta p(x | x_{t-1}) + (1 - beta) N(x; x_{t-1} + step(x_{t-1}), diag s²)

    ``log_q`` is the exact mixture density, and the filter weights by ``p(x | x_{t-1}) / q(x | x_{t-1})``
    (Hauberg eq. 2; the I-CONDENSATION correction of :mod:`torchpf.proposals`), so the estimate stays that
    of the dynamics' model, only sampled where the action says the person goes. Follows the
    ``sample(state, obs, generator) -> (x, log_q)`` protocol of :class:`torchpf.filters.ParticleFilter`.

    Args:
        model: the :class:`ActionModel`.
        dynamics: the tracker's motion prior ``p`` (a :class:`Dynamics` with ``log_prob``); its ``std`` or
            ``sigma`` is the noise of the non-posture DOFs.
        fps: tracking rate (Hz); default the model's.
        beta: share of draws from the dynamics, in [0, 1).
        sigma_scale: multiplies the posture noise σ_φ.
        skeleton: the particles' skeleton (puts the model in its DOF order).
        manifold_radius: as :class:`ActionConstrained`'s: a gradient refinement moves a pose within this
            many soft-prior stds of the action in its aSpace (:meth:`refine_space`); ``None``: never.

    Example::

        dyn = make_dynamics("random_walk", skel, fps=30)
        q = ActionProposal(ActionModel.load("walk.npz"), dyn, fps=30, skeleton=skel)
        pf = ParticleFilter(dyn, likelihood, proposal=q, n_particles=500)
    """

    def __init__(
        self,
        model: ActionModel,
        dynamics: Any,
        *,
        fps: float | None = None,
        beta: float = 0.3,
        sigma_scale: float = 1.0,
        skeleton=None,
        manifold_radius: float | None = 4.0,
    ):
        super().__init__()
        self.manifold_radius = _radius(manifold_radius)
        if not 0.0 <= float(beta) < 1.0:
            raise ValueError(f"beta must be in [0, 1), got {beta}")
        if skeleton is not None:
            model = model.for_dof_names(skeleton.dof_names).check_revolute(skeleton.dof_revolute)
        self.advance = 1.0 if fps is None else model.fps / float(fps)
        model = model if fps is None else model.at_fps(fps)
        self.model = model
        self.dynamics = as_dynamics(dynamics)
        std = getattr(self.dynamics, "std", None)
        std = getattr(self.dynamics, "sigma", None) if std is None else std
        if std is None:
            raise ValueError("ActionProposal needs dynamics with a std (or sigma) for the non-posture DOFs")
        noise = torch.as_tensor(std, dtype=torch.float64).expand(len(model.dof_names)).clone()
        index = model.posture_index.cpu()
        noise[index] = model.sigma_phi.cpu()[index] * float(sigma_scale)
        self.register_buffer("noise", noise.clamp_min(1e-6))
        self.beta = float(beta)

    def refine_space(self, x: Tensor) -> ActionSubspace:
        """As :meth:`ActionConstrained.refine_space`: the model's aSpace for poses ``x (..., K, D)`` that
        perform the action, their DOFs for the others."""
        return ActionSubspace.around([self.model], x, self.manifold_radius)

    def mean(self, x: Tensor) -> Tensor:
        """Phase-advanced poses ``(..., N, D) -> (..., N, D)``."""
        return x + self.model.phase_step(x, self.advance)

    def sample(self, state: Any, obs: Any = None, generator: torch.Generator | None = None):
        """``(x (..., N, D), log_q (..., N))`` from the parents ``state.particles`` (and their extras)."""

        parents, extras = state.particles, state.extras
        mu = self.mean(parents)
        noise = self.noise.to(parents)
        guided = mu + noise * randn_like(parents, generator)
        plain = self.dynamics.sample(parents, generator, extras=extras)
        u = torch.rand(parents.shape[:-1], generator=generator, dtype=parents.dtype, device=parents.device)
        x = torch.where((u < self.beta).unsqueeze(-1), plain, guided)
        log_guided = diag_normal_log_prob(x, mu, noise)
        if self.beta == 0.0:
            return x, log_guided
        log_plain = self.dynamics.log_prob(x, parents, extras=extras).to(x.dtype)
        log_q = torch.logaddexp(math.log(self.beta) + log_plain, math.log1p(-self.beta) + log_guided)
        return x, log_q

    def extra_repr(self) -> str:
        return f"advance={self.advance:g} postures/frame, beta={self.beta:g}"


def _json_default(obj):
    """numpy scalars and other stragglers in the metadata's training info."""
    return obj.item() if hasattr(obj, "item") else str(obj)
