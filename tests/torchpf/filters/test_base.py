"""Mechanics shared by every filter: state/track contract, failure frames, extras, seeding, dtypes, devices.

Accuracy against exact references lives in ``test_filters_kalman.py`` (Kalman), ``test_filters_search.py``
(multimodal search) and ``test_filters_mcmc.py`` (HMC invariance).
"""

import math

import pytest
import torch
from torch import nn

from torchpf.filters import (
    AnnealedParticleFilter,
    MCMCParticleFilter,
    ParticleFilter,
    ParticleState,
    PartitionedParticleFilter,
    Track,
    anneal_beta,
    qrs_normal,
)
from torchpf.filters.qmc import rank_within_parent
from torchpf.proposals import (
    Gaussian,
    GaussianRandomWalk,
    ICondensationProposal,
    LinearGaussianDynamics,
    ObservationGaussian,
)

D = 3
STD = 0.3


class VelocityDynamics(nn.Module):
    """Stateful test dynamics: ``x_t = x_{t-1} + 0.5 v + std eps`` with ``v`` a per-particle extra."""

    std = STD

    def sample(self, x, generator=None, *, extras):
        return self.sample_from_noise(
            x, torch.randn(x.shape, generator=generator, dtype=x.dtype), extras=extras
        )

    def sample_from_noise(self, x, eps, *, extras):
        return x + 0.5 * extras["velocity"] + self.std * eps

    def log_prob(self, x_new, x_old, *, extras):
        r = (x_new - x_old - 0.5 * extras["velocity"]) / self.std
        return -0.5 * (r * r).sum(-1) - x_new.shape[-1] * (math.log(self.std) + 0.5 * math.log(2 * math.pi))

    def update_extras(self, x_new, x_old, extras):
        return {**extras, "velocity": x_new - x_old}

    def init_extras(self, x0):
        return {"velocity": torch.zeros_like(x0)}


class FlaggedLikelihood(nn.Module):
    """Gaussian log-likelihood around ``z``; ``mode`` 1 makes a sequence's frame ``-inf``, 2 makes it NaN."""

    def forward(self, x, obs):
        z, mode = obs
        ll = -0.5 * ((x - z.unsqueeze(-2)) ** 2).sum(-1) / 0.2**2
        ll = torch.where((mode == 1).unsqueeze(-1), torch.full_like(ll, -math.inf), ll)
        return torch.where((mode == 2).unsqueeze(-1), torch.full_like(ll, math.nan), ll)


def _partial(dims):
    lik = FlaggedLikelihood()

    def partial(x, obs):
        z, mode = obs
        return lik(x[..., dims], (z[..., dims], mode))

    return partial


def make_filter(kind: str, dynamics=None, **kw):
    dyn = dynamics if dynamics is not None else GaussianRandomWalk(STD)
    lik = FlaggedLikelihood()
    common = {"progress": False, **kw}
    if kind == "sir":
        return ParticleFilter(dyn, lik, **common)
    if kind == "qrs":
        return ParticleFilter(dyn, lik, sampling="qrs", **common)
    if kind == "icondensation":
        q = ICondensationProposal(
            dyn, ObservationGaussian(lambda o: o[0], 0.5), Gaussian(0.0, 2.0), alpha=0.2, beta=0.7
        )
        return ParticleFilter(dyn, lik, q, **common)
    if kind == "apf":
        return AnnealedParticleFilter(dyn, lik, diffusion_std=0.1, **common)
    if kind == "apf_adaptive":
        return AnnealedParticleFilter(dyn, lik, betas="adaptive", diffusion_std=0.1, **common)
    if kind == "partitioned":
        return PartitionedParticleFilter(dyn, [_partial([0]), _partial([1, 2])], [[0], [1, 2]], **common)
    if kind == "partitioned_qrs":
        return PartitionedParticleFilter(
            dyn, [_partial([0]), _partial([1, 2])], [[0], [1, 2]], sampling="qrs", **common
        )
    if kind == "mcmc":
        return MCMCParticleFilter(dyn, lik, n_moves=2, n_leapfrog=3, step_size=0.05, burn_in=3, **common)
    raise KeyError(kind)


KINDS = ["sir", "qrs", "icondensation", "apf", "apf_adaptive", "partitioned", "partitioned_qrs", "mcmc"]


