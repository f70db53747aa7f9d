"""ActionBank: the action as a discrete particle state, switching by a transition matrix, and the per-frame
posterior over actions in the track's stats."""

from __future__ import annotations

import pytest
import torch

from priors.bank import ActionBank
from torchpf.filters import ParticleFilter
from torchpf.proposals import GaussianRandomWalk

from .test_action import NAMES, near_mean_poses, tiny_model


def two_models():
    walk = tiny_model(action="walk")
    run = tiny_model(action="run", mean_performance=[[3.0, 0.0], [3.5, 0.1], [4.0, 0.0], [3.5, -0.1]])
    return walk, run


def test_the_posterior_names_the_action_the_poses_belong_to():
    walk, run = two_models()
    bank = ActionBank([walk, run], GaussianRandomWalk(torch.full((len(NAMES),), 0.01, dtype=torch.float64)))
    assert bank.actions == ["walk", "run"]
    torch.testing.assert_close(bank.transition.sum(-1), torch.ones(2, dtype=torch.float64))
    x = near_mean_poses(run, 200, 0.02)

    def likelihood(p, obs):
        return -0.5 * ((p - obs) ** 2).sum(-1) / 0.1**2

    pf = ParticleFilter(bank, likelihood, n_particles=200, progress=False)
    track = pf.run([x[0]] * 4, x.clone(), generator=0)
    post = track.stats["action_posterior"]
    assert post.shape == (4, 2)
    torch.testing.assert_close(post.sum(-1), torch.ones(4, dtype=post.dtype))
    assert (post.argmax(-1) == 1).all() and torch.isfinite(track.estimates).all()
    assert track.final_state.extras["action"].shape == (200,)


def test_a_loose_model_does_not_claim_the_poses_of_a_tight_one():
    """Responsibilities compare normalised densities (ActionModel.log_density): a model fitted loosely (10x
    the spread, like a one-performer model) scores every pose higher on the unnormalised soft prior, yet
    the poses of the tight model's action stay with it, and the loose model keeps its own far poses."""
    tight = tiny_model(action="walk")
    loose = tiny_model(action="run", std=10 * tight.std)
    bank = ActionBank(
        [tight, loose], GaussianRandomWalk(torch.full((len(NAMES),), 0.01, dtype=torch.float64))
    )
    near = near_mean_poses(tight, 100, 0.02)
    assert (loose.soft_accept_probability(near) > tight.soft_accept_probability(near)).all()
    uniform = torch.full((100, 2), 0.5, dtype=torch.float64)
    assert (bank._responsibilities(near, uniform).argmax(-1) == 0).all()
    far = near_mean_poses(tight, 100, 2.0, seed=1)  # 40 sigma of the tight model away, 4 of the loose one
    assert (bank._responsibilities(far, uniform).argmax(-1) == 1).float().mean() > 0.9


def test_switching_follows_the_transition_matrix():
    walk, run = two_models()
    base = GaussianRandomWalk(torch.full((len(NAMES),), 0.01, dtype=torch.float64))
    sticky = ActionBank([walk, run], base, transition=torch.eye(2, dtype=torch.float64))
    x = near_mean_poses(walk, 100, 0.02)
    extras = sticky.init_extras(x)
    assert (extras["action"] == 0).all()
    out = sticky.sample(x, torch.Generator().manual_seed(0), extras=extras)
    new = sticky.update_extras(out, x, extras)
    assert (new["action"] == 0).all()  # an identity transition never leaves the walk
    lp = sticky.log_prob(out, x, extras=extras)
    assert lp.shape == (100,) and torch.isfinite(lp).all()
    with pytest.raises(ValueError, match="sum to 1"):
        ActionBank([walk, run], base, transition=torch.ones(2, 2))
