"""Local pose refinement (`torchpf.refine.Refiner`) and its cue (`SilhouetteDistanceLikelihood`).

The masks come from the independent renderer of `_masks.py` (convex hulls of projected sphere points drawn
with OpenCV), not from torchpf.synth or torchpf.geometry, so the refiner's optimum is the renderer's pose up
to the capsule model's pixel-level differences, not a copy of its own rendering.
"""

import copy
import math

import numpy as np
import pytest
import torch

from torchpf.camera import camera_ring
from torchpf.geometry import Capsules2D, distance_to_capsules
from torchpf.likelihoods import DualSilhouetteLikelihood, SilhouetteDistanceLikelihood
from torchpf.observations import Silhouettes
from torchpf.refine import Refiner

from ._masks import render_masks


@pytest.fixture(scope="module")
def scene(human):
    """3 cameras 160x120 on a 3 m ring, 4 poses with random limb angles, masks of the shipped body."""
    rig = camera_ring(3, radius=3.0, height=1.5, target=(0, 0, 0.85), width=160, height_px=120)
    g = torch.Generator().manual_seed(3)
    D = len(human.dof_names)
    rev = human.dof_revolute
    poses = torch.zeros(4, D, dtype=torch.float64)
    poses[:, rev] = 0.3 * torch.randn(4, int(rev.sum()), generator=g, dtype=torch.float64)
    poses[:, :6] = 0.0
    poses = human.clamp(poses)
    up = human.dof_names.index("Hips_Yposition")  # its URDF axis is world z
    poses[:, up] = 0.05 - human.fk(poses)[..., 2].min(-1).values
    joints = human.fk(poses)
    obs = [Silhouettes(render_masks(joints[f], human.tree.bones, human.radii, rig.cameras)) for f in range(4)]
    return {"rig": rig, "poses": poses, "obs": obs}


def _mpjpe(skel, a, b):
    return float((skel.fk(a) - skel.fk(b)).norm(dim=-1).mean())


def test_distance_to_capsules_matches_the_closed_form():
    # a straight capsule (radius 2 from (0,0) to (10,0)) and a disc (radius 3 at (20,20)): distance to the
    # union is the min of |p - segment| - 2 and |p - c| - 3, floored at 0
    caps = Capsules2D(
        pa=torch.tensor([[0.0, 0.0], [20.0, 20.0]], dtype=torch.float64),
        pb=torch.tensor([[10.0, 0.0], [20.0, 20.0]], dtype=torch.float64),
        ra=torch.tensor([2.0, 3.0], dtype=torch.float64),
        rb=torch.tensor([2.0, 3.0], dtype=torch.float64),
        valid=torch.tensor([True, True]),
    )
    pts = torch.tensor([[5.0, 6.0], [-4.0, 0.0], [14.0, 3.0], [20.0, 30.0], [1.0, 1.0], [21.0, 19.0]])
    pts = pts.double()
    seg = np.array([np.hypot(u - np.clip(u, 0, 10), v) - 2 for u, v in pts.numpy()])
    disc = np.hypot(pts[:, 0].numpy() - 20, pts[:, 1].numpy() - 20) - 3
    want = np.maximum(np.minimum(seg, disc), 0.0)
    got = distance_to_capsules(pts, caps)
    np.testing.assert_allclose(got.numpy(), want, atol=1e-9)
    # an invalid capsule is ignored
    caps.valid[1] = False
    np.testing.assert_allclose(distance_to_capsules(pts, caps).numpy(), np.maximum(seg, 0.0), atol=1e-9)


def test_outside_distance_is_zero_inside_and_grows_outside():
    mask = np.zeros((20, 30), np.uint8)
    mask[5:10, 5:15] = 255
    d = Silhouettes(mask).outside_distance()[0]
    assert float(d[5:10, 5:15].abs().max()) == 0.0
    assert float(d[7, 20]) == pytest.approx(20 - 14 - 0.5, abs=1e-3)  # 6 pixel centres right of the edge
    assert float(d[7, 25]) > float(d[7, 20])


