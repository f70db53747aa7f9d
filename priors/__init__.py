"""priors: motion models and importance distributions for articulated tracking (depends on torchpf).

* :mod:`priors.motion`: ``AngularRandomWalk`` (Hauberg eq. 3) within the joint limits, ``ConstantVelocity``
  (Rius eq. 3),
  ``DampedSecondOrder`` (Brubaker eq. 13), ``ProjectedGaussian`` (Hauberg eq. 6-7).
* :mod:`priors.diffusion`: the default per-DOF stds from the kinematic structure (no names), and
  ``LearnedDynamics`` (step stds and α learned from mocap).
* :mod:`priors.table5`: Fontmarty Table 5, the random-walk stds per joint group, mapped onto a skeleton.
* :mod:`priors.proposals`: data-driven importance distributions ``SilhouetteGuided`` (Hauberg eq. 12),
  ``DepthGuided`` (Hauberg eq. 13-14) and the ``AngularRejection`` baseline (Hauberg eq. 4).
* :mod:`priors.action`: the action model Γ = (Ω, ĝ, σ), ``ActionConstrained`` dynamics (Rius eq. 1-6, or
  a soft prior), the phase-advance importance distribution ``ActionProposal`` and ``ActionSubspace``, the
  aSpace as the coordinates of a gradient refinement (the hybrid filter refines on the action's manifold).
* :mod:`priors.bank`: ``ActionBank``, several action models with the action as a discrete particle state.

Each motion prior is a :class:`torchpf.distributions.Dynamics` (an ``nn.Module``): ``sample(x, generator, *,
extras)`` and ``log_prob(x_new, x_old, *, extras)`` where it is tractable, with no-op extras hooks unless it
keeps per-particle state.
"""

from importlib import import_module

# Resolved lazily so that each submodule can be imported (and developed) on its own.
_LAZY = {
    "AngularRandomWalk": "priors.motion",
    "ConstantVelocity": "priors.motion",
    "DampedSecondOrder": "priors.motion",
    "ProjectedGaussian": "priors.motion",
    "SilhouetteGuided": "priors.proposals",
    "DepthGuided": "priors.proposals",
    "AngularRejection": "priors.proposals",
    "ActionModel": "priors.action",
    "ActionConstrained": "priors.action",
    "ActionProposal": "priors.action",
    "ActionSubspace": "priors.action",
    "read_name_map": "priors.action",
    "ActionBank": "priors.bank",
}


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'priors' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
