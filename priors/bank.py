"""A bank of action models with the action as a discrete state of each particle (walk -> run -> walk).

One action model constrains the motion to one action; a person who starts to run while a walk model
constrains the filter is lost. :class:`ActionBank` carries, with every particle, which action it is
performing, and switches it with a Markov transition matrix ``T`` ``(M, M)`` (``T[a, b] = P(a_t = b |
a_{t-1} = a)``) before the prediction:

1. ``a_t ~ T[a_{t-1}]`` per particle (one uniform each, inverse CDF);
2. the particle is predicted by the action-constrained dynamics of ``a_t``
   (:class:`priors.action.ActionConstrained`, all sharing one plain ``dynamics``; ``mode="soft"`` by default,
   so a model's rejection is a soft preference, and each falls back to the plain dynamics on its own);
3. once the frame's particles are final, each particle's responsibilities ``r_a ∝ T[a_{t-1}, a] ·
   p(x_t | a)`` (:meth:`priors.action.ActionModel.log_density`, a normalised density of the posture under
   each action, so a loosely fitted model does not claim every pose) are the extra
   ``"action_prob"`` ``(..., N, M)`` and its action label ``"action"`` ``(..., N)`` their argmax.

The per-frame posterior over actions, ``P(a_t = a | z_{1:t}) ≈ Σ_i w_i r_{i,a}``, is the filter statistic
``action_posterior`` ``(..., M)`` (:meth:`frame_stats`, stacked over time in ``Track.stats`` and
``TrackResult.stats``): action recognition for free. Its argmax per frame names the action
(:attr:`ActionBank.actions`).

Example::

    bank = ActionBank([walk, run], random_walk(skel, fps=30), fps=30, skeleton=skel, switch=0.05)
    result = Tracker(skel, cams, dynamics=bank, fps=30).track(seq)
    labels = [bank.actions[i] for i in result.stats["action_posterior"].argmax(-1)]
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from priors.action import ActionConstrained, ActionModel, ActionSubspace
from torchpf.distributions import Dynamics, as_dynamics, flatten_batch, unflatten_batch


class ActionBank(Dynamics):
    """Switching action-constrained dynamics over ``M`` action models (module docstring).

    Args:
        models: the ``M`` :class:`ActionModel` s (same DOFs; their ``action`` names label the states).
        dynamics: the plain motion prior every action constrains (and falls back to).
        transition: ``(M, M)`` row-stochastic matrix; default ``1 - switch`` on the diagonal and ``switch``
            spread evenly over the other actions.
        switch: per-frame switching probability of the default ``transition``.
        mode, fps, skeleton, max_tries, min_accept: passed to each :class:`ActionConstrained`.
        manifold_radius: a gradient refinement moves a pose in the aSpace of its likeliest action model
            when it lies within this many soft-prior stds of that model's mean postures, freely otherwise
            (:meth:`refine_space`); ``None``: always freely.
    """

    def __init__(
        self,
        models: Sequence[ActionModel],
        dynamics: Any,
        *,
        transition: Tensor | None = None,
        switch: float = 0.05,
        mode: str = "soft",
        fps: float | None = None,
        skeleton=None,
        max_tries: int = 20,
        min_accept: float = 0.01,
        manifold_radius: float | None = 4.0,
    ):
        super().__init__()
        models = list(models)
        M = len(models)
        if M < 1:
            raise ValueError("ActionBank needs at least one action model")
        if transition is None:
            if not 0.0 <= switch < 1.0:
                raise ValueError(f"switch must be in [0, 1), got {switch}")
            off = switch / (M - 1) if M > 1 else 0.0
            transition = torch.full((M, M), off, dtype=torch.float64)
            transition.fill_diagonal_(1.0 - switch if M > 1 else 1.0)
        transition = torch.as_tensor(transition, dtype=torch.float64)
        if transition.shape != (M, M) or (transition < 0).any():
            raise ValueError(f"transition must be a non-negative ({M}, {M}) matrix")
        if not torch.allclose(transition.sum(-1), torch.ones(M, dtype=torch.float64)):
            raise ValueError("transition rows must sum to 1")
        base = as_dynamics(dynamics)
        self.dynamics = base
        self.constrained = nn.ModuleList(
            ActionConstrained(
                m,
                base,
                mode=mode,
                fps=fps,
                skeleton=skeleton,
                max_tries=max_tries,
                min_accept=min_accept,
                manifold_radius=manifold_radius,
            )
            for m in models
        )
        self.actions = [c.model.action for c in self.constrained]
        self.min_accept = float(min_accept)
        self.manifold_radius = self.constrained[0].manifold_radius
        self.register_buffer("transition", transition)

    @property
    def n_actions(self) -> int:
        return len(self.constrained)

    def refine_space(self, x: Tensor) -> ActionSubspace:
        """Coordinates in which a gradient refinement moves poses ``x (..., K, D)``: per pose the aSpace of
        its likeliest action model (:meth:`ActionModel.log_density`, :func:`priors.action.manifold_choice`),
        or its DOFs where it lies more than ``manifold_radius`` from that action."""
        return ActionSubspace.around([c.model for c in self.constrained], x, self.manifold_radius)

    def _soft(self, x: Tensor) -> Tensor:
        """``(..., N, M)`` soft acceptance of each action model."""
        return torch.stack([c.model.soft_accept_probability(x).to(x.dtype) for c in self.constrained], -1)

    def _responsibilities(self, x: Tensor, prior: Tensor) -> Tensor:
        """``r ∝ prior · p(x | a)`` ``(..., N, M)`` (:meth:`ActionModel.log_density`, in log space: the
        densities of ~50 posture DOFs span hundreds of nats); a pose without a finite density keeps the
        prior."""
        log_density = torch.stack([c.model.log_density(x).to(x.dtype) for c in self.constrained], -1)
        r = torch.softmax(prior.log() + log_density, -1)
        return torch.where(torch.isfinite(r).all(-1, keepdim=True), r, prior)

    def init_extras(self, x0: Tensor) -> dict[str, Tensor]:
        """The plain dynamics' extras, ``"action_prob"`` from a uniform prior and ``"action"`` its argmax."""
        M = self.n_actions
        uniform = torch.full((*x0.shape[:-1], M), 1.0 / M, dtype=x0.dtype, device=x0.device)
        prob = self._responsibilities(x0, uniform)
        return {**self.dynamics.init_extras(x0), "action_prob": prob, "action": prob.argmax(-1)}

    def update_extras(self, x_new: Tensor, x_old: Tensor, extras: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """Responsibilities ``r ∝ T[a_{t-1}] · p(x_t | a)`` and the plain dynamics' extras."""
        inner = {k: v for k, v in extras.items() if k not in ("action_prob", "action")}
        prior = self._prior(extras, x_new)
        prob = self._responsibilities(x_new, prior)
        return {
            **self.dynamics.update_extras(x_new, x_old, inner),
            "action_prob": prob,
            "action": prob.argmax(-1),
        }

    def _prior(self, extras: Mapping[str, Tensor] | None, x: Tensor) -> Tensor:
        """``P(a_t | a_{t-1})`` per particle ``(..., N, M)`` from the parents' responsibilities."""
        T = self.transition.to(x)
        if extras is None or "action_prob" not in extras:
            return torch.full(
                (*x.shape[:-1], self.n_actions), 1.0 / self.n_actions, dtype=x.dtype, device=x.device
            )
        return extras["action_prob"].to(x) @ T

    def sample(self, x: Tensor, generator: torch.Generator | None = None, *, extras=None) -> Tensor:
        """Switch each particle's action (``a_t ~ r_{t-1} T``), then predict it under that action's
        constrained dynamics: ``(..., N, D) -> (..., N, D)``."""
        prior = self._prior(extras, x)
        cdf = prior.cumsum(-1)
        u = torch.rand((*x.shape[:-1], 1), generator=generator, dtype=x.dtype, device=x.device)
        action = torch.searchsorted(cdf.contiguous(), (u * cdf[..., -1:]).contiguous()).squeeze(-1)
        action = action.clamp_max(self.n_actions - 1)
        flat_x, batch = flatten_batch(x, 1)
        flat_a = action.reshape(-1)
        flat_extras = {
            k: flatten_batch(v, v.ndim - len(batch))[0]
            for k, v in (extras or {}).items()
            if k not in ("action_prob", "action")
        }
        out = flat_x.clone()
        for m, dyn in enumerate(self.constrained):  # M is small; particles of one action are vectorised
            idx = (flat_a == m).nonzero().squeeze(-1)
            if idx.numel() == 0:
                continue
            sub_extras = {k: v[idx] for k, v in flat_extras.items()}
            out = out.index_copy(0, idx, dyn.sample(flat_x[idx], generator, extras=sub_extras))
        return unflatten_batch(out, batch)

    def log_prob(self, x_new: Tensor, x_old: Tensor, *, extras: Mapping[str, Tensor] | None = None) -> Tensor:
        """``log p(x_new | x_old) + log Σ_a P(a | a_{t-1}) (m + (1 - m) soft_a(x_new))`` ``(..., N)``,
        unnormalised in ``x_old`` like :meth:`ActionConstrained.log_prob`."""
        inner = {k: v for k, v in (extras or {}).items() if k not in ("action_prob", "action")}
        base = self.dynamics.log_prob(x_new, x_old, extras=inner)
        prior = self._prior(extras, x_new)
        m = self.min_accept
        return base + torch.log((prior * (m + (1.0 - m) * self._soft(x_new))).sum(-1)).to(base)

    def frame_stats(self, x: Tensor, log_weights: Tensor, extras: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """``action_posterior`` ``(..., M)``: ``Σ_i w_i r_{i,a}``, the posterior over actions."""
        w = torch.softmax(log_weights, -1).unsqueeze(-1)
        return {"action_posterior": (w * extras["action_prob"].to(w)).sum(-2)}

    def extra_repr(self) -> str:
        return f"actions={self.actions}"
