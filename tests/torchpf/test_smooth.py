"""TrajectorySmoother: the MAP trajectory of a linear Gaussian model against its closed form, windows,
held DOFs, wrapped angles, non-finite frames, and the tracker's smoothed track."""

import copy
import math

import pytest
import torch
from torch import nn

from torchpf import Skeleton, metrics
from torchpf.assets import path
from torchpf.camera import camera_ring
from torchpf.io import read_mocap_csv
from torchpf.observations import Silhouettes
from torchpf.smooth import TrajectorySmoother
from torchpf.synth import synthesize
from torchpf.tracker import Tracker
from training.synthetic import generate

R = 0.05  # the quadratic cue's std (rad / m)


class Quadratic(nn.Module):
    """``log p(z_t | x_t) = -|x_t - z_t|^2 / (2 R^2)``: observations of the DOFs themselves."""

    def forward(self, x, obs):  # x (T B, 1, D), obs (T B, D)
        return -0.5 * (x - obs.unsqueeze(-2)).square().sum(-1) / R**2


class QuadraticWithGrad(Quadratic):
    def log_likelihood_and_grad(self, x, obs):
        return self(x, obs), -(x - obs.unsqueeze(-2)) / R**2


@pytest.fixture(scope="module")
def skel():
    return Skeleton.from_urdf(path("human.urdf")).double()


