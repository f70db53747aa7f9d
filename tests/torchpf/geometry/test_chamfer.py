"""`capsule_chamfer` (values and hand-written gradient) against the composition it replaces, differentiated
by autograd: area points (`sample_in_capsules`), a `grid_sample` look-up in the mask's distance image and
`distance_to_capsules`. The masks come from the independent renderer of `_masks.py` (OpenCV), at poses
other than the capsules'. Both implementations are checked: the tensor operations and, on a CPU, the fused
numba kernel (`torchpf.geometry._chamfer_cpu`)."""

import numpy as np
import pytest
import torch

from torchpf.camera import camera_ring
from torchpf.geometry import (
    Capsules2D,
    _chamfer_cpu,
    capsule_area_mean,
    capsule_chamfer,
    chamfer,
    distance_to_capsules,
    project_capsules,
    sample_in_capsules,
)
from torchpf.geometry.chamfer import distance_lookup as _distance_lookup
from torchpf.observations import Silhouettes

from .._masks import render_masks

TAU = 6.0


def _reference(caps, outside, fg, tau=TAU, n_body=8, n_cap=2, linear=0.0):
    """The composition of the distance cue before `capsule_chamfer` (autograd through all of it), with
    ``rho(d) = min(d, tau)^2 + 2 linear min(d, tau)``."""

    def rho(d):
        d = d.clamp_max(tau)
        return d * d + 2 * linear * d

    pts, w = sample_in_capsules(caps, n_body, n_cap)  # (V, N, P, 2)
    model = (w * rho(_distance_lookup(outside, pts))).sum(-1) / w.sum(-1).clamp_min(1e-9)
    return model, rho(distance_to_capsules(fg, caps)).mean(-1)


@pytest.fixture(scope="module")
def scene(human):
    """Camera-major capsules (V, N, C) of 5 random poses, some limbs outside the image, one capsule behind a
    camera; the distance images and foreground samples of masks rendered at other poses."""
    rig = camera_ring(3, radius=3.0, height=1.5, target=(0, 0, 0.85), width=160, height_px=120)
    g = torch.Generator().manual_seed(5)
    D, rev = len(human.dof_names), human.dof_revolute
    poses = torch.zeros(7, D, dtype=torch.float64)
    poses[:, rev] = 0.4 * torch.randn(7, int(rev.sum()), generator=g, dtype=torch.float64)
    poses[:, :6] = 0.0
    poses = human.clamp(poses)
    up = human.dof_names.index("Hips_Yposition")
    poses[:, up] = 0.05 - human.fk(poses)[..., 2].min(-1).values
    joints = human.fk(poses)
    masks = render_masks(joints[0], human.tree.bones, human.radii, rig.cameras)
    obs = Silhouettes(masks)
    joints = joints[1:6].clone()
    joints[3] += torch.tensor([1.6, 0.0, 0.0], dtype=torch.float64)  # a pose half out of the images
    ends = joints[:, torch.as_tensor(human.bones)]  # (N, C, 2, 3)
    caps = project_capsules(rig, ends[..., 0, :], ends[..., 1, :], human.radii)  # (N, V, C)
    fields = [f.transpose(0, 1).contiguous() for f in (caps.pa, caps.pb, caps.ra, caps.rb, caps.valid)]
    fields[4][1, 2, 3] = False  # a capsule behind the camera
    fg, ok = obs.foreground_samples(128)
    return {
        "caps": Capsules2D(*fields),
        "outside": obs.outside_distance().double(),
        "fg": fg[:, None].double(),
    }


@pytest.fixture(params=["tensor", "fused"])
def path(request, monkeypatch):
    """Which implementation `capsule_chamfer` runs on the CPU."""
    if request.param == "fused" and not _chamfer_cpu.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(chamfer, "FUSED_CPU", request.param == "fused")
    return request.param


