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


# ---------------------------------------------------------------------- validation (issue 16)
def _tiny(root, n=4, cams=2, w=16, h=12, value=255, dtype=np.uint8, truth=False):
    """A sequence directory of ``n`` frames of ``cams`` cameras with a block of foreground in each mask."""
    import cv2

    from torchpf.camera import camera_ring, save_cameras

    rig = camera_ring(cams, width=w, height_px=h)
    save_cameras(root / "cameras.yaml", rig)
    m = np.zeros((h, w), dtype)
    m[3:8, 4:9] = value
    for c in rig:
        (root / "masks" / c).mkdir(parents=True, exist_ok=True)
        for t in range(n):
            cv2.imwrite(str(root / "masks" / c / f"{t:06d}.png"), m)
    if truth:
        save_truth_csv(root / "truth.csv", np.zeros((n, 2)), ["a", "b"], times=np.arange(n) / 30)
    return m


def test_stray_frame_file_is_refused_before_allocating(tmp_path):
    _tiny(tmp_path)
    src = tmp_path / "masks" / "cam0" / "000001.png"
    (tmp_path / "masks" / "cam0" / "99999999.png").write_bytes(src.read_bytes())
    with pytest.raises(ValueError, match=r"not contiguous: no file for frame\(s\) 4-99999998.*99999999\.png"):
        read_sequence(tmp_path)
    _tiny(tmp_path, truth=True)  # truth.csv lists 4 frames: the file is past them
    with pytest.raises(
        ValueError, match=r"99999999\.png: frame 99999999 is past the 4 frames that .*truth\.csv"
    ):
        read_sequence(tmp_path)


def test_gaps_without_a_listing_are_reported(tmp_path):
    _tiny(tmp_path, n=9)
    for c in ("cam0", "cam1"):
        for t in (2, 3, 6):
            os.remove(tmp_path / "masks" / c / f"{t:06d}.png")
    with pytest.raises(ValueError, match=r"no file for frame\(s\) 2-3, 6 "):
        read_sequence(tmp_path)
    os.remove(tmp_path / "masks" / "cam0" / "000004.png")  # one camera missing a frame is no gap
    save_truth_csv(tmp_path / "truth.csv", np.zeros((9, 1)), ["a"])
    seq = read_sequence(tmp_path)
    assert len(seq) == 9 and seq.masks[2] == [None, None] and seq.masks[4][0] is None
    assert not seq.frame(2).has_evidence() and seq.frame(4).has_evidence()


@pytest.mark.parametrize("name", ["1e3.png", "²³.png", "٣.png", "12a.png", "-1.png"])
def test_frame_names_are_ascii_numbers(tmp_path, name):
    _tiny(tmp_path, n=1)
    (tmp_path / "masks" / "cam1" / name).write_bytes(b"")
    with pytest.raises(ValueError, match="unexpected file"):
        read_sequence(tmp_path)


@pytest.mark.parametrize(
    ("dtype", "value"), [(np.uint8, 1), (np.uint8, 255), (np.uint16, 1), (np.uint16, 65535)]
)
def test_masks_stored_any_way_read_alike(tmp_path, dtype, value):
    ref = _tiny(tmp_path, n=2, value=value, dtype=dtype) > 0
    seq = read_sequence(tmp_path)
    row = seq.masks[1]
    assert all(m.dtype == np.uint8 and np.array_equal(m > 127, ref) for m in row)
    assert seq.frame(0).silhouettes.masks.sum() == 2 * ref.sum()


def test_lazy_frames_index_like_a_list(tmp_path):
    _tiny(tmp_path, n=5)
    seq = read_sequence(tmp_path)
    assert len(seq.masks) == 5 and seq.masks.n_files == 10
    assert len(seq.masks[1:3]) == 2 and np.array_equal(seq.masks[-1][0], seq.masks[4][0])
    assert sum(1 for _ in seq.masks) == 5
    with pytest.raises(IndexError):
        seq.masks[5]


