"""`python -m torchpf track` / `evaluate` on a small synthetic sequence directory."""

import subprocess
import sys

import pytest
import torch

from torchpf import Skeleton
from torchpf.__main__ import main
from torchpf.assets import path
from torchpf.io import read_mocap_csv, write_mocap_csv

from ._sequences import write_wave_sequence


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    """The 8-frame version of the shared fixture (tests/torchpf/conftest.py)."""
    return write_wave_sequence(tmp_path_factory.mktemp("cli") / "seq", 8)


def test_track_then_evaluate(seq_dir, tmp_path, capsys):
    out = tmp_path / "track.csv"
    args = [
        "track",
        str(seq_dir),
        "--skeleton",
        str(path("human.urdf")),
        "--out",
        str(out),
        "--filter",
        "sir",
        "--particles",
        "120",
        "--dynamics",
        "constant_velocity",
        "--likelihood",
        "silhouette=1",
        "--likelihood",
        "dual_silhouette=0.5",
        "--no-progress",
        "--seed",
        "1",
    ]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "tracked 8 frames with sir" in printed and "RMSE" in printed
    assert "have no limits" not in printed  # the shipped body has joint limits
    skel = Skeleton.from_urdf(path("human.urdf"))
    names, times, values = read_mocap_csv(out, expected_dof_names=skel.dof_names)
    assert values.shape == (8, 96) and times[1] == pytest.approx(1 / 15)

    # two "runs": the track and the truth itself (zero error); dispersion is half their distance
    assert (
        main(
            [
                "evaluate",
                str(out),
                str(seq_dir / "truth.csv"),
                "--truth",
                str(seq_dir / "truth.csv"),
                "--skeleton",
                str(path("human.urdf")),
            ]
        )
        == 0
    )
    table = capsys.readouterr().out
    assert "2 run(s), 8 frames, 38 joints" in table
    for key in ("rmse", "bias", "dispersion", "failure_rate", "mpjpe", "angle_mse"):
        assert f"| {key} |" in table


def test_errors_are_one_line(seq_dir, tmp_path, capsys):
    urdf = str(path("human.urdf"))
    assert (
        main(["track", str(tmp_path / "nowhere"), "--skeleton", urdf, "--out", str(tmp_path / "t.csv")]) == 2
    )
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "sequence directory not found" in err
    bad = tmp_path / "bad.csv"
    write_mocap_csv(bad, ["a", "b"], torch.zeros(3, 2))
    assert main(["evaluate", str(bad), "--truth", str(seq_dir / "truth.csv"), "--skeleton", urdf]) == 2
    err = capsys.readouterr().err.strip()
    assert "bad.csv" in err and err.count("\n") == 0
    assert (
        main(
            [
                "track",
                str(seq_dir),
                "--skeleton",
                urdf,
                "--out",
                str(tmp_path / "t.csv"),
                "--likelihood",
                "silhouette=heavy",
            ]
        )
        == 2
    )
    assert "weight must be a number" in capsys.readouterr().err
    for bad_temperature in ("warm", "-1", "inf"):
        track = ["track", str(seq_dir), "--skeleton", urdf, "--out", str(tmp_path / "t.csv")]
        assert main([*track, "--temperature", bad_temperature]) == 2
        assert "--temperature" in capsys.readouterr().err


def _rejects(track: list[str], option: str, values, capsys) -> None:
    """Each of ``values`` given to ``option`` is a one-line error (exit 2) that names the option."""
    for bad in values:
        assert main([*track, option, bad]) == 2
        err = capsys.readouterr().err
        assert option in err and err.strip().count("\n") == 0


def test_track_torso_limit_option(seq_dir, tmp_path, capsys, monkeypatch):
    import torchpf.tracker as tracker_module

    track = ["track", str(seq_dir), "--skeleton", str(path("human.urdf")), "--out", str(tmp_path / "t.csv")]
    _rejects(track, "--torso-limit", ("wide", "0", "-0.5", "inf"), capsys)
    seen = []
    real = tracker_module.Tracker.from_config.__func__
    monkeypatch.setattr(
        tracker_module.Tracker,
        "from_config",
        classmethod(lambda cls, cfg, **kw: seen.append(dict(cfg)) or real(cls, cfg, **kw)),
    )
    quick = ["--filter", "sir", "--particles", "30", "--no-progress"]
    for given, expected in (("none", None), ("0.3", 0.3)):
        assert main([*track, *quick, "--torso-limit", given]) == 0
        assert seen[-1]["torso_limit"] == expected
    assert main([*track, *quick]) == 0
    assert "torso_limit" not in seen[-1]  # the Tracker's default


def test_track_hold_thin_arms_option(seq_dir, tmp_path, capsys, monkeypatch):
    """``--hold-thin-arms PX`` sets the tracker's attribute (the body fits'), ``none`` turns it off, no
    option leaves the default (2 px); a word or a non-positive number is a one-line error naming the
    option."""
    import torchpf.tracker as tracker_module

    track = ["track", str(seq_dir), "--skeleton", str(path("human.urdf")), "--out", str(tmp_path / "t.csv")]
    _rejects(track, "--hold-thin-arms", ("thin", "0", "-2", "inf"), capsys)
    seen = []
    real = tracker_module.Tracker.track
    monkeypatch.setattr(
        tracker_module.Tracker,
        "track",
        lambda self, *a, **kw: seen.append(self.hold_thin_arms) or real(self, *a, **kw),
    )
    quick = ["--filter", "sir", "--particles", "30", "--no-progress"]
    for given, expected in (("none", None), ("2", 2.0), ("1.5", 1.5)):
        assert main([*track, *quick, "--hold-thin-arms", given]) == 0
        assert seen[-1] == expected
    assert main([*track, *quick]) == 0
    assert seen[-1] == 2.0


