"""``python -m training fit`` and ``inspect``: models that load back for the skeleton, plots, errors."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from priors.action import ActionModel
from torchpf.assets import path as asset_path
from torchpf.skeleton import Skeleton
from training.__main__ import main
from training.mocap import Motion, save_csv
from training.synthetic import generate_dataset

HUMAN = str(asset_path("human.urdf"))


@pytest.fixture(scope="module")
def walk_csvs(tmp_path_factory):
    out = tmp_path_factory.mktemp("walk")
    return [str(p) for p in generate_dataset(out, action="walk", n_performers=3, seconds=3.0, seed=0)]


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert err, "no error message"
    return err[-1]


def test_fit_then_inspect(walk_csvs, tmp_path, capsys):
    out = tmp_path / "walk.npz"
    argv = ["fit", "--action", "walk", "--skeleton", HUMAN, "--out", str(out), "--components", "5", "--quiet"]
    assert main(argv + walk_csvs) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed and "from 3 performances" in printed and "D=5" in printed
    model = ActionModel.load(out, dof_names=Skeleton.from_urdf(HUMAN).dof_names)
    assert model.action == "walk" and model.n_components == 5 and model.cyclic
    assert model.training_data["info"]["performances"] == ["walk_00", "walk_01", "walk_02"]

    assert main(["inspect", str(out), "--out", str(tmp_path / "plots")]) == 0
    printed = capsys.readouterr().out
    assert "action model 'walk': cyclic" in printed
    for name in ("synchronisation.png", "explained_variance.png"):
        png = tmp_path / "plots" / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_fit_options_reach_the_fitter(walk_csvs, tmp_path, capsys):
    out = tmp_path / "walk.npz"
    argv = ["fit", "--action", "walk", "--out", str(out), "--components", "0.9", "--fps", "15"]
    argv += [
        "--no-exclude-root",
        "--exclude",
        "Hips_.position",
        "--alpha",
        "0.5",
        "--n-sigma",
        "3",
        "--quiet",
    ]
    assert main(argv + walk_csvs) == 0
    model = ActionModel.load(out)
    assert model.fps == 15 and (model.alpha == 0.5).all() and model.n_sigma == 3
    assert "Hips_Zrotation" in model.posture_dofs and "Hips_Xposition" not in model.posture_dofs
    assert "LeftHand_Xrotation" in model.posture_dofs  # --exclude replaced the default hand patterns


def test_fit_errors_are_one_line_with_status_2(walk_csvs, tmp_path, capsys):
    out = str(tmp_path / "m.npz")
    base = ["fit", "--action", "walk", "--out", out, "--quiet"]

    assert main(base + [str(tmp_path / "missing.csv")]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("python -m training fit: error:") and "missing.csv" in line

    other = tmp_path / "other.csv"
    save_csv(other, Motion(["A_Xrotation", "B_Xrotation"], 30.0, torch.zeros(10, 2)))
    assert main(base + ["--skeleton", HUMAN, str(other)]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("python -m training fit: error:") and "other.csv" in line

    assert main(["fit", "--action", "walk", "--out", str(tmp_path / "m.txt"), "--quiet", *walk_csvs]) == 2
    assert ".npz" in _one_error_line(capsys)

    with pytest.raises(SystemExit) as e:
        main(base + ["--components", "1.5", *walk_csvs])
    assert e.value.code == 2 and "--components" in _one_error_line(capsys)
    assert not (tmp_path / "m.npz").exists()

    # one performance cannot be validated: the error says which file and what to give instead
    assert main(base + walk_csvs[:1]) == 2
    line = _one_error_line(capsys)
    assert "--components D" in line and walk_csvs[0] in line and not (tmp_path / "m.npz").exists()
    assert main(base + ["--components", "3", *walk_csvs[:1]]) == 0 and (tmp_path / "m.npz").exists()


def test_inspect_errors_are_one_line_with_status_2(tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    bad.write_text("not a model")
    assert main(["inspect", str(bad), "--out", str(tmp_path)]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("python -m training inspect: error:") and "bad.npz" in line
    assert main(["inspect", str(tmp_path / "none.npz"), "--out", str(tmp_path)]) == 2
    assert "none.npz" in _one_error_line(capsys)


def test_help_lists_the_commands():
    run = subprocess.run(
        [sys.executable, "-m", "training", "--help"], capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 0
    for command in ("convert", "fit", "inspect"):
        assert command in run.stdout


def test_fit_chooses_components_by_validation_and_inspect_prints_the_curve(walk_csvs, tmp_path, capsys):
    out = tmp_path / "walk.npz"
    assert (
        main(["fit", "--action", "walk", "--skeleton", HUMAN, "--out", str(out), "--quiet", *walk_csvs]) == 0
    )
    printed = capsys.readouterr().out
    assert "leave-one-performer-out acceptance" in printed and "chosen D=" in printed
    model = ActionModel.load(out)
    chosen = model.training_data["info"]["validation"]["chosen"]
    assert model.n_components == chosen and f"chosen D={chosen}," in printed
    assert main(["inspect", str(out), "--out", str(tmp_path / "plots")]) == 0
    assert f"chosen D={chosen}," in capsys.readouterr().out
