"""Mirror limbs and their swap, from the tree and the rest pose: the swapped pose's joints are the reflection
of the original's (closed-form geometry), whatever the joints are called."""

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import path
from torchpf.kinematics.symmetry import limb_swaps, mirror_limbs


@pytest.fixture(scope="module", params=["human.urdf", "fontmarty22.urdf"])
def skeleton(request):
    return Skeleton.from_urdf(path(request.param)).double()


def _limb_pose(skel, swap, seed):
    """Zero pose (root and torso included: a symmetric body) with random angles on both limbs of ``swap``."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(len(skel.dof_names), dtype=torch.float64)
    for idx in (swap.a, swap.b):
        x[idx] = 0.6 * torch.randn(len(idx), generator=g, dtype=torch.float64)
    return skel.clamp(x)


def test_swap_reflects_the_limbs(skeleton):
    pairs = [(a, b, n) for a, b, n in mirror_limbs(skeleton) if b is not None]
    swaps = limb_swaps(skeleton)
    assert len(pairs) == len(swaps) == 2  # legs and arms, found without names
    rest = skeleton.fk(torch.zeros(len(skeleton.dof_names), dtype=torch.float64))
    for (a, b, normal), swap in zip(pairs, swaps, strict=True):
        mid = 0.5 * (rest[a].mean(0) + rest[b].mean(0))

        def reflect(p, mid=mid, normal=normal):
            return p - 2 * ((p - mid) @ normal)[..., None] * normal

        for seed in range(3):
            x = _limb_pose(skeleton, swap, seed)
            y = swap(x)
            before, after = skeleton.fk(x), skeleton.fk(y)
            # the swapped limb b is limb a reflected across the body's mirror plane, and vice versa
            torch.testing.assert_close(after[b], reflect(before[a]), atol=1e-9, rtol=0)
            torch.testing.assert_close(after[a], reflect(before[b]), atol=1e-9, rtol=0)
            torch.testing.assert_close(swap(y), x, atol=0, rtol=0)
            others = torch.ones(len(x), dtype=torch.bool)
            others[swap.a] = others[swap.b] = False
            assert torch.equal(y[others], x[others])


def test_swap_is_batched_and_follows_the_device(device):
    skel = Skeleton.from_urdf(path("human.urdf"))
    swap = limb_swaps(skel)[0].to(device)
    assert swap.a.device.type == device.type
    x = torch.randn(5, 3, len(skel.dof_names), device=device)
    y = swap(x)
    assert y.shape == x.shape and y.dtype == x.dtype and y.device == x.device
    torch.testing.assert_close(y[1, 2], swap(x[1, 2]))


def test_asymmetric_limbs_are_not_swapped():
    human = Skeleton.from_urdf(path("human.urdf")).double()
    lopsided = human.with_body(lengths={"LeftLeg": 1.4})  # the left thigh 40 % longer: no mirror pair
    swaps = limb_swaps(lopsided)
    assert len(swaps) == 1  # the arms only
    arm = {lopsided.dof_names[i] for i in swaps[0].a.tolist() + swaps[0].b.tolist()}
    assert "LeftArm_Zrotation" in arm and not any("Leg" in n for n in arm)


def test_tracker_gives_the_hybrid_the_swaps():
    from torchpf import Tracker
    from torchpf.camera import camera_ring

    skel = Skeleton.from_urdf(path("human.urdf"))
    tracker = Tracker(
        skel, camera_ring(3, radius=4.0, width=80, height_px=60), n_particles=100, progress=False
    )
    assert tracker.filter_name == "hybrid" and len(tracker.filter.swaps) == 2
    off = Tracker(
        skel,
        camera_ring(3, radius=4.0, width=80, height_px=60),
        n_particles=100,
        progress=False,
        filter_options={"swaps": ()},
    )
    assert len(off.filter.swaps) == 0
