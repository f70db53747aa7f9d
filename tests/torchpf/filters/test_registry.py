"""torchpf.filters.registry: filters by name and the equal-likelihood-budget rule (Fontmarty §3.3.2)."""

import pytest
import torch

from torchpf.filters import (
    AnnealedParticleFilter,
    MCMCParticleFilter,
    ParticleFilter,
    PartitionedParticleFilter,
)
from torchpf.filters.registry import FILTERS
from torchpf.proposals import GaussianRandomWalk


def _lik(x, obs):
    return -(x**2).sum(-1)


def test_names_and_alias():
    assert FILTERS.names() == ["apf", "hybrid", "mcmc", "partitioned", "partitioned_qrs", "qrs", "sir"]
    assert FILTERS.get("CONDENSATION") is FILTERS.get("sir")
    with pytest.raises(ValueError, match="unknown filter 'kalman'"):
        FILTERS.get("kalman")


@pytest.mark.parametrize(
    ("name", "options", "particles", "cost"),
    [
        ("sir", {}, 600, 1),
        ("qrs", {}, 600, 1),
        ("apf", {}, 200, 3),  # Fontmarty: N / 3 per layer
        ("apf", {"betas": (0.2, 1.0)}, 300, 2),
        ("apf", {"betas": "adaptive", "n_layers": 4}, 150, 4),
        ("partitioned", {"groups": [[0], [1]]}, 300, 2),  # Fontmarty: N / 2 per partition
        ("partitioned_qrs", {"groups": [[0], [1], [2]]}, 200, 3),
        ("mcmc", {}, 46, 13),  # 1 + 2 moves x (5 leapfrog + 1) gradients
        ("mcmc", {"n_moves": 1, "n_leapfrog": 2}, 150, 4),
    ],
)
def test_for_budget_and_built_filters_spend_the_same_budget(name, options, particles, cost):
    kind = FILTERS.get(name)
    n = kind.for_budget(600, **options)
    assert n == particles and kind.evaluations_per_particle(**options) == cost
    dyn = GaussianRandomWalk(0.1)
    args = (dyn, [_lik] * len(options["groups"])) if kind.partitioned else (dyn, _lik)
    f = kind.build(*args, n_particles=n, progress=False, **options)
    assert f.likelihood_evaluations == n * cost <= 600
    expected = {
        "sir": ParticleFilter,
        "qrs": ParticleFilter,
        "apf": AnnealedParticleFilter,
        "partitioned": PartitionedParticleFilter,
        "partitioned_qrs": PartitionedParticleFilter,
        "mcmc": MCMCParticleFilter,
    }[name]
    assert type(f) is expected and f.sampling == ("qrs" if name.endswith("qrs") else "mc")


def test_the_budget_counts_real_likelihood_calls():
    """Count the particles the likelihood actually sees in one frame (gradients included for MCMC)."""
    seen = []

    def counting(x, obs):
        seen.append(x.shape[-2])
        return -(x**2).sum(-1)

    dyn = GaussianRandomWalk(0.1)
    for name, options in [("sir", {}), ("apf", {}), ("partitioned", {"groups": [[0], [1]]})]:
        kind = FILTERS.get(name)
        n = kind.for_budget(90, **options)
        args = (dyn, [counting] * 2) if kind.partitioned else (dyn, counting)
        f = kind.build(*args, n_particles=n, progress=False, **options)
        seen.clear()
        f.step(f.init(torch.zeros(n, 2)), None, torch.Generator().manual_seed(0))
        assert sum(seen) == f.likelihood_evaluations <= 90


def test_partitioned_budget_needs_groups():
    with pytest.raises(ValueError, match="groups"):
        FILTERS.get("partitioned").for_budget(100)
    with pytest.raises(ValueError, match="budget"):
        FILTERS.get("sir").for_budget(0)