def observations(batch=(2,), steps=6, seed=0, dtype=torch.float64, failures=()):
    """``steps`` frames of ``(z (*batch, D), mode (*batch,))``; ``failures``: ``(frame, index, mode)``."""
    g = torch.Generator().manual_seed(seed)
    z = torch.cumsum(0.2 * torch.randn((steps, *batch, D), generator=g, dtype=dtype), 0)
    modes = torch.zeros((steps, *batch), dtype=torch.long)
    for frame, index, mode in failures:
        modes[(frame, *index)] = mode
    return [(z[t], modes[t]) for t in range(steps)]


def _x0(batch=(2,), n=64, dtype=torch.float64):
    return torch.zeros((*batch, n, D), dtype=dtype)


# --------------------------------------------------------------------------- contract


@pytest.mark.parametrize("kind", KINDS)
def test_track_shapes_and_state_contract(kind):
    pf = make_filter(kind)
    obs = observations()
    track = pf.run(obs, _x0(), torch.Generator().manual_seed(0))
    assert isinstance(track, Track)
    assert track.estimates.shape == (2, 6, D) and track.map_estimates.shape == (2, 6, D)
    assert track.ess.shape == track.failed.shape == track.resampled.shape == (2, 6)
    assert track.log_evidence.shape == (2,) and track.log_evidence_increments.shape == (2, 6)
    torch.testing.assert_close(track.log_evidence, track.log_evidence_increments.sum(-1))
    assert torch.all(torch.isfinite(track.estimates)) and not track.failed.any()
    assert torch.all((track.ess >= 1 - 1e-9) & (track.ess <= 64 + 1e-9))
    state = track.final_state
    assert isinstance(state, ParticleState)
    assert state.particles.shape == (2, 64, D) and state.log_weights.shape == (2, 64)
    torch.testing.assert_close(torch.logsumexp(state.log_weights, -1), torch.zeros(2, dtype=torch.float64))
    with pytest.raises(AttributeError):
        state.particles = state.particles  # frozen


def test_state_summaries_match_definitions():
    x = torch.tensor([[0.0, 0.0], [1.0, 2.0], [3.0, -1.0]])
    w = torch.tensor([0.5, 0.3, 0.2])
    state = ParticleState(x, torch.log(w) + 7.0, torch.zeros(()))  # unnormalised on purpose
    torch.testing.assert_close(state.mean(), (w[:, None] * x).sum(0))
    torch.testing.assert_close(state.ess(), 1 / (w * w).sum())
    torch.testing.assert_close(state.map(), x[0])
    centred = x - state.mean()
    torch.testing.assert_close(
        state.cov(), (w[:, None, None] * centred[:, :, None] * centred[:, None, :]).sum(0)
    )


def test_extra_leading_dims_and_single_particle_x0():
    pf = make_filter("sir", n_particles=32)
    obs = observations(batch=(2, 3))
    track = pf.run(obs, torch.zeros(2, 3, 1, D, dtype=torch.float64), torch.Generator().manual_seed(0))
    assert track.estimates.shape == (2, 3, 6, D) and track.ess.shape == (2, 3, 6)
    with pytest.raises(ValueError, match="particles"):
        pf.init(torch.zeros(2, 5, D))


def test_invalid_configuration_raises():
    dyn, lik = GaussianRandomWalk(STD), FlaggedLikelihood()
    with pytest.raises(ValueError):
        ParticleFilter(dyn, lik, ess_threshold=1.5)
    with pytest.raises(ValueError):
        ParticleFilter(dyn, lik, sampling="sobol")
    with pytest.raises(ValueError):
        ParticleFilter(dyn, lik, resampler="nope")
    with pytest.raises(ValueError):
        AnnealedParticleFilter(dyn, lik, betas=(0.1, 0.5))  # must end with 1
    with pytest.raises(ValueError):
        AnnealedParticleFilter(dyn, lik, alphas=(2.0, 4.0, 4.0))  # layer 1 is the proposal
    with pytest.raises(ValueError):
        AnnealedParticleFilter(dyn, lik, alphas=(1.0, 4.0, 4.0), annealing_rate=0.5)
    no_std = LinearGaussianDynamics(torch.eye(D), 0.01 * torch.eye(D))
    with pytest.raises(ValueError, match="diffusion_std"):
        AnnealedParticleFilter(no_std, lik)  # no diffusion_std and no dynamics.std
    with pytest.raises(TypeError, match="sample"):
        ParticleFilter(object(), lik)  # not a dynamics at all
    with pytest.raises(ValueError):
        PartitionedParticleFilter(dyn, [lik], [[0], [1]])
    with pytest.raises(ValueError):
        PartitionedParticleFilter(dyn, [lik, lik], [[0, 1], [1, 2]])
    pf = PartitionedParticleFilter(dyn, [lik, lik], [[0], [1]], progress=False)
    with pytest.raises(ValueError, match="partition"):
        pf.step(pf.init(torch.zeros(4, D)), observations()[0])  # dim 2 in no group
    with pytest.raises(ValueError, match="likelihood returned shape"):
        ParticleFilter(dyn, lambda x, z: x.sum(), progress=False).step(
            ParticleFilter(dyn, lik).init(_x0()), None
        )


