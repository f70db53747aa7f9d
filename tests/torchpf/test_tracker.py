"""Tracker: assembly by name, end-to-end tracking of a synthetic walk, sequence directories, configs."""

import warnings

import pytest
import torch

from torchpf import Skeleton, metrics
from torchpf.assets import path
from torchpf.camera import camera_ring
from torchpf.filters import HybridParticleFilter
from torchpf.io import read_mocap_csv
from torchpf.kinematics import body_partition
from torchpf.likelihoods import ProductLikelihood, SilhouetteLikelihood
from torchpf.proposals import GaussianRandomWalk
from torchpf.sequence import write_sequence
from torchpf.synth import synthesize
from torchpf.tracker import Tracker
from training.synthetic import generate


@pytest.fixture(scope="module")
def scene():
    skel = Skeleton.from_urdf(path("human.urdf"))
    angles = generate("walk", 24, 30.0, seed=1).angles[::2]  # 12 frames at 15 Hz
    angles[:, [0, 2]] -= angles[0, [0, 2]].clone()  # start at the origin, in the cameras' view
    cams = camera_ring(3, radius=4.0, width=80, height_px=60, target=(0.0, -0.3, 0.9))
    seq = synthesize(skel, angles, cams, fps=15.0)
    return skel, cams, seq, angles


def walk(std=0.03, d=96):
    return GaussianRandomWalk(torch.full((d,), std))


@pytest.mark.parametrize("name", ["sir", "partitioned", "hybrid"])
def test_tracks_a_synthetic_walk(scene, name):
    skel, cams, seq, angles = scene
    tracker = Tracker(
        skel, cams, likelihood="silhouette", dynamics=walk(), filter=name, n_particles=600, progress=False
    )
    result = tracker.track(seq, seed=0)
    assert result.angles.shape == angles.shape and result.ess.shape == (len(angles),)
    assert not result.failed.any()
    truth = skel.fk(angles)
    error = float(metrics.mpjpe(truth, skel.fk(result.angles)))
    static = float(metrics.mpjpe(truth, skel.fk(angles[:1].expand_as(angles))))
    # the body walks about 0.4 m in these 12 frames; holding the first pose is off by ~0.36 m per joint
    assert error < 0.5 * static, (error, static)
    assert torch.all(result.ess >= 1) and torch.all(result.ess <= tracker.filter.n_particles)
    assert result.likelihood_evaluations <= 600
    if name == "hybrid":  # the refinement lowered its objective on every frame (keep-best: never raised it)
        assert (
            result.stats["refine_gain"].shape == (len(angles),) and (result.stats["refine_gain"] >= 0).all()
        )


def test_same_seed_same_track_and_equal_budget(scene):
    skel, cams, seq, _ = scene
    kwargs = dict(likelihood="silhouette", dynamics=walk(), n_particles=300, progress=False)
    apf = Tracker(
        skel, cams, filter="apf", filter_options={"diffusion_std": torch.full((96,), 0.03)}, **kwargs
    )
    assert apf.filter.n_particles == 100  # 3 layers x 100 = 300 likelihood evaluations per frame
    a = apf.track(seq, seed=3)
    b = apf.track(seq, seed=3)
    assert torch.equal(a.angles, b.angles)
    part = Tracker(skel, cams, filter="partitioned", filter_options={"per_limb": True}, **kwargs)
    assert part.filter.n_particles * len(body_partition(skel, per_limb=True)) <= 300
    assert apf.likelihood_evaluations == 300 and part.likelihood_evaluations == 300


def test_partitioned_stages_use_partial_likelihoods(scene):
    skel, cams, _, _ = scene
    tracker = Tracker(
        skel,
        cams,
        likelihood={"silhouette": 1.0, "dual_silhouette": 0.5},
        dynamics=walk(),
        filter="partitioned",
        n_particles=300,
        progress=False,
        filter_options={"per_limb": False, "partial_likelihoods": True},
    )
    first, last = tracker.filter.likelihoods
    assert last is tracker.likelihood
    torso = set(body_partition(skel, joints=True)[0])
    for term in first.terms.values():  # stage 1 scores the torso's bones only
        assert term.bones and all(skel.bones[c][1] in torso for c in term.bones)
    assert tracker.likelihood_evaluations == 300 and tracker.filter.n_particles == 150
    default = Tracker(skel, cams, dynamics=walk(), filter="partitioned", n_particles=300, progress=False)
    assert len(default.filter.groups) == 5  # torso, then a stage per limb, all with the full likelihood
    assert all(lik is default.likelihood for lik in default.filter.likelihoods)


