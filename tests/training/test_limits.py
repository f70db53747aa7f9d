"""Joint limits learned from mocap (training.limits), written into the URDF (Skeleton.with_limits), and
``python -m training fit-limits``."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from torchpf.assets import path as asset_path
from torchpf.skeleton import Skeleton
from training.__main__ import main
from training.limits import circular_range, fit_limits
from training.mocap import Motion, bvh_motion

HUMAN = str(asset_path("human.urdf"))
CMU = Path(__file__).resolve().parents[2].parent / "shared" / "mocap" / "cmu"


@pytest.fixture(scope="module")
def human():
    return Skeleton.from_urdf(HUMAN)


def _motion(skel, angles, name="m"):
    return Motion(list(skel.dof_names), 30.0, angles, name=name)


def test_circular_range_is_the_shortest_arc_holding_every_sample():
    g = torch.Generator().manual_seed(0)
    # a column inside (-pi, pi], one across the cut (2.9 .. 3.4 = -2.88), one constant
    inside = torch.rand(200, generator=g, dtype=torch.float64) * 1.3 - 0.4
    across = 2.9 + torch.rand(200, generator=g, dtype=torch.float64) * 0.5
    across = torch.atan2(torch.sin(across), torch.cos(across))
    data = torch.stack([inside, across, torch.full((200,), 0.7, dtype=torch.float64)], 1)
    start, width = circular_range(data)
    assert start[0] == pytest.approx(float(inside.min()), abs=1e-12)
    assert width[0] == pytest.approx(float(inside.max() - inside.min()), abs=1e-12)
    # the arc across the cut starts at its smallest angle above 2.9 and ends past pi
    assert 2.9 <= float(start[1]) < math.pi and float(start[1] + width[1]) > math.pi
    assert float(width[1]) == pytest.approx(float((2.9 + 0.5) - start[1]), abs=0.02)
    assert float(width[2]) == 0.0 and float(start[2]) == pytest.approx(0.7)


def test_fit_limits_is_the_range_plus_the_margin_within_the_skeletons_limits(human):
    D = len(human.dof_names)
    g = torch.Generator().manual_seed(1)
    lo_true = (torch.rand(D, generator=g, dtype=torch.float64) - 0.5) * 0.4
    span = torch.rand(D, generator=g, dtype=torch.float64) * 0.6
    # two performances that together cover [lo_true, lo_true + span]
    a = lo_true + span * torch.rand(100, D, generator=g, dtype=torch.float64)
    a[0], a[1] = lo_true, lo_true + span  # the extremes are in the data
    b = lo_true + span * torch.rand(50, D, generator=g, dtype=torch.float64)
    lower, upper, report = fit_limits([_motion(human, a), _motion(human, b)], human, margin=0.1)
    assert report.frames == 150
    root = torch.tensor([human.parents[j] < 0 for j in human.dof_joints])
    learned = torch.tensor([n in report.learned for n in human.dof_names])
    # the root's DOFs and prismatic ones keep their limits; every other DOF is learned
    assert torch.equal(learned, human.dof_revolute & ~root)
    expect_lo = torch.maximum(lo_true - 0.1, human.lower)
    expect_hi = torch.minimum(lo_true + span + 0.1, human.upper)
    torch.testing.assert_close(lower[learned], expect_lo[learned], rtol=0, atol=1e-12)
    torch.testing.assert_close(upper[learned], expect_hi[learned], rtol=0, atol=1e-12)
    assert torch.equal(lower[~learned], human.lower[~learned])
    assert torch.equal(upper[~learned], human.upper[~learned])


def test_fit_limits_keeps_what_a_urdf_interval_cannot_say(human):
    D = len(human.dof_names)
    names = human.dof_names
    knee, hip, elbow = (
        names.index(n) for n in ("LeftLeg_Xrotation", "LeftUpLeg_Zrotation", "LeftArm_Xrotation")
    )
    x = torch.zeros(40, D, dtype=torch.float64)
    x[:, knee] = torch.linspace(3.0, 3.3, 40)  # crosses +-pi once wrapped
    x[:, hip] = torch.linspace(-3.1, 3.1, 40)  # nearly a full turn
    x[:, elbow] = 3.0  # outside the shipped limits of that DOF
    motion = _motion(human, torch.atan2(torch.sin(x), torch.cos(x)))
    lower, upper, report = fit_limits([motion], human)
    assert names[knee] in report.wrapped and names[hip] in report.full_turn
    assert names[elbow] in report.conflicts
    for d in (knee, hip, elbow):
        assert (lower[d], upper[d]) == (human.lower[d], human.upper[d])
    # a performance of a subset of the DOFs: the others are unseen and keep theirs
    part = Motion([names[knee]], 30.0, torch.zeros(5, 1, dtype=torch.float64), name="part")
    _, _, report = fit_limits([part], human)
    assert report.learned == [names[knee]] and names[hip] in report.unseen
    assert "in no performance" in report.summary()


def test_fit_limits_bad_input_names_it(human):
    other = Motion(["nope"], 30.0, torch.zeros(3, 1, dtype=torch.float64), name="walk_07.csv")
    with pytest.raises(ValueError, match="walk_07.csv"):
        fit_limits([other], human)
    with pytest.raises(ValueError, match="at least one"):
        fit_limits([], human)
    with pytest.raises(ValueError, match="margin"):
        fit_limits([_motion(human, torch.zeros(2, len(human.dof_names)))], human, margin=-1)


def test_with_limits_writes_the_urdf_and_keeps_the_body(human, tmp_path):
    D = len(human.dof_names)
    lower, upper = human.lower.clone(), human.upper.clone()
    knee = human.dof_names.index("LeftLeg_Xrotation")
    lower[knee], upper[knee] = 0.1, 1.2
    limited = human.with_limits(lower, upper)
    assert (float(limited.lower[knee]), float(limited.upper[knee])) == pytest.approx((0.1, 1.2))
    others = torch.arange(D) != knee
    assert torch.equal(limited.lower[others], human.lower[others])
    x = torch.randn(4, D, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.2
    torch.testing.assert_close(limited.fk(x), human.fk(x))
    torch.testing.assert_close(limited.radii, human.radii)
    # the pose a limit clamps, and the file round trip
    assert float(limited.clamp(torch.full((D,), 2.0, dtype=torch.float64))[knee]) == pytest.approx(1.2)
    limited.save_urdf(tmp_path / "limited.urdf")
    again = Skeleton.from_urdf(str(tmp_path / "limited.urdf"))
    torch.testing.assert_close(again.lower, limited.lower)
    torch.testing.assert_close(again.upper, limited.upper)
    # a resized body keeps the limits
    torch.testing.assert_close(limited.with_body(scale=1.1).upper, limited.upper)
    with pytest.raises(ValueError, match="lower > upper"):
        human.with_limits(upper, lower)
    with pytest.raises(ValueError, match="shape"):
        human.with_limits(lower[:3])


def test_with_limits_limits_a_converted_skeletons_continuous_joints(tmp_path):
    # a joint without limits (continuous) becomes a limited revolute one
    urdf = """<?xml version="1.0"?>
