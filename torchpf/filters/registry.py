"""Filters by name: the one table that the tracker, the CLI and the benchmarks build filters from.

=====================  ==============================  =================================================
name                   class                           fixed keywords
=====================  ==============================  =================================================
``sir``                ``ParticleFilter``              ``sampling="mc"`` (alias ``condensation``)
``qrs``                ``ParticleFilter``              ``sampling="qrs"`` (Fontmarty Table 4)
``partitioned``        ``PartitionedParticleFilter``   ``sampling="mc"`` (Fontmarty Table 2)
``partitioned_qrs``    ``PartitionedParticleFilter``   ``sampling="qrs"``
``apf``                ``AnnealedParticleFilter``      (Brubaker Alg. 2; Fontmarty Table 3)
``mcmc``               ``MCMCParticleFilter``          (Brubaker Alg. 3-4)
``hybrid``             ``HybridParticleFilter``        (APF + gradient refinement, Gall et al. 2010)
=====================  ==============================  =================================================

Each entry is a :class:`FilterKind`; :meth:`FilterKind.for_budget` is the equal-budget rule of Fontmarty
§3.3.2 (particles such that every filter evaluates the likelihood the same number of times per frame).

Example::

    kind = FILTERS.get("apf")
    n = kind.for_budget(600)                                  # 200 particles x 3 layers
    apf = kind.build(dynamics, likelihood, n_particles=n)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from torchpf.filters.annealed import AnnealedParticleFilter
from torchpf.filters.base import ParticleFilter
from torchpf.filters.hybrid import HybridParticleFilter
from torchpf.filters.mcmc import MCMCParticleFilter
from torchpf.filters.partitioned import PartitionedParticleFilter
from torchpf.registry import Registry


@dataclass(frozen=True)
class FilterKind:
    """A named filter: its class and the constructor keywords that the name fixes.

    ``partitioned`` kinds take ``(dynamics, likelihoods, groups)`` instead of ``(dynamics, likelihood,
    proposal)``.
    """

    cls: type[ParticleFilter]
    fixed: Mapping[str, Any] = field(default_factory=dict)

    @property
    def partitioned(self) -> bool:
        return issubclass(self.cls, PartitionedParticleFilter)

    def evaluations_per_particle(self, **options: Any) -> int:
        """Likelihood evaluations per particle and frame with constructor keywords ``options``."""
        return self.cls.evaluations_per_particle(**{**options, **self.fixed})

    def for_budget(self, budget: int, **options: Any) -> int:
        """Particles for at most ``budget`` likelihood evaluations per frame (see the module docstring)."""
        return self.cls.for_budget(budget, **{**options, **self.fixed})

    def build(self, *args: Any, **options: Any) -> ParticleFilter:
        """The filter: ``cls(*args, **fixed, **options)``."""
        return self.cls(*args, **{**options, **self.fixed})


FILTERS: Registry[FilterKind] = Registry("filter", aliases={"condensation": "sir"})
FILTERS.register("sir", FilterKind(ParticleFilter, {"sampling": "mc"}))
FILTERS.register("qrs", FilterKind(ParticleFilter, {"sampling": "qrs"}))
FILTERS.register("partitioned", FilterKind(PartitionedParticleFilter, {"sampling": "mc"}))
FILTERS.register("partitioned_qrs", FilterKind(PartitionedParticleFilter, {"sampling": "qrs"}))
FILTERS.register("apf", FilterKind(AnnealedParticleFilter))
FILTERS.register("mcmc", FilterKind(MCMCParticleFilter))
FILTERS.register("hybrid", FilterKind(HybridParticleFilter))
