"""Body calibration (`torchpf.calibrate`), `Skeleton.with_body` / `save_urdf` and the CLI.

The masks come from the independent renderer of `_masks.py` (convex hulls of projected sphere points drawn
with OpenCV), never from torchpf.synth or torchpf.geometry. The subject is the shipped human with its
realistic radii and 4 % taller; the fit starts from the same skeleton with radii a quarter of those (a
converted stick figure) and scale 1.
"""

import copy

import numpy as np
import pytest
import torch

from torchpf import Skeleton
from torchpf.__main__ import main
from torchpf.assets import path
from torchpf.calibrate import (
    bone_groups,
    fit_body,
    outline_disagreement,
    overlay_image,
    projected_radii,
    scaled_joints,
)
from torchpf.camera import camera_ring
from torchpf.kinematics.anatomy import arm_bones
from torchpf.sequence import SequenceData, write_sequence

from ._masks import render_masks

TRUE_SCALE = 1.04
N_FRAMES = 5


@pytest.fixture(scope="module")
def scene(human):
    """3 cameras 160x120 on a 3 m ring, 5 poses (random limb angles, turning), masks of the true body."""
    rig = camera_ring(3, radius=3.0, height=1.5, target=(0, 0, 0.85), width=160, height_px=120)
    truth = human.with_body(scale=TRUE_SCALE)
    g = torch.Generator().manual_seed(1)
    D = len(human.dof_names)
    revolute = human.dof_revolute
    poses = torch.zeros(N_FRAMES, D, dtype=torch.float64)
    poses[:, revolute] = 0.35 * torch.randn(N_FRAMES, int(revolute.sum()), generator=g, dtype=torch.float64)
    poses[:, :6] = 0.0
    poses[:, 3] = torch.linspace(0.0, 2.5, N_FRAMES)  # turn about the vertical
    poses = human.clamp(poses)
    up = human.dof_names.index("Hips_Yposition")  # its URDF axis is world z
    poses[:, up] = 0.05 - truth.fk(poses)[..., 2].min(-1).values
    joints = truth.fk(poses)
    masks = np.stack([render_masks(joints[f], truth.tree.bones, truth.radii, rig.cameras) for f in range(5)])
    stick = human.with_body(radii=human.radii * 0.25)
    return {"rig": rig, "truth": truth, "poses": poses, "masks": masks, "stick": stick}


def _observable(skel, groups, min_length=0.1):
    """Groups whose bones are at least ``min_length`` m long (>= 4 px here): shorter ones (fingers, toe
    tips, the neck) hide mostly inside their neighbours' end caps and have no radius of their own to see."""
    rest = skel.fk(torch.zeros(len(skel.dof_names), dtype=torch.float64))
    out = []
    for g, bones in enumerate(groups):
        p, c = skel.bones[bones[0]]
        if float((rest[c] - rest[p]).norm()) >= min_length:
            out.append(g)
    return out


def _check_fit(human, fitted, report):
    true_radii = human.radii * TRUE_SCALE
    observable = _observable(human, report.groups)
    assert len(observable) >= 10
    for g in observable:
        want = float(true_radii[report.groups[g]].mean())
        got = float(report.radii_after[g])
        assert got == pytest.approx(want, rel=0.10), report.labels[g]
    assert report.scale == pytest.approx(TRUE_SCALE, rel=0.03)
    # the fitted skeleton carries them (radius = group radius; with_body applied the scale)
    assert torch.allclose(
        fitted.radii,
        report.radii_after[
            [g for b in range(len(human.bones)) for g, m in enumerate(report.groups) if b in m]
        ],
        rtol=1e-6,
    )
    for cam in report.iou_after:
        assert report.iou_after[cam] > 0.95 > report.iou_before[cam]


def test_bone_groups_tie_mirror_limbs_from_structure(human):
    groups = bone_groups(human)
    assert sorted(b for g in groups for b in g) == list(range(len(human.bones)))
    named = {tuple(sorted(human.joint_names[human.bones[b][1]] for b in g)) for g in groups}
    for pair in [("LeftLeg", "RightLeg"), ("LeftForeArm", "RightForeArm"), ("LeftFoot", "RightFoot")]:
        assert pair in named
    assert ("Spine",) in named and ("Head_end",) in named  # torso bones stand alone
    # names play no part: fontmarty22 calls its joints l_knee / r_knee
    f22 = Skeleton.from_urdf(path("fontmarty22.urdf"))
    named = {tuple(sorted(f22.joint_names[f22.bones[b][1]] for b in g)) for g in bone_groups(f22)}
    assert ("l_knee", "r_knee") in named and ("l_elbow", "r_elbow") in named and ("neck",) in named


