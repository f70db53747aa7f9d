"""The hybrid filter (APF layers + refinement of the best particles): budget accounting, the weight of a
refined particle (ratio of the filtering target, module docstring of `torchpf.filters.hybrid`), the
"estimate" mode, and the reduction to the APF when the refiner does nothing. The refiners here are exact
moves on a linear-Gaussian model (a known map), so every expected value is computed independently."""

import math

import numpy as np
import pytest
import torch

from torchpf.filters import AnnealedParticleFilter, HybridParticleFilter
from torchpf.filters.registry import FILTERS
from torchpf.refine import RefineResult

from .linear_gaussian import F64, model_4d


class ShiftRefiner(torch.nn.Module):
    """A refiner whose move is known: ``x -> x + shift`` (``steps`` only feeds the cost accounting)."""

    def __init__(self, shift: float, steps: int = 10):
        super().__init__()
        self.shift, self.steps = shift, steps
        self.calls = []

    def evaluations(self, n_poses: int) -> int:
        return math.ceil(n_poses * (3.0 * self.steps + 1))

    def clamp(self, x):
        return x

    def forward(self, x, obs, log_prior=None):
        self.calls.append(x.clone())
        loss = x.square().sum(-1)
        return RefineResult(x=x + self.shift, loss_before=loss, loss=loss - 1.0, steps=self.steps)


@pytest.fixture
def setup():
    model = model_4d()
    g = torch.Generator().manual_seed(0)
    truth, zs = model.simulate(2, 5, g)
    x0 = model.initial_particles(2, 64, g)
    return model, zs, x0


def _filters(model, refiner, **kw):
    opts = dict(n_particles=64, betas=(0.3, 1.0), diffusion_std=0.1, progress=False)
    apf = AnnealedParticleFilter(model.dynamics(), model.likelihood(), **opts)
    hybrid = HybridParticleFilter(model.dynamics(), model.likelihood(), refiner=refiner, **opts, **kw)
    return apf, hybrid


def test_budget_counts_layers_and_refinement():
    kind = FILTERS.get("hybrid")
    refiner = ShiftRefiner(0.0, steps=10)
    n = kind.for_budget(500, refiner=refiner, n_refine=4, betas=(0.1, 0.4, 1.0), refine_mode="particles")
    refine = 4 * 31 + 2 * 4  # the refiner's cost plus the weight ratio's 2K evaluations
    assert n == (500 - refine) // 3
    model = model_4d()
    built = kind.build(
        model.dynamics(),
        model.likelihood(),
        refiner=refiner,
        n_particles=n,
        diffusion_std=0.1,
        refine_mode="particles",
    )
    assert built.likelihood_evaluations == 3 * n + refine <= 500
    est = kind.for_budget(500, refiner=refiner, n_refine=4)  # "estimate" mode: no weight ratio
    assert est == (500 - 4 * 31 - 2) // 3  # the refiner plus the likelihood check of the estimate
    # with swaps, one more: the best unswapped candidate's score
    assert kind.for_budget(500, refiner=refiner, n_refine=4, swaps=[lambda x: x]) == (500 - 4 * 31 - 3) // 3


def test_a_refiner_that_does_nothing_gives_the_apf(setup):
    model, zs, x0 = setup
    apf, hybrid = _filters(model, ShiftRefiner(0.0), refine_mode="particles")
    a = apf.run(zs, x0, generator=1)
    h = hybrid.run(zs, x0, generator=1)
    torch.testing.assert_close(h.estimates, a.estimates)
    torch.testing.assert_close(h.final_state.log_weights, a.final_state.log_weights)
    torch.testing.assert_close(h.log_evidence, a.log_evidence)


def test_refined_particles_get_the_target_ratio(setup):
    model, zs, x0 = setup
    shift = 0.05
    apf, hybrid = _filters(model, ShiftRefiner(shift), n_refine=3, refine_mode="particles")
    state = apf.init(x0)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    ref = apf.step(state, zs[0], g1)  # the same layers, unrefined
    out = hybrid.step(state, zs[0], g2)
    top = ref.log_weights.topk(3, -1).indices
    x_k = ref.particles.gather(-2, top.unsqueeze(-1).expand(-1, -1, 4))
    torch.testing.assert_close(out.particles.gather(-2, top.unsqueeze(-1).expand(-1, -1, 4)), x_k + shift)
    # independent target ratio: Gaussian likelihood and dynamics evaluated on the parents of the APF frame
    _, x, log_w, _, _, _, x_prev, _, _ = apf._anneal(state, zs[0], torch.Generator().manual_seed(5))
    prev = x_prev.gather(-2, top.unsqueeze(-1).expand(-1, -1, 4))
    lik, dyn = model.likelihood(), model.dynamics()
    ratio = (
        lik(x_k + shift, zs[0]) - lik(x_k, zs[0]) + dyn.log_prob(x_k + shift, prev) - dyn.log_prob(x_k, prev)
    )
    want = log_w.scatter(-1, top, log_w.gather(-1, top) + ratio)
    want = want - torch.logsumexp(want, -1, keepdim=True)
    torch.testing.assert_close(out.log_weights, want)
    assert torch.allclose(out.info["refine_gain"], torch.ones(2, dtype=F64))