def test_track_with_auto_temperature(seq_dir, tmp_path, capsys):
    out = tmp_path / "auto.csv"
    urdf = str(path("human.urdf"))
    args = [
        "track",
        str(seq_dir),
        "--skeleton",
        urdf,
        "--out",
        str(out),
        "--filter",
        "sir",
        "--particles",
        "60",
    ]
    assert main([*args, "--temperature", "auto", "--no-progress"]) == 0
    names, values, _ = read_mocap_csv(out)
    assert values.shape[0] == 8 and torch.isfinite(torch.as_tensor(values)).all()


def test_track_with_boundary_offset(seq_dir, tmp_path, monkeypatch):
    import torchpf.tracker as tracker_module

    seen = []
    measure = tracker_module._with_outline_offset
    monkeypatch.setattr(tracker_module, "_with_outline_offset", lambda *a: seen.append(1) or measure(*a))
    out = tmp_path / "offset.csv"
    args = ["track", str(seq_dir), "--skeleton", str(path("human.urdf")), "--out", str(out)]
    assert main([*args, "--filter", "sir", "--particles", "60", "--boundary-offset", "--no-progress"]) == 0
    assert len(seen) == 8  # measured before every frame
    assert torch.isfinite(torch.as_tensor(read_mocap_csv(out)[1])).all()


def test_track_reports_frames_without_evidence(seq_dir, tmp_path, capsys):
    import shutil

    import cv2
    import numpy as np

    root = tmp_path / "seq"
    shutil.copytree(seq_dir, root)
    urdf = str(path("human.urdf"))
    track = ["track", str(root), "--skeleton", urdf, "--filter", "sir", "--particles", "40", "--no-progress"]
    assert main([*track, "--out", str(tmp_path)]) == 2  # refused before any work
    assert "is a directory" in capsys.readouterr().err
    for cam in ("cam0", "cam1"):
        for t in (2, 3):
            f = root / "masks" / cam / f"{t:06d}.png"
            cv2.imwrite(str(f), np.zeros(cv2.imread(str(f)).shape[:2], np.uint8))
    assert main([*track, "--out", str(tmp_path / "t.csv")]) == 0
    printed = capsys.readouterr().out
    assert "0 failed frames, 2 frames without evidence" in printed and "evidence" in printed.splitlines()[1]
    assert "2-3" in printed.splitlines()[1]
    for f in (root / "masks").rglob("*.png"):
        cv2.imwrite(str(f), np.zeros(cv2.imread(str(f)).shape[:2], np.uint8))
    assert main([*track, "--out", str(tmp_path / "u.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert "no frame has evidence" in err and err.count("\n") == 0 and not (tmp_path / "u.csv").exists()


def test_module_entry_point_help():
    res = subprocess.run([sys.executable, "-m", "torchpf", "track", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "--particles" in res.stdout


def test_track_smooths_unless_told_not_to(seq_dir, tmp_path, capsys):
    """The default writes the smoothed track; ``--no-smooth`` the filter's own estimates (the tracker's test
    checks that these are the smoothed run's ``filtered_angles``)."""
    args = ["track", str(seq_dir), "--skeleton", str(path("human.urdf")), "--filter", "sir"]
    args += ["--particles", "60", "--no-progress", "--seed", "2"]
    smoothed, filtered = tmp_path / "smoothed.csv", tmp_path / "filtered.csv"
    assert main([*args, "--out", str(smoothed)]) == 0
    assert "(smoothed; --no-smooth" in capsys.readouterr().out
    assert main([*args, "--out", str(filtered), "--no-smooth"]) == 0
    assert "smoothed" not in capsys.readouterr().out
    a = torch.as_tensor(read_mocap_csv(smoothed)[2])
    b = torch.as_tensor(read_mocap_csv(filtered)[2])
    assert a.shape == b.shape == (8, 96) and torch.isfinite(a).all()
    assert float((a - b).abs().max()) > 1e-4  # the smoother moved the track


def test_track_says_when_the_skeleton_has_no_joint_limits(seq_dir, tmp_path, capsys):
    """A skeleton without limits (what a BVH converts to) gets a one-line note on fit-limits."""
    import math

    human = Skeleton.from_urdf(path("human.urdf"))
    free = torch.where(human.posture_dofs, 2 * math.pi, torch.nan)
    unlimited = human.with_limits(-free, free)
    assert len(unlimited.free_rotations()) == int(human.posture_dofs.sum()) and not human.free_rotations()
    urdf = tmp_path / "unlimited.urdf"
    unlimited.save_urdf(urdf)
    out = tmp_path / "track.csv"
    args = ["track", str(seq_dir), "--skeleton", str(urdf), "--out", str(out), "--filter", "sir"]
    assert main([*args, "--particles", "30", "--no-smooth", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "have no limits" in printed and "python -m training fit-limits" in printed
    assert f"note: {int(human.posture_dofs.sum())} joint rotations" in printed
    # with --torso-limit the 18 torso rotations get limits (torchpf.kinematics.anatomy): the rest are counted
    assert main([*args, "--particles", "30", "--no-smooth", "--no-progress", "--torso-limit", "0.5"]) == 0
    assert f"note: {int(human.posture_dofs.sum()) - 18} joint rotations" in capsys.readouterr().out
