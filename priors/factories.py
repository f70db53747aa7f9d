"""Motion priors by name, for ``torchpf.Tracker(dynamics="...")`` and ``python -m torchpf track``.

torchpf never imports this package; it finds these factories through the ``torchpf.dynamics`` entry-point
group declared in ``pyproject.toml``. Each factory is ``factory(skeleton, **options) -> dynamics``.

* ``random_walk``: angular random walk (Hauberg eq. 3, Fontmarty §3.1) with the per-joint-group stds of
  Fontmarty Table 5 (:func:`priors.table5.table5_sigma`), restricted to the joint limits.
* ``constant_velocity``: Rius eq. 3 (:class:`priors.motion.ConstantVelocity`), diffusion from Table 5.
* ``damped``: Brubaker eq. 13 (:class:`priors.motion.DampedSecondOrder`).
* ``action``: the action-constrained dynamics of Rius eq. 3 + 6 from a saved action model (``model=path``).

Example::

    from torchpf import Tracker
    tracker = Tracker(skel, cams, dynamics="random_walk", dynamics_options={"fps": 15.0, "scale": 0.5})
"""

from __future__ import annotations

from priors.action import ActionConstrained, ActionModel
from priors.motion import AngularRandomWalk, ConstantVelocity, DampedSecondOrder
from priors.table5 import TABLE5_FPS, table5_sigma

__all__ = ["action", "constant_velocity", "damped", "random_walk"]


def random_walk(skeleton, *, fps: float = TABLE5_FPS, scale: float = 1.0, **options):
    """Angular random walk with Table 5 stds, restricted to the joint limits (Hauberg eq. 3)."""
    return AngularRandomWalk.from_skeleton(skeleton, fps=fps, scale=scale, **options)


def constant_velocity(
    skeleton, *, fps: float = TABLE5_FPS, scale: float = 1.0, alpha: float = 0.5, **options
):
    """Rius eq. 3 with Table 5 diffusion stds."""
    return ConstantVelocity(table5_sigma(skeleton, fps, scale), alpha=alpha, **options)


def damped(skeleton, *, fps: float = TABLE5_FPS, scale: float = 1.0, kappa: float = 0.8, **options):
    """Brubaker eq. 13 with Table 5 diffusion stds."""
    return DampedSecondOrder(table5_sigma(skeleton, fps, scale), kappa=kappa, **options)


def action(skeleton, *, model, **options):
    """Action-constrained dynamics (Rius eq. 3 + 6) from an action model file (``.npz``) or object."""
    if not isinstance(model, ActionModel):
        model = ActionModel.load(model, dof_names=skeleton.dof_names)
    return ActionConstrained(model, **options)
