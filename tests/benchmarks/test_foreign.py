"""The foreign renderer (benchmarks/foreign.py): body plan from structure, widths, closed-form areas, defects,
sequences a user can track, and the --renderer foreign evaluation."""

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from benchmarks import foreign
from torchpf import Skeleton
from torchpf.assets import path as asset_path
from torchpf.camera import camera_ring

CMU = Path(__file__).resolve().parents[2].parent / "shared" / "mocap" / "cmu"
needs_cmu = pytest.mark.skipif(not (CMU / "07_01.bvh").is_file(), reason="CMU clips not present")


@pytest.fixture(scope="module")
def cmu():
    if not (CMU / "07_01.bvh").is_file():
        pytest.skip("CMU clips not present")
    from training.mocap import load_bvh

    return load_bvh(CMU / "07_01.bvh", scale=foreign.CMU_SCALE)


def _camera(f=500.0, width=640, height=480):
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return foreign.CameraParams(K, np.eye(3), np.zeros(3), np.zeros(5), width, height)


def test_body_plan_from_structure_not_names(cmu):
    skel, _ = cmu
    names = skel.joint_names
    plan = foreign.body_plan(skel)
    legs = {(names[limb.top], names[limb.mid], names[limb.end]) for limb in plan.legs}
    arms = {(names[limb.top], names[limb.mid], names[limb.end]) for limb in plan.arms}
    assert legs == {("LeftUpLeg", "LeftLeg", "LeftFoot"), ("RightUpLeg", "RightLeg", "RightFoot")}
    assert arms == {("LeftArm", "LeftForeArm", "LeftHand"), ("RightArm", "RightForeArm", "RightHand")}
    assert names[plan.torso[0]] == "Hips" and names[plan.torso[-1]] == "Head_end"
    assert len(plan.eval_joints()) == 15
    # fontmarty22: arms hang down in its rest pose and there are no hands or feet; still found
    f22 = Skeleton.from_urdf(asset_path("fontmarty22.urdf"))
    plan = foreign.body_plan(f22)
    n = f22.joint_names
    assert {n[limb.mid] for limb in plan.arms} == {"l_elbow", "r_elbow"}
    assert {n[limb.mid] for limb in plan.legs} == {"l_knee", "r_knee"}
    assert all(limb.tip == -1 for limb in (*plan.arms, *plan.legs))
    assert plan.stature == pytest.approx(1.66, abs=0.01)


def test_body_widths_scale_with_stature_and_vary_per_performer():
    a, b = foreign.body_shape(1.5, seed=3), foreign.body_shape(1.8, seed=3)
    for k in a:
        assert b[k] == pytest.approx(a[k] * 1.8 / 1.5)
    mean = foreign.body_shape(1.0, seed=None)
    assert mean == pytest.approx(foreign.PROPORTIONS)
    ratios = np.array([[foreign.body_shape(1.0, seed=s)[k] / mean[k] for k in mean] for s in range(40)])
    assert ratios.min() >= 0.85 - 1e-12 and ratios.max() <= 1.15 + 1e-12
    assert ratios.std(0).min() > 0.05  # every entry varies across performers (uniform +-15 %: std 8.7 %)
    assert mean["upper_arm_radius"] == pytest.approx(0.028) and mean["thigh_radius"] == pytest.approx(0.053)


def test_cylinder_and_ellipsoid_areas_match_closed_form():
    cam = _camera()
    f, z, r, L = 500.0, 3.0, 0.05, 0.6
    # a cylinder seen side-on: a 2 r f / z by L f / z rectangle
    cyl = foreign.frustum((-L / 2, 0.0, z), (L / 2, 0.0, z), r, r)
    area = (foreign.draw_solids([("limb", cyl)], cam) > 0).sum()
    assert area == pytest.approx(2 * r * L * f**2 / z**2, rel=0.1)
    # an ellipsoid seen along its third axis (small, far from the image border): pi a b f^2 / z^2
    ell = foreign.ellipsoid((0.0, 0.0, z), np.eye(3), (0.2, 0.1, 0.3))
    area = (foreign.draw_solids([("head", ell)], cam) > 0).sum()
    assert area == pytest.approx(math.pi * 0.2 * 0.1 * f**2 / z**2, rel=0.1)
    # a part in `drop` is not drawn
    assert (foreign.draw_solids([("arm0", cyl)], cam, drop={"arm0"}) == 0).all()


