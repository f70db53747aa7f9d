"""Sensor preprocessing: background subtraction, mask clean-up, depth back-projection, edges and distance
images."""

import cv2
import numpy as np
import pytest
import torch

from torchpf.camera import look_at
from torchpf.observations import DistanceMaps
from torchpf.sensors import (
    BackgroundSubtractor,
    clean_mask,
    depth_to_points,
    distance_image,
    edge_map,
    silhouettes_from_video,
    skin_mask,
)


def textured_background(h=120, w=160, seed=0):
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.integers(60, 200, (h // 8, w // 8, 3)).astype(np.uint8), (w, h), cv2.INTER_LINEAR)
    return base


def scene(t, rng, shadow=False):
    """Frame t: static background with camera noise and a bright disc moving left to right."""
    bg = textured_background().astype(np.float32)
    frame = bg + rng.normal(0, 2.0, bg.shape)
    truth = np.zeros(bg.shape[:2], np.uint8)
    if t >= 0:
        centre = (20 + 6 * t, 60)
        if shadow:
            # A cast shadow: same chromaticity, 35 % darker, beside the person.
            sh = np.zeros_like(truth)
            cv2.ellipse(sh, (centre[0] + 25, 95), (20, 8), 0, 0, 360, 1, -1)
            frame[sh > 0] *= 0.65
        cv2.circle(truth, centre, 18, 1, -1)
        frame[truth > 0] = (40, 220, 90)
    return np.clip(frame, 0, 255).astype(np.uint8), truth > 0


def iou(a, b):
    return (a & b).sum() / max(1, (a | b).sum())


@pytest.mark.parametrize("method", ["mog2", "knn"])
def test_background_subtraction_recovers_moving_disc(method):
    rng = np.random.default_rng(1)
    sub = BackgroundSubtractor(method, history=100)
    sub.learn(scene(-1, rng)[0] for _ in range(40))
    scores = []
    for t in range(10):
        frame, truth = scene(t, rng, shadow=True)
        mask = sub.apply(frame)
        assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
        scores.append(iou(mask > 0, truth))
    assert min(scores) > 0.9


def test_shadows_are_removed():
    rng = np.random.default_rng(2)
    sub = BackgroundSubtractor("mog2", history=100)
    sub.learn(scene(-1, rng)[0] for _ in range(40))
    frame, truth = scene(5, rng, shadow=True)
    mask = sub.apply(frame, learning_rate=0) > 0
    shadow_region = np.zeros_like(mask)
    cv2.ellipse(shadow_region.view(np.uint8), (20 + 30 + 25, 95), (16, 6), 0, 0, 360, 1, -1)
    assert mask[shadow_region & ~truth].mean() < 0.05
    no_shadow_model = BackgroundSubtractor("mog2", history=100, detect_shadows=False, fill_holes=False)
    no_shadow_model.learn(scene(-1, np.random.default_rng(2))[0] for _ in range(40))
    raw = no_shadow_model.apply(frame, learning_rate=0) > 0
    assert raw[shadow_region & ~truth].mean() > 0.5  # without shadow detection it would be foreground


def test_silhouettes_from_video_file(tmp_path):
    rng = np.random.default_rng(3)
    path = str(tmp_path / "v.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 25, (160, 120))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG video")
    truths = []
    for t in range(-30, 8):
        frame, truth = scene(t, rng)
        writer.write(frame)
        truths.append(truth)
    writer.release()
    masks = list(silhouettes_from_video(path, warmup=30, history=100))
    assert len(masks) == 8
    assert min(iou(m > 0, tr) for m, tr in zip(masks, truths[30:], strict=True)) > 0.85
    with pytest.raises(OSError, match="cannot open"):
        list(silhouettes_from_video(str(tmp_path / "missing.avi")))


def test_clean_mask_removes_speckle_and_fills_holes():
    m = np.zeros((100, 100), bool)
    m[20:80, 30:70] = True
    m[45:55, 45:55] = False  # a hole
    rng = np.random.default_rng(0)
    speckle = rng.random(m.shape) < 0.01
    out = clean_mask(m ^ (speckle & ~m), open_px=3, close_px=5, min_area=0.01)
    expected = np.zeros_like(m)
    expected[20:80, 30:70] = True
    assert iou(out > 0, expected) > 0.97
    assert out[50, 50] == 255 and out[5, 5] == 0


def test_depth_to_points_plane_and_range():
    cam = look_at((0.0, -3.0, 1.0), (0.0, 0.0, 1.0), width=64, height=48, fov_deg=60)
    depth = np.full((48, 64), 3.0)
    depth[:10] = 0.0  # no measurement
    depth[40:] = 9.0  # background, cut by max_depth
    pts = depth_to_points(depth, cam, max_depth=5.0)
    assert pts.shape == (30 * 64, 3) and pts.dtype == torch.float32
    # z-depth 3 m in front of a camera looking along +y: the points lie on the plane y = 0.
    np.testing.assert_allclose(pts[:, 1].numpy(), 0.0, atol=1e-5)
    np.testing.assert_allclose(cam.depth(pts.double()).numpy(), 3.0, atol=1e-5)
    # Reprojection lands on the pixel centres it came from.
    uv = cam.project(pts.double()).numpy()
    jj, ii = np.meshgrid(np.arange(64), np.arange(10, 40))
    np.testing.assert_allclose(uv[:, 0], jj.reshape(-1), atol=1e-3)
    np.testing.assert_allclose(uv[:, 1], ii.reshape(-1), atol=1e-3)
    mask = np.zeros((48, 64), np.uint8)
    mask[20:22, 5:9] = 1
    assert depth_to_points(depth, cam, mask=mask, stride=1).shape == (8, 3)
    assert depth_to_points(depth, cam, max_depth=5.0, stride=2).shape == (15 * 32, 3)


def test_distance_image_matches_brute_force():
    rng = np.random.default_rng(4)
    f = np.zeros((30, 40), np.uint8)
    ys, xs = rng.integers(0, 30, 6), rng.integers(0, 40, 6)
    f[ys, xs] = 255
    d = distance_image(f)
    yy, xx = np.mgrid[0:30, 0:40]
    ref = np.min(np.hypot(yy[..., None] - ys, xx[..., None] - xs), -1)
    # exact: the square root of an integer, in float32, bit for bit (a track must not depend on OpenCV's
    # rounding, which varies with the buffer's alignment)
    np.testing.assert_array_equal(d, ref.astype(np.float32))
    for offset in range(1, 4):  # the same mask in buffers of other alignments
        buf = np.zeros(f.size + offset, np.uint8)
        shifted = buf[offset:].reshape(f.shape)
        shifted[...] = f
        np.testing.assert_array_equal(distance_image(shifted), d)
    empty = distance_image(np.zeros((3, 4)))
    assert np.all(empty == 5.0)


def test_edge_map_and_distance_maps():
    img = np.zeros((60, 80), np.uint8)
    img[20:40, 30:60] = 200
    e = edge_map(img)
    assert e[30, 45] == 0 and e[20:40, 28:32].any() and e[5, 5] == 0
    dm = DistanceMaps.from_edges_of([img, cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)])
    assert dm.distance.shape == (2, 60, 80)
    torch.testing.assert_close(dm.distance[0], dm.distance[1])
    assert dm.distance[0, 30, 45] > 5 and bool(dm.valid.all())


def test_skin_mask_finds_skin_coloured_blob():
    img = np.full((60, 80, 3), (200, 120, 40), np.uint8)  # blue-ish background (BGR)
    cv2.circle(img, (40, 30), 8, (120, 160, 220), -1)  # skin tone in BGR
    m = skin_mask(img)
    assert m[30, 40] == 255 and m[5, 5] == 0