# --------------------------------------------------------------------------- failures


@pytest.mark.parametrize("kind", KINDS)
def test_all_invalid_weights_keep_prediction_and_flag_frame(kind):
    # sequence 0 gets an all -inf frame at t = 2, sequence 1 an all-NaN frame at t = 3
    obs = observations(failures=[(2, (0,), 1), (3, (1,), 2)])
    pf = make_filter(kind)
    g = torch.Generator().manual_seed(0)
    track = pf.run(obs, _x0(), g)
    expected = torch.zeros(2, 6, dtype=torch.bool)
    expected[0, 2] = expected[1, 3] = True
    assert torch.equal(track.failed, expected)
    assert track.log_evidence_increments[0, 2] == 0 and track.log_evidence_increments[1, 3] == 0
    assert torch.all(torch.isfinite(track.log_evidence)) and torch.all(torch.isfinite(track.estimates))
    torch.testing.assert_close(track.failure_rate, torch.tensor([1 / 6, 1 / 6], dtype=torch.float64))

    # step by step: the failed sequence has uniform weights, the other one does not
    state = pf.init(_x0())
    for frame in obs[:3]:
        state = pf.step(state, frame, g)
    torch.testing.assert_close(state.log_weights[0], torch.full((64,), -math.log(64), dtype=torch.float64))
    assert torch.all(torch.isfinite(state.particles))


# --------------------------------------------------------------------------- extras


@pytest.mark.parametrize("kind", KINDS)
def test_extras_follow_their_particles(kind):
    """A velocity extra, updated as ``v = x_t - x_{t-1}`` by stateful dynamics, must stay paired with its
    particle through every resampling: ``x_t - v_t`` is then exactly one of the previous frame's particles."""
    pf = make_filter(kind, dynamics=VelocityDynamics(), ess_threshold=1.0)
    g = torch.Generator().manual_seed(1)
    x0 = torch.randn(2, 64, D, generator=g, dtype=torch.float64)
    state = pf.init(x0, extras={"velocity": torch.zeros_like(x0), "label": torch.arange(64.0).expand(2, 64)})
    for frame in observations():
        parents = state
        state = pf.step(state, frame, g)
        origin = state.particles - state.extras["velocity"]
        gap = (origin.unsqueeze(-2) - parents.particles.unsqueeze(-3)).abs().amax(-1).amin(-1)
        assert gap.max() < 1e-12
        assert state.extras["label"].shape == (2, 64)
    # labels are gathered with the particles: each is still one of the original ones, and they got mixed
    labels = state.extras["label"]
    assert torch.equal(labels, labels.round()) and labels.min() >= 0 and labels.max() <= 63
    assert not torch.equal(labels, torch.arange(64.0).expand(2, 64))


def test_plain_extras_are_resampled_with_particles():
    # deterministic "dynamics" (no motion): each particle keeps its initial value, stored as an extra
    class Still:
        def sample(self, x, generator=None):
            return x

        def log_prob(self, x_new, x_old):
            return torch.zeros(x_new.shape[:-1], dtype=x_new.dtype)

    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(3, 50, 1, generator=g, dtype=torch.float64)
    pf = ParticleFilter(
        Still(), lambda x, z: -((x[..., 0] - z) ** 2) / 0.1, ess_threshold=1.0, progress=False
    )
    state = pf.init(x0, extras={"copy": x0.clone()})
    for _ in range(4):
        state = pf.step(state, torch.tensor(0.5, dtype=torch.float64), g)
        assert torch.equal(state.extras["copy"], state.particles)
    assert state.ess().max() < 50  # it did resample and concentrate


@pytest.mark.parametrize("kind", ["sir", "apf", "mcmc"])
def test_iterate_yields_what_run_keeps(kind):
    pf = make_filter(kind)
    obs = observations()
    track = pf.run(obs, _x0(), torch.Generator().manual_seed(3))
    states = list(pf.iterate(iter(obs), _x0(), torch.Generator().manual_seed(3)))  # a lazy iterable
    assert len(states) == 6
    est = torch.stack([s.mean() for s in states], 1)
    assert torch.equal(est, track.estimates)
    assert torch.equal(states[-1].log_evidence, track.log_evidence)