def test_rest_pose_is_wider_than_the_trackers_capsules(cmu):
    from torchpf.synth import render_silhouette

    skel, _ = cmu
    theta = torch.zeros(len(skel.dof_names), dtype=torch.float64)
    rig = camera_ring(3, radius=4.0, target=(0.0, 0.0, 0.0), width=160, height_px=120)
    renderer = foreign.ForeignRenderer(skel, performer_seed=None)
    joints = renderer.joints(theta)
    ours = renderer.render(joints, rig) > 0
    waist = torch.as_tensor(joints[[renderer.plan.torso[0], renderer.plan.neck_base]])
    for v in range(len(rig)):
        theirs = render_silhouette(skel, theta, rig[v]).numpy()
        # the capsules' mask lies mostly inside ours; ours is larger in every view (T-pose: the limbs are of
        # similar width, 0.15 x bone length against ~0.05 x stature for a thigh)
        assert (theirs & ~ours[v]).sum() <= 0.15 * theirs.sum()
        assert ours[v].sum() > 1.15 * theirs.sum()
        # the torso is wider: rows from the hips half way up to the neck base (in the side views the T-pose
        # arms cross the upper rows); seen from the front (camera 0), several times wider
        (u0, v0), (_, v1) = rig[v].project(waist).tolist()
        rows = slice(round((v0 + v1) / 2), round(v0))
        assert ours[v][rows].sum() > 1.5 * theirs[rows].sum()
        if v == 0:
            assert (ours[v][rows].sum(1) >= 3 * theirs[rows].sum(1)).all()


def test_renderer_is_deterministic_per_seed_and_defects_change_a_stated_fraction(cmu):
    skel, motion = cmu
    angles = motion.angles[1:40:8]  # 5 frames
    rig = camera_ring(3, radius=4.0, target=(0.0, 0.0, 0.9), width=160, height_px=120)
    angles = foreign.centre_root(skel, angles)
    renderer = foreign.ForeignRenderer(skel, performer_seed=1)
    clean = renderer.render_sequence(angles, rig, defects="clean")
    assert clean.shape == (5, 3, 120, 160) and clean.dtype == np.uint8
    assert set(np.unique(clean)) == {0, 255}
    a = renderer.render_sequence(angles, rig, defects="noisy", seed=4)
    b = renderer.render_sequence(angles, rig, defects="noisy", seed=4)
    c = renderer.render_sequence(angles, rig, defects="noisy", seed=5)
    np.testing.assert_array_equal(a, b)
    assert (a != c).any()
    # another performer (seed) is another body
    other = foreign.ForeignRenderer(skel, performer_seed=2).render_sequence(angles, rig)
    assert (other != clean).any()
    # speckle alone: each pixel redrawn with probability s as salt or pepper, so s / 2 of them change
    speckle = renderer.render_sequence(angles, rig, defects=foreign.Defects(speckle=0.02), seed=0)
    assert (speckle != clean).mean() == pytest.approx(0.01, rel=0.15)
    # the noisy preset changes 1-4 % of all pixels (1.4-1.6 % on walks: speckle 0.5 %, the rest at the body)
    assert 0.01 < (a != clean).mean() < 0.04