<robot name="arm">
  <link name="base"/>
  <link name="upper"><collision name="lower"><origin xyz="0 0 0.15" rpy="0 0 0"/>
    <geometry><cylinder radius="0.03" length="0.3"/></geometry></collision></link>
  <link name="lower"/>
  <joint name="shoulder" type="continuous"><parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="1 0 0"/></joint>
  <joint name="elbow" type="fixed"><parent link="upper"/><child link="lower"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/></joint>
</robot>
"""
    f = tmp_path / "arm.urdf"
    f.write_text(urdf)
    skel = Skeleton.from_urdf(str(f))
    limited = skel.with_limits(torch.tensor([-0.5]), torch.tensor([0.5]))
    assert (float(limited.lower[0]), float(limited.upper[0])) == (-0.5, 0.5)
    assert 'type="revolute"' in limited.urdf_xml


@pytest.mark.skipif(not (CMU / "07_01.bvh").exists(), reason=f"CMU clips not found in {CMU}")
def test_fit_limits_cli_on_a_converted_cmu_clip(tmp_path, capsys):
    # the user's path: convert a BVH (which says the skeleton has no limits), learn its range of motion
    bvh = CMU / "07_01.bvh"
    assert main(["convert", str(bvh), "--scale", "0.056444", "--out-dir", str(tmp_path)]) == 0
    assert "fit-limits" in capsys.readouterr().out
    urdf, csv = tmp_path / "skeleton.urdf", tmp_path / "07_01.csv"
    skel = Skeleton.from_urdf(str(urdf))
    motion = bvh_motion(bvh, 0.056444, dof_names=skel.dof_names)
    out = tmp_path / "limited.urdf"
    argv = ["fit-limits", str(csv), "--skeleton", str(urdf), "--out", str(out), "--skip-first", "1"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "DOFs limited" in printed and str(out) in printed
    limited = Skeleton.from_urdf(str(out))
    angles = motion.angles[1:]
    # every frame of the performance is inside what was learned from it; the knee is now a narrow range
    wrapped = torch.atan2(torch.sin(angles), torch.cos(angles))
    finite = (
        torch.isfinite(limited.lower) & torch.isfinite(limited.upper) & (limited.upper - limited.lower < 6)
    )
    inside = (wrapped >= limited.lower - 1e-6) & (wrapped <= limited.upper + 1e-6)
    assert bool(inside[:, finite].all())
    knee = skel.dof_names.index("LeftLeg_Zrotation")
    assert (
        float(skel.upper[knee] - skel.lower[knee]) > 6 > 1 > float(limited.upper[knee] - limited.lower[knee])
    )
    # bad input: one line, status 2, nothing written
    out2 = tmp_path / "x.urdf"
    assert main(["fit-limits", str(tmp_path / "none.csv"), "--skeleton", str(urdf), "--out", str(out2)]) == 2
    assert main(["fit-limits", str(csv), "--skeleton", str(urdf), "--out", str(tmp_path / "x.txt")]) == 2
    assert main(["fit-limits", str(csv), "--skeleton", str(urdf), "--out", str(out2), "--margin", "-1"]) == 2
    with pytest.raises(SystemExit) as stop:  # refused while parsing, as argparse does
        main(["fit-limits", str(csv), "--skeleton", str(urdf), "--out", str(out2), "--skip-first", "-1"])
    assert stop.value.code == 2
    assert not out2.exists()
    err = capsys.readouterr().err
    assert "margin" in err and "argument --skip-first: must be >= 0" in err