@pytest.mark.parametrize("tau, linear", [(TAU, 0.0), (1e9, 0.0), (TAU, 1.5)])
def test_values_and_gradients_match_autograd_of_the_composition(scene, tau, linear, path):
    caps = scene["caps"]
    leaves = [f.clone().requires_grad_() for f in (caps.pa, caps.pb, caps.ra, caps.rb)]
    ref_leaves = [f.clone().requires_grad_() for f in leaves]
    got = capsule_chamfer(
        Capsules2D(*leaves, caps.valid), scene["outside"], scene["fg"], tau=tau, linear=linear
    )
    ref = _reference(
        Capsules2D(*ref_leaves, caps.valid), scene["outside"], scene["fg"], tau=tau, linear=linear
    )
    assert got[0].shape == got[1].shape == caps.valid.shape[:2]
    for a, b in zip(got, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    g = torch.Generator().manual_seed(0)
    weights = [torch.rand(got[0].shape, generator=g, dtype=torch.float64) for _ in range(2)]
    loss = sum((w * t).sum() for w, t in zip(weights, got, strict=True))
    ref_loss = sum((w * t).sum() for w, t in zip(weights, ref, strict=True))
    grads = torch.autograd.grad(loss, leaves, retain_graph=True)
    for a, b in zip(grads, torch.autograd.grad(ref_loss, ref_leaves), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9)
    assert bool(torch.autograd.grad(got[1].sum(), leaves[2])[0].abs().sum() > 0)
    with torch.no_grad():  # the forward alone gives the same values
        alone = capsule_chamfer(caps, scene["outside"], scene["fg"], tau=tau, linear=linear)
        for a, b in zip(alone, got, strict=True):
            torch.testing.assert_close(a, b.detach(), rtol=1e-9, atol=1e-9)


def test_float32_and_per_sequence_images(scene, path):
    """float32 agrees with float64; (S, V, H, W) images with (S, V, N, C) capsules score each sequence on
    its own images, as one call per sequence does."""
    caps, outside, fg = scene["caps"], scene["outside"], scene["fg"]
    ref = capsule_chamfer(caps, outside, fg, tau=TAU)
    f32 = Capsules2D(*(f.float() for f in (caps.pa, caps.pb, caps.ra, caps.rb)), caps.valid)
    for a, b in zip(capsule_chamfer(f32, outside.float(), fg.float(), tau=TAU), ref, strict=True):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a.double(), b, rtol=1e-4, atol=1e-3)
    flipped = outside.flip(-1)
    two = Capsules2D(*(torch.stack([f, f]) for f in (caps.pa, caps.pb, caps.ra, caps.rb, caps.valid)))
    both = capsule_chamfer(two, torch.stack([outside, flipped]), torch.stack([fg, fg]), tau=TAU)
    other = capsule_chamfer(caps, flipped, fg, tau=TAU)
    for a, b, c in zip(both, ref, other, strict=True):
        torch.testing.assert_close(a[0], b)
        torch.testing.assert_close(a[1], c)