def test_built_sequence_reads_back_and_tracks(tmp_path):
    if not (CMU / "35_24.bvh").is_file():
        pytest.skip("CMU clips not present")
    from torchpf.sequence import read_sequence
    from torchpf.tracker import Tracker

    seq = foreign.build_sequence(CMU / "35_24.bvh", tmp_path / "seq", defects="noisy", frames=3)
    assert (seq.path / "skeleton.urdf").is_file() and (seq.path / "render.json").is_file()
    data = read_sequence(seq.path)
    assert len(data) == 3 and len(data.cameras) == 3
    assert data.masks[0][0].shape == (120, 160)
    np.testing.assert_allclose(data.times[1] - data.times[0], 1 / 30)
    skel = Skeleton.from_urdf(str(seq.skeleton_path))
    assert list(data.dof_names) == list(skel.dof_names)
    torch.testing.assert_close(data.truth, seq.angles)
    # the root is centred: its mean horizontal position is the origin
    root = skel.fk(data.truth)[:, skel.parents.index(-1)]
    assert root[:, :2].mean(0).abs().max() < 1e-6
    result = Tracker(skel, data.cameras, n_particles=30, progress=False).track(seq.path)
    assert result.angles.shape == (3, len(skel.dof_names)) and torch.isfinite(result.angles).all()


@needs_cmu
def test_video_option_films_a_textured_scene_that_background_subtraction_segments(tmp_path):
    from torchpf.sequence import read_sequence
    from torchpf.video import FrameReader, segment_videos

    seq = foreign.build_sequence(CMU / "07_01.bvh", tmp_path / "clip", frames=8, video=True)
    names = list(seq.cameras.names)
    videos = [seq.path / "video" / f"{n}.mp4" for n in names]
    frames = list(FrameReader(videos[0]))
    assert len(frames) == 8 and frames[0].shape == (240, 320, 3)  # filmed at twice the masks' size
    plate = cv2.imread(str(seq.path / "background" / f"{names[0]}.png"))
    assert plate.shape == (240, 320, 3) and plate.std() > 30  # textured, not a flat colour
    report = segment_videos(
        videos,
        seq.path / "cameras.yaml",
        tmp_path / "seg",
        clean_plates=[seq.path / "background" / f"{n}.png" for n in names],
        size=(160, 120),
        subtractor={"close_px": 3, "threshold": 25},
        progress=False,
    )
    assert report.n_frames == 8
    truth, seg = read_sequence(seq.path), read_sequence(tmp_path / "seg")
    A = np.stack([m > 127 for row in truth.masks for m in row])
    B = np.stack([m > 127 for row in seg.masks for m in row])
    assert (A & B).sum() / (A | B).sum() > 0.75  # the renderer's silhouettes, recovered from the films


@needs_cmu
def test_foreign_evaluation_smoke(tmp_path):
    from benchmarks import evaluate as ev

    args = ev.build_parser().parse_args(
        [
            "--renderer",
            "foreign",
            "--clips",
            "16_46",
            "--presets",
            "clean",
            "--frames",
            "3",
            "--particles",
            "30",
            "--runs",
            "2",
        ]
    )
    cfg = ev.foreign_config_from_args(args)
    assert cfg.setups == ("before", "defaults") and cfg.fps == 30.0 and cfg.particles == (30,)
    result = ev.run_foreign(cfg, tmp_path)
    assert [row["setup"] for row in result.rows] == ["before", "defaults"]
    for row in result.rows:
        assert row["clip"] == "16_46" and row["frames"] == 3 and row["joints"] == 15
        assert 0 <= row["frame_failure"] <= 1 and 0 < row["mpjpe"] < 1 and row["mean_ess"] >= 1
        assert 0 <= row["mpjpe_sd"] < 1  # two runs: their spread
    for mean, row in zip(result.means(), result.rows, strict=True):  # one clip: the SE is sd / sqrt(runs)
        assert mean["mpjpe_se"] == pytest.approx(row["mpjpe_sd"] / math.sqrt(2))
    paths = ev.write_foreign_outputs(result, tmp_path / "out")
    table = paths["table"].read_text()
    assert "Foreign renders" in table and "| before |" in table and "**mean**" in table and " ± " in table
    with pytest.raises(ValueError, match="unknown setup"):
        ev.ForeignConfig(setups=("tomorrow",))


