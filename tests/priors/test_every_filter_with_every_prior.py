"""Every registered filter with every registered motion prior, through ``Tracker`` (what ``track --filter F
--dynamics P`` builds), at a budget that refines only the mean and at an ordinary one: a track of finite
poses within the evaluation budget, or the one clear refusal (quasi-random sampling needs a prior that maps
noise to a sample). The crash it was written for: the hybrid with an action bank at a budget that refines
only the mean (K = 0 best particles)."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchpf.distributions import DYNAMICS
from torchpf.filters.registry import FILTERS
from torchpf.sequence import read_sequence
from torchpf.tracker import Tracker
from training.dynamics import fit_dynamics
from training.synthetic import generate

NO_NOISE_MAP = {"action", "bank"}  # the learned action priors: a discrete action / a projection step


@pytest.fixture(scope="module")
def world(saved_models):
    skel, root = saved_models
    fit_dynamics([generate("walk", 60, 15.0, seed=k) for k in range(2)], skeleton=skel, fps=15.0).save(
        root / "dynamics.npz"
    )
    options = {
        "action": {"model": root / "walk.npz"},
        "bank": {"models": [root / "walk.npz", root / "wave.npz"]},
        "learned": {"path": root / "dynamics.npz"},
    }
    return skel, root / "seq", options


def test_the_matrix_covers_every_registered_name():
    assert {"sir", "qrs", "partitioned", "partitioned_qrs", "apf", "mcmc", "hybrid"} <= set(FILTERS.names())
    assert set(DYNAMICS.names()) <= {
        "random_walk",
        "constant_velocity",
        "damped",
        "action",
        "bank",
        "learned",
    }


@pytest.mark.parametrize("budget", [6, 120])
@pytest.mark.parametrize("dynamics", sorted(DYNAMICS.names()))
@pytest.mark.parametrize("filter_name", sorted(FILTERS.names()))
def test_every_filter_tracks_with_every_motion_prior(world, filter_name, dynamics, budget):
    skel, seq, options = world
    data = read_sequence(seq)

    def build():
        return Tracker(
            skel,
            data.cameras,
            filter=filter_name,
            n_particles=budget,
            fps=15.0,
            progress=False,
            dynamics=dynamics,
            dynamics_options=options.get(dynamics, {}),
            smooth=False,
        )

    if filter_name.endswith("qrs") and dynamics in NO_NOISE_MAP:
        with pytest.raises(ValueError, match="has none: use the Monte Carlo filters"):
            build()
        return
    truth = data.truth_in(skel.dof_names)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tracker = build()
    result = tracker.track(seq, init=truth[0], seed=0)
    assert result.angles.shape == truth.shape
    assert torch.isfinite(result.angles).all()
    # 6 evaluations per frame lose tracks, and the lost-track detector may flag them: flagged, not hidden
    assert result.failed.shape == truth.shape[:1] and result.failed.dtype == torch.bool
    # the budget holds, or the tracker said why not (one HMC particle costs 13 evaluations)
    below = any("more than n_particles" in str(w.message) for w in caught)
    assert result.likelihood_evaluations <= budget or below