def test_scaled_joints_is_with_body_fk(human):
    g = torch.Generator().manual_seed(0)
    theta = human.clamp(0.3 * torch.randn(3, len(human.dof_names), generator=g, dtype=torch.float64))
    theta[:, :3] = torch.tensor([0.2, 0.9, -0.1], dtype=torch.float64)
    lengths = torch.ones(len(human.joint_names), dtype=torch.float64)
    lengths[human.joint_names.index("LeftLeg")] = 1.2
    lengths[human.joint_names.index("RightForeArm")] = 0.9
    from torchpf.calibrate import _ancestors

    got = scaled_joints(
        human, theta, torch.tensor(1.1, dtype=torch.float64).log(), lengths.log(), _ancestors(human.parents)
    )
    want = human.with_body(scale=1.1, lengths=lengths).fk(theta)
    assert torch.allclose(got, want, atol=1e-6)


def test_save_urdf_round_trip(human, tmp_path):
    body = human.with_body(
        radii={"LeftLeg": 0.09, "RightLeg": 0.09},
        scale=1.07,
        lengths={"LeftForeArm": 1.1, "RightForeArm": 1.1},
    )
    body.save_urdf(tmp_path / "fitted.urdf")
    back = Skeleton.from_urdf(tmp_path / "fitted.urdf")
    assert back.joint_names == body.joint_names and back.dof_names == body.dof_names
    assert back.bones == body.bones
    assert torch.equal(back.lower, human.lower) and torch.equal(back.upper, human.upper)
    theta = human.clamp(0.4 * torch.randn(4, len(human.dof_names), dtype=torch.float64))
    assert torch.allclose(back.fk(theta), body.fk(theta), atol=1e-7)
    assert torch.allclose(back.radii, body.radii, rtol=1e-8)
    leg = [c for _, c in body.bones].index(body.joint_names.index("LeftLeg"))
    assert float(back.radii[leg]) == pytest.approx(0.09 * 1.07)
    # radii that came from a table, not from the URDF, are written too
    table = Skeleton.from_urdf(path("fontmarty22.urdf"), radii={"l_knee": 0.123})
    table.save_urdf(tmp_path / "table.urdf")
    assert torch.allclose(Skeleton.from_urdf(tmp_path / "table.urdf").radii, table.radii, rtol=1e-8)


def test_fit_recovers_radii_and_scale(human, scene):
    fitted, report = fit_body(scene["stick"], scene["rig"], scene["masks"], scene["poses"], iterations=200)
    _check_fit(human, fitted, report)
    assert report.iterations == len(report.loss) <= 200 and report.loss[-1] < 0.1 * report.loss[0]
    assert "LeftLeg/RightLeg" in report.table() and "cam0" in report.table()


def test_fit_converges_from_a_wrong_pose(human, scene):
    g = torch.Generator().manual_seed(3)
    revolute = human.dof_revolute
    delta = torch.zeros_like(scene["poses"])
    delta[:, revolute] = torch.randn(N_FRAMES, int(revolute.sum()), generator=g, dtype=torch.float64)
    delta[:, :3] = 1.0

    def joint_error(k):
        wrong = human.clamp(scene["poses"] + k * delta)
        return wrong, (scene["truth"].fk(wrong) - scene["truth"].fk(scene["poses"])).norm(dim=-1)

    # the largest perturbation along ``delta`` that keeps every joint within 9 cm (root off by ~4 cm)
    k = 0.1
    while float(joint_error(k)[1].max()) > 0.09:
        k *= 0.9
    wrong, error = joint_error(k)
    assert 0.07 < float(error.max()) < 0.10
    fitted, report = fit_body(scene["stick"], scene["rig"], list(scene["masks"]), wrong, iterations=200)
    _check_fit(human, fitted, report)
    after = (scene["truth"].fk(report.poses) - scene["truth"].fk(scene["poses"])).norm(dim=-1)
    assert float(after.mean()) < float(error.mean())


def test_scale_sigma_holds_the_scale_as_a_prior(human, scene):
    """``scale_sigma`` is a prior on the global scale, not a clamp: a loose one leaves the masks' evidence
    (true scale 1.04) in charge, a tight one keeps the scale at 1."""
    fits = {
        sigma: fit_body(
            scene["stick"],
            scene["rig"],
            scene["masks"],
            scene["poses"],
            frames_used=2,
            iterations=150,
            scale_sigma=sigma,
        )[1].scale
        for sigma in (0.05, 0.002)
    }
    assert fits[0.05] == pytest.approx(TRUE_SCALE, rel=0.02)
    assert fits[0.002] == pytest.approx(1.0, abs=0.01)


