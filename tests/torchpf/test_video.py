"""Videos -> masks (:mod:`torchpf.video`, ``python -m torchpf masks``) on synthetic videos made here: a
textured background with sensor noise and a coloured ellipse walking across it, whose true silhouette is
known (no torchpf rendering involved)."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from torchpf.__main__ import main
from torchpf.camera import camera_ring, load_cameras, save_cameras
from torchpf.sequence import read_sequence
from torchpf.video import FrameReader, background_plate, expand_sources, match_cameras, segment_videos

H, W, T = 120, 160, 24


def _background(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 256, (6, 8, 3)).astype(np.uint8)
    bg = cv2.resize(coarse, (W, H), interpolation=cv2.INTER_CUBIC)
    stripes = (np.arange(W)[None, :, None] // 6 % 2 * 30).astype(np.uint8)  # texture the model must learn
    return cv2.add(bg, np.broadcast_to(stripes, bg.shape).copy())


def _truth(t: int, v: int, lead_in: int = 0) -> np.ndarray:
    m = np.zeros((H, W), np.uint8)
    if t >= lead_in:
        cv2.ellipse(m, (25 + 4 * (t - lead_in) + 10 * v, 62), (11, 34), 0, 0, 360, 255, -1)
    return m > 0


def _frames(v: int, lead_in: int = 0, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(100 + v + seed)
    bg = _background(v)
    frames, truths = [], []
    for t in range(T + lead_in):
        m = _truth(t, v, lead_in)
        img = bg.astype(np.float64)
        img[m] = (40, 90, 210)  # clothing: another hue than the background
        img += rng.normal(0.0, 2.0, img.shape)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
        truths.append(m)
    return frames, truths


def _write(path: str, frames, kind: str) -> str:
    if kind == "folder":
        os.makedirs(path)
        for t, f in enumerate(frames):
            cv2.imwrite(os.path.join(path, f"{t:04d}.png"), f)
        return path
    w = cv2.VideoWriter(path + ".avi", cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
    for f in frames:
        w.write(f)
    w.release()
    return path + ".avi"


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


@pytest.fixture()
def rig_file(tmp_path):
    path = tmp_path / "cameras.yaml"
    save_cameras(path, camera_ring(2, width=W, height_px=H))
    return path


@pytest.mark.parametrize("kind", ["video", "folder"])
def test_clean_plate_masks_match_the_silhouettes(kind, tmp_path, rig_file):
    sources, truths = [], []
    for v in range(2):
        frames, tr = _frames(v)
        sources.append(_write(str(tmp_path / f"cam{v}"), frames, kind))
        truths.append(tr)
        cv2.imwrite(str(tmp_path / f"plate{v}.png"), _background(v))
    plates = [str(tmp_path / f"plate{v}.png") for v in range(2)]
    report = segment_videos(sources, rig_file, tmp_path / "seq", clean_plates=plates, progress=False)
    assert report.n_frames == T and report.cameras == ["cam0", "cam1"]
    seq = read_sequence(tmp_path / "seq")
    assert len(seq) == T and list(seq.cameras) == ["cam0", "cam1"]
    ious = [_iou(seq.masks[t][v] > 127, truths[v][t]) for t in range(T) for v in range(2)]
    # lossless frames give the silhouette back; a compressed video rings around the person's edges
    floor = 0.95 if kind == "folder" else 0.75
    assert min(ious) > floor and np.mean(ious) > floor, (min(ious), np.mean(ious))
    # the frames were kept beside the masks, frame t <-> mask t
    video = FrameReader(tmp_path / "seq" / "video" / "cam1.mp4")
    assert sum(1 for _ in video) == T


def test_background_from_the_first_frames_and_a_lead_in(tmp_path, rig_file):
    lead = 6
    sources, truths = [], []
    for v in range(2):
        frames, tr = _frames(v, lead_in=lead)
        sources.append(_write(str(tmp_path / f"cam{v}"), frames, "video"))
        truths.append(tr[lead:])
    # the person walks through the frames the median is taken over: it must not stay in the background
    report = segment_videos(
        sources,
        rig_file,
        tmp_path / "seq",
        background_frames=T,
        start=lead,
        write_video=False,
        progress=False,
    )
    assert report.n_frames == T and report.background.startswith("median")
    seq = read_sequence(tmp_path / "seq")
    ious = [_iou(seq.masks[t][v] > 127, truths[v][t]) for t in range(T) for v in range(2)]
    assert np.mean(ious) > 0.8, np.mean(ious)
    assert not (tmp_path / "seq" / "video").exists()


def test_plate_is_the_median_and_sources_match_cameras(tmp_path, rig_file):
    frames = [np.full((4, 4, 3), v, np.uint8) for v in (10, 200, 12, 11, 250)]
    assert (background_plate(frames) == 12).all()
    rig = load_cameras(rig_file)
    assert match_cameras(["cam1", "cam0"], rig) == ["cam1", "cam0"]  # by name
    assert match_cameras(["left", "right"], rig) == ["cam0", "cam1"]  # in order
    with pytest.raises(ValueError, match="name each video"):
        match_cameras(["a", "b", "c"], rig)
    folder = tmp_path / "video"
    folder.mkdir()
    for n in ("cam1.mp4", "cam0.mp4"):
        (folder / n).write_bytes(b"")
    assert expand_sources([folder]) == [str(folder / "cam0.mp4"), str(folder / "cam1.mp4")]


def test_masks_cli(tmp_path, rig_file, capsys):
    sources = []
    for v in range(2):
        frames, _ = _frames(v)
        sources.append(_write(str(tmp_path / f"cam{v}"), frames, "video"))
        cv2.imwrite(str(tmp_path / f"plate{v}.png"), _background(v))
    out = tmp_path / "seq"
    argv = ["masks", *sources, "--cameras", str(rig_file), "--out", str(out), "--no-progress"]
    plates = ["--clean-plate", str(tmp_path / "plate0.png"), str(tmp_path / "plate1.png")]
    assert main(argv + plates + ["--frames", "10", "--method", "knn", "--size", "80x60"]) == 0
    assert "segmented 10 frames x 2 cameras" in capsys.readouterr().out
    seq = read_sequence(out)
    assert len(seq) == 10 and seq.masks[0][0].shape == (60, 80)  # masks at the asked size
    assert main(argv + plates + ["--size", "80by60"]) == 2
    assert "--size must be WIDTHxHEIGHT" in capsys.readouterr().err
    # one unnamed source for two cameras; a plate of another size: one-line errors, status 2
    os.replace(sources[0], tmp_path / "left.avi")
    assert main(["masks", str(tmp_path / "left.avi"), "--cameras", str(rig_file), "--out", str(out)]) == 2
    assert "name each video" in capsys.readouterr().err
    os.replace(tmp_path / "left.avi", sources[0])
    cv2.imwrite(str(tmp_path / "plate1.png"), np.zeros((60, 80, 3), np.uint8))
    assert main(argv + plates) == 2
    err = capsys.readouterr().err
    assert "background plate 80x60" in err and err.count("\n") == 1