# --------------------------------------------------------------------------- randomness, dtype, device


@pytest.mark.parametrize("kind", KINDS)
def test_same_seed_same_result(kind):
    pf = make_filter(kind)
    obs = observations()
    a = pf.run(obs, _x0(), torch.Generator().manual_seed(5))
    b = pf.run(obs, _x0(), torch.Generator().manual_seed(5))
    c = pf.run(obs, _x0(), torch.Generator().manual_seed(6))
    assert torch.equal(a.estimates, b.estimates) and torch.equal(a.log_evidence, b.log_evidence)
    assert not torch.equal(a.estimates, c.estimates)


@pytest.mark.parametrize("kind", KINDS)
def test_device_and_dtype_follow_x0(kind, device, dtype, generator):
    pf = make_filter(kind).to(device)
    obs = [(z.to(device), m.to(device)) for z, m in observations(dtype=dtype)]
    x0 = _x0(dtype=dtype).to(device)
    track = pf.run(obs, x0, generator)
    for t in (track.estimates, track.ess, track.log_evidence, track.final_state.log_weights):
        assert t.dtype == dtype and t.device.type == device.type
    for value in track.stats.values():  # floating diagnostics in the particles' dtype, counts as integers
        assert value.dtype == (dtype if value.is_floating_point() else torch.long)
        assert value.device.type == device.type
    assert torch.all(torch.isfinite(track.estimates))
    again = pf.run(obs, x0, torch.Generator(device=device).manual_seed(0))
    assert torch.equal(track.estimates, again.estimates)
    # a CPU generator or a seed drives a run on any device (as_generator derives one there)
    from_cpu = pf.run(obs, x0, torch.Generator().manual_seed(0))
    assert torch.equal(from_cpu.estimates, pf.run(obs, x0, torch.Generator().manual_seed(0)).estimates)
    assert torch.isfinite(pf.run(obs, x0, 3).estimates).all()


# --------------------------------------------------------------------------- resampling policy


@pytest.mark.parametrize(("threshold", "expected"), [(0.0, False), (1.0, True)])
def test_ess_threshold_extremes(threshold, expected):
    track = make_filter("sir", ess_threshold=threshold).run(
        observations(), _x0(), torch.Generator().manual_seed(0)
    )
    assert torch.all(track.resampled == expected)


def test_ess_threshold_triggers_exactly_below_threshold():
    pf = make_filter("sir", ess_threshold=0.5)
    g = torch.Generator().manual_seed(0)
    state = pf.init(_x0())
    for frame in observations(steps=8):
        needs = state.ess() < 0.5 * 64
        state = pf.step(state, frame, g)
        assert torch.equal(state.info["resampled"], needs)


def test_single_layer_apf_is_sir():
    obs = observations()
    sir = make_filter("sir").run(obs, _x0(), torch.Generator().manual_seed(3))
    apf = AnnealedParticleFilter(GaussianRandomWalk(STD), FlaggedLikelihood(), betas=(1.0,), progress=False)
    apf = apf.run(obs, _x0(), torch.Generator().manual_seed(3))
    torch.testing.assert_close(apf.estimates, sir.estimates)
    torch.testing.assert_close(apf.log_evidence, sir.log_evidence)


def test_apf_reports_its_schedule():
    track = make_filter("apf").run(observations(), _x0(), torch.Generator().manual_seed(0))
    expected = torch.tensor([0.1, 0.4, 1.0], dtype=torch.float64).expand(2, 6, 3)
    torch.testing.assert_close(track.stats["betas"], expected)
    adaptive = make_filter("apf_adaptive").run(observations(), _x0(), torch.Generator().manual_seed(0))
    betas = adaptive.stats["betas"]
    assert torch.all(betas[..., -1] == 1) and torch.all(betas[..., 1:] >= betas[..., :-1])


def test_anneal_beta_hits_the_survival_rate():
    g = torch.Generator().manual_seed(0)
    energy = -50 * torch.rand(4, 500, generator=g, dtype=torch.float64) ** 2
    energy[3] = -1e-3 * torch.rand(500, generator=g, dtype=torch.float64)  # flat: beta = 1 keeps > 50 %
    base = torch.zeros_like(energy)
    beta = anneal_beta(base, energy, 0.5, torch.zeros(4, dtype=torch.float64))
    log_w = beta[:, None] * energy
    survival = torch.exp(2 * torch.logsumexp(log_w, -1) - torch.logsumexp(2 * log_w, -1)) / 500
    torch.testing.assert_close(survival[:3], torch.full((3,), 0.5, dtype=torch.float64), atol=1e-6, rtol=0)
    assert beta[3] == 1 and torch.all(beta[:3] < 1)


