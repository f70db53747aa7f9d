"""Hybrid filter: a stochastic search (the annealed particle filter) followed by gradient refinement of its
best hypotheses, Gall, Rosenhahn, Brox & Seidel (IJCV 2010), "Optimization and filtering for human motion
capture - a multi-layer framework" (global stochastic optimisation, then local optimisation).

Each frame runs the ``L`` APF layers (:class:`~torchpf.filters.AnnealedParticleFilter`, Brubaker Alg. 2),
then refines ``K`` poses by projected Adam on a differentiable cue (:class:`~torchpf.refine.Refiner`; default
the two-sided distance-transform silhouette cue). How the refined poses re-enter (``refine_mode``):

* ``"recentre"`` (default): the weighted mean and the ``K - 1`` particles of highest weight are refined; the
  frame's estimate is the candidate the refinement left best on its objective (``info["estimate"]``) if the
  filter's likelihood scores it at least as high as the mean (else the mean; ``info["refine_accepted"]``; the
  estimate's score is ``info["estimate_log_likelihood"]``), and every particle is shifted by that estimate
  minus the weighted mean (clamped to the limits), weights unchanged: the set keeps its spread and follows the
  refinement into the next frame. A deterministic move of the whole set, not an importance-weighted one (the
  weights do not see it): the "filtering around the optimum" of Gall et al.'s layered framework, where the
  stochastic search explores and the local optimisation corrects its drift.
* ``"estimate"``: the same estimate, but the particle set is left as the APF made it: a post-processing the
  filter never sees, so the next frame starts from the unrefined particles and the drift stays.
* ``"particles"``: the ``K`` particles of highest weight are refined, each ``x' = T(x)`` replaces its
  particle, and its weight is moved by the ratio of the filtering target
  ``pi(x) = p(z_t | x) p(x | x_{t-1})`` at the two points::

      log w' = log w + log p(z_t | x') - log p(z_t | x) + log p(x' | x_{t-1}) - log p(x | x_{t-1})

  the importance weight of a deterministic move that ignores the Jacobian ``|det dT/dx|`` of the
  optimiser's map (unknown). With ``refine_prior=True`` the refiner climbs the same target (cue times
  motion prior), the ratio is positive and the refined particles take all the weight (the set collapses
  onto ``K`` poses); with ``refine_prior=False`` it climbs the cue alone and the prior term of the ratio
  rejects the move (the refiner moves DOFs that the silhouettes leave free), so the refinement is lost.

**Swapped limbs.** ``swaps`` (``Tracker`` gives the mirror limbs of the skeleton,
:func:`~torchpf.kinematics.symmetry.limb_swaps`) adds the weighted mean with a pair of mirror limbs exchanged
to the refined candidates; taken only where the filter's likelihood prefers it by ``swap_margin`` nats, it
puts a track that took the left leg for the right one back, and the set with it.

**On an action's manifold.** A motion prior or importance distribution with a ``refine_space(x)`` method
(an action model's: :class:`priors.action.ActionConstrained`, a bank of them, or
:class:`priors.action.ActionProposal`) gives the coordinates the refiner moves each
candidate in (:class:`~torchpf.refine.RefineSpace`): the action's aSpace (Rius eq. 1) for a candidate that
performs the action, so the refined estimate, and in ``"recentre"`` mode the set that follows it, stays a
combination of the action's principal postures instead of following the masks' defects along DOFs the
silhouettes leave free (BENCHMARKS.md, "Learned priors on a held-out performer"). ``refine_space=False``
refines in the DOFs always.

Measured on foreign renders (BENCHMARKS.md, "Hybrid search (issue 12)"; CMU 07_01, calibrated body, 500
evaluations per frame, clean masks): APF 138 mm; hybrid ``"particles"`` 181 mm, ``"estimate"`` 93 mm,
``"recentre"`` 35 mm. Hence the default.

Equal budget (:mod:`torchpf.filters.registry`): per frame ``L N`` likelihood evaluations for the layers plus
:meth:`~torchpf.refine.Refiner.evaluations` for the ``K`` refinements (``steps`` gradient steps at
``Refiner.cost_per_step`` evaluations each, plus one look) plus, in ``"particles"`` mode, ``2 K`` for the
weight ratio; :meth:`HybridParticleFilter.for_budget` gives the layers what the refinement leaves.

Example::

    from torchpf.refine import Refiner
    hybrid = HybridParticleFilter(dynamics, likelihood, refiner=Refiner(skel, cameras), n_particles=100)
    track = hybrid.run(frames, x0, generator=0)   # track.stats["refine_gain"]: (T,) nats gained by refining
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from torchpf.filters.annealed import AnnealedParticleFilter
from torchpf.filters.state import ParticleState, gather_particles
from torchpf.filters.weights import normalise
from torchpf.refine import Refiner

__all__ = ["HybridParticleFilter"]

_MODES = ("particles", "estimate", "recentre")


class HybridParticleFilter(AnnealedParticleFilter):
    """APF layers, then gradient refinement of the ``n_refine`` best particles (module docstring).

    Args:
        dynamics, likelihood, proposal: as :class:`~torchpf.filters.AnnealedParticleFilter`.
        refiner: a :class:`~torchpf.refine.Refiner` (``(x (..., K, D), obs) -> RefineResult``).
        n_refine: ``K``, particles refined per frame and sequence.
        refine_mode: ``"particles"`` or ``"estimate"``.
        refine_prior: refine on the cue times the motion prior ``p(x | x_{t-1})`` of each particle's parent
            (the filtering target), or on the cue alone (default: the random walk's per-frame std pulls a
            refined pose back towards the previous frame, 101 -> 234 mm on the synthetic walk).
        refine_space: refine in the coordinates the motion prior's (or proposal's) ``refine_space(x)``
            gives (default True: an action model's aSpace, module docstring); False: always in the DOFs.
        swaps: moves ``x (..., D) -> x'`` tried as refinement candidates in ``"estimate"`` and
            ``"recentre"`` modes: the weighted mean moved by each (e.g. the legs exchanged,
            :func:`~torchpf.kinematics.symmetry.limb_swaps`) takes one of the ``K`` slots after the mean
            (``K - 2`` at most: one particle of highest weight is always refined). Where such a candidate
            becomes the estimate, the whole set takes the same move before it is recentred. Silhouettes
            cannot tell a walker's legs apart, and a track that takes the swapped pair keeps it; the move
            lets it go back (BENCHMARKS.md, "Swapped limbs").
        swap_margin: nats by which the filter's likelihood must prefer a refined swapped candidate to the
            best refined unswapped one (besides the refiner's objective preferring it): on noisy masks the
            two are often a tie, and a track that flips on ties swaps its arms for good.
        **options: the APF's keywords (``n_particles`` per layer, ``betas``, ``alphas``, ...).

    ``info`` adds ``refine_gain (...)``: the refinement's decrease of the refiner's objective (nats of its
    cue), averaged over the ``K``; with a motion prior's space, ``refine_on_manifold (...)``: the share of
    the ``K`` it moved on the action's manifold; with ``swaps``, ``refine_swapped (...)``: 1 where a moved
    candidate became the estimate; in ``"particles"`` mode ``refined_weight (...)``: the share of the
    posterior's weight that the refined particles carry.
    """

    needs_refiner = True

    def __init__(
        self,
        dynamics: Any,
        likelihood: Any,
        proposal: Any = None,
        *,
        refiner: Any = None,
        n_refine: int = 4,
        refine_mode: str = "recentre",
        refine_prior: bool = False,
        refine_space: bool = True,
        swaps: Any = (),
        swap_margin: float = 1.0,
        **options: Any,
    ):
        super().__init__(dynamics, likelihood, proposal, **options)
        if refiner is None:
            raise ValueError("HybridParticleFilter needs refiner=torchpf.refine.Refiner(skeleton, cameras)")
        if refine_mode not in _MODES:
            raise ValueError(f"refine_mode must be one of {_MODES}, got {refine_mode!r}")
        if int(n_refine) < 1:
            raise ValueError(f"n_refine must be >= 1, got {n_refine}")
        self.refiner = refiner
        self.n_refine = int(n_refine)
        self.refine_mode = refine_mode
        self.refine_prior = bool(refine_prior)
        self.refine_space = bool(refine_space)
        swaps = list(swaps or ())
        # modules (LimbSwap) move with the filter; any other callable is kept as it is
        self.swaps = nn.ModuleList(swaps) if swaps and all(isinstance(m, nn.Module) for m in swaps) else swaps
        self.swap_margin = float(swap_margin)

    # ------------------------------------------------------------------ equal likelihood budget
    @classmethod
    def refine_evaluations(cls, **options: Any) -> int:
        """Likelihood-evaluation equivalents of one frame's refinement with constructor keywords
        ``options``: the refiner's cost for ``n_refine`` poses, plus ``2 n_refine`` for the weight ratio in
        ``"particles"`` mode or 2 for the likelihood check of the estimate in the other modes."""
        refiner = options.get("refiner")
        k = int(options.get("n_refine", 4))
        if refiner is None:
            return 0
        # the weight ratio (2 K), or the check of the refined estimate against the mean (2, and 1 more for
        # the best unswapped candidate where swaps are tried)
        if options.get("refine_mode", "recentre") == "particles":
            extra = 2 * k
        else:
            extra = 2 + (1 if options.get("swaps") and k > 2 else 0)
        return refiner.evaluations(k) + extra

    @staticmethod
    def plan_refinement(
        budget: int, *, n_refine: int = 4, steps: int = 20, refiner: type = Refiner, share: float = 0.5
    ) -> tuple[int, int]:
        """``(n_refine, steps)`` such that one frame's refinement costs at most ``share`` of a ``budget`` of
        likelihood evaluations per frame (``refiner.cost(K, steps) + 2``, :meth:`refine_evaluations`), the
        rest left to the APF layers: ``K`` falls first (down to the mean alone), then the steps (down to 0, a
        refinement that only looks). At 500 evaluations the defaults fit (246); at 100, 1 pose x 15 steps;
        at 30, 1 x 4 (what ``Tracker`` uses when neither is given)."""
        cap = share * int(budget)
        k, steps = max(1, int(n_refine)), max(0, int(steps))

        while k > 1 and refiner.cost(k, steps) + 2 > cap:
            k -= 1
        if refiner.cost(k, steps) + 2 > cap:  # the most steps that fit: cost(k, s) is linear in s
            steps = max(0, int(((cap - 2) / k - 1) // refiner.cost_per_step))
        return k, steps

    @classmethod
    def for_budget(cls, budget: int, **options: Any) -> int:
        """Particles per layer such that the layers plus the refinement evaluate the likelihood at most
        ``budget`` times per frame (at least 1 particle, so a budget below the refinement's cost is
        exceeded by the layers' minimum; :attr:`likelihood_evaluations` says by how much)."""
        if int(budget) < 1:
            raise ValueError(f"the likelihood budget must be >= 1, got {budget}")
        left = int(budget) - cls.refine_evaluations(**options)
        return max(1, left // cls.evaluations_per_particle(**options))

    def budget_options(self) -> dict[str, Any]:
        return {
            **super().budget_options(),
            "refiner": self.refiner,
            "n_refine": self.n_refine,
            "refine_mode": self.refine_mode,
            "swaps": self.swaps,
        }

    @property
    def likelihood_evaluations(self) -> int | None:
        """Layers' evaluations plus the refinement's (:meth:`refine_evaluations`) per frame."""
        layers = super().likelihood_evaluations
        if layers is None:
            return None
        return layers + self.refine_evaluations(**self.budget_options())

    # ------------------------------------------------------------------ one frame
    def step(self, state: ParticleState, obs: Any, generator: torch.Generator | None = None) -> ParticleState:
        """APF layers, then refinement; ``info`` adds ``refine_gain`` (and ``estimate`` in ``"estimate"``
        mode)."""
        state, x, log_w, inc, failed, resampled, x_prev, extras_prev, info = self._anneal(
            state, obs, generator
        )
        estimate = self.refine_mode in ("estimate", "recentre")
        # "estimate" refines the mean, the mean moved by each swap, and the particles of highest weight
        swaps = self.swaps[: max(0, self.n_refine - 2)] if estimate else []
        k = min(self.n_refine - estimate - len(swaps), x.shape[-2])
        top = log_w.topk(k, dim=-1).indices  # (..., K)
        xk = gather_particles(x, top)
        prev = gather_particles(x_prev, top)
        dim = x.ndim - 2  # the particle dim, also of the extras (..., N, *e)
        extras_k = {key: gather_particles(v, top) for key, v in extras_prev.items()}
        if estimate:
            # the weighted mean as a candidate (ParticleState.mean: zero-weight NaN particles do not count)
            mean = state.replace(particles=x, log_weights=log_w).mean().unsqueeze(-2)
            mean_prev = state.replace(particles=x_prev, log_weights=log_w).mean().unsqueeze(-2)
            n = 1 + len(swaps)
            xk = torch.cat([mean, *(swap(mean) for swap in swaps), xk], -2)
            prev = torch.cat([mean_prev.expand(*mean_prev.shape[:-2], n, -1), prev], -2)
            # the mean and its swaps carry the extras (an action's state) of the particle of highest weight;
            # with a small budget K may be 0 and only those candidates are refined
            best = log_w.argmax(dim=-1, keepdim=True)
            extras_k = {
                key: torch.cat([gather_particles(extras_prev[key], best)] * n + [v], dim)
                for key, v in extras_k.items()
            }
        log_prior = None
        if self.refine_prior:

            def log_prior(z):
                return self.dynamics.log_prob(z, prev, extras=extras_k)

        # an action model's manifold, from the motion prior or the importance distribution that holds one
        source = next((m for m in (self.dynamics, self.proposal) if hasattr(m, "refine_space")), None)
        if self.refine_space and source is not None:
            space = source.refine_space(xk)
            refined = self.refiner(xk, obs, log_prior=log_prior, space=space)
            if hasattr(space, "active"):
                info["refine_on_manifold"] = space.active.to(refined.loss.dtype).mean(-1)
        else:  # a refiner of the poses' DOFs only (the space keyword is optional for duck-typed ones)
            refined = self.refiner(xk, obs, log_prior=log_prior)
        info["refine_gain"] = (refined.loss_before - refined.loss).mean(-1)
        if estimate:  # the candidate the refinement left best (the mean where every objective is NaN)
            loss = torch.nan_to_num(refined.loss, nan=torch.inf)
            best = loss.argmin(-1, keepdim=True)
            # The filter's own likelihood arbitrates: the refiner's cue is a surrogate that a mask defect can
            # mislead (a stray blob, a limb missing from one camera), so a refined estimate the likelihood
            # scores below the plain mean is not taken.
            if swaps:
                # a swapped candidate must also beat the best unswapped one by `swap_margin` nats: where the
                # masks cannot tell the two apart, the track keeps its limbs instead of flipping them
                n = 1 + len(swaps)
                plain = torch.cat(
                    [loss[..., :1], torch.full_like(loss[..., 1:n], torch.inf), loss[..., n:]], -1
                )
                plain = plain.argmin(-1, keepdim=True)
                pair = gather_particles(refined.x, torch.cat([plain, best], -1))
                ll = self._loglik(self.likelihood, torch.cat([xk[..., :1, :], pair], -2), obs)
                flip = (best.squeeze(-1) != plain.squeeze(-1)) & (ll[..., 2] >= ll[..., 1] + self.swap_margin)
                best = torch.where(flip.unsqueeze(-1), best, plain)
                both = torch.stack([ll[..., 0], torch.where(flip, ll[..., 2], ll[..., 1])], -1)
            else:
                both = self._loglik(
                    self.likelihood, torch.cat([xk[..., :1, :], gather_particles(refined.x, best)], -2), obs
                )
            chosen = gather_particles(refined.x, best)
            accept = both[..., 1] >= both[..., 0]
            info["refine_accepted"] = accept
            info["estimate"] = torch.where(accept.unsqueeze(-1), chosen.squeeze(-2), xk[..., 0, :])
            # kept for the lost-track check (torchpf.detect.Recovery), which would otherwise score it again
            info["estimate_log_likelihood"] = torch.where(accept, both[..., 1], both[..., 0])
            # where a swapped mean became the estimate, the set is swapped too, then follows it
            start, moved = xk[..., 0, :], x
            if swaps:
                swapped = torch.zeros_like(accept)
                for c, swap in enumerate(swaps, start=1):
                    use = accept & (best.squeeze(-1) == c)
                    start = torch.where(use.unsqueeze(-1), xk[..., c, :], start)
                    if self.refine_mode == "recentre":
                        moved = torch.where(use.unsqueeze(-1).unsqueeze(-1), swap(x), moved)
                    swapped = swapped | use
                info["refine_swapped"] = swapped
            if self.refine_mode == "recentre":  # the whole set follows its refined estimate
                shift = info["estimate"] - start
                shift = torch.where(torch.isfinite(shift), shift, 0.0).unsqueeze(-2)
                x = self.refiner.clamp(moved + shift)
        else:
            extras = {key: torch.cat([v, v], dim) for key, v in extras_k.items()}
            both = torch.cat([xk, refined.x], -2)
            loglik = self._loglik(self.likelihood, both, obs)
            target = loglik + self.dynamics.log_prob(both, torch.cat([prev, prev], -2), extras=extras).to(
                loglik
            )
            ratio = target[..., k:] - target[..., :k]
            # a refined pose the target rejects (-inf, or NaN) is dropped: its particle stays as it was
            keep = torch.isfinite(ratio)
            w_k = log_w.gather(-1, top)
            new_x = torch.where(keep.unsqueeze(-1), refined.x, xk)
            new_w = torch.where(keep, w_k + ratio, w_k)
            x = x.scatter(-2, top.unsqueeze(-1).expand_as(new_x), new_x)
            log_w = normalise(log_w.scatter(-1, top, new_w))
            info["refined_weight"] = log_w.gather(-1, top).logsumexp(-1).exp()
        return self._end_frame(state, x, log_w, inc, failed, resampled, x_prev, extras_prev, **info)
