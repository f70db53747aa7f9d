"""Learned dynamics: the versioned .npz file, its loader errors, the learned factory, track --dynamics."""

import json

import numpy as np
import pytest
import torch

from priors.diffusion import LearnedDynamics, LearnedDynamicsFormatError
from priors.factories import learned
from priors.motion import AngularRandomWalk, ConstantVelocity
from torchpf import Skeleton
from torchpf.assets import path
from torchpf.distributions import DYNAMICS, make_dynamics


@pytest.fixture(scope="module")
def f22():
    return Skeleton.from_urdf(path("fontmarty22.urdf"))


@pytest.fixture
def registered():
    """``learned`` by name, also where the installed entry points predate it (they need a reinstall)."""
    added = "learned" not in DYNAMICS
    if added:
        DYNAMICS.register("learned", learned)
    yield
    if added:
        DYNAMICS.unregister("learned")


def _stats(f22, fps=60.0):
    D = len(f22.dof_names)
    step = torch.linspace(0.01, 0.05, D, dtype=torch.float64)
    return LearnedDynamics(f22.dof_names, fps, step, 0.6, step / 2, f22.dof_revolute, {"frames": 100})


def test_round_trip_in_any_dof_order(f22, tmp_path):
    stats = _stats(f22)
    stats.save(tmp_path / "dyn.npz")
    back = LearnedDynamics.load(tmp_path / "dyn.npz")
    assert back.dof_names == f22.dof_names and back.fps == 60.0 and back.alpha == 0.6
    torch.testing.assert_close(back.step_std, stats.step_std)
    torch.testing.assert_close(back.cv_std, stats.cv_std)
    assert torch.equal(back.revolute, f22.dof_revolute) and back.info == {"frames": 100}
    order = list(reversed(f22.dof_names))
    flipped = LearnedDynamics.load(tmp_path / "dyn.npz", dof_names=order)
    torch.testing.assert_close(flipped.step_std, stats.step_std.flip(0))


def test_loader_errors_name_the_file(f22, tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        LearnedDynamics.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(LearnedDynamicsFormatError, match="junk.npz: not a readable"):
        LearnedDynamics.load(junk)
    meta = {"format": "torchpf-learned-dynamics", "version": 99, "dof_names": ["a"], "fps": 30, "alpha": 0.5}
    newer = tmp_path / "newer.npz"
    np.savez(newer, metadata=np.array(json.dumps(meta)), step_std=[0.1], cv_std=[0.1], revolute=[True])
    with pytest.raises(LearnedDynamicsFormatError, match="newer.npz: format version 99 is newer"):
        LearnedDynamics.load(newer)
    other = tmp_path / "other.npz"
    np.savez(other, metadata=np.array(json.dumps({**meta, "format": "torchpf-action-model"})))
    with pytest.raises(LearnedDynamicsFormatError, match="other.npz: not a learned-dynamics file"):
        LearnedDynamics.load(other)
    short = tmp_path / "short.npz"
    np.savez(short, metadata=np.array(json.dumps({**meta, "version": 1})), step_std=[0.1])
    with pytest.raises(
        LearnedDynamicsFormatError, match=r"short.npz: missing entries \['cv_std', 'revolute'\]"
    ):
        LearnedDynamics.load(short)
    bad = tmp_path / "bad.npz"
    np.savez(
        bad,
        metadata=np.array(json.dumps({**meta, "version": 1})),
        step_std=[-1.0],
        cv_std=[0.1],
        revolute=[1],
    )
    with pytest.raises(LearnedDynamicsFormatError, match="bad.npz: step_std must be finite and >= 0"):
        LearnedDynamics.load(bad)
    _stats(f22).save(tmp_path / "dyn.npz")
    with pytest.raises(ValueError, match="dyn.npz was learned on other DOFs"):
        LearnedDynamics.load(tmp_path / "dyn.npz", dof_names=["pelvis_tx"])


def test_factory_builds_the_walk_or_rius_prior_and_rescales_the_rate(f22, tmp_path, registered):
    stats = _stats(f22, fps=60.0)
    stats.save(tmp_path / "dyn.npz")
    walk = make_dynamics("learned", f22, path=str(tmp_path / "dyn.npz"))
    assert isinstance(walk, AngularRandomWalk)
    torch.testing.assert_close(walk.sigma, stats.step_std)
    torch.testing.assert_close(walk.lower, f22.lower)
    # tracking at 30 fps: twice the step (steps scale like a speed), alpha with the same time constant
    cv = make_dynamics("learned", f22, path=str(tmp_path / "dyn.npz"), model="constant_velocity", fps=30.0)
    assert isinstance(cv, ConstantVelocity) and cv.alpha == pytest.approx(0.36)
    torch.testing.assert_close(cv.sigma, stats.cv_std * 2)
    torch.testing.assert_close(learned(f22, path=stats, scale=0.5).sigma, stats.step_std / 2)
    with pytest.raises(ValueError, match="model must be"):
        learned(f22, path=stats, model="teleport")


def test_track_takes_a_dynamics_file(f22, tmp_path, registered, capsys):
    from torchpf.__main__ import main
    from torchpf.camera import camera_ring
    from torchpf.sequence import write_sequence
    from torchpf.synth import synthesize

    human = Skeleton.from_urdf(path("human.urdf"))
    angles = human.clamp(torch.zeros(4, len(human.dof_names), dtype=torch.float64))
    cams = camera_ring(2, radius=4.0, width=48, height_px=36, target=(0.0, 0.0, 1.0))
    seq = tmp_path / "seq"
    write_sequence(seq, synthesize(human, angles, cams, fps=15.0))  # a CLI smoke test, not an evaluation
    step = torch.full((len(human.dof_names),), 0.01, dtype=torch.float64)
    LearnedDynamics(human.dof_names, 15.0, step, 0.5, step, human.dof_revolute).save(tmp_path / "dyn.npz")
    argv = ["track", str(seq), "--skeleton", str(path("human.urdf")), "--out", str(tmp_path / "t.csv")]
    argv += ["--filter", "sir", "--particles", "20", "--no-progress"]
    assert main(argv + ["--dynamics", str(tmp_path / "dyn.npz")]) == 0
    assert "tracked 4 frames" in capsys.readouterr().out
    assert main(argv + ["--dynamics", str(tmp_path / "none.npz")]) == 2
    assert "dynamics file not found" in capsys.readouterr().err


def test_per_dof_alpha_round_trips_and_drives_a_constant_velocity(tmp_path):
    from priors.diffusion import LearnedDynamics
    from priors.motion import ConstantVelocity

    names = ["A_Xrotation", "B_Xrotation", "C_Xposition"]
    alpha = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    stats = LearnedDynamics(
        names, 120.0, [0.01, 0.02, 0.001], alpha, [0.01, 0.01, 0.001], [True, True, False]
    )
    stats.save(tmp_path / "d.npz")
    back = LearnedDynamics.load(tmp_path / "d.npz", dof_names=names[::-1])
    torch.testing.assert_close(back.alpha, alpha.flip(0))
    torch.testing.assert_close(stats.at_fps(30.0).alpha, alpha**4)
    cv = ConstantVelocity(stats.cv_std, alpha=stats.alpha)
    x_old, x_new = torch.zeros(1, 3), torch.ones(1, 3)
    v = cv.update_extras(x_new, x_old, {"velocity": torch.zeros(1, 3)})["velocity"]
    torch.testing.assert_close(v, (1 - alpha.float()).unsqueeze(0))
