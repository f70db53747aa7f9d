"""Particle filters for tracking: SIR, annealed, partitioned, quasi-Monte-Carlo and MCMC variants.

A filter approximates the posterior ``p(x_t | z_{1:t})`` over a state vector (a pose ``theta``, ``D`` DOFs) by
``N`` weighted particles, for any number of independent sequences at once (leading dims ``...``). Models are
separate objects (:mod:`torchpf.filters.protocols`): a dynamics ``p(x_t | x_{t-1})``
(:class:`torchpf.distributions.Dynamics`, or any object with ``sample(x, generator)`` / ``log_prob(x_new,
x_old)``), a likelihood ``(x, obs) -> (..., N)`` log-density and,
optionally, a proposal (:mod:`torchpf.proposals`). The state is an immutable
:class:`~torchpf.filters.state.ParticleState` passed in and out of ``step``; nothing is stored on the filter.

==============================  ============================================  ============================
class                           what it does                                   source
==============================  ============================================  ============================
``ParticleFilter``              SIR / CONDENSATION, ESS-triggered resampling   Brubaker Alg. 1, eq. 16-18;
                                (``sampling="qrs"``: QRS-CONDENSATION)          Fontmarty Tables 1, 4
``AnnealedParticleFilter``      ``L`` annealing layers per frame, fixed or     Brubaker Alg. 2, eq. 19-20;
                                adaptive (survival-rate) betas                  Fontmarty Table 3
``PartitionedParticleFilter``   stage-wise diffusion/weighting of DOF groups   Fontmarty Table 2
                                (``sampling="qrs"``: PARTITIONED QRS)
``MCMCParticleFilter``          SIR + hybrid Monte Carlo rejuvenation moves    Brubaker Alg. 3-4, eq. 21-22
``HybridParticleFilter``        APF layers, then gradient refinement of the    Gall et al. IJCV 2010
                                best particles (:mod:`torchpf.refine`)
==============================  ============================================  ============================

Conventions: log-weights everywhere, handled only by :mod:`torchpf.filters.weights`; randomness only through
an explicit ``torch.Generator`` (same generator state, same result; it must live on the particles' device);
device and dtype follow ``x0``. A frame where every weight is ``-inf``/NaN keeps the predicted particles with
uniform weights, adds nothing to the log-evidence and is flagged (``Track.failed``).

Example::

    from torchpf.filters import ParticleFilter
    pf = ParticleFilter(dynamics, likelihood, n_particles=500, resampler="systematic", ess_threshold=0.5)
    track = pf.run(observations, x0, generator=torch.Generator().manual_seed(0))  # estimates (..., T, D)
"""

from torchpf.filters.annealed import AnnealedParticleFilter, anneal_beta
from torchpf.filters.base import ParticleFilter
from torchpf.filters.hybrid import HybridParticleFilter
from torchpf.filters.mcmc import MCMCParticleFilter, hmc_move
from torchpf.filters.partitioned import PartitionedParticleFilter
from torchpf.filters.protocols import Dynamics, Likelihood, Proposal
from torchpf.filters.qmc import qrs_normal, sobol_normal
from torchpf.filters.state import ParticleState, Track, gather_particles
from torchpf.filters.weights import ess, normalise, reweight, temper

__all__ = [
    "AnnealedParticleFilter",
    "Dynamics",
    "HybridParticleFilter",
    "Likelihood",
    "MCMCParticleFilter",
    "ParticleFilter",
    "ParticleState",
    "PartitionedParticleFilter",
    "Proposal",
    "Track",
    "ess",
    "normalise",
    "temper",
    "anneal_beta",
    "gather_particles",
    "hmc_move",
    "qrs_normal",
    "reweight",
    "sobol_normal",
]