def test_mpjpe_standard_error_matches_the_spread_of_simulated_means():
    """Clips of different difficulty, each run ``R`` times with its own run-to-run std: the standard error
    is the std of the mean over clips across many repetitions of the whole evaluation (1 % tolerance with
    100,000 repetitions: the sample std's relative error is ~0.2 %)."""
    from benchmarks.evaluate import mpjpe_standard_error

    rng = np.random.default_rng(0)
    level = rng.uniform(0.03, 0.15, 11)  # per-clip MPJPE (m): fixed by the masks, not by the runs
    spread = rng.uniform(0.002, 0.04, 11)  # per-clip run-to-run std (m)
    runs = 2
    means = (level + spread * rng.standard_normal((100_000, runs, 11))).mean(1).mean(-1)
    assert mpjpe_standard_error(spread, runs) == pytest.approx(means.std(), rel=0.01)
    assert math.isnan(mpjpe_standard_error(spread, 1)) and math.isnan(
        mpjpe_standard_error([0.01, math.nan], 2)
    )


@needs_cmu
def test_learned_limits_setup_leaves_the_performer_out(tmp_path):
    """`--setups learned_limits`: the clip's skeleton limited to the range of the *other* performers'
    clips (INDEX.tsv subjects), which holds every frame of theirs; the tracker it builds uses it."""
    from benchmarks import evaluate as ev
    from training.mocap import bvh_motion

    seq = foreign.build_sequence(CMU / "16_46.bvh", tmp_path / "seq", defects="clean", frames=3)
    skel = Skeleton.from_urdf(str(seq.skeleton_path))
    assert len(skel.free_rotations()) > len(skel.dof_names) // 2  # a converted BVH: no limits
    tracker = ev.FOREIGN_SETUPS["learned_limits"](seq.path, skel, n_particles=30)
    limited = tracker.skeleton
    ((clips, _, margin),) = [k for k in ev._LIMITS if k[1] == skel.source]
    assert margin == 0.15
    assert clips and not any(c.startswith("16_") for c in clips) and "35_24" in clips
    assert len(limited.free_rotations()) < 8  # what crosses +-pi or flips in the hands' data
    for clip in ("07_01", "35_24"):
        angles = bvh_motion(CMU / f"{clip}.bvh", dof_names=skel.dof_names).angles[1:]
        wrapped = torch.atan2(torch.sin(angles), torch.cos(angles))
        narrow = limited.posture_dofs & (limited.upper - limited.lower < 6)
        inside = (wrapped >= limited.lower - 1e-6) & (wrapped <= limited.upper + 1e-6)
        assert bool(inside[:, narrow].all()), clip


@needs_cmu
def test_action_bank_setup_learns_each_action_from_the_other_performers(tmp_path):
    """`--setups action_bank`: a walk and a run model fitted on the other performers' clips only; the bank
    the tracker predicts with tells their walks from their runs (the responsibilities of each frame)."""
    from benchmarks import evaluate as ev
    from priors.bank import ActionBank
    from training.mocap import bvh_motion

    seq = foreign.build_sequence(CMU / "16_46.bvh", tmp_path / "seq", defects="clean", frames=3)
    skel = Skeleton.from_urdf(str(seq.skeleton_path))
    tracker = ev.FOREIGN_SETUPS["action_bank"](seq.path, skel, n_particles=30)
    bank = tracker.dynamics
    assert isinstance(bank, ActionBank) and bank.actions == ["walk", "run"]
    ((clips, _, fps, _),) = [k for k in ev._ACTIONS if k[1] == skel.source]
    assert fps == 30.0 and not any(c.startswith("16_") for c in clips) and {"35_24", "07_01"} <= set(clips)
    for clip, action in (("07_01", 0), ("35_24", 1)):
        angles = bvh_motion(CMU / f"{clip}.bvh", dof_names=skel.dof_names).angles[1::4]
        label = bank.init_extras(angles.to(torch.float64))["action_prob"].argmax(-1)
        assert (label == action).float().mean() > 0.9, clip
