"""Projected 2-D capsules against OpenCV drawing, independent per-point formulas and pixel counts."""

import cv2
import numpy as np
import pytest
import torch

from torchpf.camera import camera_ring, look_at
from torchpf.geometry import (
    Capsules2D,
    capsule_coverage,
    capsule_masks,
    distance_to_capsules,
    outline_points,
    project_capsules,
    sample_in_capsules,
)
from torchpf.geometry.projected import _uneven_capsule_sdf


def test_project_capsules_radius_on_axis():
    cam = look_at((0.0, -4.0, 1.0), (0.0, 0.0, 1.0), width=160, height=120, fov_deg=50)
    a = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    b = torch.tensor([[0.0, 0.0, 1.5]], dtype=torch.float64)
    caps = project_capsules(cam, a, b, torch.tensor([0.1], dtype=torch.float64))
    f = cam.K[0, 0].item()
    assert caps.ra.item() == pytest.approx(f * 0.1 / 4.0)
    np.testing.assert_allclose(caps.pa.numpy(), [[79.5, 59.5]])
    assert caps.pb[0, 1] < caps.pa[0, 1] and bool(caps.valid.all())
    behind = project_capsules(
        cam, a - torch.tensor([0.0, 5.0, 0.0], dtype=torch.float64), b, caps.ra.new_tensor([0.1])
    )
    assert not bool(behind.valid.any())


def _rig_and_capsules():
    """Three cameras and 5 poses of 4 random capsules (float64) in front of them."""
    rig = camera_ring(3, radius=4.0, width=160, height_px=120)
    g = torch.Generator().manual_seed(0)
    a = torch.randn(5, 4, 3, generator=g, dtype=torch.float64) * 0.3 + torch.tensor([0.0, 0.0, 1.0])
    b = a + torch.randn(5, 4, 3, generator=g, dtype=torch.float64) * 0.2
    return rig, a, b, torch.full((4,), 0.05, dtype=torch.float64)


@pytest.fixture(params=["tensor", "fused"])
def fused(request, monkeypatch):
    """The rig projection's two CPU versions: the tensor operations and the numba kernels
    (:mod:`torchpf.geometry._project_cpu`)."""
    from torchpf.geometry import _project_cpu

    if request.param == "fused" and not _project_cpu.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setenv("TORCHPF_FUSED", "1" if request.param == "fused" else "0")
    assert _project_cpu.applies(torch.zeros(1, 2, 3)) == (request.param == "fused")
    return request.param


def test_project_capsules_into_a_rig(fused):
    rig, a, b, r = _rig_and_capsules()
    caps = project_capsules(rig, a, b, r)
    assert caps.pa.shape == (5, 3, 4, 2) and caps.ra.shape == (5, 3, 4)
    for v, (cam, one) in enumerate(zip(rig.values(), caps.unbind(1), strict=True)):
        ref = project_capsules(cam, a, b, r)
        for x, y in zip((one.pa, one.pb, one.ra, one.rb), (ref.pa, ref.pb, ref.ra, ref.rb), strict=True):
            torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-9)
        assert torch.equal(one.valid, ref.valid), v


def test_rig_projection_gradient_matches_autograd_per_camera(fused):
    """The rig's projection (one autograd node with the Jacobian written out, or the fused CPU kernels) has
    the gradient in the ends and radii that autograd gives through the per-camera projection, with an end
    behind a camera and extra batch dims."""
    rig, a, b, r = _rig_and_capsules()
    a, b = a.reshape(5, 1, 4, 3).expand(5, 2, 4, 3).clone(), b.reshape(5, 1, 4, 3).expand(5, 2, 4, 3).clone()
    a[1, 1, 2] = -rig.R[0].T @ rig.t[0] - 0.5 * rig.R[0, 2]  # behind camera 0
    g = torch.Generator().manual_seed(2)
    leaves = [x.clone().requires_grad_() for x in (a, b, r)]
    caps = project_capsules(rig, *leaves)
    assert caps.pa.shape == (5, 2, 3, 4, 2) and caps.pa.grad_fn is not None
    assert not bool(caps.valid[1, 1, 0, 2]) and bool(caps.valid.sum() > 100)
    weights = [
        torch.rand(f.shape, generator=g, dtype=torch.float64) for f in (caps.pa, caps.pb, caps.ra, caps.rb)
    ]
    loss = sum((w * f).sum() for w, f in zip(weights, (caps.pa, caps.pb, caps.ra, caps.rb), strict=True))
    got = torch.autograd.grad(loss, leaves)
    ref_leaves = [x.clone().requires_grad_() for x in (a, b, r)]
    ref_loss = 0
    for v, cam in enumerate(rig.values()):
        one = project_capsules(cam, *ref_leaves)
        for w, f in zip(weights, (one.pa, one.pb, one.ra, one.rb), strict=True):
            ref_loss = ref_loss + (w[:, :, v] * f).sum()
    for x, y in zip(got, torch.autograd.grad(ref_loss, ref_leaves), strict=True):
        torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-9)
    # one pose, only some fields used (the others get no gradient)
    got = torch.autograd.grad(
        project_capsules(rig, leaves[0][:1, 0], b[:1, 0], leaves[2]).ra.sum(), (leaves[0], leaves[2])
    )
    ref = torch.autograd.grad(
        sum(
            project_capsules(cam, ref_leaves[0][:1, 0], b[:1, 0], ref_leaves[2]).ra.sum()
            for cam in rig.values()
        ),
        (ref_leaves[0], ref_leaves[2]),
    )
    for x, y in zip(got, ref, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-9)