def test_radius_sigma_holds_the_spread_of_the_widths_not_what_the_masks_show(human, scene):
    """``radius_sigma`` is a shrinkage prior on the log radii's spread: at the true poses the groups the
    masks show come out as well as fitted freely (5 % here, 1 % when written), while at poses 0.3 rad off in
    every joint the free fit explains the masks with a collapsed group (under 1 mm when written: its width
    taken over by its neighbours) and the held one keeps every group above 3 mm, with half the spread."""

    def fit(poses, sigma, **options):
        return fit_body(
            scene["stick"], scene["rig"], scene["masks"], poses, iterations=200, radius_sigma=sigma, **options
        )[1]

    for report in (fit(scene["poses"], None), fit(scene["poses"], 0.25)):
        observable = _observable(human, report.groups)
        want = torch.stack([(human.radii * TRUE_SCALE)[report.groups[g]].mean() for g in observable])
        assert float((report.radii_after[observable] / want).log().abs().max()) < 0.05
    g = torch.Generator().manual_seed(5)
    off = scene["poses"].clone()
    off[:, 6:] += 0.3 * torch.randn(off.shape[0], off.shape[1] - 6, generator=g, dtype=torch.float64)
    off = human.clamp(off)
    free, held = fit(off, None, pose_sigma=0.01), fit(off, 0.25, pose_sigma=0.01)
    assert float(free.radii_after.min()) < 0.001 < 0.003 < float(held.radii_after.min())
    assert float(held.radii_after.log().std()) < 0.6 * float(free.radii_after.log().std())
    with pytest.raises(ValueError, match="radius_sigma"):
        fit_body(scene["stick"], scene["rig"], scene["masks"], scene["poses"], radius_sigma=0.0)


def test_fixed_bones_keep_their_radii_and_the_rest_is_fitted(human, scene):
    """``fixed``: the arms' bones keep the stick figure's radii exactly (their groups get no step), every
    other group the masks show is fitted as without them (10 %: ``_check_fit``'s tolerance); a bone index
    out of range is an error naming the count."""
    arms = arm_bones(human)
    fitted, report = fit_body(
        scene["stick"], scene["rig"], scene["masks"], scene["poses"], iterations=200, fixed=arms
    )
    assert torch.allclose(fitted.radii[arms], scene["stick"].radii[arms], rtol=1e-9, atol=0)
    groups_of_arms = {g for g, bones in enumerate(report.groups) if set(bones) & set(arms)}
    assert groups_of_arms and all(set(report.groups[g]) <= set(arms) for g in groups_of_arms)
    true_radii = human.radii * TRUE_SCALE
    others = [g for g in _observable(human, report.groups) if g not in groups_of_arms]
    assert len(others) >= 6
    for g in others:
        want = float(true_radii[report.groups[g]].mean())
        assert float(report.radii_after[g]) == pytest.approx(want, rel=0.10), report.labels[g]
    with pytest.raises(ValueError, match=f"the skeleton has {len(human.bones)} bones"):
        fit_body(scene["stick"], scene["rig"], scene["masks"], scene["poses"], fixed=[len(human.bones)])


def test_projected_radii_match_opencv(human, scene):
    """Each capsule's radius in pixels against OpenCV: both ends and a point one radius off each end,
    perpendicular to the bone and to the line of sight, projected with ``cv2.projectPoints``; the mean over
    the ends and the cameras agrees within 3 % (the model's ``sqrt(cos t)`` area correction off the optical
    axis is the difference). Masks at half the cameras' size halve every radius."""
    import cv2

    skel, rig, pose = scene["truth"], scene["rig"], scene["poses"][2]
    got = projected_radii(skel, rig, pose)
    joints = skel.fk(pose).double().numpy()
    want = np.zeros(len(skel.bones))
    for cam in rig.cameras:
        K, R, t = (x.double().numpy() for x in (cam.K, cam.R, cam.t))
        centre = -R.T @ t
        rvec = cv2.Rodrigues(R)[0]
        for k, (p, c) in enumerate(skel.bones):
            a, b = joints[p], joints[c]
            axis = (b - a) / max(np.linalg.norm(b - a), 1e-9)
            for end in (a, b):
                sight = end - centre
                side = np.cross(axis, sight)
                side = (
                    side / np.linalg.norm(side)
                    if np.linalg.norm(side) > 1e-9
                    else np.cross(sight, [0, 0, 1.0])
                )
                side /= np.linalg.norm(side)
                r = float(skel.radii[k])
                uv = cv2.projectPoints(np.stack([end, end + r * side]), rvec, t, K, None)[0].reshape(2, 2)
                want[k] += np.linalg.norm(uv[1] - uv[0]) / (2 * len(rig.cameras))
    assert np.allclose(got.numpy(), want, rtol=0.03)
    half = projected_radii(skel, rig, pose, (80, 60))
    assert torch.allclose(half, got / 2, rtol=1e-4)


