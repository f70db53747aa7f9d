"""``python -m training convert``: outputs that load back into the same skeleton and motion; errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchpf.skeleton import Skeleton
from training.__main__ import main
from training.mocap import CMU_SCALE, load_bvh, load_csv

REPO = Path(__file__).resolve().parents[2]
CMU_CLIP = REPO.parent / "shared" / "mocap" / "cmu" / "16_46.bvh"

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 1 2 3
  CHANNELS 6 Xposition Yposition Zposition Yrotation Xrotation Zrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 3 Xrotation Zrotation Yrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.04
0 90 0 10 20 30 40 50 60
1 91 0 11 21 31 41 51 61
2 92 0 12 22 32 42 52 62
"""


def _check_outputs(bvh: Path, out: Path, scale: float):
    skel, motion = load_bvh(bvh, scale)
    disk = Skeleton.from_urdf(out / "skeleton.urdf")
    back = load_csv(out / f"{bvh.stem}.csv", dof_names=disk.dof_names)
    assert disk.dof_names == skel.dof_names and disk.joint_names == skel.joint_names
    assert torch.equal(back.angles, motion.angles)
    assert back.fps == pytest.approx(motion.fps, rel=1e-9)
    torch.testing.assert_close(disk.fk(back.angles), skel.fk(motion.angles), rtol=0, atol=1e-12)


def test_convert_small_file(tmp_path, capsys):
    bvh = tmp_path / "walk.bvh"
    bvh.write_text(SMALL)
    assert main(["convert", str(bvh), "--scale", "0.01", "--out-dir", str(tmp_path / "out")]) == 0
    assert "3 frames at 25 fps" in capsys.readouterr().out
    _check_outputs(bvh, tmp_path / "out", 0.01)
    header = (tmp_path / "out" / "walk.csv").read_text().splitlines()[0]
    assert header.startswith("time,Hips_Xposition,Hips_Yposition,Hips_Zposition,Hips_Yrotation")


@pytest.mark.skipif(not CMU_CLIP.exists(), reason=f"CMU clip not found: {CMU_CLIP}")
def test_convert_cmu_clip(tmp_path, capsys):
    assert main(["convert", str(CMU_CLIP), "--scale", str(CMU_SCALE), "--out-dir", str(tmp_path)]) == 0
    _check_outputs(CMU_CLIP, tmp_path, CMU_SCALE)
    out = capsys.readouterr().out
    assert "20 rotation channels never move in this file" in out and "--hold-static holds them" in out
    disk = Skeleton.from_urdf(tmp_path / "skeleton.urdf")
    assert not bool((disk.lower == disk.upper).any())  # every channel free, as in the file
    # --hold-static: those channels held at their value
    argv = ["convert", str(CMU_CLIP), "--scale", str(CMU_SCALE), "--out-dir", str(tmp_path), "--hold-static"]
    assert main(argv) == 0
    assert "held at their values" in capsys.readouterr().out
    disk = Skeleton.from_urdf(tmp_path / "skeleton.urdf")
    held = disk.lower == disk.upper
    assert int(held.sum()) == 20 and disk.dof_names[int(held.nonzero()[0])] == "LHipJoint_Zrotation"


@pytest.mark.parametrize(
    ("content", "args", "words"),
    [
        (None, [], "No such file or directory"),
        (
            SMALL.replace("0 90 0 10 20 30 40 50 60", "0 90 0 10 20 30 40 50"),
            [],
            "walk.bvh:19: expected 9 numbers",
        ),
        (
            SMALL.replace("Xrotation Zrotation Yrotation", "Xrotation Zrotation Qrotation"),
            [],
            "unknown channel",
        ),
        (SMALL.replace("2 92 0", "2 nan 0"), [], "walk.bvh:21: column 2 ('Hips_Yposition')"),
    ],
)
def test_convert_errors_are_one_line_exit_2(tmp_path, capsys, content, args, words):
    bvh = tmp_path / "walk.bvh"
    if content is not None:
        bvh.write_text(content)
    assert main(["convert", str(bvh), "--out-dir", str(tmp_path / "out"), *args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("python -m training convert: error: ") and words in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "argv", [["convert", "x.bvh", "--scale", "-1", "--out-dir", "o"], ["convert", "x.bvh"], []]
)
def test_bad_arguments_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    assert "error:" in capsys.readouterr().err


def test_module_entry_point(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "training", "convert", "--help"], capture_output=True, text=True, cwd=REPO
    )
    assert run.returncode == 0 and "--out-dir" in run.stdout and "--scale" in run.stdout
    run = subprocess.run(
        [sys.executable, "-m", "training", "convert", str(tmp_path / "none.bvh"), "--out-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "none.bvh" in run.stderr


def test_convert_without_scale_infers_centimetres_or_refuses(tmp_path, capsys):
    bvh = tmp_path / "walk.bvh"
    bvh.write_text(SMALL.replace("OFFSET 0 10 0", "OFFSET 0 100 0").replace("OFFSET 0 5 0", "OFFSET 0 50 0"))
    assert main(["convert", str(bvh), "--out-dir", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "no --scale" in err and "centimetres (--scale 0.01, a 1.50 m body)" in err
    _check_outputs(bvh, tmp_path / "out", 0.01)

    bvh.write_text(SMALL)  # 15 units: no usual unit makes it a person
    assert main(["convert", str(bvh), "--out-dir", str(tmp_path / "out2")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pass --scale (metres per file unit)" in err


@pytest.mark.skipif(not CMU_CLIP.exists(), reason=f"CMU clip not found: {CMU_CLIP}")
def test_convert_cmu_clip_without_scale_reads_cmu_units(tmp_path, capsys):
    assert main(["convert", str(CMU_CLIP), "--out-dir", str(tmp_path)]) == 0
    assert f"read as CMU units (--scale {CMU_SCALE:g}" in capsys.readouterr().err
    _check_outputs(CMU_CLIP, tmp_path, CMU_SCALE)