def test_estimate_mode_reports_the_best_refined_candidate_and_keeps_the_particles(setup):
    model, zs, x0 = setup
    apf, hybrid = _filters(
        model, ShiftRefiner(0.5), refine_mode="estimate"
    )  # its objective: |x|^2, lower is better
    sa, sh = apf.init(x0), hybrid.init(x0)
    ga, gh = torch.Generator().manual_seed(2), torch.Generator().manual_seed(2)
    seen = set()
    for z in zs:
        sa, sh = apf.step(sa, z, ga), hybrid.step(sh, z, gh)
        torch.testing.assert_close(sh.particles, sa.particles)
        torch.testing.assert_close(sh.log_weights, sa.log_weights)
        # candidates: the weighted mean and the 3 particles of highest weight; the estimate is the one of
        # lowest objective, moved by the refiner
        top = sa.log_weights.topk(3, -1).indices
        cands = torch.cat(
            [sa.mean().unsqueeze(-2), sa.particles.gather(-2, top.unsqueeze(-1).expand(-1, -1, 4))], -2
        )
        best = cands.square().sum(-1).argmin(-1)
        chosen = cands[torch.arange(2), best] + 0.5
        # taken only where the filter's own likelihood scores it at least as high as the mean
        lik = model.likelihood()
        accept = lik(chosen.unsqueeze(-2), z)[:, 0] >= lik(cands[:, :1], z)[:, 0]
        want = torch.where(accept.unsqueeze(-1), chosen, cands[:, 0])
        torch.testing.assert_close(sh.info["estimate"], want)
        assert torch.equal(sh.info["refine_accepted"], accept)
        # the estimate's score, for the lost-track check (it would otherwise score the estimate again)
        torch.testing.assert_close(sh.info["estimate_log_likelihood"], lik(want.unsqueeze(-2), z)[:, 0])
        seen.update(accept.tolist())
    assert seen == {True, False}  # both branches ran


def test_recentre_mode_shifts_the_set_to_the_refined_estimate(setup):
    model, zs, x0 = setup
    apf, hybrid = _filters(model, ShiftRefiner(0.5), refine_mode="recentre")
    state = apf.init(x0)
    ref = apf.step(state, zs[0], torch.Generator().manual_seed(3))
    out = hybrid.step(state, zs[0], torch.Generator().manual_seed(3))
    shift = out.info["estimate"] - ref.mean()  # the ShiftRefiner moved the chosen candidate by 0.5
    torch.testing.assert_close(out.particles, ref.particles + shift.unsqueeze(-2))
    torch.testing.assert_close(out.log_weights, ref.log_weights)
    torch.testing.assert_close(out.mean(), out.info["estimate"])


@pytest.mark.parametrize("mode,margin", [("estimate", 0.0), ("recentre", 0.0), ("recentre", 0.5)])
def test_swap_candidates_and_the_set_that_follows_a_swap(setup, mode, margin):
    """A move (here x -> x / 2, any map will do) adds the moved mean as a candidate after the mean. It
    becomes the estimate where the refinement leaves it best and the likelihood scores it ``swap_margin``
    above the best unmoved candidate (and above the mean); "recentre" then moves the whole set by it, then by
    the refinement's correction."""
    model, zs, x0 = setup

    def halve(x):
        return x / 2

    apf, hybrid = _filters(
        model, ShiftRefiner(0.05), refine_mode=mode, n_refine=4, swaps=[halve], swap_margin=margin
    )
    sh = hybrid.init(x0)
    lik = model.likelihood()
    seen = set()
    for t, z in enumerate(zs):
        ref = apf.step(sh, z, torch.Generator().manual_seed(10 + t))  # the same layers from the same state
        out = hybrid.step(sh, z, torch.Generator().manual_seed(10 + t))
        mean = ref.mean()
        top = ref.log_weights.topk(2, -1).indices  # K = 4: the mean, its move, 2 particles
        particles = ref.particles.gather(-2, top.unsqueeze(-1).expand(-1, -1, 4))
        cands = torch.cat([mean.unsqueeze(-2), halve(mean).unsqueeze(-2), particles], -2)
        objective = cands.square().sum(-1)  # the ShiftRefiner's, before its move
        refined = cands + 0.05
        rows = torch.arange(2)
        best = objective.argmin(-1)
        plain = objective.index_fill(-1, torch.tensor([1]), float("inf")).argmin(-1)
        ll_best = lik(refined[rows, best].unsqueeze(-2), z)[:, 0]
        ll_plain = lik(refined[rows, plain].unsqueeze(-2), z)[:, 0]
        flip = (best == 1) & (ll_best >= ll_plain + margin)
        chosen = torch.where(flip.unsqueeze(-1), refined[rows, best], refined[rows, plain])
        accept = lik(chosen.unsqueeze(-2), z)[:, 0] >= lik(mean.unsqueeze(-2), z)[:, 0]
        estimate = torch.where(accept.unsqueeze(-1), chosen, mean)
        torch.testing.assert_close(out.info["estimate"], estimate)
        swapped = accept & flip
        assert torch.equal(out.info["refine_swapped"], swapped)
        if mode == "recentre":
            start = torch.where(swapped.unsqueeze(-1), halve(mean), mean)
            moved = torch.where(swapped[:, None, None], halve(ref.particles), ref.particles)
            torch.testing.assert_close(out.particles, moved + (estimate - start).unsqueeze(-2))
        else:
            torch.testing.assert_close(out.particles, ref.particles)
        seen.update("swapped" for _ in range(int(swapped.sum())))
        seen.update("refused by the margin" for _ in range(int(((best == 1) & ~flip).sum())))
        sh = out
    assert ("swapped" if margin == 0 else "refused by the margin") in seen  # the branch this case is for


