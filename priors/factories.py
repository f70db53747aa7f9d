"""Motion priors by name, for ``torchpf.Tracker(dynamics="...")`` and ``python -m torchpf track``.

torchpf never imports this package; it finds these factories through the ``torchpf.dynamics`` entry-point
group declared in ``pyproject.toml``. Each factory is ``factory(skeleton, **options) -> dynamics``.

* ``random_walk``: angular random walk (Hauberg eq. 3, Fontmarty §3.1) restricted to the joint limits, with
  per-DOF stds from the kinematic structure (``stds="structural"``, :mod:`priors.diffusion`: the std that
  moves the farthest capsule point a DOF drives by a measured speed / fps; no joint names read), or
  ``stds="table5"`` (Fontmarty Table 5 by joint names, :mod:`priors.table5`), or explicit ``(D,)`` values.
* ``constant_velocity``: Rius eq. 3 (:class:`priors.motion.ConstantVelocity`), diffusion as ``random_walk``.
* ``damped``: Brubaker eq. 13 (:class:`priors.motion.DampedSecondOrder`), diffusion as ``random_walk``.
* ``action``: the action-constrained dynamics of Rius eq. 6 from a saved action model (``model=path``),
  constraining the structural random walk (``base="rius"``: the model's constant velocity, eq. 3);
  ``name_map=FILE`` renames the model's DOFs for a skeleton that names them differently.
* ``bank``: several saved action models at once (``models=[walk.npz, run.npz]``,
  :class:`priors.bank.ActionBank`): the action is a discrete state of each particle.
* ``learned``: stds (and α) learned from mocap by ``python -m training fit-dynamics`` (``path=dyn.npz``,
  :class:`priors.diffusion.LearnedDynamics`): a random walk, or Rius eq. 3 with ``model="constant_velocity"``.

The diffusion factories log a one-line summary of their stds per body part to the ``priors`` logger (INFO)
and warn when they guess (no ``fps``, Table 5 names that would hold a moving DOF still).

Example::

    from torchpf import Tracker
    tracker = Tracker(skel, cams, dynamics="random_walk", fps=15.0, dynamics_options={"scale": 0.5})
    tracker = Tracker(skel, cams, dynamics="learned", fps=15.0, dynamics_options={"path": "dyn.npz"})
"""

from __future__ import annotations

import os

from priors.action import ActionConstrained, ActionModel, read_name_map
from priors.bank import ActionBank
from priors.diffusion import LearnedDynamics, diffusion_sigma
from priors.motion import AngularRandomWalk, ConstantVelocity, DampedSecondOrder

__all__ = ["action", "bank", "constant_velocity", "damped", "learned", "random_walk"]


def random_walk(skeleton, *, stds="structural", fps: float | None = None, scale: float = 1.0, **options):
    """Angular random walk restricted to the joint limits (Hauberg eq. 3); ``stds``: ``"structural"``
    (default), ``"table5"`` or ``(D,)`` values, per frame at ``fps`` (see
    :func:`priors.diffusion.diffusion_sigma`)."""
    return AngularRandomWalk.from_skeleton(skeleton, stds, fps=fps, scale=scale, **options)


def constant_velocity(
    skeleton,
    *,
    stds="structural",
    fps: float | None = None,
    scale: float = 1.0,
    alpha: float = 0.5,
    **options,
):
    """Rius eq. 3 with diffusion stds as :func:`random_walk`'s."""
    sigma = diffusion_sigma(skeleton, stds, fps=fps, scale=scale, name="constant_velocity")
    return ConstantVelocity(sigma, alpha=alpha, **options)


def damped(
    skeleton,
    *,
    stds="structural",
    fps: float | None = None,
    scale: float = 1.0,
    kappa: float = 0.8,
    **options,
):
    """Brubaker eq. 13 with diffusion stds as :func:`random_walk`'s."""
    sigma = diffusion_sigma(skeleton, stds, fps=fps, scale=scale, name="damped")
    return DampedSecondOrder(sigma, kappa=kappa, **options)


def _model_for(skeleton, model, name_map=None) -> ActionModel:
    """``model`` (an ``.npz`` path or an :class:`ActionModel`) renamed by ``name_map`` and put in the
    skeleton's DOF order; an error names the file."""
    source = model
    if not isinstance(model, ActionModel):
        model = ActionModel.load(model)
    if name_map is not None:
        model = model.renamed(
            read_name_map(name_map) if isinstance(name_map, str | os.PathLike) else name_map
        )
    try:
        return model.for_dof_names(skeleton.dof_names)
    except ValueError as e:
        raise ValueError(f"{source}: {e}" if not isinstance(source, ActionModel) else str(e)) from None