def test_sequence_directory_and_csv(scene, tmp_path):
    skel, cams, seq, angles = scene
    write_sequence(tmp_path / "seq", seq)
    tracker = Tracker(
        skel,
        cams,
        likelihood={"silhouette": 1.0, "dual_silhouette": 0.5},
        dynamics=walk(),
        filter="sir",
        n_particles=200,
        progress=False,
    )
    assert isinstance(tracker.likelihood, ProductLikelihood)
    result = tracker.track(tmp_path / "seq")
    assert result.fps == pytest.approx(15.0)
    result.save_csv(tmp_path / "track.csv")
    names, times, values = read_mocap_csv(tmp_path / "track.csv", expected_dof_names=skel.dof_names)
    assert names == skel.dof_names and values.shape == tuple(angles.shape)
    torch.testing.assert_close(torch.as_tensor(values), result.angles)


def test_config_and_errors(scene, tmp_path):
    skel, cams, seq, _ = scene
    cfg = tmp_path / "tracker.yaml"
    cfg.write_text("filter: sir\nn_particles: 50\nlikelihood: silhouette\nprogress: false\n")
    tracker = Tracker.from_config(cfg, skeleton=skel, cameras=cams, dynamics=walk())
    assert tracker.filter_name == "sir" and tracker.n_particles == 50
    assert isinstance(tracker.likelihood, SilhouetteLikelihood)
    with pytest.raises(ValueError, match="unknown filter"):
        Tracker(skel, cams, dynamics=walk(), filter="kalman")
    with pytest.raises(ValueError, match="unknown likelihood"):
        Tracker(skel, cams, dynamics=walk(), likelihood="smell")
    with pytest.raises(ValueError, match="unknown dynamics"):
        Tracker(skel, cams, dynamics="teleport")
    frames = [seq.frame(t) for t in range(3)]
    with pytest.raises(ValueError, match="no initial pose"):
        tracker.track(frames)
    bad = tmp_path / "bad.yaml"
    bad.write_text("filter: [unclosed\n")
    with pytest.raises(ValueError, match="bad.yaml"):
        Tracker.from_config(bad, skeleton=skel)


def test_mcmc_and_wrapped_dynamics_budget(scene):
    skel, cams, seq, _ = scene
    mcmc = Tracker(
        skel,
        cams,
        dynamics=walk(),
        filter="mcmc",
        n_particles=390,
        progress=False,
        filter_options={"n_moves": 2, "n_leapfrog": 5},
    )
    assert mcmc.filter.n_particles == 30  # 390 / (1 + 2 x 6)
    # below one particle's cost the filter still runs one particle, and says what it spends
    said = r"filter 'mcmc' spends 13 .* 1 particle\(s\), more than n_particles=6"
    with pytest.warns(UserWarning, match=said):
        one = Tracker(skel, cams, dynamics=walk(), filter="mcmc", n_particles=6, progress=False)
    assert one.filter.likelihood_evaluations == 13

    class Wrapper(torch.nn.Module):  # like ActionConstrained: the step std lives on the wrapped prior
        def __init__(self):
            super().__init__()
            self.dynamics = walk(0.02)

        def sample(self, x, generator=None):
            return self.dynamics.sample(x, generator)

        def log_prob(self, x_new, x_old):
            return self.dynamics.log_prob(x_new, x_old)

    apf = Tracker(skel, cams, dynamics=Wrapper(), filter="apf", n_particles=90, progress=False)
    torch.testing.assert_close(torch.as_tensor(apf.filter.diffusion_std), torch.full((96,), 0.02))


def test_public_name():
    import torchpf

    assert torchpf.Tracker is Tracker and "Tracker" in dir(torchpf)


def test_hybrid_puts_swapped_legs_back(scene):
    """Started with the legs exchanged (each foot ~0.5 m off), the hybrid's leg-swap candidate puts them back
    on the first frame; without it the track keeps them swapped for several frames."""
    from torchpf.kinematics.symmetry import limb_swaps

    skel, cams, seq, angles = scene
    legs = limb_swaps(skel)[0]
    feet = [skel.joint_names.index(n) for n in ("LeftFoot", "RightFoot")]
    frames = [seq.frame(t) for t in range(3)]

    def feet_error(**filter_options):
        tracker = Tracker(
            skel, cams, n_particles=500, fps=15.0, progress=False, filter_options=filter_options
        )
        result = tracker.track(frames, init=legs(angles[0]), seed=0)
        return (skel.fk(result.angles)[:, feet] - skel.fk(angles[:3])[:, feet]).norm(dim=-1).mean(-1), result

    start = float((skel.fk(legs(angles[0]))[feet] - skel.fk(angles[0])[feet]).norm(dim=-1).mean())
    assert start > 0.4
    with_swaps, result = feet_error()
    without, _ = feet_error(swaps=())
    assert bool(result.stats["refine_swapped"][0]) and (with_swaps < 0.06).all()
    assert (without > 0.3).all()


