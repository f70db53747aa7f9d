"""The masks' outline offset: ``Silhouettes.offset``, the silhouette cues' widened or thinned capsules, its
measurement by area matching (``ImageLikelihood.boundary_offset``) and ``Tracker(boundary_offset=True)``.

The masks come from the independent renderer of ``tests/torchpf/_masks.py`` (OpenCV convex hulls), and the
fattened or thinned masks from OpenCV's morphology, never from torchpf's own capsule geometry."""

import cv2
import numpy as np
import pytest
import torch

from torchpf import Tracker
from torchpf.camera import camera_ring
from torchpf.likelihoods import LIKELIHOODS
from torchpf.likelihoods.images import SilhouetteLikelihood
from torchpf.observations import Silhouettes

from .._masks import render_masks


@pytest.fixture(scope="module")
def scene(human):
    """The shipped human in a random pose, 3 cameras 160x120 on a 3 m ring, masks of its own capsules."""
    rig = camera_ring(3, radius=3.0, height=1.5, target=(0, 0, 0.85), width=160, height_px=120)
    D = len(human.dof_names)
    g = torch.Generator().manual_seed(3)
    pose = torch.zeros(D, dtype=torch.float64)
    pose[human.dof_revolute] = 0.3 * torch.randn(
        int(human.dof_revolute.sum()), generator=g, dtype=torch.float64
    )
    pose[:6] = 0.0
    pose = human.clamp(pose)
    up = human.dof_names.index("Hips_Yposition")
    pose[up] = 0.05 - float(human.fk(pose)[..., 2].min())
    masks = render_masks(human.fk(pose), human.tree.bones, human.radii, rig.cameras)
    return {"rig": rig, "pose": pose, "masks": masks}