def test_mask_size_and_aspect_are_checked(tmp_path):
    import cv2

    _tiny(tmp_path, n=2, w=16, h=12)
    half = np.zeros((6, 8), np.uint8)
    for c in ("cam0", "cam1"):  # the same aspect at another size: the cameras are rescaled to it
        for t in range(2):
            cv2.imwrite(str(tmp_path / "masks" / c / f"{t:06d}.png"), half)
    assert read_sequence(tmp_path).frame(0).silhouettes.masks.shape == (2, 6, 8)
    cv2.imwrite(str(tmp_path / "masks" / "cam1" / "000001.png"), np.zeros((8, 6), np.uint8))
    with pytest.raises(ValueError, match=r"cam1/000001\.png: mask is 6x8 pixels but .* is 8x6"):
        read_sequence(tmp_path)
    for c in ("cam0", "cam1"):  # transposed masks: refused, not tracked with a wrong camera
        for t in range(2):
            cv2.imwrite(str(tmp_path / "masks" / c / f"{t:06d}.png"), np.zeros((16, 12), np.uint8))
    with pytest.raises(ValueError, match=r"mask is 12x16 pixels, camera 'cam0' images are 16x12"):
        read_sequence(tmp_path)
    (tmp_path / "masks" / "cam0" / "000000.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"cam0/000000\.png: not a PNG"):
        read_sequence(tmp_path)


def test_stray_camera_folder_and_unsafe_names(tmp_path):
    _tiny(tmp_path, n=1)
    (tmp_path / "masks" / "cam7").mkdir()
    with pytest.raises(ValueError, match=r"masks/cam7: no camera 'cam7'"):
        read_sequence(tmp_path)
    os.rmdir(tmp_path / "masks" / "cam7")
    text = (tmp_path / "cameras.yaml").read_text().replace("cam1:", "../../outside:")
    (tmp_path / "cameras.yaml").write_text(text)
    with pytest.raises(ValueError, match=r"cameras\.yaml: camera name '\.\./\.\./outside' is not a safe"):
        read_sequence(tmp_path)


def test_points_and_keypoints_are_checked(tmp_path):
    _tiny(tmp_path, n=3)
    (tmp_path / "points").mkdir()
    np.save(tmp_path / "points" / "000000.npy", np.zeros((4, 3), np.float32))
    np.save(tmp_path / "points" / "000001.npy", np.full((2, 3), np.inf, np.float32))
    np.save(tmp_path / "points" / "000002.npy", np.zeros((2, 2), np.float32))
    seq = read_sequence(tmp_path)
    assert seq.points[0].shape == (4, 3)
    with pytest.raises(ValueError, match=r"000001\.npy: holds non-finite"):
        seq.points[1]
    with pytest.raises(ValueError, match=r"000002\.npy: expected a \(K, 3\) array"):
        seq.frame(2)
    # a header promising more than the file holds
    np.save(tmp_path / "points" / "000002.npy", np.zeros((2, 3), np.float32))
    hdr = (tmp_path / "points" / "000002.npy").read_bytes()
    (tmp_path / "points" / "000002.npy").write_bytes(hdr.replace(b"(2, 3)", b"(9, 3)"))
    with pytest.raises(ValueError, match="more data than the file holds"):
        read_sequence(tmp_path).points[2]
    np.savez(tmp_path / "keypoints.npz", uv=np.zeros((3, 2, 1, 2)), joints=["j"], cameras=["cam1", "cam0"])
    assert read_sequence(tmp_path).keypoints.shape == (3, 2, 1, 2)
    np.savez(tmp_path / "keypoints.npz", uv=np.zeros((3, 2, 1, 2)), joints=["j"], cameras=["cam1", "x"])
    with pytest.raises(ValueError, match=r"keypoints\.npz: keypoints of cameras"):
        read_sequence(tmp_path)
    (tmp_path / "keypoints.npz").write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(ValueError, match=r"keypoints\.npz: not a readable keypoints"):
        read_sequence(tmp_path)


def test_has_observations(tmp_path):
    _tiny(tmp_path, n=2)
    assert read_sequence(tmp_path).has_observations()
    import shutil

    shutil.rmtree(tmp_path / "masks")
    save_truth_csv(tmp_path / "truth.csv", np.zeros((3, 1)), ["a"])
    seq = read_sequence(tmp_path)
    assert len(seq) == 3 and not seq.has_observations()