def cv2_capsule_mask(pa, pb, ra, rb, H, W, shift=8):
    """Reference raster: both discs plus the convex hull of densely sampled disc boundaries, sub-pixel."""
    m = np.zeros((H, W), np.uint8)
    s = 1 << shift
    for (x, y), rad in ((pa, ra), (pb, rb)):
        cv2.circle(m, (round(x * s), round(y * s)), round(rad * s), 255, -1, cv2.LINE_8, shift)
    phi = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    pts = np.concatenate(
        [np.stack([c[0] + rad * np.cos(phi), c[1] + rad * np.sin(phi)], 1) for c, rad in ((pa, ra), (pb, rb))]
    )
    hull = cv2.convexHull(np.round(pts * s).astype(np.int32))
    cv2.fillConvexPoly(m, hull, 255, cv2.LINE_8, shift)
    return m > 0


@pytest.mark.parametrize("seed", range(4))
def test_capsule_masks_match_opencv_drawing(seed):
    rng = np.random.default_rng(seed)
    H, W = 60, 80
    pa, pb = rng.uniform([10, 10], [70, 50]), rng.uniform([10, 10], [70, 50])
    ra, rb = rng.uniform(2, 8), rng.uniform(2, 8)
    caps = Capsules2D(
        torch.from_numpy(pa)[None, None],
        torch.from_numpy(pb)[None, None],
        torch.tensor([[ra]]),
        torch.tensor([[rb]]),
        torch.tensor([[True]]),
    )
    mask = capsule_masks(caps, H, W)[0].numpy()
    ref = cv2_capsule_mask(pa, pb, ra, rb, H, W)
    v, u = np.mgrid[0:H, 0:W]
    sdf = _uneven_capsule_sdf(
        torch.from_numpy(np.stack([u, v], -1)).double(),
        torch.tensor(pa),
        torch.tensor(pb),
        torch.tensor(ra),
        torch.tensor(rb),
    ).numpy()
    differ = mask != ref
    # OpenCV fills a little beyond the exact edge (up to ~0.7 px); every pixel centre further than that from
    # the boundary must agree, and the disagreement band is thin.
    assert np.abs(sdf[differ]).max(initial=0) < 0.75
    assert differ.sum() < 0.25 * ref.sum() and mask.sum() > 0


def test_capsule_masks_union_soft_and_invalid():
    caps = Capsules2D(
        torch.tensor([[[10.0, 10.0], [30.0, 20.0]]]),
        torch.tensor([[[20.0, 10.0], [30.0, 25.0]]]),
        torch.tensor([[3.0, 2.0]]),
        torch.tensor([[3.0, 2.0]]),
        torch.tensor([[True, False]]),
    )
    hard = capsule_masks(caps, 32, 40)
    assert hard.dtype == torch.bool and hard.shape == (1, 32, 40)
    assert bool(hard[0, 10, 15]) and not bool(hard[0, 22, 30])  # the invalid capsule is not drawn
    soft = capsule_masks(caps, 32, 40, soft=0.5)
    assert soft.dtype == torch.float32 and float(soft[0, 10, 15]) > 0.99 and float(soft[0, 0, 0]) < 1e-6