def _disk(r):
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def test_offset_is_checked_and_carried():
    masks = torch.zeros(3, 12, 16)
    with pytest.raises(ValueError, match="offset must have one value per mask"):
        Silhouettes(masks, offset=torch.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        Silhouettes(masks, offset=torch.tensor([0.0, float("nan"), 0.0]))
    sil = Silhouettes(masks)
    dist = sil.outside_distance()
    moved = sil.with_offset(torch.tensor([1.0, -1.0, 0.5]))
    assert sil.offset is None and moved.outside_distance() is dist  # derived images are shared
    assert torch.equal(moved.despeckled(3).offset, moved.offset)
    assert sil.despeckled(3).offset is None  # the shared cache does not leak the copy's offset back


def test_capsules_widen_thin_and_vanish_with_the_offset(human, scene):
    lik = SilhouetteLikelihood(human, scene["rig"])
    body = lik.body(scene["pose"].float().reshape(1, 1, -1))
    plain = lik._caps2d(body, 1, 120, 160)
    off = torch.tensor([1.0, -0.5, -50.0])
    caps = lik._caps2d(body, 1, 120, 160, off)
    assert torch.allclose(caps.ra[0, 0], plain.ra[0, 0] + 1.0)
    assert torch.allclose(caps.rb[0, 1], (plain.rb[0, 1] - 0.5).clamp_min(0.5))
    # camera 1: a capsule thinner than the erosion at both ends is gone from the mask, the others stay
    thin = (plain.ra[0, 1] - 0.5 <= 0.5) & (plain.rb[0, 1] - 0.5 <= 0.5)
    assert torch.equal(caps.valid[0, 1], plain.valid[0, 1] & ~thin)
    assert not caps.valid[0, 2].any()  # an erosion wider than every limb leaves nothing to look for


def test_measured_offset_follows_opencv_dilation_and_erosion(human, scene):
    """At the true pose the model's own masks give ~0; OpenCV's dilation by a radius-1 disk (a 3x3 cross:
    between 1 px along the axes and 0.7 px along the diagonals) gives ~+0.85 px, erosion by it less than
    -0.6 px (thin parts vanish too, so the area drops by more than the outline's length); a radius-2 disk
    about twice as much."""
    lik = SilhouetteLikelihood(human, scene["rig"])
    pose, masks = scene["pose"], scene["masks"]

    def measure(ms):
        return lik.boundary_offset(pose, Silhouettes(np.stack(ms)), despeckle=1)

    base = measure(masks)
    assert base.abs().max() < 0.3
    grown = measure([cv2.dilate(m, _disk(1)) for m in masks]) - base
    assert torch.all((grown > 0.6) & (grown < 1.15)), grown
    grown2 = measure([cv2.dilate(m, _disk(2)) for m in masks])
    assert torch.all((grown2 - base > 1.5) & (grown2 <= 2.0)), grown2  # at most the limit, 2 px
    shrunk = measure([cv2.erode(m, _disk(1)) for m in masks])
    assert torch.all((shrunk - base < -0.6) & (shrunk >= -2.0)), shrunk
    # a pose error moves the model, not its area: 5 cm off at the root changes the offset little
    moved = pose.clone()
    moved[:3] += 0.05
    assert torch.allclose(lik.boundary_offset(moved, Silhouettes(masks), despeckle=1), base, atol=0.3)
    # nothing to match: an empty or invalid camera gets 0
    empty = Silhouettes(np.stack([masks[0] * 0, masks[1], masks[2]]), valid=torch.tensor([True, False, True]))
    assert torch.equal(lik.boundary_offset(pose, empty, despeckle=1)[:2], torch.zeros(2))


def test_offset_batches_over_sequences(human, scene):
    lik = SilhouetteLikelihood(human, scene["rig"])
    fat = np.stack([cv2.dilate(m, _disk(1)) for m in scene["masks"]])
    both = Silhouettes(np.stack([scene["masks"], fat]))  # (S=2, V, H, W)
    got = lik.boundary_offset(scene["pose"].expand(2, -1), both, despeckle=1)
    assert got.shape == (2, 3)
    for s, m in enumerate((scene["masks"], fat)):
        assert torch.allclose(got[s], lik.boundary_offset(scene["pose"], Silhouettes(m), despeckle=1))


def test_the_cues_prefer_the_true_pose_on_fattened_masks_once_told(human, scene):
    """On masks dilated by 2 px the dual cue scores the true pose worse than with the offset it is told;
    the offset restores a score close to the undilated masks'."""
    rig, pose = scene["rig"], scene["pose"].float()
    dual = LIKELIHOODS.get("dual_silhouette")(human, rig)
    fat = Silhouettes(np.stack([cv2.dilate(m, _disk(2)) for m in scene["masks"]]))
    told = fat.with_offset(dual.boundary_offset(pose, fat))
    clean = float(dual(pose[None], Silhouettes(scene["masks"])))
    assert float(dual(pose[None], told)) > float(dual(pose[None], fat)) + 1.0
    assert float(dual(pose[None], told)) > clean - 1.0


class _Recording(SilhouetteLikelihood):
    """A silhouette cue that remembers the offsets of the observations it scored."""

    seen: list

    def _log_lik(self, body, obs):
        self.seen.append(obs.offset)
        return super()._log_lik(body, obs)


def test_tracker_measures_the_offset_before_each_frame(human, scene):
    fat = np.stack([cv2.dilate(m, _disk(2)) for m in scene["masks"]])
    frames = [Silhouettes(scene["masks"]), Silhouettes(fat), Silhouettes(scene["masks"])]
    lik = _Recording(human, scene["rig"])
    lik.seen = []
    tracker = Tracker(
        human,
        scene["rig"],
        likelihood=lik,
        filter="apf",
        n_particles=30,
        fps=30,
        boundary_offset=True,
        progress=False,
    )
    result = tracker.track(frames, init=scene["pose"], calibrate=False)
    assert torch.isfinite(result.angles).all()
    offsets = [o for o in lik.seen if o is not None]
    assert len(offsets) == len(lik.seen) > 0  # every look had one
    assert max(float(o.min()) for o in offsets) > 1.0  # the dilated frame was seen as fattened
    lik.seen = []
    Tracker(human, scene["rig"], likelihood=lik, filter="apf", n_particles=30, fps=30, progress=False).track(
        frames, init=scene["pose"], calibrate=False
    )
    assert all(o is None for o in lik.seen)  # off by default


def test_the_smoothing_reads_the_masks_as_they_are(human, scene, monkeypatch):
    """The filter's cues see the measured offsets, the smoothing does not: smoothed on the offsets too, the
    noisy foreign renders tracked worse (BENCHMARKS.md, "The rig's unanimated channels, and the masks'
    outline offset, as defaults")."""
    import torchpf.tracker as tracker_module
    from torchpf.smooth import TrajectorySmoother

    measured, smoothed = [], []
    measure = tracker_module._with_outline_offset

    def spy(*a):
        out = measure(*a)
        measured.append(out.offset)
        return out

    smooth = TrajectorySmoother.forward

    def seen(self, x, observations):
        smoothed.extend(getattr(observations[t], "offset", None) for t in range(len(observations)))
        return smooth(self, x, observations)

    monkeypatch.setattr(tracker_module, "_with_outline_offset", spy)
    monkeypatch.setattr(TrajectorySmoother, "forward", seen)
    fat = np.stack([cv2.dilate(m, _disk(2)) for m in scene["masks"]])
    frames = [Silhouettes(scene["masks"]), Silhouettes(fat), Silhouettes(scene["masks"])]
    tracker = Tracker(human, scene["rig"], n_particles=30, fps=30, boundary_offset=True, progress=False)
    result = tracker.track(frames, init=scene["pose"], calibrate=False)
    assert result.filtered_angles is not None and torch.isfinite(result.angles).all()
    assert len(measured) == len(smoothed) == 3
    assert float(measured[1].min()) > 1.0  # the filter saw the dilated frame as fattened
    assert all(o is None for o in smoothed)