def test_outline_disagreement_in_pixels(scene):
    """The masks' outline against the body's silhouette, in pixels: the count from OpenCV (the symmetric
    difference read off ``overlay_image``'s colours, the outline as the mask minus its 3x3 ``cv2.erode``) per
    camera; the true body on its own masks (another rasteriser) strays under 0.1 px, and the same masks
    grown or shrunk by one pixel 0.9-1.15 px more (a one-pixel move of the whole outline); the stick figure
    (radii a quarter) more than 2 px; a missing or empty mask is NaN."""
    import cv2

    rig, truth, poses, masks = scene["rig"], scene["truth"], scene["poses"], scene["masks"]
    kernel = np.ones((3, 3), np.uint8)
    for f in range(N_FRAMES):
        got = outline_disagreement(truth, rig, masks[f], poses[f])
        tiles = np.split(overlay_image(truth, rig, masks[f], poses[f]), len(rig.cameras), axis=1)
        for v, tile in enumerate(tiles):
            mask = (masks[f][v] > 127).astype(np.uint8)
            wrong = (tile[:, :, 2] == 230).sum() + (tile[:, :, 0] == 110).sum()  # model only + mask only
            outline = (mask.astype(bool) & ~cv2.erode(mask, kernel).astype(bool)).sum()
            assert float(got[v]) == pytest.approx(wrong / outline, rel=1e-9)
        assert float(got.max()) < 0.1
        for grow in (cv2.dilate, cv2.erode):
            moved = np.stack([grow(m, kernel) for m in masks[f]])
            more = outline_disagreement(truth, rig, moved, poses[f]) - got
            assert 0.9 < float(more.min()) and float(more.max()) < 1.15, grow.__name__
        assert float(outline_disagreement(scene["stick"], rig, masks[f], poses[f]).min()) > 2.0
    partial = [masks[0][0], None, np.zeros_like(masks[0][2])]
    got = outline_disagreement(truth, rig, partial, poses[0])
    assert torch.isfinite(got[0]) and torch.isnan(got[1:]).all()


def test_outline_disagreement_where_the_tracker_runs(scene, device):
    """Masks, skeleton and rig on the tracker's device give the CPU's figures (the rasterisation runs on
    CPU copies)."""
    rig, truth, poses, masks = scene["rig"], scene["truth"], scene["poses"], scene["masks"]
    want = outline_disagreement(truth, rig, masks[1], poses[1])
    there = torch.from_numpy(masks[1]).to(device)
    moved = copy.deepcopy(truth).to(device), copy.deepcopy(rig).to(device)  # the fixture's stay put
    got = outline_disagreement(*moved, there, poses[1].to(device))
    assert torch.equal(got, want)


def test_fit_lengths_recovers_longer_thighs(human, scene):
    lengths = {"LeftLeg": 1.12, "RightLeg": 1.12, "LeftForeArm": 0.9, "RightForeArm": 0.9}
    truth = human.with_body(scale=TRUE_SCALE, lengths=lengths)
    poses = scene["poses"].clone()
    up = human.dof_names.index("Hips_Yposition")
    poses[:, up] = 0.0
    poses[:, up] = 0.05 - truth.fk(poses)[..., 2].min(-1).values
    joints = truth.fk(poses)
    rig = scene["rig"]
    masks = np.stack([render_masks(joints[f], truth.tree.bones, truth.radii, rig.cameras) for f in range(5)])
    fitted, report = fit_body(scene["stick"], rig, masks, poses, iterations=200, fit_lengths=True)
    factor = dict(zip(report.labels, report.lengths.tolist(), strict=True))
    # absolute lengths (global scale x factor); the factors are weakly held at 1, the forearm most visibly
    assert report.scale * factor["LeftLeg/RightLeg"] == pytest.approx(TRUE_SCALE * 1.12, rel=0.04)
    assert report.scale * factor["LeftForeArm/RightForeArm"] == pytest.approx(TRUE_SCALE * 0.9, rel=0.08)
    assert min(report.iou_after.values()) > 0.97
    assert float((fitted.fk(report.poses) - joints).norm(dim=-1).mean()) < 0.02