def _caps(seed, n=4, C=3):
    g = torch.Generator().manual_seed(seed)
    pa = torch.rand(n, C, 2, generator=g, dtype=torch.float64) * 60 + 10
    pb = pa + torch.randn(n, C, 2, generator=g, dtype=torch.float64) * 15
    ra = torch.rand(n, C, generator=g, dtype=torch.float64) * 5 + 2
    rb = torch.rand(n, C, generator=g, dtype=torch.float64) * 5 + 2
    return Capsules2D(pa, pb, ra, rb, torch.ones(n, C, dtype=torch.bool))


def round_cone_sdf(p, pa, pb, ra, rb):
    """Independent per-point formula of the sampled region {|p - q(t)| <= r(t)}."""
    e = pb - pa
    t = np.clip((p - pa) @ e / (e @ e), 0, 1)
    return np.linalg.norm(p - pa - t * e) - (ra + t * (rb - ra))


@pytest.mark.parametrize("generator", [None, 7])
def test_sample_in_capsules_inside_and_area(generator):
    caps = _caps(0)
    gen = None if generator is None else torch.Generator().manual_seed(generator)
    pts, w = sample_in_capsules(caps, 24, 6, generator=gen)
    assert pts.shape == (4, 3 * 36, 2) and w.shape == (4, 3 * 36)
    for n in range(4):
        for c in range(3):
            sl = slice(c * 36, (c + 1) * 36)
            args = [x[n, c].numpy() for x in (caps.pa, caps.pb, caps.ra, caps.rb)]
            sd = np.array([round_cone_sdf(p, *args) for p in pts[n, sl].numpy()])
            assert sd.max() < 1e-9
            pa, pb, ra, rb = args
            area = np.linalg.norm(pb - pa) * (ra + rb) + 0.5 * np.pi * (ra**2 + rb**2)
            assert w[n, sl].sum().item() == pytest.approx(area, rel=1e-9)
    if gen is not None:
        again, _ = sample_in_capsules(caps, 24, 6, generator=torch.Generator().manual_seed(generator))
        assert torch.equal(pts, again)


def test_sample_in_capsules_is_area_uniform():
    # The weighted share of points left of a vertical line equals the share of area (pixel count) there.
    caps = Capsules2D(
        torch.tensor([[[20.0, 30.0]]]),
        torch.tensor([[[90.0, 40.0]]]),
        torch.tensor([[4.0]]),
        torch.tensor([[12.0]]),
        torch.tensor([[True]]),
    )
    pts, w = sample_in_capsules(caps, 400, 100)
    mask = capsule_masks(caps, 80, 120)[0]
    for x in (30.0, 55.0, 80.0):
        share = (w * (pts[..., 0] < x)).sum() / w.sum()
        pix = mask[:, : int(x + 0.5)].sum() / mask.sum()
        assert share.item() == pytest.approx(pix.item(), abs=0.02)


