"""A bank of saved action models by name (``dynamics="bank"``) and from ``track --action A --action B``."""

from __future__ import annotations

import pytest
import torch

from priors.bank import ActionBank
from priors.factories import bank
from torchpf.__main__ import main
from torchpf.assets import path
from torchpf.distributions import make_dynamics
from training.synthetic import generate

HUMAN = str(path("human.urdf"))


def test_the_bank_factory_loads_each_model_in_the_skeleton_order(saved_models):
    skel, root = saved_models
    dyn = make_dynamics(
        "bank", skel, fps=15.0, models=[root / "walk.npz", str(root / "wave.npz")], switch=0.1
    )
    assert isinstance(dyn, ActionBank) and dyn.actions == ["walk", "wave"]
    assert all(c.model.dof_names == skel.dof_names for c in dyn.constrained)
    torch.testing.assert_close(dyn.transition, torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float64))
    # a walk's postures belong to the walk model: the responsibilities of the bank say so
    walk = generate("walk", 20, 15.0, seed=11).angles.to(torch.float64)
    prob = dyn.init_extras(walk)["action_prob"]
    assert (prob.argmax(-1) == 0).float().mean() > 0.9
    with pytest.raises(ValueError, match="at least one action model"):
        bank(skel, models=[], fps=15.0)
    with pytest.raises(FileNotFoundError, match=r"nope\.npz"):
        bank(skel, models=[root / "walk.npz", root / "nope.npz"], fps=15.0)


def test_track_cli_makes_a_bank_of_repeated_actions_and_names_the_action_per_frame(
    saved_models, tmp_path, capsys
):
    _, root = saved_models
    track = [
        "track", str(root / "seq"), "--skeleton", HUMAN, "--action", str(root / "walk.npz"),
        "--action", str(root / "wave.npz"), "--filter", "sir", "--particles", "60", "--no-progress",
    ]  # fmt: skip
    assert main([*track, "--out", str(tmp_path / "a.csv")]) == 0
    out = capsys.readouterr().out
    assert "tracked 6 frames" in out and (tmp_path / "a.csv").exists()
    assert "actions: walk on frames 0-5" in out
    missing = [str(tmp_path / "missing.npz") if t.endswith("wave.npz") else t for t in track]
    assert main([*missing, "--out", str(tmp_path / "b.csv")]) == 2
    assert "missing.npz" in capsys.readouterr().err and not (tmp_path / "b.csv").exists()


def test_a_tracker_with_the_bank_runs_on_the_particles_device(saved_models, device):
    """The default (hybrid) tracker with ``dynamics="bank"`` tracks on ``device``: the models' buffers and
    the action state follow the particles (one device rule); the walk is recognised on every frame."""
    from torchpf.sequence import read_sequence
    from torchpf.tracker import Tracker

    skel, root = saved_models
    data = read_sequence(root / "seq")
    tracker = Tracker(
        skel,
        data.cameras,
        n_particles=60,
        fps=15.0,
        progress=False,
        device=device,
        dynamics="bank",
        dynamics_options={"models": [root / "walk.npz", root / "wave.npz"]},
    )
    result = tracker.track(root / "seq", init=data.truth_in(skel.dof_names)[0], seed=0)
    assert torch.isfinite(result.angles).all() and result.angles.shape[0] == 6
    posterior = result.stats["action_posterior"]
    assert posterior.shape == (6, 2) and bool((posterior.argmax(-1) == 0).all())