def test_named_prior_gets_the_frame_rate(scene):
    from priors.diffusion import structural_sigma

    skel, cams, _, _ = scene
    tracker = Tracker(
        skel, cams, dynamics="random_walk", fps=20.0, filter="sir", n_particles=10, progress=False
    )
    torch.testing.assert_close(torch.as_tensor(tracker.dynamics.sigma), structural_sigma(skel, fps=20.0))


def test_named_prior_without_a_rate_takes_the_sequences(scene):
    """fps=None: a sequence with times (15 Hz here) gets the prior built for its rate, the same track as
    fps=15 given; no warning about a missing rate. An explicit other rate is honoured."""
    skel, cams, seq, angles = scene

    def run(**options):
        tracker = Tracker(
            skel, cams, likelihood="silhouette", filter="sir", n_particles=40, progress=False, **options
        )
        return tracker.track(seq, seed=0).angles

    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*no fps given")
        unset = run()
    torch.testing.assert_close(unset, run(fps=15.0), rtol=0, atol=0)
    assert not torch.equal(unset, run(fps=5.0))
    # frames without times and no rate anywhere: tracked, with a warning that names the missing rate
    tracker = Tracker(skel, cams, likelihood="silhouette", filter="sir", n_particles=40, progress=False)
    with pytest.warns(UserWarning, match="no fps given and the sequence has no times"):
        tracker.track([seq.frame(t) for t in range(2)], init=angles[0], seed=0)


def test_auto_temperature_sets_the_first_frame_survival_rate(scene):
    """temperature="auto": the exponent found on frame 0 gives the predicted particles ESS/N = 0.2 there."""
    from torchpf.filters.weights import survival_fraction

    skel, cams, seq, angles = scene
    kwargs = dict(likelihood="silhouette", dynamics=walk(), filter="sir", n_particles=400, progress=False)
    tracker = Tracker(skel, cams, temperature="auto", **kwargs)
    result = tracker.track(seq, seed=0)
    beta = result.stats["temperature"]
    assert beta.shape == () and 1e-3 < float(beta) < 1e3 and torch.isfinite(result.angles).all()
    # recompute: same seed -> same initial particles and the same first prediction step
    from torchpf.distributions import as_generator

    g = as_generator(0)
    x0 = tracker.initial_particles(angles[0], g)
    x1 = tracker.filter.dynamics.sample(x0, g)
    frame = seq.frame(0)
    energy = tracker.likelihood.likelihood(x1, frame).double()
    torch.testing.assert_close(
        survival_fraction(float(beta) * energy), torch.tensor(0.2, dtype=torch.float64), rtol=1e-3, atol=0
    )
    with pytest.raises(ValueError, match="temperature"):
        Tracker(skel, cams, temperature="hot", **kwargs)
    fixed = Tracker(skel, cams, temperature=0.5, **kwargs)
    assert float(fixed.track(seq, seed=0).stats["temperature"]) == 0.5


def test_to_moves_the_computation(scene, device, dtype):
    skel, cams, seq, angles = scene
    tracker = Tracker(skel, cams, likelihood="silhouette", dynamics=walk(), filter="sir", n_particles=200)
    tracker.progress = tracker.filter.progress = False
    assert tracker.to(device) is tracker and tracker.to(dtype) is tracker
    assert tracker.device.type == device.type and tracker.dtype == dtype
    assert all(b.device.type == device.type for b in tracker.buffers())
    x0 = tracker.initial_particles(angles[0], torch.Generator(device=device).manual_seed(0))
    assert x0.device.type == device.type and x0.dtype == dtype
    # a CPU generator drives a run on any device (a generator there is derived from it)
    result = tracker.track(seq, generator=torch.Generator().manual_seed(0))
    assert not result.failed.any() and torch.isfinite(result.angles).all()
    truth = skel.fk(angles)
    error = float(metrics.mpjpe(truth, skel.fk(result.angles)))
    static = float(metrics.mpjpe(truth, skel.fk(angles[:1].expand_as(angles))))
    assert error < 0.5 * static, (error, static)
    tracker.cpu().float()
    assert tracker.device == torch.device("cpu") and tracker.dtype == torch.float32
    with pytest.raises(TypeError, match="floating"):
        tracker.to(torch.int64)


