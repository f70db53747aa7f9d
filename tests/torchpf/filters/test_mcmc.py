"""Hybrid Monte Carlo moves (Brubaker Alg. 4) keep their target invariant; the burn-in adapts the step."""

import math

import torch

from torchpf.filters import MCMCParticleFilter, hmc_move
from torchpf.proposals import GaussianRandomWalk

F64 = torch.float64
MEAN = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
STD = torch.tensor([0.5, 1.0, 2.0], dtype=F64)  # anisotropic on purpose: 4x between the extreme scales


def gaussian_log_target(q):
    return -0.5 * (((q - MEAN) / STD) ** 2).sum(-1)


def test_hmc_leaves_a_gaussian_invariant():
    """Start 4000 chains (2 sequences x 2000) at exact samples, make 30 moves, compare moments.

    Chains are independent, so the sample mean has standard error ``std / sqrt(4000)``: we allow 5 of them.
    The sample variance of 4000 normal draws has relative standard error ``sqrt(2 / 3999) = 2.2 %``: we allow
    12 %. The step (0.35) is large for the narrowest direction (std 0.5), so the Metropolis test matters: the
    leapfrog end points alone (no accept/reject) inflate that variance by ~14 %.
    """
    g = torch.Generator().manual_seed(0)
    q = MEAN + STD * torch.randn(2, 2000, 3, generator=g, dtype=F64)
    accepted = []
    for _ in range(30):
        q, prob, acc = hmc_move(q, gaussian_log_target, 0.35, n_leapfrog=5, generator=g)
        accepted.append(acc.to(F64).mean())
    flat = q.reshape(-1, 3)
    se = STD / math.sqrt(flat.shape[0])
    assert torch.all((flat.mean(0) - MEAN).abs() < 5 * se), flat.mean(0)
    assert torch.all((flat.var(0) / STD**2 - 1).abs() < 0.12), flat.var(0)
    rate = torch.stack(accepted).mean()
    assert 0.3 < rate < 0.99  # the moves are real moves, some get rejected


def test_hmc_converges_from_a_wrong_start_and_rejects_bad_energies():
    g = torch.Generator().manual_seed(1)
    q = torch.zeros(1, 2000, 3, dtype=F64)
    for _ in range(60):
        q, _, _ = hmc_move(q, gaussian_log_target, 0.35, n_leapfrog=5, generator=g)
    flat = q.reshape(-1, 3)
    assert torch.all((flat.mean(0) - MEAN).abs() < 0.1 * STD + 5 * STD / math.sqrt(2000))

    # A target that is -inf everywhere except at the start: every move is rejected, nothing becomes NaN.
    def spike(x):
        return torch.where(
            (x == 0).all(-1), torch.zeros(x.shape[:-1], dtype=F64), torch.full(x.shape[:-1], -math.inf)
        )

    start = torch.zeros(1, 10, 3, dtype=F64)
    out, prob, acc = hmc_move(start, spike, 0.1, n_leapfrog=3, generator=g)
    assert torch.equal(out, start) and not acc.any() and torch.all(prob == 0)


def test_per_sequence_steps_and_step_scale_broadcast():
    g = torch.Generator().manual_seed(2)
    q = MEAN + STD * torch.randn(3, 500, 3, generator=g, dtype=F64)
    step = torch.tensor([1e-4, 0.3, 5.0], dtype=F64)
    _, prob, _ = hmc_move(q, gaussian_log_target, step, n_leapfrog=5, generator=g, step_scale=STD)
    acc = prob.mean(-1)
    assert acc[0] > 0.99 and acc[1] > 0.8 and acc[2] < 0.5  # tiny steps always pass, huge ones mostly fail


def test_burn_in_adapts_step_size_then_freezes_it():
    # Gaussian likelihood around the observation: the HMC target of each frame is a 2-D Gaussian.
    def likelihood(x, z):
        return -0.5 * ((x - z.unsqueeze(-2)) ** 2).sum(-1) / 0.1**2

    pf = MCMCParticleFilter(
        GaussianRandomWalk(0.3),
        likelihood,
        n_moves=2,
        n_leapfrog=4,
        step_size=1.0,  # far too large to start with
        burn_in=8,
        progress=False,
    )
    g = torch.Generator().manual_seed(3)
    zs = torch.cumsum(0.2 * torch.randn(16, 2, 2, generator=g, dtype=F64), 0)
    track = pf.run(zs, torch.zeros(2, 500, 2, dtype=F64), g)
    steps, acceptance = track.stats["step_size"], track.stats["acceptance"]
    assert steps.shape == acceptance.shape == (2, 16)
    assert torch.all(steps[:, 8:] == steps[:, 8:9])  # fixed after the burn-in
    assert torch.all(steps[:, 8] < 0.5)  # adapted down from 1.0
    assert torch.all((acceptance[:, 8:].mean(-1) > 0.6) & (acceptance[:, 8:].mean(-1) < 0.9))
    assert track.final_state.aux["hmc_frames"].eq(16).all()
