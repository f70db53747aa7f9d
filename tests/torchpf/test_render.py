"""Overlay rendering (:mod:`torchpf.render`, ``python -m torchpf render``): the projection checked against
``cv2.projectPoints`` (distortion, enlarged tiles), the drawing, video and PNG output, errors."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest
import torch

from torchpf.__main__ import main
from torchpf.camera import Camera, CameraRig, camera_ring, look_at
from torchpf.io import write_mocap_csv
from torchpf.render import JOINT, overlay_frame, project_joints
from torchpf.sequence import SequenceData, write_sequence
from torchpf.video import FrameReader


def _pose(human, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    theta = human.clamp(0.3 * torch.randn(len(human.dof_names), generator=g, dtype=torch.float64))
    theta[:3] = torch.tensor([0.1, 0.95, -0.2], dtype=torch.float64)  # x, height (world z), -y
    return theta


def _distorted_camera() -> Camera:
    base = look_at((0.5, -3.5, 1.6), (0.0, 0.0, 0.9), width=160, height=120, fov_deg=55)
    dist = torch.tensor([-0.12, 0.03, 0.002, -0.001, 0.004], dtype=torch.float64)
    return Camera(base.K, base.R, base.t, dist, width=160, height=120, name="distorted")


def _cv2_project(points: np.ndarray, cam: Camera, K: np.ndarray | None = None) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(cam.R.numpy())
    dist = np.zeros(5) if cam.dist is None else cam.dist.numpy()
    uv, _ = cv2.projectPoints(points, rvec, cam.t.numpy(), cam.K.numpy() if K is None else K, dist)
    return uv.reshape(-1, 2)


def test_projection_matches_opencv(human):
    cam = _distorted_camera()
    theta = _pose(human)
    joints = human.fk(theta).numpy()
    assert np.abs(project_joints(human, cam, theta).numpy() - _cv2_project(joints, cam)).max() < 1e-6
    # an enlarged tile (k = 3): pixel centres kept, u' + 0.5 = 3 (u + 0.5)
    big = cam.resized(480, 360)
    K = cam.K.numpy().copy()
    K[:2, :2] *= 3
    K[:2, 2] = 3 * (K[:2, 2] + 0.5) - 0.5
    assert np.abs(project_joints(human, big, theta).numpy() - _cv2_project(joints, cam, K)).max() < 1e-6


def test_overlay_draws_the_model_at_the_projected_joints(human):
    rig = CameraRig([_distorted_camera(), camera_ring(2, width=160, height_px=120, target=(0, 0, 0.9))[1]])
    theta = _pose(human)
    masks = [np.zeros((120, 160), np.uint8), None]
    img = overlay_frame(human, rig, theta, masks, labels=False)
    assert img.shape == (240, 640, 3) and img.dtype == np.uint8  # two tiles enlarged x2 to 240 px high
    for v in range(2):
        cam = rig[v].resized(160, 120).resized(320, 240)
        uv = project_joints(human, cam, theta).numpy()
        inside = (uv[:, 0] > 3) & (uv[:, 0] < 316) & (uv[:, 1] > 3) & (uv[:, 1] < 236)
        assert inside.sum() > 20
        for u, w in np.round(uv[inside]).astype(int):
            assert tuple(img[w, u + 320 * v]) == JOINT
    # the capsules cover a good part of the image, drawn in the model colour over the black background
    tinted = (img[..., 2] > img[..., 0] + 40).mean()
    assert 0.02 < tinted < 0.5


@pytest.fixture()
def seq_and_track(human, tmp_path):
    rig = camera_ring(2, width=160, height_px=120, target=(0, 0, 0.9))
    T = 5
    masks = [[np.zeros((120, 160), np.uint8) for _ in range(2)] for _ in range(T)]
    write_sequence(tmp_path / "seq", SequenceData(cameras=rig, masks=masks))
    angles = torch.stack([_pose(human, s) for s in range(T)]).numpy()
    write_mocap_csv(tmp_path / "track.csv", human.dof_names, angles, times=np.arange(T) / 25.0)
    human.save_urdf(tmp_path / "s.urdf")
    argv = ["render", str(tmp_path / "track.csv"), "--skeleton", str(tmp_path / "s.urdf")]
    return tmp_path, T, [*argv, "--sequence", str(tmp_path / "seq")]


def test_render_cli_video_and_png_frames(seq_and_track, capsys):
    tmp, T, base = seq_and_track
    assert main([*base, "--out", str(tmp / "overlay.mp4"), "--no-progress"]) == 0
    assert "rendered 5 frames at 25 fps" in capsys.readouterr().out
    frames = list(FrameReader(tmp / "overlay.mp4"))
    assert len(frames) == T and frames[0].shape == (240, 640, 3)
    assert main([*base, "--out", str(tmp / "frames"), "--no-progress"]) == 0
    assert sorted(os.listdir(tmp / "frames")) == [f"{t:06d}.png" for t in range(T)]
    # over the video frames when the sequence has them
    os.makedirs(tmp / "seq" / "video")
    for name in ("cam0", "cam1"):
        w = cv2.VideoWriter(
            str(tmp / "seq" / "video" / f"{name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25, (160, 120)
        )
        for _ in range(T):
            w.write(np.full((120, 160, 3), (200, 180, 20), np.uint8))
        w.release()
    assert main([*base, "--out", str(tmp / "video_bg"), "--no-progress"]) == 0
    first = cv2.imread(str(tmp / "video_bg" / "000000.png"))
    assert np.abs(first[2, 300].astype(int) - (200, 180, 20)).max() < 12  # the video, not a grey mask


def test_render_cli_errors(seq_and_track, capsys):
    tmp, _, base = seq_and_track
    assert main([*base, "--out", str(tmp / "o.mp4"), "--background", "video"]) == 2
    assert "no video for camera" in capsys.readouterr().err
    write_mocap_csv(tmp / "track.csv", ["a"], np.zeros((2, 1)))
    assert main([*base, "--out", str(tmp / "o.mp4")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("python -m torchpf render: error:") and err.count("\n") == 1


def test_fast_capsule_fill_is_the_rasterised_model(human):
    from torchpf.geometry import capsule_masks, project_capsules
    from torchpf.render import _fill_capsules

    cam = _distorted_camera()
    ends, radii = human.capsules(_pose(human, 3))
    caps = project_capsules(cam, ends[..., 0, :], ends[..., 1, :], radii)
    exact, fast = capsule_masks(caps, 120, 160).numpy(), _fill_capsules(caps, 120, 160)
    assert (exact & fast).sum() / (exact | fast).sum() > 0.8  # they differ by boundary pixels only
    assert not (exact & ~fast).any() or (exact & ~fast).sum() < 0.05 * exact.sum()