def test_the_default_hybrid_runs_on_the_particles_device(scene, device):
    """`track`'s default filter (APF layers, then gradient refinement) and the lost-track detector on
    ``device``: the refiner's poses and the detector's visual hull follow the tracker there."""
    skel, cams, seq, angles = scene
    tracker = Tracker(skel, cams, dynamics=walk(), n_particles=300, progress=False, device=device)
    assert tracker.filter_name == "hybrid" and tracker.device.type == device.type
    result = tracker.track(seq, seed=0, calibrate=False)
    assert torch.isfinite(result.angles).all() and not result.failed.any()
    truth = skel.fk(angles)
    error = float(metrics.mpjpe(truth, skel.fk(result.angles.cpu().to(angles.dtype))))
    static = float(metrics.mpjpe(truth, skel.fk(angles[:1].expand_as(angles))))
    assert error < 0.3 * static, (error, static)


@pytest.mark.parametrize("name", ["sir", "qrs", "apf", "partitioned", "mcmc"])
def test_a_run_draws_only_from_its_own_generator(scene, name):
    """A second CPU generator (the global one) must not be touched: code that forgets to pass the
    generator would draw from it, and the track would then change with the global seed."""
    skel, cams, seq, _ = scene
    tracker = Tracker(skel, cams, likelihood="silhouette", filter=name, n_particles=150, fps=15.0)
    tracker.filter.progress = False
    torch.manual_seed(1)
    state = torch.get_rng_state()
    a = tracker.to(torch.float64).track(seq, generator=torch.Generator().manual_seed(4))
    assert torch.equal(torch.get_rng_state(), state)
    torch.manual_seed(2)
    b = tracker.track(seq, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a.angles, b.angles) and a.log_evidence == b.log_evidence


# ---------------------------------------------------------------------- evidence and streaming (issue 16)
def _sir(skel, cams, n=60):
    return Tracker(
        skel, cams, likelihood="silhouette", dynamics=walk(), filter="sir", n_particles=n, progress=False
    )


def test_frames_without_evidence_are_flagged(scene, tmp_path):
    import os

    import numpy as np

    skel, cams, seq, angles = scene
    root = tmp_path / "seq"
    write_sequence(root, seq)
    for c in cams:  # frame 3: every camera missing; frame 5: every mask empty
        os.remove(root / "masks" / c / "000003.png")
        (root / "masks" / c / "000005.png").write_bytes((root / "masks" / c / "000000.png").read_bytes())
    import cv2

    for c in cams:
        cv2.imwrite(str(root / "masks" / c / "000005.png"), np.zeros((60, 80), np.uint8))
    result = _sir(skel, cams).track(root, out=tmp_path / "track.csv")
    assert result.no_evidence.tolist() == [t in (3, 5) for t in range(len(angles))]
    assert not result.failed.any() and torch.isfinite(result.angles).all()
    _, _, values = read_mocap_csv(tmp_path / "track.csv", expected_dof_names=skel.dof_names)
    torch.testing.assert_close(torch.as_tensor(values), result.angles, rtol=0, atol=0)


def test_sequences_without_observations_are_refused(scene, tmp_path):
    import shutil

    import cv2
    import numpy as np

    skel, cams, seq, _ = scene
    root = tmp_path / "seq"
    write_sequence(root, seq)
    for c in cams:  # every mask empty: tracked, then refused (never "0 failed frames")
        for f in (root / "masks" / c).iterdir():
            cv2.imwrite(str(f), np.zeros((60, 80), np.uint8))
    with pytest.raises(ValueError, match="no frame has evidence"):
        _sir(skel, cams).track(root, out=tmp_path / "t.csv")
    assert not (tmp_path / "t.csv").exists()
    shutil.rmtree(root / "masks")
    with pytest.raises(ValueError, match="no observations to track"):
        _sir(skel, cams).track(root)


