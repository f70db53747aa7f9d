"""The sequence directory (DESIGN.md "File formats"): truth CSV and the directory round trip."""

import os

import numpy as np
import pytest
import torch

from torchpf.sequence import load_truth_csv, read_sequence, save_truth_csv, write_sequence
from torchpf.synth import SynthOptions, synthesize

W, H = 160, 120


def test_truth_csv_roundtrip(tmp_path):
    angles = torch.randn(5, 3, dtype=torch.float64)
    save_truth_csv(tmp_path / "t.csv", angles, ["a", "b", "c"], times=np.arange(5) / 30)
    text = (tmp_path / "t.csv").read_text().splitlines()
    assert text[0] == "time,a,b,c" and len(text) == 6
    got, names, times = load_truth_csv(tmp_path / "t.csv")
    assert names == ["a", "b", "c"]
    torch.testing.assert_close(got, angles, rtol=0, atol=0)
    np.testing.assert_allclose(times, np.arange(5) / 30)
    save_truth_csv(tmp_path / "u.csv", angles, ["a", "b", "c"])
    got, names, times = load_truth_csv(tmp_path / "u.csv")
    assert times is None and torch.equal(got, angles)
    (tmp_path / "bad.csv").write_text("time,a\n0.0,1.0,2.0\n")
    with pytest.raises(ValueError, match=r"bad\.csv:2: expected 2 fields"):
        load_truth_csv(tmp_path / "bad.csv")


def test_sequence_directory_roundtrip(tmp_path, human, rig, depth_cam):
    skel = human
    motion = torch.zeros(4, len(skel.dof_names), dtype=torch.float64)
    motion[:, skel.dof_names.index("Hips_Yposition")] = 1.0
    motion[:, skel.dof_names.index("LeftArm_Yrotation")] = torch.linspace(0.2, 0.8, 4, dtype=torch.float64)
    opts = SynthOptions(missing_frames=0.3, keypoint_dropout=0.2)
    seq = synthesize(skel, motion, rig, depth_camera=depth_cam, options=opts, seed=4)
    root = tmp_path / "seq"
    write_sequence(root, seq)
    assert sorted(os.listdir(root)) == ["cameras.yaml", "keypoints.npz", "masks", "points", "truth.csv"]
    assert sorted(os.listdir(root / "masks")) == ["cam0", "cam1", "cam2"]
    n_missing = sum(m is None for row in seq.masks for m in row)
    n_files = sum(len(os.listdir(root / "masks" / c)) for c in ("cam0", "cam1", "cam2"))
    assert n_files == 3 * len(motion) - n_missing and os.listdir(root / "masks" / "cam0")[0].endswith(".png")
    back = read_sequence(root)
    assert len(back) == len(motion) and list(back.cameras) == ["cam0", "cam1", "cam2"]
    assert back.depth_camera is not None and back.depth_camera.name == "depth"
    for row_a, row_b in zip(seq.masks, back.masks, strict=True):
        for m, n in zip(row_a, row_b, strict=True):
            assert (m is None and n is None) or np.array_equal(m, n)
    for p, q in zip(seq.points, back.points, strict=True):
        np.testing.assert_array_equal(p, q)
    torch.testing.assert_close(back.truth, seq.truth, rtol=0, atol=0)
    assert back.dof_names == skel.dof_names
    np.testing.assert_allclose(back.times, seq.times)
    np.testing.assert_array_equal(back.keypoints, seq.keypoints.astype(np.float32))
    assert back.keypoint_joints == skel.joint_names
    fr = back.frame(1)
    assert fr.silhouettes.masks.shape == (3, H, W)
    assert fr.silhouettes.valid.tolist() == [m is not None for m in seq.masks[1]]
    with pytest.raises(FileNotFoundError, match="cameras.yaml"):
        read_sequence(tmp_path)