def test_capsule_coverage_matches_masks():
    caps = _caps(1, n=2)
    H, W = 90, 100
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    grid = torch.stack([u, v], -1).reshape(-1, 2)
    cov = capsule_coverage(grid, caps).reshape(2, H, W)
    mask = capsule_masks(caps, H, W).double()
    differ = cov != mask
    assert differ.sum() <= 0.01 * mask.sum()
    # Counting mode: pixels covered by two capsules count twice; per-pose points give the same values.
    count = capsule_coverage(grid, caps, reduce="sum")
    assert torch.equal(count >= 1, cov.reshape(2, -1) > 0)
    per_pose = capsule_coverage(grid.expand(2, -1, 2), caps)
    assert torch.equal(per_pose, cov.reshape(2, -1))
    soft = capsule_coverage(grid, caps, softness=1.0).reshape(2, H, W)
    assert float((soft - cov).abs().max()) <= 1.0 and bool(((soft > 0) & (soft < 1)).any())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_hard_coverage_kernel_matches_tensor_version_and_formula(dtype, monkeypatch):
    """The fused CPU kernel of the hard coverage (:mod:`torchpf.geometry._coverage_cpu`) gives the tensor
    version's 0/1 values and the per-point formula's (:func:`round_cone_sdf` <= 0), for shared, per-camera
    and per-pose points, with invalid, NaN, zero-length and zero-radius capsules; only points within
    rounding of a boundary may differ."""
    from torchpf.geometry import _coverage_cpu

    if not _coverage_cpu.AVAILABLE:
        pytest.skip("numba is not installed")
    V, N, C = 2, 5, 6
    base = _caps(11, n=V * N, C=C)
    caps = Capsules2D(
        *(f.reshape(V, N, *f.shape[1:]).clone() for f in (base.pa, base.pb, base.ra, base.rb, base.valid))
    )
    caps.valid[0, 1, 2] = False
    caps.pa[1, 3, 4] = float("nan")
    caps.pb[0, 2, 1] = caps.pa[0, 2, 1]  # a disc
    caps.ra[1, 0, 0] = caps.rb[1, 0, 0] = 0.0  # covers only the points on its axis
    caps = Capsules2D(
        *(
            f.to(dtype) if f.is_floating_point() else f
            for f in (caps.pa, caps.pb, caps.ra, caps.rb, caps.valid)
        )
    )
    g = torch.Generator().manual_seed(3)
    layouts = {
        "shared": torch.rand(300, 2, generator=g, dtype=torch.float64) * 90,
        "per camera": torch.rand(V, 1, 300, 2, generator=g, dtype=torch.float64) * 90,
        "per pose": torch.rand(V, N, 300, 2, generator=g, dtype=torch.float64) * 90,
    }
    layouts["shared"][7] = float("nan")  # a NaN point is covered by nothing
    for name, pts in layouts.items():
        pts = pts.to(dtype)
        monkeypatch.setenv("TORCHPF_FUSED", "0")
        tensor = capsule_coverage(pts, caps)
        monkeypatch.setenv("TORCHPF_FUSED", "1")
        fused = capsule_coverage(pts, caps)
        assert fused.shape == tensor.shape == (V, N, 300) and fused.dtype == dtype, name
        # the definition, per point and capsule in float64 (NaN and invalid capsules cover nothing)
        P = pts.double().expand(V, N, 300, 2).numpy()
        pa, pb, ra, rb = (f.double().numpy() for f in (caps.pa, caps.pb, caps.ra, caps.rb))
        margin = np.full((V, N, 300), np.inf)
        for v, n, c in np.ndindex(V, N, C):
            if not bool(caps.valid[v, n, c]) or np.isnan(pa[v, n, c]).any():
                continue
            e = pb[v, n, c] - pa[v, n, c]
            ee = e @ e
            t = np.clip((P[v, n] - pa[v, n, c]) @ e / ee, 0, 1) if ee > 1e-12 else np.zeros(300)
            d = np.linalg.norm(P[v, n] - pa[v, n, c] - t[:, None] * e, axis=-1)
            margin[v, n] = np.minimum(margin[v, n], d - (ra[v, n, c] + t * (rb[v, n, c] - ra[v, n, c])))
        sure = np.abs(margin) > (1e-9 if dtype == torch.float64 else 1e-3)
        want = torch.from_numpy(margin <= 0).to(dtype)
        assert torch.equal(fused[sure], want[sure]), name
        assert torch.equal(tensor[sure], want[sure]), name
        assert 0.1 < float(want.mean()) < 0.9, name  # both outcomes are tested
        if name == "shared":
            assert not fused[..., 7].any() and not tensor[..., 7].any()


def test_capsule_coverage_exclude_own_and_gradient():
    caps = _caps(2, n=1, C=2)
    pts, _ = sample_in_capsules(caps, 8, 2)
    own = capsule_coverage(pts, caps, reduce="sum")
    others = capsule_coverage(pts, caps, reduce="sum", exclude_own=12)
    assert bool((own - others >= 1 - 1e-12).all())
    ra = caps.ra.clone().requires_grad_()
    g = (
        torch.tensor([[40.0, 40.0]], dtype=torch.float64).expand(1, 50, 2)
        + torch.randn(1, 50, 2, dtype=torch.float64) * 10
    )
    cov = capsule_coverage(g, Capsules2D(caps.pa, caps.pb, ra, caps.rb, caps.valid), softness=2.0).sum()
    cov.backward()
    assert torch.isfinite(ra.grad).all()