@pytest.mark.skipif(not _chamfer_cpu.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("linear", [0.0, 4.0])
def test_the_fused_kernel_equals_the_tensor_version_at_the_edge_cases(monkeypatch, linear):
    """Random capsules with the cases each implementation branches on: an axis of length 0, capsules off
    the image, invalid capsules, a pose with none valid (its cover term is ``rho(tau)``), a one-pixel-wide
    image; values and gradients of both terms equal to rounding."""
    g = torch.Generator().manual_seed(3)
    out = {}
    for shape in [(40, 50), (30, 1)]:
        H, W = shape
        G, N, C, n = 3, 5, 7, 64
        size = torch.tensor([W, H], dtype=torch.float64)
        pa = torch.rand(G, N, C, 2, generator=g, dtype=torch.float64) * size
        pb = pa + 6 * torch.randn(G, N, C, 2, generator=g, dtype=torch.float64)
        pb[0, 0, 0] = pa[0, 0, 0]
        pa[1, 1, 1] = torch.tensor([-5.0, 60.0], dtype=torch.float64)
        ra = 0.5 + 3 * torch.rand(G, N, C, 1, generator=g, dtype=torch.float64)
        rb = 0.5 + 3 * torch.rand(G, N, C, 1, generator=g, dtype=torch.float64)
        valid = torch.rand(G, N, C, generator=g) > 0.15
        valid[2, 3] = False
        image = 10 * torch.rand(G, H, W, generator=g, dtype=torch.float64)
        fg = torch.rand(G, 1, n, 2, generator=g, dtype=torch.float64) * size
        for fused in (False, True):
            monkeypatch.setattr(chamfer, "FUSED_CPU", fused)
            leaves = [f.clone().requires_grad_() for f in (pa, pb, ra, rb)]
            model, cover = capsule_chamfer(Capsules2D(*leaves, valid), image, fg, tau=TAU, linear=linear)
            grads = torch.autograd.grad((model * 0.3).sum() + cover.sum(), leaves)
            out[shape, fused] = (model, cover, *grads)
        assert float(out[shape, True][1][2, 3].detach()) == pytest.approx(TAU * (TAU + 2 * linear))
        for a, b in zip(out[shape, True], out[shape, False], strict=True):
            torch.testing.assert_close(a.detach(), b.detach(), rtol=1e-9, atol=1e-9)


def test_a_nan_pose_scores_nan_and_leaves_the_others_alone(scene, path):
    """A pose whose capsules are NaN (a particle that left the reals) scores NaN in both terms' sum, never
    an index computed from NaN; the other poses' values are those of a call without it."""
    caps, outside, fg = scene["caps"], scene["outside"], scene["fg"]
    fields = [f.clone() for f in (caps.pa, caps.pb, caps.ra, caps.rb)]
    fields[0][:, 2] = float("nan")
    model, cover = capsule_chamfer(Capsules2D(*fields, caps.valid), outside, fg, tau=TAU, linear=4.0)
    assert torch.isnan(model[:, 2] + cover[:, 2]).all()
    ref = capsule_chamfer(caps, outside, fg, tau=TAU, linear=4.0)
    keep = [0, 1, 3, 4]
    torch.testing.assert_close(model[:, keep], ref[0][:, keep])
    torch.testing.assert_close(cover[:, keep], ref[1][:, keep])


def _bilinear_zeros(image, u, v):
    """Independent numpy bilinear look-up, pixel centres at integers, 0 outside the image."""
    H, W = image.shape
    x0, y0 = np.floor(u).astype(int), np.floor(v).astype(int)
    out = np.zeros(u.shape)
    for dy in (0, 1):
        for dx in (0, 1):
            x, y = x0 + dx, y0 + dy
            w = (u - x0 if dx else 1 - (u - x0)) * (v - y0 if dy else 1 - (v - y0))
            inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            out += np.where(inside, w * image[y.clip(0, H - 1), x.clip(0, W - 1)], 0.0)
    return out


def test_capsule_area_mean_is_the_area_weighted_mask_share(scene, path):
    """`capsule_area_mean` (Fontmarty eq. 2's share of the model inside the mask) equals the area-weighted
    mean of a numpy bilinear look-up at the area points of `sample_in_capsules`, for the mask and a
    non-binary image, in float64 and float32, per-sequence images; a NaN pose is NaN, the others unchanged."""
    caps = scene["caps"]
    mask = (scene["outside"] == 0).double()
    smooth = mask + 0.5 * torch.rand(
        mask.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64
    )
    pts, w = sample_in_capsules(caps, 8, 2)  # (V, N, P, 2), (V, N, P)
    for image in (mask, smooth):
        got = capsule_area_mean(caps, image)
        look = np.stack(
            [
                _bilinear_zeros(image[v].numpy(), pts[v, ..., 0].numpy(), pts[v, ..., 1].numpy())
                for v in range(3)
            ]
        )
        want = (w.numpy() * look).sum(-1) / w.sum(-1).numpy()
        assert got.shape == want.shape == (3, 5)
        np.testing.assert_allclose(got.numpy(), want, rtol=1e-10, atol=1e-12)
        f32 = Capsules2D(*(f.float() for f in (caps.pa, caps.pb, caps.ra, caps.rb)), caps.valid)
        low = capsule_area_mean(f32, image.float())
        assert low.dtype == torch.float32
        np.testing.assert_allclose(low.double().numpy(), want, rtol=1e-5, atol=1e-5)
    share = capsule_area_mean(caps, mask)  # pose 3 lies half off the images: (nearly) nothing inside
    assert float(share[:, 3].max()) < 0.05 and 0.4 < float(share.max()) <= 1.0
    two = Capsules2D(*(torch.stack([f, f]) for f in (caps.pa, caps.pb, caps.ra, caps.rb, caps.valid)))
    both = capsule_area_mean(two, torch.stack([mask, smooth]))
    torch.testing.assert_close(both[0], capsule_area_mean(caps, mask))
    torch.testing.assert_close(both[1], capsule_area_mean(caps, smooth))
    fields = [f.clone() for f in (caps.pa, caps.pb, caps.ra, caps.rb)]
    fields[0][:, 2] = float("nan")
    with_nan = capsule_area_mean(Capsules2D(*fields, caps.valid), mask)
    assert torch.isnan(with_nan[:, 2]).all()
    keep = [0, 1, 3, 4]
    torch.testing.assert_close(with_nan[:, keep], capsule_area_mean(caps, mask)[:, keep])
