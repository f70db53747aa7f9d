"""Command-line conventions of issue 15: what a command assumes is said, inputs fail in one clear line,
outputs get the usual permissions."""

import math
import shutil

import numpy as np
import pytest
import torch

from torchpf import Skeleton
from torchpf.__main__ import main
from torchpf.assets import path
from torchpf.camera import camera_ring, load_cameras
from torchpf.io import read_mocap_csv, write_mocap_csv
from torchpf.likelihoods import Keypoints2DLikelihood
from torchpf.sequence import load_truth_csv, read_sequence, write_sequence
from torchpf.synth import synthesize
from training.synthetic import generate

URDF = str(path("human.urdf"))


@pytest.fixture(scope="module")
def untimed_seq(seq_dir, tmp_path_factory):
    """The conftest sequence with a truth.csv without time column (as a hand-made one often has)."""
    root = tmp_path_factory.mktemp("untimed") / "seq"
    shutil.copytree(seq_dir, root)
    truth, names, _ = load_truth_csv(root / "truth.csv")
    write_mocap_csv(root / "truth.csv", names, truth)  # no times
    return root


def _track(seq, out, *extra):
    argv = ["track", str(seq), "--skeleton", URDF, "--out", str(out), "--filter", "sir", "--particles", "40"]
    return main([*argv, "--no-progress", "--threads", "1", *extra])


def test_track_says_which_frame_rate_it_assumed(untimed_seq, tmp_path, capsys, recwarn):
    assert _track(untimed_seq, tmp_path / "a.csv") == 0
    err = capsys.readouterr().err
    assert "no timestamps" in err and "assuming 30 fps" in err and "--fps" in err
    # the prior got the same rate: no fallback to Table 5's 5 Hz
    assert not [w for w in recwarn if "fps" in str(w.message)], [str(w.message) for w in recwarn]
    _, times, _ = read_mocap_csv(tmp_path / "a.csv")
    assert times[1] == pytest.approx(1 / 30)

    assert _track(untimed_seq, tmp_path / "b.csv", "--fps", "15") == 0
    assert "fps" not in capsys.readouterr().err
    _, times, _ = read_mocap_csv(tmp_path / "b.csv")
    assert times[1] == pytest.approx(1 / 15)


def test_track_refuses_a_bad_fps(untimed_seq, tmp_path, capsys):
    assert _track(untimed_seq, tmp_path / "a.csv", "--fps", "0") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--fps must be positive" in err


def _opencv_files(rig, folder):
    """One cv2.FileStorage calibration file per camera, as OpenCV's calibration samples write them."""
    cv2 = pytest.importorskip("cv2")
    paths = []
    for name, cam in rig.items():
        paths.append(str(folder / f"{name}.yml"))
        fs = cv2.FileStorage(paths[-1], cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", cam.K.numpy().astype(np.float64))
        fs.write("distortion_coefficients", np.zeros((1, 5)))
        fs.write("image_width", int(cam.width))
        fs.write("image_height", int(cam.height))
        fs.write("R", cam.R.numpy().astype(np.float64))
        fs.write("T", cam.t.numpy().astype(np.float64).reshape(3, 1))
        fs.release()
    return paths


def _one_line(capsys, *words):
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error: " in err and all(w in err for w in words), err


def test_cameras_merge_and_single_camera_files(untimed_seq, tmp_path, capsys):
    seq = tmp_path / "seq"
    shutil.copytree(untimed_seq, seq)
    rig = load_cameras(seq / "cameras.yaml")
    files = _opencv_files(rig, tmp_path)

    shutil.copy(files[0], seq / "cameras.yaml")  # one camera's calibration where the rig should be
    assert _track(seq, tmp_path / "t.csv") == 2
    _one_line(capsys, "one-camera OpenCV calibration file", "cameras merge")
    argv = ["masks", "a.mp4", "b.mp4", "--cameras", files[0], "--out", str(tmp_path / "m")]
    assert main(argv) == 2
    _one_line(capsys, "2 sources for one camera", "cameras merge")

    assert main(["cameras", "merge", *files, "--out", str(seq / "cameras.yaml")]) == 0
    assert "2 cameras (cam0 64x48, cam1 64x48)" in capsys.readouterr().out
    merged = load_cameras(seq / "cameras.yaml")
    assert merged.names == rig.names
    for key in ("K", "R", "t"):
        torch.testing.assert_close(getattr(merged, key), getattr(rig, key))
    assert len(read_sequence(seq)) == 3

    assert main(["cameras", "merge", files[0], files[0], "--out", str(tmp_path / "c.yaml")]) == 2
    _one_line(capsys, "camera 'cam0' is also in")


def test_keypoints_of_a_sequence_are_scored_in_the_mask_grid(tmp_path, capsys):
    skel = Skeleton.from_urdf(URDF)
    angles = generate("walk", 4, 15.0, seed=3).angles
    cams = camera_ring(2, radius=4.0, width=256, height_px=192, target=(0.0, 0.0, 1.0))
    seq = synthesize(skel, angles, cams, fps=15.0, mask_size=(64, 48))  # detections on the 64x48 masks
    write_sequence(tmp_path / "seq", seq)
    for data in (seq, read_sequence(tmp_path / "seq")):
        assert data.mask_size == (64, 48)
        lik = Keypoints2DLikelihood(skel, data.cameras, sigma=2.0)
        truth = data.truth_in(skel.dof_names)[:1].float()
        # noise-free detections: the truth's residuals vanish, its log-likelihood is the density's peak
        peak = -len(skel.joint_names) * len(cams) * math.log(2 * math.pi * 4.0)
        assert float(lik(truth, data.frame(0))) == pytest.approx(peak, abs=1e-2)

    out = tmp_path / "t.csv"  # scored in the cameras' 256x192 grid instead: 62 cm (6.7 here)
    argv = ["--likelihood", "keypoints", "--init-spread", "0.05", "--seed", "0"]
    assert _track(tmp_path / "seq", out, *argv) == 0
    printed = capsys.readouterr().out
    mpjpe = float(printed.split("MPJPE ")[1].split(" cm")[0])
    assert mpjpe < 10.0, printed