def test_points_per_camera_broadcast_and_chunks():
    """(V, 1, P, 2) points against (V, N, C) capsules (each camera's points shared by its poses) give what
    V separate calls give, in any chunking; empty batches give empty results."""
    caps = _caps(4, n=6, C=3)
    V, N = 2, 3
    caps = Capsules2D(
        *(f.reshape(V, N, *f.shape[1:]) for f in (caps.pa, caps.pb, caps.ra, caps.rb, caps.valid))
    )
    caps.valid[1, 2, 0] = False
    pts = torch.rand(V, 1, 40, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 80
    for fn, kw in [
        (capsule_coverage, {}),
        (capsule_coverage, {"softness": 1.5}),
        (capsule_coverage, {"reduce": "sum"}),
        (distance_to_capsules, {}),
    ]:
        loop = torch.stack(
            [
                fn(pts[v, 0], Capsules2D(caps.pa[v], caps.pb[v], caps.ra[v], caps.rb[v], caps.valid[v]), **kw)
                for v in range(V)
            ]
        )
        torch.testing.assert_close(fn(pts, caps, **kw), loop, rtol=1e-12, atol=1e-12)
        per_pose = pts.expand(V, N, 40, 2)
        torch.testing.assert_close(fn(per_pose, caps, **kw), loop, rtol=1e-12, atol=1e-12)
        if fn is capsule_coverage:
            for chunk in (1, 2, 5):
                torch.testing.assert_close(
                    fn(pts, caps, chunk_size=chunk, **kw), loop, rtol=1e-12, atol=1e-12
                )
    empty = Capsules2D(*(f[:, :0] for f in (caps.pa, caps.pb, caps.ra, caps.rb, caps.valid)))
    assert capsule_coverage(pts, empty).shape == (V, 0, 40)
    with pytest.raises(ValueError, match="batch dims"):
        capsule_coverage(pts[None], caps)


def test_distance_to_capsules_value_and_gradient_match_the_closed_form():
    """The distance and its gradient (recomputed for each point's nearest capsule) against the closed form
    min over capsules of |p - q(t)| - r(t), differentiated by autograd."""
    caps = _caps(5, n=4, C=3)
    caps.valid[2, 1] = False
    pts = torch.rand(4, 30, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 90
    leaves = [f.clone().requires_grad_() for f in (caps.pa, caps.pb, caps.ra, caps.rb)]
    got = distance_to_capsules(pts, Capsules2D(*leaves, caps.valid))
    grads = torch.autograd.grad(got.sum(), leaves)
    ref_leaves = [f.clone().requires_grad_() for f in (caps.pa, caps.pb, caps.ra, caps.rb)]
    pa, pb = (f.unsqueeze(-2) for f in ref_leaves[:2])  # (N, C, 1, 2)
    ra, rb = (f.unsqueeze(-1) for f in ref_leaves[2:])  # (N, C, 1)
    diff, e = pts.unsqueeze(1) - pa, pb - pa
    t = ((diff * e).sum(-1) / (e * e).sum(-1)).clamp(0, 1)
    d = (diff - t.unsqueeze(-1) * e).norm(dim=-1) - (ra + t * (rb - ra))
    ref = torch.where(caps.valid.unsqueeze(-1), d, torch.inf).amin(1).clamp_min(0)
    torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-9)
    for g, r in zip(grads, torch.autograd.grad(ref.sum(), ref_leaves), strict=True):
        torch.testing.assert_close(g, r, rtol=1e-9, atol=1e-9)
    with torch.no_grad():
        torch.testing.assert_close(distance_to_capsules(pts, caps), ref.detach(), rtol=1e-9, atol=1e-9)


def test_outline_points_lie_on_the_boundary():
    caps = _caps(3, n=2, C=2)
    pts, ok = outline_points(caps, 5, 3)
    assert pts.shape == (2, 2 * 16, 2) and bool(ok.all())
    for n in range(2):
        for c in range(2):
            args = [x[n, c].numpy() for x in (caps.pa, caps.pb, caps.ra, caps.rb)]
            sd = np.array([round_cone_sdf(p, *args) for p in pts[n, c * 16 : (c + 1) * 16].numpy()])
            np.testing.assert_allclose(sd, 0.0, atol=1e-9)


def test_projected_geometry_follows_the_device(device, dtype, generator):
    rig, a, b, r = _rig_and_capsules()
    ref = project_capsules(rig, a, b, r)
    caps = project_capsules(rig.to(device), *(x.to(device, dtype) for x in (a, b, r)))
    rig.to("cpu")
    for x, y in zip((caps.pa, caps.ra), (ref.pa, ref.ra), strict=True):
        assert x.device.type == device.type and x.dtype == dtype
        torch.testing.assert_close(x.cpu().double(), y, rtol=1e-4, atol=1e-3)
    one = caps.unbind(1)[0]
    pts, w = sample_in_capsules(one, 8, 2, generator=generator)
    cover = capsule_coverage(pts, one, softness=1.0)
    outline, ok = outline_points(one, 4, 2)
    masks = capsule_masks(one, 120, 160)
    for t in (pts, w, cover, outline, ok, masks):
        assert t.device.type == device.type
    assert (
        pts.dtype == dtype and cover.dtype == dtype and bool((cover >= 0.5 - 1e-4).all())
    )  # inside: ramp >= 1/2