def observations(skel, T: int, seed: int = 0) -> torch.Tensor:
    """(T, D) noisy observations of a smooth trajectory, well inside the joint limits."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = skel.lower, skel.upper
    centre = torch.where(torch.isfinite(lo + hi), (lo + hi) / 2, 0.0)
    half = torch.where(torch.isfinite(hi - lo), (hi - lo) / 2, 1.0).clamp(max=1.0)
    t = torch.arange(T, dtype=torch.float64).unsqueeze(-1)
    phase = torch.rand(len(lo), generator=g, dtype=torch.float64) * 6.0
    smooth = centre + 0.2 * half * torch.sin(0.2 * t + phase)
    return smooth + 0.05 * half * torch.randn(T, len(lo), generator=g, dtype=torch.float64)


def closed_form(z: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """argmin sum_t |x_t - z_t|^2 / (2 R^2) + sum_t |x_{t+1} - 2 x_t + x_{t-1}|^2 / (2 sigma^2), per DOF: the
    normal equations (I / R^2 + A^T A / sigma_d^2) x_d = z_d / R^2, A the second differences."""
    T = len(z)
    A = torch.zeros(T - 2, T, dtype=torch.float64)
    for k in range(T - 2):
        A[k, k : k + 3] = torch.tensor([1.0, -2.0, 1.0], dtype=torch.float64)
    eye = torch.eye(T, dtype=torch.float64)
    H = eye / R**2 + (A.T @ A).unsqueeze(0) / sigma.square().view(-1, 1, 1)  # (D, T, T)
    return torch.linalg.solve(H, (z.T / R**2).unsqueeze(-1)).squeeze(-1).T


@pytest.mark.parametrize("cue", [Quadratic, QuadraticWithGrad], ids=["autograd", "own_gradient"])
def test_linear_gaussian_map_trajectory_matches_the_normal_equations(skel, cue):
    """With a quadratic cue the energy is that of a linear Gaussian state-space model (random-acceleration
    prior, direct observations): its minimiser (the Kalman smoother's mean) solves a linear system."""
    T, sigma = 30, 0.02
    z = observations(skel, T)
    smoother = TrajectorySmoother(skel, cue=cue(), sigma=sigma, steps=600, window=64)
    out = smoother(z, list(z))  # started at the observations
    free = skel.lower < skel.upper
    want = closed_form(z, torch.full((z.shape[1],), sigma, dtype=torch.float64))
    assert float((out.x - want)[:, free].abs().max()) < 1e-4
    assert torch.equal(out.x[:, ~free], z[:, ~free].clamp(skel.lower[~free], skel.upper[~free]))
    assert float(out.loss) < float(out.loss_before) and out.windows == 1
    # the prior did its work: the smoothed track is closer to the normal equations' than the data are
    assert float((z - want)[:, free].abs().max()) > 0.05


def test_windows_agree_with_one_window(skel, device):
    """A long sequence in overlapping windows (each anchored on the one before) ends within a few mrad of
    the whole sequence optimised at once; on the poses' device."""
    T, sigma = 70, 0.02
    z = observations(skel, T, seed=1).to(device)
    skel = copy.deepcopy(skel).to(device)  # the module's fixture stays on the CPU
    whole = TrajectorySmoother(skel, cue=QuadraticWithGrad(), sigma=sigma, steps=600, window=128)(z, list(z))
    windowed = TrajectorySmoother(skel, cue=QuadraticWithGrad(), sigma=sigma, steps=600, window=24, overlap=8)
    out = windowed(z, list(z))
    assert out.windows == 4 and out.x.device.type == device.type  # [0, 24), [16, 40), [32, 56), [48, 70)
    assert float((out.x - whole.x).abs().max()) < 1e-2  # 4.6e-3 here
    # what makes them agree: each window re-optimises the last frames of the one before with their future
    bare = TrajectorySmoother(skel, cue=QuadraticWithGrad(), sigma=sigma, steps=600, window=24, overlap=2)
    assert float((bare(z, list(z)).x - whole.x).abs().max()) > 0.05  # 0.08 here


def test_a_track_on_another_device_is_a_clear_error(skel):
    """The trajectory must be where the smoother's cue and prior are (the tracker moves its CPU rows to
    its device first); elsewhere the error names both devices, not a failed operation deep in the cue."""
    z = observations(skel, 10)
    smoother = TrajectorySmoother(skel, cue=QuadraticWithGrad(), sigma=0.02, steps=5)
    with pytest.raises(ValueError, match=r"x is on meta but the smoother is on cpu"):
        smoother(z.to("meta"), list(z))


class TruncatedQuadratic(nn.Module):
    """``log p(z_t | x_t) = -sum_d min((x_d - z_d)^2 / R^2, C) / 2``: a cue with no gradient beyond
    ``sqrt(C) R`` of the observation (as a truncated chamfer has none beyond its reach)."""

    C = 16.0

    def forward(self, x, obs):
        return -0.5 * ((x - obs.unsqueeze(-2)).square() / R**2).clamp(max=self.C).sum(-1)


def lower_median_reference(x: torch.Tensor, k: int, revolute: torch.Tensor) -> torch.Tensor:
    """Per DOF, numpy's unwrapped path of a (T, D) track, the lower median of the frames within k // 2 of
    each frame (fewer at the ends), wrapped back to within pi of the frame's own value."""
    import numpy as np

    a = x.numpy()
    path = np.where(revolute.numpy(), np.unwrap(a, axis=0), a)
    h, T = k // 2, len(a)
    med = np.stack(
        [
            np.sort(path[max(0, t - h) : t + h + 1], axis=0)[(min(T, t + h + 1) - max(0, t - h) - 1) // 2]
            for t in range(T)
        ]
    )
    d = med - path
    d = np.where(revolute.numpy(), np.angle(np.exp(1j * d)), d)
    return torch.from_numpy(a + d)


def test_running_median_against_numpy_across_the_angle_wrap():
    """The start of the descent: the running median of each DOF along its unwrapped path (a revolute DOF
    that crosses +-pi is not averaged across the jump), each frame kept on its own branch."""
    from torchpf.smooth import _running_median

    g = torch.Generator().manual_seed(3)
    T = 23
    t = torch.arange(T, dtype=torch.float64).unsqueeze(-1)
    x = torch.cat([2.9 + 0.08 * t, 0.3 * torch.sin(0.5 * t), 0.02 * t], -1)  # crosses pi; swings; slides
    x = x + 0.2 * torch.randn(T, 3, generator=g, dtype=torch.float64)
    x[:, 0] = torch.atan2(torch.sin(x[:, 0]), torch.cos(x[:, 0]))  # stored wrapped, jumping by 2 pi
    revolute = torch.tensor([True, True, False])
    for k in (3, 5, 9):
        got = _running_median(x.unsqueeze(1), k, revolute).squeeze(1)
        assert torch.allclose(got, lower_median_reference(x, k, revolute), atol=1e-12)
        assert float((got - x)[:, :2].abs().max()) <= math.pi + 1e-12  # each frame on its own branch


def test_the_median_start_escapes_frames_the_cue_cannot_pull_back(skel):
    """A few frames of the track thrown far off in one DOF (beyond the cue's reach, as a mask defect throws a
    limb): from the track the descent cannot bring them back (no cue gradient there) and the prior bends the
    frames around them out of the cue's reach too; from the track's running median it reaches the normal
    equations' optimum, which the truncated cue shares within its reach."""
    T, sigma = 30, 0.02
    z = observations(skel, T, seed=4)
    free = skel.lower < skel.upper
    dof = int(torch.nonzero(free & skel.dof_revolute & (skel.upper - skel.lower > 4.0))[0])
    x = z.clone()
    x[[6, 13, 21], dof] += 1.5  # 7.5 reaches of the cue away
    want = closed_form(z, torch.full((z.shape[1],), sigma, dtype=torch.float64))
    out = {
        k: TrajectorySmoother(skel, cue=TruncatedQuadratic(), sigma=sigma, steps=600, median=k)(x, list(z))
        for k in (1, 5)
    }
    assert float((out[5].x - want)[:, free].abs().max()) < 1e-3
    # from the track, the prior drags their neighbours out of the cue's reach (0.2 rad) with them: 0.69 here
    assert float((out[1].x - want)[:, dof].abs().max()) > 0.4
    assert float(out[5].loss) < float(out[1].loss)
    assert float(out[5].loss_before) == float(out[1].loss_before)  # E before: the track's, both times


def test_the_track_itself_is_kept_where_its_energy_is_lower_than_its_median(skel):
    """The median is only a start: with no steps the result is whichever of the track and its median has
    the lower energy (the optimum itself stays; a track with spikes gives way to its median)."""
    T, sigma = 30, 0.02
    z = observations(skel, T, seed=5)
    want = closed_form(z, torch.full((z.shape[1],), sigma, dtype=torch.float64))
    smoother = TrajectorySmoother(skel, cue=QuadraticWithGrad(), sigma=sigma, steps=0, median=5)
    kept = smoother(want, list(z))
    assert torch.equal(kept.x, skel.clamp(want)) and float(kept.loss) == float(kept.loss_before)
    spiky = want.clone()
    spiky[[4, 11, 18]] += 0.4
    moved = smoother(spiky, list(z))
    assert float(moved.loss) < float(moved.loss_before)
    assert float((moved.x - want)[[4, 11, 18]].abs().max()) < float((spiky - want)[[4, 11, 18]].abs().max())
    with pytest.raises(ValueError, match="median must be an odd number"):
        TrajectorySmoother(skel, cue=QuadraticWithGrad(), sigma=sigma, median=4)


def test_held_dofs_and_non_finite_frames(skel):
    """A DOF with sigma 0 stays where the track put it; a NaN frame stays NaN and splits the sequence."""
    T = 20
    z = observations(skel, T, seed=2)
    sigma = torch.full((z.shape[1],), 0.02, dtype=torch.float64)
    held = 10
    sigma[held] = 0.0
    x = z + 0.01
    x[7] = math.nan
    out = TrajectorySmoother(skel, cue=QuadraticWithGrad(), sigma=sigma, steps=50)(x, list(z))
    assert torch.isnan(out.x[7]).all()
    finite = torch.ones(T, dtype=torch.bool)
    finite[7] = False
    assert torch.isfinite(out.x[finite]).all()
    assert torch.equal(out.x[finite, held], x[finite, held])
    assert out.windows == 2  # [0, 7) and [8, 20)


class _Offsets(nn.Module):
    """A flat cue that records the outline offsets of the silhouettes it reads."""

    def forward(self, x, obs):
        self.seen = obs.offset
        return x.new_zeros(x.shape[:-1])


def test_the_masks_outline_offsets_reach_the_cue(skel):
    """Frames with an outline offset (``Tracker(boundary_offset=...)``) keep it in the smoothed windows; a
    frame without one reads as 0 px."""
    masks = torch.zeros(3, 12, 16)
    masks[:, 4:8, 6:10] = 1.0
    offsets = [torch.tensor([1.0, -1.0, 0.5]), None, torch.tensor([0.0, 2.0, -0.5])]
    frames = [Silhouettes(masks, offset=o) for o in offsets]
    cue = _Offsets()
    x = torch.zeros(3, len(skel.dof_names), dtype=torch.float64)
    TrajectorySmoother(skel, cue=cue, sigma=0.02, steps=1)(x, frames)
    want = torch.stack([offsets[0], torch.zeros(3), offsets[2]])
    assert torch.equal(cue.seen.reshape(3, 3), want)
    TrajectorySmoother(skel, cue=cue, sigma=0.02, steps=1)(x, [Silhouettes(masks)] * 3)
    assert cue.seen is None  # no frame has one: the cue reads the masks as they are


@pytest.mark.parametrize("cue", [Quadratic, QuadraticWithGrad], ids=["autograd", "own_gradient"])
def test_two_frames_have_no_prior(skel, cue):
    """Too short for an acceleration: each frame goes to its own observation."""
    z = observations(skel, 2, seed=3)
    out = TrajectorySmoother(skel, cue=cue(), sigma=0.02, steps=600)(z + 0.02, list(z))
    free = skel.lower < skel.upper
    assert float((out.x - z)[:, free].abs().max()) < 1e-4


def test_the_prior_wraps_revolute_angles(skel):
    """A joint turning at constant speed through +-pi has no acceleration: the prior reads wrapped steps."""
    smoother = TrajectorySmoother(skel, cue=Quadratic(), sigma=0.01)
    d = int(torch.nonzero(skel.dof_revolute)[0])
    x = torch.zeros(6, len(skel.lower), dtype=torch.float64)
    turning = torch.arange(6, dtype=torch.float64) * 0.3 + 2.5  # 2.5 .. 4.0 rad
    x[:, d] = torch.atan2(torch.sin(turning), torch.cos(turning))  # jumps from ~+pi to ~-pi
    assert float(smoother.prior_energy(x)) < 1e-20
    x[3, d] += 0.01
    # one frame off by 0.01 rad: accelerations 0.01, -0.02, 0.01 at frames 2, 3, 4
    assert float(smoother.prior_energy(x)) == pytest.approx(0.5 * 6e-4 / 0.01**2, rel=1e-9)


def test_bad_arguments(skel):
    with pytest.raises(ValueError, match="sigma"):
        TrajectorySmoother(skel, cue=Quadratic(), sigma=torch.ones(3))
    with pytest.raises(ValueError, match="window"):
        TrajectorySmoother(skel, cue=Quadratic(), window=8, overlap=8)
    with pytest.raises(ValueError, match="robust"):
        TrajectorySmoother(skel, cue=Quadratic(), robust=0.0)
    with pytest.raises(ValueError, match="reweight"):
        TrajectorySmoother(skel, cue=Quadratic(), reweight=0)
    smoother = TrajectorySmoother(skel, cue=Quadratic())
    with pytest.raises(ValueError, match="observations"):
        smoother(torch.zeros(5, len(skel.lower), dtype=torch.float64), [None] * 4)


@pytest.fixture(scope="module")
def scene():
    skel = Skeleton.from_urdf(path("human.urdf"))
    angles = generate("walk", 24, 30.0, seed=1).angles[::2]  # 12 frames at 15 Hz
    angles[:, [0, 2]] -= angles[0, [0, 2]].clone()
    cams = camera_ring(3, radius=4.0, width=80, height_px=60, target=(0.0, -0.3, 0.9))
    return skel, cams, synthesize(skel, angles, cams, fps=15.0), angles


def test_the_tracker_smooths_its_track_and_writes_it(scene, tmp_path):
    """``track``'s default on silhouettes: the smoothed track is returned and written, the filter's own
    estimates kept in ``filtered_angles``; the smoother lowered its energy, so the track changed, and stays
    about as close to the truth (12 frames of clean renders: a check of the plumbing, not of accuracy)."""
    skel, cams, seq, angles = scene
    tracker = Tracker(skel, cams, n_particles=200, progress=False)
    out = tmp_path / "track.csv"
    result = tracker.track(seq, seed=0, calibrate=False, out=out)
    assert result.filtered_angles is not None and result.filtered_angles.shape == result.angles.shape
    assert torch.isfinite(result.angles).all()
    assert float((result.angles - result.filtered_angles).abs().max()) > 1e-4
    _, _, rows = read_mocap_csv(out, expected_dof_names=skel.dof_names)
    assert torch.allclose(torch.as_tensor(rows), result.angles, atol=1e-6)
    assert not (tmp_path / "track.csv.partial").exists()
    truth = skel.fk(angles)
    smoothed = float(metrics.mpjpe(truth, skel.fk(result.angles)))
    filtered = float(metrics.mpjpe(truth, skel.fk(result.filtered_angles)))
    assert smoothed < 1.2 * filtered, (smoothed, filtered)
    off = Tracker(skel, cams, n_particles=200, progress=False, smooth=False).track(
        seq, seed=0, calibrate=False
    )
    assert off.filtered_angles is None
    assert torch.equal(off.angles, result.filtered_angles)  # the same filter run underneath


def test_smoothing_needs_silhouettes_or_a_cue(scene):
    skel, cams, _, _ = scene
    with pytest.raises(ValueError, match="smooth"):
        Tracker(skel, None, likelihood="pointcloud", smooth=True, progress=False)


def test_the_smoother_reads_more_foreground_samples_than_the_refiner(scene):
    """The default cue of the smoother takes ``SAMPLES`` foreground samples per camera and
    ``AREA_POINTS`` model points per capsule (the refiner's keeps its 128 and 8 / 2; the smoother sees one
    pose per frame, not hundreds); given options win, and a refiner's cue that is not the default one is
    used as it is."""
    from torchpf.smooth import AREA_POINTS, SAMPLES

    skel, cams, _, _ = scene
    assert SAMPLES > 128 and AREA_POINTS > (8, 2)
    default = TrajectorySmoother(skel, cams).cue
    assert (default.n_samples, (default.n_body, default.n_cap)) == (SAMPLES, AREA_POINTS)
    given = TrajectorySmoother(skel, cams, cue_options={"n_samples": 64, "n_cap": 1}).cue
    assert (given.n_samples, given.n_body, given.n_cap) == (64, AREA_POINTS[0], 1)
    tracker = Tracker(skel, cams, n_particles=200, progress=False)
    refiner_cue = tracker.filter.refiner.cue
    assert (refiner_cue.n_samples, refiner_cue.n_body, refiner_cue.n_cap) == (128, 8, 2)
    smoother = tracker._smoother()
    assert (smoother.cue.n_samples, (smoother.cue.n_body, smoother.cue.n_cap)) == (SAMPLES, AREA_POINTS)
    # Tracker's acceleration std: 12 times the random walk's per-frame step std
    from torchpf.tracker import _diffusion_std

    sigma = 12.0 * torch.as_tensor(_diffusion_std(tracker.dynamics)).to(smoother.precision)
    moving = sigma > 0
    assert bool(moving.any())
    assert torch.allclose(smoother.precision[moving], sigma[moving] ** -2)
    tau = {"refine_options": {"cue_options": {"tau": 4.0}}}
    smoother = Tracker(skel, cams, n_particles=200, progress=False, filter_options=tau)._smoother()
    assert (smoother.cue.tau, smoother.cue.n_samples) == (4.0, SAMPLES)
    overlap = {"refine_options": {"cue": "overlap"}}
    custom = Tracker(skel, cams, n_particles=200, progress=False, filter_options=overlap)
    assert custom._smoother().cue is custom.filter.refiner.cue


def test_a_mask_a_defect_spoiled_is_heard_less(scene):
    """One camera's mask in one frame slid 8 px sideways (a spoiled segmentation): its robust weight falls
    to almost 0 while every other mask keeps 1 or close to it (its energy near its camera's median), and
    the smoothed frames around it stay closer to the truth than with every mask weighing 1. A weight the
    frame came with multiplies the robust one."""
    from torchpf.smooth import ROBUST, _stack

    skel, cams, seq, angles = scene
    sil = [seq.frame(t).silhouettes for t in range(len(seq))]
    t0 = 6
    masks = sil[t0].masks.clone()
    masks[1] = torch.roll(masks[1], shifts=8, dims=-1)
    spoiled = [s if t != t0 else Silhouettes(masks, valid=s.valid) for t, s in enumerate(sil)]
    x = angles.float()
    smoother = TrajectorySmoother(skel, cams, sigma=0.05)
    assert smoother.robust == ROBUST
    w = smoother._robust_weights(x.reshape(len(x), 1, -1), _stack(spoiled, 1)).weight.reshape(len(x), 3)
    assert float(w[t0, 1]) < 0.05
    others = torch.ones_like(w, dtype=torch.bool)
    others[t0, 1] = False
    assert float(w[others].min()) > 0.6 and float(w[others].max()) == 1.0
    assert float((w[others] == 1.0).float().mean()) > 0.5  # at least the masks up to the median level
    given = [s.with_weight(torch.tensor([1.0, 0.5, 1.0])) for s in spoiled]
    w2 = smoother._robust_weights(x.reshape(len(x), 1, -1), _stack(given, 1)).weight.reshape(len(x), 3)
    torch.testing.assert_close(w2, w * torch.tensor([1.0, 0.5, 1.0]))
    truth = skel.fk(angles)

    def error_near_the_defect(robust):
        out = TrajectorySmoother(skel, cams, sigma=0.05, robust=robust)(x, spoiled).x
        return float((skel.fk(out) - truth).norm(dim=-1).mean(-1)[t0 - 2 : t0 + 3].mean())

    heard_less, as_given = error_near_the_defect(ROBUST), error_near_the_defect(None)
    assert heard_less < 0.6 * as_given, (heard_less, as_given)