def test_distance_cue_peaks_at_the_rendered_pose_and_has_a_gradient_far_from_it(human, scene):
    lik = SilhouetteDistanceLikelihood(human, scene["rig"]).double()
    dual = DualSilhouetteLikelihood(human, scene["rig"]).double()
    truth, obs = scene["poses"][0], scene["obs"][0]
    j = human.dof_names.index("Hips_Xposition")
    shifts = torch.linspace(-0.6, 0.6, 25, dtype=torch.float64)
    x = truth.repeat(25, 1)
    x[:, j] += shifts
    values = lik(x, obs)
    assert int(values.argmax()) == 12, values  # the peak at no shift
    # 0.5 m off (a body width): Fontmarty's dual cue is nearly flat there, the distance cue keeps pulling
    far = x[[1, -2]].clone().requires_grad_(True)
    (g,) = torch.autograd.grad(lik(far, obs).sum(), far)
    assert g[0, j] > 0 and g[1, j] < 0  # uphill is back towards the truth from both sides
    assert torch.isfinite(dual(x, obs)).all()


def test_empty_and_invalid_cameras_contribute_nothing(human, scene):
    lik = SilhouetteDistanceLikelihood(human, scene["rig"]).double()
    masks = scene["obs"][0].masks.clone()
    x = scene["poses"][:2]
    full = lik(x, Silhouettes(masks))
    masks[1] = 0
    without = lik(x, Silhouettes(masks))
    two = lik(x, Silhouettes(scene["obs"][0].masks, valid=torch.tensor([True, False, True])))
    torch.testing.assert_close(without, two)
    assert (without >= full).all()  # one camera's cost removed


def test_refiner_brings_perturbed_poses_back(human, scene):
    g = torch.Generator().manual_seed(0)
    rev = human.dof_revolute
    refiner = Refiner(human, scene["rig"], steps=40).double()
    before, after = [], []
    for f in range(4):
        truth = scene["poses"][f]
        start = human.clamp(
            truth
            + torch.randn(3, len(truth), generator=g, dtype=torch.float64) * torch.where(rev, 0.12, 0.04)
        )
        out = refiner(start, scene["obs"][f])
        assert (out.loss <= out.loss_before + 1e-9).all()  # keep-best: never worse on the objective
        assert torch.equal(human.clamp(out.x), out.x)  # inside the limits
        before.append(_mpjpe(human, start, truth))
        after.append(_mpjpe(human, out.x, truth))
    # measured: about 55 mm -> 25 mm; the capsule model differs from the renderer's hulls by a pixel
    assert np.mean(after) < 0.6 * np.mean(before), (before, after)


def test_refiner_follows_the_poses_device(human, scene, device):
    """The refiner runs where its poses are (one device rule) and lands where the CPU's run lands."""
    g = torch.Generator().manual_seed(2)
    truth, obs = scene["poses"][1], scene["obs"][1]
    start = human.clamp(truth + 0.05 * torch.randn(2, len(truth), generator=g, dtype=torch.float64))
    cpu = Refiner(human, scene["rig"], steps=15).double()(start, obs)
    # a copy: .to() moves a module's skeleton in place, and `human` is shared by the session's tests
    refiner = Refiner(copy.deepcopy(human), copy.deepcopy(scene["rig"]), steps=15).double().to(device)
    out = refiner(start.to(device), obs)
    assert out.x.device.type == device.type and out.loss.device.type == device.type
    # float64 on both: the runs agree to rounding, well inside a millimetre of joint position
    assert _mpjpe(human, out.x.cpu(), cpu.x) < 1e-3
    torch.testing.assert_close(out.loss.cpu(), cpu.loss, rtol=1e-6, atol=1e-9)


def test_refiner_is_batch_independent_and_respects_frozen_dofs(human, scene):
    frozen = torch.zeros(len(human.dof_names), dtype=torch.bool)
    frozen[:6] = True  # the root
    refiner = Refiner(human, scene["rig"], steps=5, frozen=frozen).double()
    g = torch.Generator().manual_seed(1)
    start = scene["poses"][0] + 0.1 * torch.randn(3, len(human.dof_names), generator=g, dtype=torch.float64)
    start = human.clamp(start)
    both = refiner(start, scene["obs"][0]).x
    alone = refiner(start[1:2], scene["obs"][0]).x
    torch.testing.assert_close(both[1:2], alone)
    torch.testing.assert_close(both[:, :6], start[:, :6], rtol=0, atol=0)
    assert not torch.equal(both[:, 6:], start[:, 6:])


