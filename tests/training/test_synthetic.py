"""Procedural motion generator: limits, determinism, gait structure, per-performer skeletons, files."""

import math

import pytest
import torch

from torchpf import Skeleton
from training.mocap import load_csv
from training.synthetic import ACTIONS, generate, generate_dataset, performer_urdf, sample_style


def joint(skel, positions, name):
    return positions[..., skel.joint_names.index(name), :]


@pytest.mark.parametrize("action", ACTIONS)
def test_performances_are_within_limits_and_reproducible(human, action):
    for seed in range(4):
        m = generate(action, 90, 30.0, seed=seed)
        assert m.dof_names == human.dof_names and m.angles.shape == (90, 96)
        assert torch.isfinite(m.angles).all()
        assert human.within_limits(m.angles).all()
        assert torch.equal(m.angles, generate(action, 90, 30.0, seed=seed).angles)
    assert not torch.allclose(generate(action, 90, seed=0).angles, generate(action, 90, seed=1).angles)


def dominant_frequency(x, fps):
    x = x - x.mean()
    spectrum = torch.fft.rfft(x * torch.hann_window(len(x), dtype=x.dtype)).abs()
    spectrum[0] = 0
    return float(spectrum.argmax()) * fps / len(x)


def test_walk_is_a_gait(human):
    fps, n = 60.0, 600
    style = sample_style("walk", torch.Generator().manual_seed(5))
    m = generate("walk", n, fps, style=style, seed=5)
    skel = Skeleton.from_urdf(performer_urdf(style.bone_scale))
    pos = skel.fk(m.angles)
    idx = {
        n: m.dof_names.index(n) for n in ("LeftLeg_Xrotation", "LeftUpLeg_Xrotation", "RightUpLeg_Xrotation")
    }
    # one gait cycle per 1/tempo seconds (frequency resolution fps/n = 0.1 Hz)
    assert dominant_frequency(m.angles[:, idx["LeftUpLeg_Xrotation"]], fps) == pytest.approx(
        style.tempo, abs=0.1
    )
    # left and right hips in antiphase
    left, right = m.angles[:, idx["LeftUpLeg_Xrotation"]], m.angles[:, idx["RightUpLeg_Xrotation"]]
    assert torch.corrcoef(torch.stack([left, right]))[0, 1] < -0.8
    # knee peak flexion in swing (about 60 degrees), never hyperextended
    knee = torch.rad2deg(m.angles[:, idx["LeftLeg_Xrotation"]])
    assert 45 < knee.max() < 80 and knee.min() > -1
    # on the performer's own skeleton the feet touch the floor, never go below it, and lift in swing
    names = ("LeftToeBase", "LeftToeBase_end", "RightToeBase", "RightToeBase_end")
    toes = torch.stack([joint(skel, pos, n)[:, 2] for n in names], 1)
    assert toes.min() > -1e-3  # heels (not joints) may be the lowest point, toes never below the floor
    assert toes.min(1).values.median() < 0.05
    assert toes[:, 0].max() > 0.08
    # no skating: in mid-stance (10-45% of its cycle) a foot moves at a small fraction of the walking speed
    t = torch.arange(n, dtype=torch.float64) / fps
    q = torch.remainder(style.tempo * t + style.phase, 1.0)
    left_toe = joint(skel, pos, "LeftToeBase")[:, :2]
    foot_speed = (left_toe[1:] - left_toe[:-1]).norm(dim=-1) * fps
    hips = joint(skel, pos, "Hips")[:, :2]
    speed = ((hips[-1] - hips[0]).norm() / t[-1]).item()
    mid_stance = ((q > 0.1) & (q < 0.45))[1:]
    assert foot_speed[mid_stance].median() < 0.1 * speed
    assert 0.6 < speed < 1.8  # m/s, adult walking


def test_wave_raises_the_right_hand_and_oscillates(human):
    style = sample_style("wave", torch.Generator().manual_seed(2))
    m = generate("wave", 240, 60.0, style=style, seed=2)
    pos = human.fk(m.angles)
    hand, head = joint(human, pos, "RightHandIndex1_end"), joint(human, pos, "Head_end")
    after = slice(90, None)  # the arm is up after 0.8 s
    assert (hand[after, 2] > head[after, 2] - 0.15).all()
    assert (joint(human, pos, "LeftHand")[:, 2] < 1.0).all()
    sweep = hand[after, 0] - joint(human, pos, "RightArm")[after, 0]  # side to side, relative to the shoulder
    f = dominant_frequency(sweep, 60.0)
    assert f == pytest.approx(style.tempo, abs=60.0 / 150 + 0.05)


def test_bend_lowers_the_head_and_comes_back(human):
    style = sample_style("bend", torch.Generator().manual_seed(1))
    T = int(round(30.0 / style.tempo)) + 1  # one cycle
    m = generate("bend", T, 30.0, style=style, seed=1)
    head = joint(human, human.fk(m.angles), "Head_end")[:, 2]
    assert head.max() - head.min() > 0.3
    # the knees stay nearly straight and the feet stay under the body
    knee = m.angles[:, m.dof_names.index("LeftLeg_Xrotation")]
    assert knee.abs().max() < math.radians(20)


def test_performer_skeleton_scales_bones():
    small, big = Skeleton.from_urdf(performer_urdf(0.9)), Skeleton.from_urdf(performer_urdf(1.1))
    zero = torch.zeros(96, dtype=torch.float64)
    a, b = small.fk(zero), big.fk(zero)
    torch.testing.assert_close(b * 0.9, a * 1.1)
    torch.testing.assert_close(big.radii * 0.9, small.radii * 1.1)
    with pytest.raises(ValueError, match="bone_scale"):
        performer_urdf(0.0)


def test_dataset_files_round_trip(tmp_path):
    paths = generate_dataset(tmp_path / "walk", action="walk", n_performers=3, seconds=1.0, fps=25.0, seed=7)
    assert [p.name for p in paths] == ["walk_00.csv", "walk_01.csv", "walk_02.csv"]
    for k, p in enumerate(paths):
        m = load_csv(p)
        assert m.fps == pytest.approx(25.0) and m.angles.shape == (25, 96)
        style = sample_style("walk", torch.Generator().manual_seed(7000 + k))
        ref = generate("walk", 25, 25.0, style=style, seed=7000 + k)
        torch.testing.assert_close(m.angles, ref.angles, rtol=0, atol=0)
        Skeleton.from_urdf(p.with_suffix(".urdf"))  # a loadable skeleton per performer


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown action 'jump'"):
        generate("jump")
    with pytest.raises(ValueError, match="n_frames"):
        generate("walk", 0)
