"""Observation containers: input normalisation, shape checks and the derived caches."""

import numpy as np
import pytest
import torch

from torchpf.observations import Keypoints2D, PointCloud, Silhouettes


def test_silhouettes_container():
    masks = np.zeros((2, 20, 30), np.uint8)
    masks[0, 5:15, 10:20] = 255
    obs = Silhouettes(masks)
    assert obs.masks.max() == 1.0 and obs.height == 20 and obs.width == 30
    torch.testing.assert_close(obs.area(), torch.tensor([100.0, 0.0]))
    pts, ok = obs.foreground_samples(40)
    assert ok.tolist() == [True, False] and pts.shape == (2, 40, 2)
    u, v = pts[0, :, 0].long(), pts[0, :, 1].long()
    assert bool((obs.masks[0, v, u] == 1).all())
    assert len({(int(a), int(b)) for a, b in zip(u, v, strict=True)}) >= 35  # spread, not repeated
    again, _ = Silhouettes(masks).foreground_samples(40)
    assert torch.equal(pts, again)
    assert obs.blurred(1.0).shape == (2, 20, 30) and float(obs.blurred(1.0)[0, 10, 15]) > 0.9
    with pytest.raises(ValueError, match="valid"):
        Silhouettes(masks, valid=[True])


def test_keypoints_and_pointcloud_containers():
    uv = torch.tensor([[[1.0, 2.0], [float("nan"), 3.0]]])
    kp = Keypoints2D(uv)
    assert kp.visible.tolist() == [[True, False]] and not torch.isnan(kp.uv).any()
    with pytest.raises(ValueError, match="shape"):
        PointCloud(torch.zeros(5, 2))


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.5])
def test_blur_is_opencvs_gaussian_in_torch(sigma, device, dtype):
    import cv2

    masks = (np.random.default_rng(0).random((3, 24, 30)) > 0.6).astype(np.float32)
    k = 2 * int(np.ceil(3 * sigma)) + 1
    expected = np.stack([cv2.GaussianBlur(m, (k, k), sigma) for m in masks])
    obs = Silhouettes(torch.from_numpy(masks).to(device, dtype))
    out = obs.blurred(sigma)
    assert out.device.type == device.type and out.dtype == dtype and out is obs.blurred(sigma)
    np.testing.assert_allclose(out.cpu().double().numpy(), expected, atol=1e-6)
    assert obs.foreground_samples(16)[0].device.type == device.type


@pytest.mark.parametrize(
    ("dtype", "on"),
    [(np.bool_, True), (np.uint8, 1), (np.uint8, 255), (np.uint16, 1), (np.uint16, 255), (np.uint16, 65535)],
)
def test_masks_of_every_storage_read_alike(dtype, on):
    from torchpf.observations import binary_mask

    ref = np.zeros((6, 8), bool)
    ref[2:5, 3:6] = True
    stored = np.where(ref, on, 0).astype(dtype)
    assert np.array_equal(binary_mask(stored), ref)
    assert np.array_equal(binary_mask(np.repeat(stored[..., None], 3, -1)), ref)  # colour PNG
    sil = Silhouettes(stored[None])
    assert torch.equal(sil.masks[0], torch.from_numpy(ref).float())


def test_frame_evidence():
    from torchpf.observations import Frame

    empty = Silhouettes(np.zeros((2, 4, 4), np.uint8))
    assert not Frame(silhouettes=empty).has_evidence() and not Frame().has_evidence()
    full = np.zeros((2, 4, 4), np.uint8)
    full[1, 1, 1] = 255
    assert Frame(silhouettes=Silhouettes(full)).has_evidence()
    assert not Frame(silhouettes=Silhouettes(full, valid=[True, False])).has_evidence()