def test_a_prior_holds_the_pose_and_a_nan_pose_is_kept(human, scene):
    truth, obs = scene["poses"][0], scene["obs"][0]
    start = human.clamp(truth + 0.1 * torch.randn(2, len(truth), generator=torch.Generator().manual_seed(4)))
    free = Refiner(human, scene["rig"], steps=10).double()(start, obs).x
    held = (
        Refiner(human, scene["rig"], steps=10)
        .double()(start, obs, log_prior=lambda x: -0.5 * ((x - start) / 0.01).square().sum(-1))
        .x
    )
    assert (held - start).abs().mean() < 0.5 * (free - start).abs().mean()
    refiner = Refiner(human, scene["rig"], steps=3).double()
    x = scene["poses"][:2].clone()
    x[0, 7] = math.nan
    out = refiner(x, scene["obs"][0])
    assert torch.isnan(out.x[0, 7])  # returned as given, never "refined" into something else
    assert torch.isfinite(out.x[1]).all()
    assert refiner.evaluations(4) == math.ceil(4 * (3 * Refiner.cost_per_step + 1))


def test_despeckle_removes_salt_and_keeps_limbs():
    mask = np.zeros((40, 60), np.uint8)
    mask[10:30, 20:25] = 255  # a 5-px limb
    noisy = mask.copy()
    rng = np.random.default_rng(0)
    ys, xs = rng.integers(0, 40, 30), rng.integers(0, 60, 30)
    noisy[ys, xs] = 255 - noisy[ys, xs]  # 30 flipped pixels, salt and pepper
    clean = Silhouettes(noisy).despeckled(3)
    kept = clean.masks[0].numpy() > 0.5
    assert (kept & (mask == 0)).sum() == 0  # no isolated salt pixel survives
    assert (kept[12:28, 21:24]).all()  # the limb's interior is intact
    obs = Silhouettes(noisy)
    assert obs.despeckled(3) is obs.despeckled(3) and obs.despeckled(1) is obs


def test_the_linear_part_gives_the_distance_cue_a_slope_at_the_boundary(human, scene):
    """A squared distance has no slope at the mask's boundary: shifting the body half a pixel (1 cm at 3 m)
    from the rendered pose costs it almost nothing, so the refinement's normalised steps walk along a flat
    optimum. The linear part (``linear``, pixels) makes the same shift cost many times more."""
    truth, obs = scene["poses"][0], scene["obs"][0]
    up = human.dof_names.index("Hips_Yposition")
    x = truth.repeat(3, 1)
    x[:, up] += torch.tensor([-0.01, 0.0, 0.01], dtype=torch.float64)
    drops = {}
    for a in (0.0, 4.0):
        values = SilhouetteDistanceLikelihood(human, scene["rig"], linear=a).double()(x, obs)
        assert int(values.argmax()) == 1  # the rendered pose is best either way
        drops[a] = float(2 * values[1] - values[0] - values[2])
    assert drops[4.0] > 10 * drops[0.0] > 0, drops  # measured: 0.002 and 0.06 nats
    with pytest.raises(ValueError, match="linear"):
        SilhouetteDistanceLikelihood(human, scene["rig"], linear=-1.0)


class _SlopeCue(torch.nn.Module):
    """``log p = -((x_a - 0.3) / 0.05)^2 / 2 - 1e-6 x_b``: one DOF the cue sees, one it barely sees."""

    def __init__(self, a: int, b: int):
        super().__init__()
        self.a, self.b = a, b

    def forward(self, x, obs):
        return -0.5 * ((x[..., self.a] - 0.3) / 0.05).square() - 1e-6 * x[..., self.b]


def test_damping_keeps_a_dof_the_cue_barely_sees_still(human):
    """Adam normalises each DOF's step by its gradient's size, so a DOF with a gradient of 1e-6 (rounding
    noise, or a mask defect's pull on a limb inside the silhouette) takes full steps; with ``damping`` its
    step is in proportion to its gradient, and the DOF the cue sees still converges."""
    rev = torch.nonzero(human.dof_revolute & (human.lower < -0.5) & (human.upper > 0.5)).flatten()
    a, b = int(rev[0]), int(rev[1])
    start = human.clamp(torch.zeros(1, len(human.dof_names), dtype=torch.float64))
    moved = {}
    for damping in (0.0, 0.1):
        out = Refiner(human, cue=_SlopeCue(a, b), steps=20, damping=damping).double()(start, None)
        assert abs(float(out.x[0, a]) - 0.3) < 0.05  # the seen DOF reaches its optimum either way
        moved[damping] = abs(float(out.x[0, b] - start[0, b]))
    assert moved[0.0] > 0.1  # plain Adam: ~20 steps of lr = 0.03 rad (decayed) for a 1e-6 slope
    assert moved[0.1] < 1e-4
    assert Refiner(human, cue=_SlopeCue(a, b)).damping == 0.1  # the default
    with pytest.raises(ValueError, match="damping"):
        Refiner(human, cue=_SlopeCue(a, b), damping=-1.0)
