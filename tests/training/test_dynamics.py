"""training.dynamics and `python -m training fit-dynamics`: step stds and Rius' alpha from mocap CSVs."""

import numpy as np
import pytest
import torch

from priors.diffusion import LearnedDynamics
from torchpf.assets import path
from torchpf.skeleton import Skeleton
from training.__main__ import main
from training.dynamics import fit_dynamics, robust_std
from training.mocap import Motion, load_csv, save_csv

F22 = str(path("fontmarty22.urdf"))


@pytest.fixture(scope="module")
def f22():
    return Skeleton.from_urdf(F22)


def _walk_csvs(f22, folder, true_std, n_files=3, frames=1500, fps=30.0, seed=0):
    """Random-walk CSVs with Gaussian steps of ``true_std`` per frame, columns in a shuffled order."""
    rng = np.random.default_rng(seed)
    order = list(rng.permutation(len(f22.dof_names)))
    names = [f22.dof_names[i] for i in order]
    paths = []
    for k in range(n_files):
        steps = rng.normal(size=(frames, len(names))) * true_std[order]
        angles = np.cumsum(steps, 0)  # wanders past ±π in places: unwrapped before the steps are taken
        p = folder / f"walk{k}.csv"
        save_csv(p, Motion(names, fps, torch.from_numpy(angles), name=f"walk{k}"))
        paths.append(str(p))
    return paths


def _motions(csvs, f22):
    return [load_csv(p, dof_names=f22.dof_names) for p in csvs]


def test_step_stds_are_recovered_from_a_random_walk(f22, tmp_path, capsys):
    true_std = np.linspace(0.005, 0.2, len(f22.dof_names))
    csvs = _walk_csvs(f22, tmp_path, true_std)
    out = tmp_path / "dyn.npz"
    assert main(["fit-dynamics", *csvs, "--skeleton", F22, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}: 22 DOFs from 3 files (4500 frames) at 30 fps" in printed
    assert "random_walk stds (learned, 30 fps, per frame): root" in printed
    stats = LearnedDynamics.load(out, dof_names=f22.dof_names)
    np.testing.assert_allclose(stats.step_std.numpy(), true_std, rtol=0.1)
    assert stats.info["performances"] == ["walk0", "walk1", "walk2"]
    # resampled to 10 fps (every third frame): a random walk's step std grows as sqrt(3)
    slow = fit_dynamics(_motions(csvs, f22), skeleton=f22, fps=10.0)
    np.testing.assert_allclose(slow.step_std.numpy(), true_std * np.sqrt(3), rtol=0.1)


def test_alpha_is_recovered_from_a_constant_velocity_process(f22):
    # Rius eq. 3 run forwards: step = V + e, V <- alpha V + (1 - alpha) step; the innovations e are the
    # prediction errors, so the fitted alpha is the true one and cv_std the std of e
    rng = np.random.default_rng(1)
    D = len(f22.dof_names)
    alpha, noise = np.where(np.arange(D) % 2 == 0, 0.7, 0.3), 0.01  # Rius §3.1 per DOF: two kinds of DOF
    motions = []
    for k in range(2):
        v, angle, rows = np.zeros(D), np.zeros(D), []
        for _ in range(2000):
            step = v + noise * rng.normal(size=D)
            v = alpha * v + (1 - alpha) * step
            angle = angle + step
            rows.append(angle)
        motions.append(Motion(f22.dof_names, 60.0, torch.from_numpy(np.array(rows)), name=f"cv{k}"))
    stats = fit_dynamics(motions, skeleton=f22)
    assert stats.alpha.shape == (D,) and stats.fps == 60.0
    np.testing.assert_allclose(stats.alpha.numpy(), alpha, atol=0.06)
    np.testing.assert_allclose(stats.cv_std.numpy(), noise, rtol=0.1)
    assert fit_dynamics(motions, skeleton=f22, alpha=0.2).alpha == 0.2
    pooled = fit_dynamics(motions, skeleton=f22, per_dof=False).alpha  # one α between the two kinds
    assert isinstance(pooled, float) and 0.3 < pooled < 0.7


def test_robust_std_ignores_glitches():
    x = np.random.default_rng(2).normal(size=(20000, 1)) * 0.1
    x[::50] = 6.0  # an Euler flip every 50 frames
    assert robust_std(x)[0] == pytest.approx(0.1, rel=0.05)
    assert x.std() > 0.8


def test_errors_are_one_line(f22, tmp_path, capsys):
    csvs = _walk_csvs(f22, tmp_path, np.full(22, 0.01), n_files=1, frames=20)
    assert main(["fit-dynamics", *csvs, "--skeleton", F22, "--out", str(tmp_path / "dyn.txt")]) == 2
    assert "--out must name a .npz file" in capsys.readouterr().err
    human = str(path("human.urdf"))
    assert main(["fit-dynamics", *csvs, "--skeleton", human, "--out", str(tmp_path / "d.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "walk0.csv" in err[0]
    missing = str(tmp_path / "none.csv")
    assert main(["fit-dynamics", missing, "--skeleton", F22, "--out", str(tmp_path / "d.npz")]) == 2
    assert "none.csv" in capsys.readouterr().err
    with pytest.raises(ValueError, match="fewer than 3 frames"):
        fit_dynamics(_motions(csvs, f22), skeleton=f22, fps=0.5)
