"""3-D capsule geometry against brute-force loops, dense surface sampling and sphere tracing."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchpf.geometry import capsule_distance, capsule_truncated_cost, raycast_capsules


def random_capsules(seed, n=3, C=5, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(n, C, 3, generator=g, dtype=dtype) * 0.4
    b = a + torch.randn(n, C, 3, generator=g, dtype=dtype) * 0.3
    r = torch.rand(C, generator=g, dtype=dtype) * 0.08 + 0.02
    return a, b, r


def brute_force_distance(P, a, b, r):
    """Per point, per capsule: distance to the segment minus the radius, minimum over capsules."""
    P, a, b, r = (x.detach().double().numpy() for x in (P, a, b, r))
    out = np.empty((a.shape[0], P.shape[0]))
    for n in range(a.shape[0]):
        for k, p in enumerate(P):
            best = math.inf
            for c in range(a.shape[1]):
                e = b[n, c] - a[n, c]
                ee = e @ e
                t = 0.0 if ee == 0 else min(1.0, max(0.0, (p - a[n, c]) @ e / ee))
                best = min(best, np.linalg.norm(p - a[n, c] - t * e) - r[c])
            out[n, k] = best
    return out


@pytest.mark.parametrize("seed", range(3))
def test_capsule_distance_matches_brute_force(seed):
    a, b, r = random_capsules(seed)
    P = torch.randn(80, 3, generator=torch.Generator().manual_seed(100 + seed), dtype=torch.float64) * 0.6
    ref = brute_force_distance(P, a, b, r)
    d = capsule_distance(P, a, b, r)
    assert d.shape == (3, 80)
    np.testing.assert_allclose(d.numpy(), ref, atol=1e-10)
    # float32: the quadratic-form expansion is centred, so the error stays far below a millimetre.
    d32 = capsule_distance(P.float(), a.float(), b.float(), r.float())
    assert d32.dtype == torch.float32
    np.testing.assert_allclose(d32.double().numpy(), ref, atol=2e-5)
    # Chunking does not change the result; per-pose point clouds go through the batched GEMM path.
    np.testing.assert_allclose(capsule_distance(P, a, b, r, chunk_size=1).numpy(), ref, atol=1e-10)
    Pb = P.expand(3, 80, 3)
    np.testing.assert_allclose(capsule_distance(Pb, a, b, r).numpy(), ref, atol=1e-10)


def test_capsule_distance_far_from_origin_and_degenerate():
    # A zero-length capsule is a sphere; points 1000 m from the origin keep float32 accuracy after centring.
    a = torch.tensor([[[1000.0, 0.0, 0.0], [1000.0, 1.0, 0.0]]])
    b = torch.tensor([[[1000.0, 0.0, 0.0], [1000.0, 1.0, 1.0]]])
    r = torch.tensor([0.1, 0.05])
    P = torch.tensor([[1000.5, 0.0, 0.0], [1000.0, 1.2, 0.5], [1000.0, 1.0, 2.0]])
    d = capsule_distance(P, a, b, r)
    np.testing.assert_allclose(d[0].numpy(), [0.4, 0.15, 0.95], atol=1e-4)
    # An outlier 1e6 m away does not spoil the precision of the other points.
    P2 = torch.cat([P, torch.tensor([[1e6, 1e6, 1e6]])])
    np.testing.assert_allclose(capsule_distance(P2, a, b, r)[0, :3].numpy(), [0.4, 0.15, 0.95], atol=1e-4)


@given(
    st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    st.floats(0.01, 0.3),
    st.floats(0.0, 0.6),
)
@settings(max_examples=40, deadline=None)
def test_capsule_distance_closed_form_cylinder(p, radius, length):
    # Capsule along z from 0 to `length`: the closed form is the distance to the clamped axis point.
    a = torch.zeros(1, 1, 3, dtype=torch.float64)
    b = torch.tensor([[[0.0, 0.0, length]]], dtype=torch.float64)
    P = torch.tensor([p], dtype=torch.float64)
    z = min(max(p[2], 0.0), length)
    expected = math.sqrt(p[0] ** 2 + p[1] ** 2 + (p[2] - z) ** 2) - radius
    d = capsule_distance(P, a, b, torch.tensor([radius], dtype=torch.float64))
    assert d.item() == pytest.approx(expected, abs=1e-9)


def test_capsule_distance_broadcast_and_gradient():
    a, b, r = random_capsules(4, n=2, C=3)
    P = torch.randn(2, 1, 6, 3, dtype=torch.float64)  # (2, 1) broadcasts against (2,) only at dim -3
    a4, b4 = a.expand(2, 2, 3, 3), b.expand(2, 2, 3, 3)
    d = capsule_distance(P, a4, b4, r)
    assert d.shape == (2, 2, 6)
    np.testing.assert_allclose(
        d[1, 0].numpy(), brute_force_distance(P[1, 0], a4[1, :1], b4[1, :1], r)[0], atol=1e-10
    )
    ag = a[:1].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: capsule_distance(P[0, 0], x, b[:1], r), (ag,))


def half_capsule_reference(P, a, b, r, view_point, n_phi=720, n_t=400):
    """Distance to a densely sampled half-shell (spheres and cylinder, visible half only)."""
    a, b, vp = a.numpy(), b.numpy(), view_point.numpy()
    e = b - a
    L = np.linalg.norm(e)
    ex = e / L
    w = vp - 0.5 * (a + b)
    v = w - (w @ ex) * ex
    v /= np.linalg.norm(v)
    u = np.cross(ex, v)
    phi = np.linspace(-np.pi / 2, np.pi / 2, n_phi)
    t = np.linspace(0, L, n_t)
    ring = np.cos(phi)[:, None] * v + np.sin(phi)[:, None] * u  # unit directions with d.v >= 0
    cyl = a + t[:, None, None] * ex + r * ring[None]
    # End caps: hemispheres restricted to the visible half (n.v >= 0), outward along the axis.
    th = np.linspace(0, np.pi / 2, n_phi // 4)
    caps = []
    for centre, out in ((a, -ex), (b, ex)):
        dirs = np.cos(th)[:, None, None] * ring[None] + np.sin(th)[:, None, None] * out
        caps.append(centre + r * dirs.reshape(-1, 3))
    surf = np.concatenate([cyl.reshape(-1, 3)] + caps)
    return np.array([np.min(np.linalg.norm(surf - p, axis=1)) for p in P.numpy()])


def test_half_capsule_against_dense_surface():
    a = torch.tensor([0.1, -0.05, 0.9], dtype=torch.float64)
    b = torch.tensor([0.2, 0.1, 1.3], dtype=torch.float64)
    r = 0.06
    vp = torch.tensor([0.3, -3.0, 1.4], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    P = 0.5 * (a + b) + torch.randn(60, 3, generator=g, dtype=torch.float64) * 0.12
    d = capsule_distance(
        P, a[None, None], b[None, None], torch.tensor([r], dtype=torch.float64), view_point=vp
    )[0]
    ref = half_capsule_reference(P, a, b, r, vp)
    # Half-shell distance is unsigned except in front of the cut plane (where it equals the full capsule's).
    np.testing.assert_allclose(d.abs().numpy(), ref, atol=2e-3)
    full = capsule_distance(P, a[None, None], b[None, None], torch.tensor([r], dtype=torch.float64))[0]
    assert bool((d >= full - 1e-12).all())


def test_raycast_matches_sphere_tracing():
    a, b, r = random_capsules(5, n=1, C=4)
    a, b = (
        a[0] + torch.tensor([0, 0, 1.0], dtype=torch.float64),
        b[0] + torch.tensor([0, 0, 1.0], dtype=torch.float64),
    )
    origin = torch.tensor([0.0, -3.0, 1.0], dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    target = (
        torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        + torch.randn(300, 3, generator=g, dtype=torch.float64) * 0.3
    )
    dirs = target - origin
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    t_hit = raycast_capsules(origin, dirs, a, b, r)
    hit = torch.isfinite(t_hit)
    assert bool(hit.any()) and bool((~hit).any())
    # Independent reference 1: densely sampled rays. Before the hit (or everywhere on a miss) every sample is
    # outside all capsules; at the hit the signed distance is zero.
    ts = torch.linspace(0, 6, 3001, dtype=torch.float64)
    samples = origin + ts[None, :, None] * dirs[:, None]  # (300, S, 3)
    sd = capsule_distance(samples.reshape(-1, 1, 3), a, b, r).reshape(300, -1)
    before = ts[None] < torch.where(hit, t_hit, torch.full_like(t_hit, 1e9))[:, None] - 1e-9
    assert bool((sd[before] > -1e-9).all())
    at = capsule_distance((origin + t_hit[hit, None] * dirs[hit])[:, None], a, b, r)[:, 0]
    np.testing.assert_allclose(at.numpy(), 0.0, atol=1e-9)
    assert bool((sd[~hit].amin(-1) > -1e-9).all())
    # Independent reference 2: sphere tracing, wherever it converges.
    t = torch.zeros(300, dtype=torch.float64)
    for _ in range(200):
        d = capsule_distance((origin + t[:, None] * dirs)[:, None], a, b, r)[:, 0]
        t = (t + d.clamp_min(0)).clamp_max(10.0)
    conv = capsule_distance((origin + t[:, None] * dirs)[:, None], a, b, r)[:, 0] < 1e-8
    assert bool(conv.any())
    assert bool(hit[conv].all())
    np.testing.assert_allclose(t_hit[conv].numpy(), t[conv].numpy(), atol=1e-6)


def test_capsule_distance_follows_the_device(device, dtype):
    a, b, r = random_capsules(0)
    P = torch.randn(100, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = capsule_distance(*(x.to(device, dtype) for x in (P, a, b, r)))
    assert out.device.type == device.type and out.dtype == dtype
    np.testing.assert_allclose(
        out.cpu().double().numpy(),
        capsule_distance(P, a, b, r).numpy(),
        atol=1e-9 if dtype == torch.float64 else 1e-5,
    )


def _cost_case():
    a, b, r = random_capsules(6, n=7, C=5, dtype=torch.float32)
    P = torch.randn(50, 3, generator=torch.Generator().manual_seed(6)) * 0.5
    return P, a, b, r


@pytest.mark.parametrize("view", [None, (0.0, -3.0, 0.5)])
def test_truncated_cost_eager(view):
    P, a, b, r = _cost_case()
    vp = None if view is None else torch.tensor(view)
    ref = capsule_distance(P, a, b, r, view_point=vp).square().clamp_max(0.01).sum(-1)
    torch.testing.assert_close(capsule_truncated_cost(P, a, b, r, tau=0.01, view_point=vp), ref)


@pytest.mark.parametrize(
    "view",
    [None, pytest.param((0.0, -3.0, 0.5), marks=pytest.mark.slow)],  # each compile takes ~15 s
)
def test_truncated_cost_compiled(view):
    P, a, b, r = _cost_case()
    vp = None if view is None else torch.tensor(view)
    ref = capsule_distance(P, a, b, r, view_point=vp).square().clamp_max(0.01).sum(-1)
    got = capsule_truncated_cost(P, a, b, r, tau=0.01, view_point=vp, compile=True, chunk_size=3)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)


def test_chunks_are_cache_sized_on_the_cpu_and_memory_sized_elsewhere():
    """The chunked kernels split the poses for the CPU's cache; on a GPU each chunk costs kernel launches,
    so chunks there are as large as memory allows (the same results either way: chunking is tested above)."""
    from torchpf.geometry.capsules import _chunk_rows, chunk_elements

    assert chunk_elements("cpu") == 1 << 18 and chunk_elements("cpu", 1 << 17) == 1 << 17
    assert chunk_elements("cuda") == chunk_elements(torch.device("cuda", 0), 1 << 17) == 1 << 24
    assert _chunk_rows(27 * 1000, None, "cpu") == 9 and _chunk_rows(27 * 1000, None, "cuda") == 621
    assert _chunk_rows(27 * 1000, 5, "cuda") == 5  # an explicit chunk size wins