def test_view_offsets_absorb_one_masks_erosion_or_dilation(human, scene):
    """A segmenter that erodes one camera's mask and dilates another's by 2 px (balanced over the 15
    masks, as the foreign renderer's noisy preset does at random): fitted as they are, the radii follow
    whichever masks pull hardest; with ``view_offset_sigma`` each mask's offset is fitted beside the shared
    radii, which stay near the truth, and the offsets come out in the sign of the morphology."""
    import cv2

    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    op = (np.arange(N_FRAMES)[:, None] + np.arange(3)[None]) % 3  # 0 erode, 1 dilate, 2 as rendered
    masks = scene["masks"].copy()
    for f, v in np.ndindex(*op.shape):
        if op[f, v] < 2:
            masks[f, v] = (cv2.erode if op[f, v] == 0 else cv2.dilate)(masks[f, v], disk)

    def radius_error(report):
        true_radii = human.radii * TRUE_SCALE
        observable = _observable(human, report.groups)
        want = torch.stack([true_radii[report.groups[g]].mean() for g in observable])
        return float((report.radii_after[observable] / want).log().abs().mean())

    plain = fit_body(scene["stick"], scene["rig"], masks, scene["poses"], iterations=200)[1]
    fitted, report = fit_body(
        scene["stick"], scene["rig"], masks, scene["poses"], iterations=200, view_offset_sigma=1.0
    )
    assert plain.offsets is None and report.offsets.shape == (N_FRAMES, 3)
    off = report.offsets.numpy()
    assert off[op == 1].min() > off[op == 2].max() and off[op == 2].min() > off[op == 0].max()
    assert abs(float(report.offsets.mean())) < 1e-6  # centred: the shared radii carry the mean
    assert off[op == 1].mean() - off[op == 0].mean() == pytest.approx(4.0, abs=0.5)  # +-2 px
    # mean |log| radius error of the observable groups (0.02 against 0.25 when written)
    assert radius_error(report) < 0.05 and radius_error(plain) > 0.15
    assert "outline offset (px)" in report.table()
    # a missing mask has no offset (NaN), and the camera's figure is over the masks it has
    holed = [list(masks[0]), list(masks[1])]
    holed[1][2] = None
    some = fit_body(
        scene["stick"], scene["rig"], holed, scene["poses"][:2], iterations=40, view_offset_sigma=1.0
    )[1]
    assert torch.isnan(some.offsets[1, 2]) and int(torch.isfinite(some.offsets).sum()) == 5
    assert "nan" not in some.table()
    with pytest.raises(ValueError, match="view_offset_sigma"):
        fit_body(scene["stick"], scene["rig"], masks, scene["poses"], view_offset_sigma=0.0)


def test_cli_calibrate(scene, tmp_path, capsys):
    seq = SequenceData(
        cameras=scene["rig"],
        masks=[list(m) for m in scene["masks"][:3]],
        truth=scene["poses"][:3],
        dof_names=scene["stick"].dof_names,
    )
    write_sequence(tmp_path / "seq", seq)
    scene["stick"].save_urdf(tmp_path / "stick.urdf")
    out = tmp_path / "fitted.urdf"
    args = ["calibrate", str(tmp_path / "seq"), "--skeleton", str(tmp_path / "stick.urdf"), "--out", str(out)]
    assert main([*args, "--frames", "2", "--iterations", "40", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "IoU before" in printed and "LeftLeg/RightLeg" in printed
    assert "outline offset" not in printed
    fitted = Skeleton.from_urdf(out)
    assert float(fitted.radii.mean()) > 2 * float(scene["stick"].radii.mean())
    import cv2

    overlay = cv2.imread(str(tmp_path / "fitted_overlay.png"))
    assert overlay.shape == (120, 3 * 160, 3)

    # the masks' outline offsets fitted: a column of the camera table
    again = [*args[:-1], str(tmp_path / "offsets.urdf"), "--frames", "2", "--iterations", "40"]
    assert main([*again, "--outline-offsets", "1", "--no-progress"]) == 0
    assert "outline offset (px)" in capsys.readouterr().out
    assert main([*again, "--outline-offsets", "0", "--no-progress"]) == 2
    assert "--outline-offsets" in capsys.readouterr().err
    # the widths' spread held
    assert main([*again, "--radius-sigma", "0.25", "--no-progress"]) == 0
    capsys.readouterr()
    assert main([*again, "--radius-sigma", "-1", "--no-progress"]) == 2
    assert "--radius-sigma" in capsys.readouterr().err

    # bad input: one line on stderr, status 2
    assert main([*args, "--init", str(tmp_path / "missing.csv"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "missing.csv" in err and len(err.splitlines()) == 1