# --------------------------------------------------------------------------- QRS building blocks


def test_rank_within_parent():
    anc = torch.tensor([[0, 0, 2, 2, 2, 5], [3, 1, 3, 1, 3, 3]])
    assert torch.equal(rank_within_parent(anc), torch.tensor([[0, 1, 0, 1, 2, 0], [0, 0, 1, 1, 2, 3]]))


def test_qrs_children_of_one_parent_are_evenly_spread():
    # one parent with all 256 children: the uniforms behind the noise form a shifted Sobol net, so their
    # empirical CDF is within 2/N of uniform (i.i.d. uniforms are typically ~1/sqrt(N) = 0.06 away)
    n = 256
    eps = qrs_normal(torch.zeros(5, n, dtype=torch.long), 2, torch.Generator().manual_seed(0), torch.float64)
    u = torch.special.ndtr(eps).sort(-2).values
    grid = (torch.arange(n, dtype=torch.float64)[:, None] + 0.5) / n
    ks = (u - grid).abs().amax(-2)
    assert ks.max() <= 2.0 / n
    # different parents get different (independently shifted) points, and marginals are N(0, 1)
    eps = qrs_normal(torch.arange(4000).reshape(1, -1), 3, torch.Generator().manual_seed(1), torch.float64)
    assert eps.mean().abs() < 0.05 and (eps.var() - 1).abs() < 0.05
    assert torch.unique(eps[0, :, 0]).numel() == 4000


def test_progress_bar_can_be_shown(capsys):
    pf = make_filter("sir", progress=True)
    pf.run(observations(steps=2), _x0(), torch.Generator().manual_seed(0))
    assert "ParticleFilter" in capsys.readouterr().err


class _SometimesNaN(GaussianRandomWalk):
    """A random walk that sends a fixed share of its draws to NaN (or all of them)."""

    def __init__(self, share):
        super().__init__(STD)
        self.share = share

    def sample(self, x, generator=None, *, extras=None):
        out = super().sample(x, generator, extras=extras)
        n = out.shape[-2]
        return out.index_fill(-2, torch.arange(int(self.share * n)), float("nan"))


@pytest.mark.parametrize("kind", ["sir", "apf", "partitioned", "mcmc"])
@pytest.mark.parametrize("share", [0.25, 1.0])
def test_nonfinite_particles_are_dropped_and_counted(kind, share):
    pf = make_filter(kind, dynamics=_SometimesNaN(share))
    track = pf.run(observations(), _x0(), torch.Generator().manual_seed(0))
    assert torch.isfinite(track.estimates).all() and torch.isfinite(track.final_state.particles).all()
    if share == 1.0:  # nothing usable: every frame flagged, the parents kept
        assert track.failed.all() and (track.stats["nonfinite"] == 64).all()
    else:  # the NaN draws get no weight (the APF's and MCMC's own resampling removes them before the end)
        assert not track.failed.any()
        if kind in ("sir", "partitioned"):
            assert (track.stats["nonfinite"] == 16).all()


def test_mean_ignores_zero_weight_nan_particles():
    x = torch.tensor([[1.0, 2.0], [float("nan"), 0.0], [3.0, 4.0]])
    state = ParticleState(x, torch.tensor([0.0, -math.inf, 0.0]), torch.tensor(0.0))
    torch.testing.assert_close(state.mean(), torch.tensor([2.0, 3.0]))
    assert torch.isfinite(state.cov()).all()


@pytest.mark.parametrize("kind", KINDS)
def test_run_with_grad_keeps_the_graph(kind):
    """``run(grad=True)``: the log-evidence is differentiable in the initial particles (the dynamics'
    reparameterised draws and the likelihood carry the graph; resampling indices are held fixed)."""
    pf = make_filter(kind)
    obs = observations()
    x0 = _x0().requires_grad_()
    assert not pf.run(obs, x0, 0).log_evidence.requires_grad  # the default: no graph
    track = pf.run(obs, x0, 0, grad=True)
    track.log_evidence.sum().backward()
    assert x0.grad is not None and torch.isfinite(x0.grad).all() and x0.grad.abs().sum() > 0
    torch.testing.assert_close(track.estimates.detach(), pf.run(obs, x0, 0).estimates)