def action(
    skeleton,
    *,
    model,
    fps: float | None = None,
    base: str = "random_walk",
    stds="structural",
    scale: float = 1.0,
    name_map=None,
    **options,
):
    """Action-constrained dynamics (Rius eq. 6) from an action model file (``.npz``) or object.

    Args:
        skeleton: the tracked skeleton (the model is put in its DOF order; joint types checked).
        model: the ``.npz`` file or an :class:`ActionModel`.
        fps: tracking frame rate; the model's σ_φ and α are rescaled to it (:meth:`ActionModel.at_fps`).
        base: the dynamics eq. 6 constrains, which is also what a frame the model rejects falls back to:
            ``"random_walk"`` (default: :func:`random_walk` with ``stds`` and ``scale``, what the tracker
            uses without a prior, so the prior is never worse than none) or ``"rius"`` (eq. 3, the model's
            constant velocity with its σ_φ and α, as in the paper).
        name_map: where the skeleton names the model's DOFs differently: a name map file
            (:func:`priors.action.read_name_map`) or a dict ``{model DOF name: skeleton DOF name}``.
        **options: :class:`ActionConstrained` keywords (``max_tries``, ``min_accept``, ``alpha``, ...).

    Raises:
        ValueError: the model's DOFs (after ``name_map``) are not the skeleton's; lists the unmatched ones.
    """
    model = _model_for(skeleton, model, name_map)
    if base == "random_walk":
        options["dynamics"] = random_walk(skeleton, stds=stds, fps=fps, scale=scale)
    elif base == "rius":
        options.setdefault("sigma_scale", scale)
    else:
        raise ValueError(f"base must be 'random_walk' or 'rius', got {base!r}")
    return ActionConstrained(model, skeleton=skeleton, fps=fps, **options)


def bank(
    skeleton,
    *,
    models,
    fps: float | None = None,
    stds="structural",
    scale: float = 1.0,
    name_map=None,
    **options,
):
    """A bank of action models (:class:`priors.bank.ActionBank`): each particle carries which action it
    performs, switched by a Markov chain, and is predicted by that action's constraint on the structural
    random walk (Rius eq. 6 per action); the hybrid filter's refinement moves a pose in the aSpace of its
    likeliest action. ``result.stats["action_posterior"]`` names the action per frame.

    Args:
        skeleton: the tracked skeleton (each model is put in its DOF order; joint types checked).
        models: ``.npz`` files of ``python -m training fit`` (one per action, e.g. a walk and a run) or
            :class:`ActionModel` objects; at least one.
        fps: tracking frame rate (the models are rescaled to it).
        stds, scale: the random walk's, as :func:`random_walk` (also what a frame every model rejects uses).
        name_map: as :func:`action`, applied to every model.
        **options: :class:`~priors.bank.ActionBank` keywords (``switch``, ``transition``,
            ``manifold_radius``, ``mode``, ...).

    Measured on the foreign renders of 11 CMU clips, walk and run models learned from the *other*
    performers' clips (BENCHMARKS.md, "A learned prior"): noisy masks 56.5 mm against 66.9 for the random
    walk (two draws); with joint limits learned from the same clips, 47.1 against 67.5 (ten draws), clean
    25.2 against 27.1. A model learned from one clip of one performer can mislead: with a run model from
    one run of performer 16, 35_24 failed 19 % of its clean frames (none without a bank); without that
    model, 46.9 mm noisy and 23.6 mm clean with 0.5 % of frames failed. Give each action two performances
    or more (``training fit`` refuses one unless ``--components`` is given).
    """
    if isinstance(models, str | os.PathLike | ActionModel):
        models = [models]
    models = [_model_for(skeleton, m, name_map) for m in models]
    if not models:
        raise ValueError("bank: give at least one action model (models=[walk.npz, run.npz])")
    walk = random_walk(skeleton, stds=stds, fps=fps, scale=scale)
    return ActionBank(models, walk, fps=fps, skeleton=skeleton, **options)


def learned(
    skeleton,
    *,
    path,
    model: str = "random_walk",
    fps: float | None = None,
    scale: float = 1.0,
    **options,
):
    """Dynamics learned from mocap by ``python -m training fit-dynamics`` (a :class:`LearnedDynamics` file).

    Args:
        skeleton: the tracked skeleton; the file must have its DOF names (any order).
        path: the ``.npz`` file, or a :class:`~priors.diffusion.LearnedDynamics`.
        model: ``"random_walk"`` (the learned step stds in :class:`AngularRandomWalk`, within the joint
            limits) or ``"constant_velocity"`` (Rius eq. 3 with the learned α and prediction-error stds).
        fps: tracking frame rate; statistics fitted at another rate are rescaled
            (:meth:`LearnedDynamics.at_fps`). ``None``: the file's rate.
        scale: multiplies the stds.
        **options: passed to the dynamics class (``limits``, ``max_tries``; ``dt``).
    """
    stats = path if isinstance(path, LearnedDynamics) else LearnedDynamics.load(path, skeleton.dof_names)
    stats = stats.select(skeleton.dof_names)
    stats = stats.at_fps(stats.fps if fps is None else fps)
    if model == "random_walk":
        sigma = diffusion_sigma(
            skeleton, stats.step_std, fps=stats.fps, scale=scale, name="learned random_walk"
        )
        return AngularRandomWalk(sigma, skeleton.lower, skeleton.upper, **options)
    if model == "constant_velocity":
        sigma = diffusion_sigma(
            skeleton, stats.cv_std, fps=stats.fps, scale=scale, name="learned constant_velocity"
        )
        return ConstantVelocity(sigma, alpha=stats.alpha, **options)
    raise ValueError(f"model must be 'random_walk' or 'constant_velocity', got {model!r}")
