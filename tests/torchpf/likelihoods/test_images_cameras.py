"""The image cues score all cameras at once (one projection, one grid_sample, one matrix product per camera):
their per-camera distances against a reference that loops over the cameras one :class:`Camera` at a time,
for random poses, with one (V, H, W) observation and with a batch of (S, V, H, W) observations."""

import pytest
import torch
import torch.nn.functional as F

from torchpf.geometry import capsule_coverage, distance_to_capsules, project_capsules, sample_in_capsules
from torchpf.likelihoods import DualSilhouetteLikelihood, SilhouetteDistanceLikelihood, SilhouetteLikelihood
from torchpf.observations import Silhouettes


def _bilinear(image, uv, padding="zeros"):
    """Reference look-up of one (H, W) image at (..., 2) pixel coordinates (pixel centres at integers)."""
    H, W = image.shape
    grid = torch.stack([(2 * uv[..., 0] + 1) / W - 1, (2 * uv[..., 1] + 1) / H - 1], -1)
    out = F.grid_sample(
        image[None, None], grid.reshape(1, 1, -1, 2), padding_mode=padding, align_corners=False
    )
    return out.reshape(uv.shape[:-1])


def _outside_lookup(dist, uv):
    """Distance image look-up that grows linearly beyond the border (the silhouette_distance rule)."""
    H, W = dist.shape
    inside = torch.stack([uv[..., 0].clamp(0, W - 1), uv[..., 1].clamp(0, H - 1)], -1)
    return _bilinear(dist, inside, "border") + (uv - inside).norm(dim=-1)


def _reference(name, skel, rig, theta, obs: Silhouettes):
    """(N, V) distances of ``theta`` (N, D) against one (V, H, W) observation, camera by camera."""
    ends, radii = skel.capsules(theta)
    H, W = obs.height, obs.width
    out = []
    for v in range(len(rig)):
        caps = project_capsules(rig[v].resized(W, H), ends[..., 0, :], ends[..., 1, :], radii)  # (N, C)
        if name == "silhouette":
            pts, w = sample_in_capsules(caps, 8, 2)
            inside = _bilinear(obs.masks[v].to(pts), pts)
            out.append(1 - (w * inside).sum(-1) / w.sum(-1))
        elif name == "dual_silhouette":
            fg, ok = obs.foreground_samples(128)
            cov = capsule_coverage(fg[v].to(theta), caps)
            out.append(1 - cov.mean(-1) if ok[v] else torch.zeros(len(theta), dtype=theta.dtype))
        else:
            clean = obs  # the cue's default: no despeckling
            pts, w = sample_in_capsules(caps, 8, 2)
            d_in = _outside_lookup(clean.outside_distance()[v].to(pts), pts).clamp_max(6.0)
            fg, ok = clean.foreground_samples(128)
            d_cov = distance_to_capsules(fg[v].to(theta), caps).clamp_max(6.0)
            a = 4.0  # the cue's default linear part: rho(d) = d^2 + 2 a d
            E = (w * (d_in**2 + 2 * a * d_in)).sum(-1) / w.sum(-1) + (d_cov**2 + 2 * a * d_cov).mean(-1)
            out.append(E if ok[v] else torch.zeros(len(theta), dtype=theta.dtype))
    return torch.stack(out, -1)


CUES = {
    "silhouette": SilhouetteLikelihood,
    "dual_silhouette": DualSilhouetteLikelihood,
    "silhouette_distance": SilhouetteDistanceLikelihood,
}


@pytest.fixture(scope="module")
def poses(skel, truth):
    g = torch.Generator().manual_seed(3)
    spread = torch.where(skel.dof_revolute, 0.15, 0.05).double()
    return skel.clamp(truth + spread * torch.randn(2, 7, len(truth), generator=g, dtype=torch.float64))


@pytest.mark.parametrize("name", list(CUES))
def test_all_cameras_at_once_match_the_per_camera_loop(name, skel, truth, rig, frame, poses):
    cue = CUES[name](skel, rig).double()
    obs = frame.silhouettes
    got = cue.distances(poses[0], obs)
    assert got.shape == (7, len(rig))
    torch.testing.assert_close(got, _reference(name, skel, rig, poses[0], obs), rtol=1e-9, atol=1e-9)
    # a batch of two sequences: the second sees a shifted person and its third camera has no mask
    masks = obs.masks.clone()
    shifted = torch.roll(masks, shifts=(3, -5), dims=(-2, -1))
    shifted[2] = 0
    second = Silhouettes(shifted)
    batched = Silhouettes(torch.stack([masks, shifted]))
    got = cue.distances(poses, batched)
    assert got.shape == (2, 7, len(rig))
    for s, single in enumerate((Silhouettes(masks), second)):
        ref = _reference(name, skel, rig, poses[s], single)
        torch.testing.assert_close(got[s], ref, rtol=1e-9, atol=1e-9)
    if name != "silhouette":  # an empty mask contributes 0
        assert torch.all(got[1, :, 2] == 0)