def test_bad_arguments():
    model = model_4d()
    with pytest.raises(ValueError, match="needs refiner"):
        HybridParticleFilter(model.dynamics(), model.likelihood(), diffusion_std=0.1)
    with pytest.raises(ValueError, match="refine_mode"):
        HybridParticleFilter(
            model.dynamics(), model.likelihood(), refiner=ShiftRefiner(0), refine_mode="x", diffusion_std=0.1
        )


@pytest.mark.parametrize("budget", [1, 5, 10, 30, 60, 100, 250, 300, 500, 2000])
def test_refinement_plan_fits_its_share_of_the_budget(budget):
    k, steps = HybridParticleFilter.plan_refinement(budget)
    cost = k * (3 * steps + 1) + 2  # the refiner's cost plus the check of the estimate (refine_evaluations)
    assert 1 <= k <= 4 and 0 <= steps <= 20
    assert cost <= max(0.5 * budget, 3)  # a budget under 6 still looks at the mean once (3 evaluations)
    if (k, steps) != (4, 20):  # reduced: one more step (or pose) would exceed the share
        bigger = (k, steps + 1) if k == 1 else (k + 1, steps)
        assert bigger[0] * (3 * bigger[1] + 1) + 2 > 0.5 * budget
    if budget >= 500:
        assert (k, steps) == (4, 20)  # the defaults fit (246 evaluations)


def test_the_default_trackers_step_keeps_a_batch_of_sequences_independent():
    """``track``'s filter (the hybrid: APF layers on silhouette x dual silhouette, then refinement of the
    mean, its limb swaps and the best particles on the distance cue) on B = 2 sequences at once ((2, N, D)
    particles, (2, V, H, W) masks): sequence 0's step does not change when sequence 1's masks do (nothing is
    normalised, ranked or refined across the batch), and each sequence's estimate goes to its own pose."""
    from torchpf import Skeleton
    from torchpf.assets import path
    from torchpf.camera import camera_ring
    from torchpf.observations import Frame, Silhouettes
    from torchpf.synth import synthesize
    from torchpf.tracker import Tracker

    skel = Skeleton.from_urdf(str(path("human.urdf")))
    names = skel.dof_names
    a = torch.zeros(len(names), dtype=F64)
    a[names.index("Hips_Zposition")] = 1.0
    b, c = a.clone(), a.clone()
    b[names.index("LeftArm_Yrotation")], b[names.index("Hips_Xposition")] = 0.8, 0.15
    c[names.index("RightUpLeg_Xrotation")] = -0.5
    rig = camera_ring(3, radius=4.0, height=1.5, target=(0, 0, 0.8), width=80, height_px=60)
    masks = torch.as_tensor(np.asarray(synthesize(skel, torch.stack([a, b, c]), rig).masks))  # (3, V, H, W)
    tracker = Tracker(skel, rig, n_particles=200, fps=15.0, progress=False)
    filt = tracker.filter
    g = torch.Generator().manual_seed(0)
    noise = 0.03 * torch.randn(2, filt.n_particles, len(names), generator=g, dtype=F64)
    x0 = (torch.stack([a, b])[:, None] + noise).float()

    def step(second):
        frame = Frame(silhouettes=Silhouettes(torch.stack([masks[0], masks[second]])))
        return filt.step(filt.init(x0), frame, torch.Generator().manual_seed(1))

    one, other = step(1), step(2)
    torch.testing.assert_close(one.particles[0], other.particles[0])
    torch.testing.assert_close(one.log_weights[0], other.log_weights[0])
    est = one.info["estimate"].double()  # (2, D)
    fk = skel.fk(torch.stack([est[0], est[1], a, b]))
    own = (fk[:2] - fk[2:]).norm(dim=-1).mean(-1)
    swapped = (fk[:2] - fk[2:].flip(0)).norm(dim=-1).mean(-1)
    assert torch.all(own < 0.5 * swapped), (own, swapped)