def test_masks_stored_as_0_1_track_like_0_255(scene, tmp_path):
    import cv2

    skel, cams, seq, _ = scene
    write_sequence(tmp_path / "a", seq)
    write_sequence(tmp_path / "b", seq)
    for f in (tmp_path / "b" / "masks").rglob("*.png"):
        cv2.imwrite(str(f), (cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) > 0).astype("uint8"))
    a = _sir(skel, cams).track(tmp_path / "a")
    b = _sir(skel, cams).track(tmp_path / "b")
    assert torch.equal(a.angles, b.angles) and not b.no_evidence.any()


def test_a_crash_keeps_the_frames_tracked_so_far(scene, tmp_path):
    skel, cams, seq, _ = scene
    frames = [seq.frame(t) for t in range(6)]
    frames[4] = "not an observation"  # the likelihood fails on frame 4
    with pytest.raises(Exception):  # noqa: B017 (whatever the likelihood raises)
        _sir(skel, cams).track(frames, init=seq.truth[0], out=tmp_path / "t.csv")
    assert not (tmp_path / "t.csv").exists()
    _, _, values = read_mocap_csv(tmp_path / "t.csv.partial", expected_dof_names=skel.dof_names)
    assert values.shape == (4, 96)
    full = _sir(skel, cams).track(frames[:4], init=seq.truth[0])
    # the rows are the filter's, written frame by frame (the smoothing comes after the last frame)
    torch.testing.assert_close(torch.as_tensor(values), full.filtered_angles, rtol=0, atol=0)


def test_hybrid_needs_cameras_or_a_cue(scene):
    skel = scene[0]
    with pytest.raises(ValueError, match="needs cameras"):
        Tracker(skel, None, likelihood="pointcloud", filter="hybrid", progress=False)


def test_auto_filter_refines_where_silhouettes_give_the_cue(scene):
    skel, cams, _, _ = scene
    assert Tracker(skel, cams, progress=False).filter_name == "hybrid"
    assert Tracker(skel, cams, likelihood="pointcloud", progress=False).filter_name == "apf"
    assert Tracker(skel, None, likelihood="pointcloud", progress=False).filter_name == "apf"
    assert Tracker(skel, cams, filter="sir", progress=False).filter_name == "sir"
    # a prior term among the cues (it reads no observation) leaves the silhouettes' filter and smoothing
    cues = ("silhouette", "dual_silhouette", "self_collision")
    with_prior = Tracker(skel, cams, likelihood=cues, progress=False)
    assert with_prior.filter_name == "hybrid" and with_prior._reads_silhouettes()


@pytest.mark.parametrize("budget", [30, 60, 100, 500])
def test_hybrid_default_stays_within_a_small_budget(scene, budget):
    skel, cams, _, _ = scene
    tracker = Tracker(skel, cams, n_particles=budget, progress=False)
    k, steps = tracker.filter.n_refine, tracker.filter.refiner.steps
    assert (k, steps) == HybridParticleFilter.plan_refinement(budget)
    assert tracker.filter.n_particles >= 1 and tracker.likelihood_evaluations <= budget
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        explicit = Tracker(
            skel, cams, n_particles=budget, filter_options={"refine_options": {"steps": 3}}, progress=False
        )
    assert explicit.filter.refiner.steps == 3 and explicit.filter.n_refine == 4  # the user's choice stands
    # ... and where it costs more than the budget (4 poses x 3 steps at 30), the tracker says so
    over = explicit.likelihood_evaluations > budget
    assert over == any("more than n_particles" in str(w.message) for w in caught)
    assert over == (budget == 30)


def test_an_initial_pose_outside_the_limits_is_warned_and_clamped(scene):
    """Limits learned from other performers (fit-limits) may not hold a new one's first pose: the track
    starts from it clamped, and says so; a pose inside the limits says nothing."""
    skel, cams, seq, angles = scene
    knee = skel.dof_names.index("LeftLeg_Xrotation")
    x0 = float(angles[0, knee])
    lower = skel.lower.clone()
    lower[knee] = x0 + 0.2
    limited = skel.with_limits(lower, None)
    frames = [seq.frame(t) for t in range(2)]
    kwargs = dict(likelihood="silhouette", dynamics=walk(), filter="sir", n_particles=20, progress=False)
    with pytest.warns(
        UserWarning, match=r"outside the skeleton's joint limits on 1 DOFs \(LeftLeg_Xrotation by 0.2"
    ):
        result = Tracker(limited, cams, **kwargs).track(frames, init=angles[0])
    assert float(result.angles[:, knee].min()) >= x0 + 0.2 - 1e-6
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Tracker(skel, cams, **kwargs).track(frames, init=angles[0])
