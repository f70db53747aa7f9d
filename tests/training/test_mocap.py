"""BVH import: FK of the converted skeleton against an independent BVH reference, conventions, bad input.

The reference below parses BVH with its own few lines and computes joint positions with the plain BVH
semantics (per-joint Euler matrices in the file's y-up frame, numpy float64), then maps them to the z-up
world with ``C`` (x, y, z) -> (x, -z, y) and scales them. Nothing in it comes from ``training.mocap``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchpf.io import MocapFormatError
from torchpf.skeleton import Skeleton
from training.mocap import (
    CMU_SCALE,
    REVOLUTE_LIMIT,
    STATIC_MIN_FRAMES,
    Motion,
    bvh_to_urdf,
    convert_bvh,
    default_radii,
    load_bvh,
    read_bvh,
    static_channels,
)

CMU_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "mocap" / "cmu"
CMU_CLIPS = sorted(CMU_DIR.glob("*.bvh")) if CMU_DIR.is_dir() else []
DEFAULT_CLIPS = ("07_01.bvh", "16_46.bvh")  # a walk and a run (all frames); the rest run under -m slow
needs_cmu = pytest.mark.skipif(not CMU_CLIPS, reason=f"CMU clips not found in {CMU_DIR}")


# ------------------------------------------------------------------------------------------------ reference
def ref_parse(text: str):
    """[(name, parent, offset (3,), channels)], frame_time, values (T, K) -- End Sites named parent_end."""
    hier, motion = text.split("MOTION")
    toks = hier.replace("{", " { ").replace("}", " } ").split()
    joints, stack, i = [], [], 0
    while i < len(toks):
        t = toks[i]
        if t in ("ROOT", "JOINT"):
            joints.append([toks[i + 1], stack[-1] if stack else -1, None, []])
            i += 2
        elif t == "End":
            joints.append([joints[stack[-1]][0] + "_end", stack[-1], None, []])
            i += 2
        elif t == "{":
            stack.append(len(joints) - 1)
            i += 1
        elif t == "}":
            stack.pop()
            i += 1
        elif t == "OFFSET":
            joints[stack[-1]][2] = np.array([float(v) for v in toks[i + 1 : i + 4]])
            i += 4
        elif t == "CHANNELS":
            n = int(toks[i + 1])
            joints[stack[-1]][3] = toks[i + 2 : i + 2 + n]
            i += 2 + n
        else:
            i += 1  # HIERARCHY
    rows = [line.split() for line in motion.splitlines() if line.strip()]
    frame_time = float(rows[1][-1])
    values = np.array(rows[2:], dtype=float).reshape(len(rows) - 2, -1)
    return joints, frame_time, values


def _elementary(axis: str, deg: np.ndarray) -> np.ndarray:
    a = np.radians(deg)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    m = {
        "X": [[o, z, z], [z, c, -s], [z, s, c]],
        "Y": [[c, z, s], [z, o, z], [-s, z, c]],
        "Z": [[c, -s, z], [s, c, z], [z, z, o]],
    }[axis]
    return np.moveaxis(np.array(m), (0, 1), (-2, -1))  # (T, 3, 3)


def ref_positions(joints, values, scale) -> dict[str, np.ndarray]:
    """World (z up, m) positions (T, 3) of every joint by the BVH formula, frame by frame in y-up."""
    T = values.shape[0]
    col, R, p, out = 0, {}, {}, {}
    for k, (name, parent, offset, channels) in enumerate(joints):
        Rk = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
        trans = np.broadcast_to(offset, (T, 3)).copy()
        for ch in channels:
            axis, kind = ch[0].upper(), ch[1:].lower()
            if kind == "position":
                trans[:, "XYZ".index(axis)] += values[:, col]
            else:
                Rk = Rk @ _elementary(axis, values[:, col])
            col += 1
        if parent < 0:
            R[k], p[k] = Rk, trans
        else:
            R[k] = R[parent] @ Rk
            p[k] = p[parent] + np.einsum("tij,tj->ti", R[parent], trans)
        C = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=float)
        out[name] = scale * p[k] @ C.T
    return out


def fk_error(path: Path, scale: float):
    """Max |FK - reference| (m) over frames and joints, and the FK positions (T, J, 3)."""
    skel, motion = load_bvh(path, scale)
    joints, frame_time, values = ref_parse(path.read_text())
    ref = ref_positions(joints, values, scale)
    assert sorted(skel.joint_names) == sorted(ref)
    assert motion.fps == pytest.approx(1.0 / frame_time, rel=1e-12)
    fk = skel.fk(motion.angles).numpy()
    expected = np.stack([ref[n] for n in skel.joint_names], axis=1)
    return float(np.abs(fk - expected).max()), skel, fk


# ------------------------------------------------------------------------------------------------ CMU clips
CMU_PARAMS = [
    pytest.param(name, marks=() if name in DEFAULT_CLIPS else pytest.mark.slow)
    for name in sorted({p.name for p in CMU_CLIPS} | set(DEFAULT_CLIPS))
]


@needs_cmu
@pytest.mark.parametrize("clip", CMU_PARAMS)
def test_cmu_fk_reproduces_bvh_positions(clip):
    path = CMU_DIR / clip
    if not path.exists():
        pytest.skip(f"{path} not found")
    err, skel, fk = fk_error(path, CMU_SCALE)
    assert err < 1e-4  # 0.1 mm; we get ~1e-8 m (float32 offsets in the chain)
    # Bone lengths are constant over frames (only the root has position channels).
    joints, _, _ = ref_parse(path.read_text())
    for c, p in enumerate(skel.parents):
        if p < 0:
            continue
        length = np.linalg.norm(fk[:, c] - fk[:, p], axis=-1)
        offset = next(j[2] for j in joints if j[0] == skel.joint_names[c])
        assert np.ptp(length) < 1e-9
        # pytorch-kinematics parses URDF origins in float32: offsets are good to ~1e-8 relative.
        assert length[0] == pytest.approx(CMU_SCALE * np.linalg.norm(offset), rel=1e-6)


@needs_cmu
def test_cmu_structure():
    skel, motion = load_bvh(CMU_DIR / "07_01.bvh", CMU_SCALE)
    assert motion.angles.dtype == torch.float64 and motion.angles.shape == (317, 96)
    assert motion.dof_names == skel.dof_names
    assert skel.dof_names[:6] == [f"Hips_{a}position" for a in "XYZ"] + [f"Hips_{a}rotation" for a in "ZYX"]
    assert "LeftUpLeg_Zrotation" in skel.dof_names and "LThumb_end" in skel.joint_names
    assert "world" not in skel.joint_names  # the root's OFFSET is zero: world is hidden
    assert torch.all(motion.angles.abs() <= skel.upper.abs())  # within the +-2 pi / +-100 m limits
    # The file is y up: standing subject's head is above the hips in z (m).
    fk = skel.fk(motion.angles[:1])[0]
    names = skel.joint_names
    assert fk[names.index("Head"), 2] - fk[names.index("Hips"), 2] > 0.4


# ------------------------------------------------------------------------------------------------ conventions
def _bvh(hierarchy: str, frames: list[list[float]], frame_time: float = 0.01, newline: str = "\n") -> str:
    lines = ["HIERARCHY", *hierarchy.strip().splitlines(), "MOTION", f"Frames: {len(frames)}"]
    lines.append(f"Frame Time: {frame_time}")
    lines += [" ".join(repr(float(v)) for v in row) for row in frames]
    return newline.join(lines) + newline


TWO_BONES = """
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 0 1 0
    CHANNELS 2 Zrotation Xrotation
    End Site
    {
      OFFSET 0 2 0
    }
  }
}
"""


def _load_text(tmp_path, text, scale=1.0, name="clip.bvh", **kw):
    path = tmp_path / name
    path.write_bytes(text.encode())
    return load_bvh(path, scale, **kw)


def test_y_up_becomes_z_up_and_scale(tmp_path):
    skel, motion = _load_text(tmp_path, _bvh(TWO_BONES, [[10, 20, 30, 0, 0, 0, 0, 0]]), scale=0.5)
    fk = skel.fk(motion.angles)[0]
    names = skel.joint_names
    assert names == ["Hips", "Chest", "Chest_end"]
    # BVH (x, y, z) -> world (x, -z, y), times 0.5 m per unit.
    torch.testing.assert_close(fk[0], torch.tensor([5.0, -15.0, 10.0], dtype=torch.float64))
    torch.testing.assert_close(fk[1], torch.tensor([5.0, -15.0, 10.5], dtype=torch.float64))
    torch.testing.assert_close(fk[2], torch.tensor([5.0, -15.0, 11.5], dtype=torch.float64))
    assert motion.fps == pytest.approx(100.0)


def test_euler_order_is_channel_order(tmp_path):
    # Chest "Zrotation Xrotation" = Rz(90) @ Rx(90): the bone (0, 2, 0) -> Rx -> (0, 0, 2) -> Rz -> (0, 0, 2)
    # in BVH, i.e. (0, -2, 0) in the world. The other order would give (-2, 0, 0).
    skel, motion = _load_text(tmp_path, _bvh(TWO_BONES, [[0, 0, 0, 0, 0, 0, 90, 90]]))
    fk = skel.fk(motion.angles)[0]
    torch.testing.assert_close(fk[2] - fk[1], torch.tensor([0.0, -2.0, 0.0], dtype=torch.float64))
    # Radians in the Motion, metres for positions.
    assert motion.angles[0, motion.dof_names.index("Chest_Zrotation")] == pytest.approx(math.pi / 2)


def test_urdf_axes_limits_and_radii(tmp_path):
    path = tmp_path / "clip.bvh"
    path.write_text(_bvh(TWO_BONES, [[0] * 8]))
    xml = bvh_to_urdf(path, scale=0.1, radii={"Chest_end": 0.05})
    assert '<joint name="Hips_Zrotation" type="revolute">' in xml
    assert '<axis xyz="0 -1 0"/>' in xml  # BVH Z -> world -y
    assert f'lower="{-REVOLUTE_LIMIT:.9g}"' in xml
    radii = default_radii(path, 0.1)
    assert radii == {"Chest": 0.015, "Chest_end": pytest.approx(0.03)}  # 0.15 x 0.1 m, 0.15 x 0.2 m
    skel, _ = load_bvh(path, 0.1, radii={"Chest_end": 0.05})
    assert skel.radii.tolist() == pytest.approx([0.015, 0.05])


def _still_chest(n_frames: int, move_x: bool = True) -> str:
    """TWO_BONES whose root turns and whose chest's Z rotation holds 15 degrees (X moves if ``move_x``)."""
    rows = [[0, 0, 0, 30, 0, 0, 15, (k % 7) * float(move_x)] for k in range(n_frames)]
    for k, row in enumerate(rows):
        row[4] = k  # the root's X rotation moves; its Z rotation (30) does not, and is not judged
    return _bvh(TWO_BONES, rows)


def test_channels_that_never_move_are_held_at_their_value(tmp_path):
    path = tmp_path / "clip.bvh"
    path.write_text(_still_chest(STATIC_MIN_FRAMES))
    urdf, skel, motion, held = convert_bvh(path, hold_static=True)
    # the root's constant Z rotation places the body: only posture DOFs are judged
    assert held == {"Chest_Zrotation": pytest.approx(math.radians(15))}
    d = skel.dof_names.index("Chest_Zrotation")
    assert float(skel.lower[d]) == pytest.approx(math.radians(15), abs=1e-7) == float(skel.upper[d])
    assert torch.allclose(skel.clamp(motion.angles), motion.angles, atol=1e-6)  # the motion fits its limits
    free = [n for n in skel.dof_names if n != "Chest_Zrotation" and n.endswith("rotation")]
    assert all(float(skel.upper[skel.dof_names.index(n)]) == pytest.approx(REVOLUTE_LIMIT) for n in free)
    assert torch.equal(Skeleton.from_urdf(urdf).upper, skel.upper)  # the URDF text says it
    # by default (load_bvh, convert_bvh): the file's rig as it is, the still channels only reported
    raw, _ = load_bvh(path)
    assert float(raw.upper[d]) == pytest.approx(REVOLUTE_LIMIT)
    _, free, _, found = convert_bvh(path)
    assert found == held and torch.equal(free.upper, raw.upper)
    same, _ = load_bvh(path, hold_static=True)
    assert torch.equal(same.upper, skel.upper)


@pytest.mark.parametrize(
    ("frames", "move_x", "why"),
    [(STATIC_MIN_FRAMES - 1, True, "too short to tell"), (STATIC_MIN_FRAMES, False, "no posture DOF moves")],
)
def test_nothing_is_held_without_evidence(tmp_path, frames, move_x, why):
    path = tmp_path / "clip.bvh"
    path.write_text(_still_chest(frames, move_x))
    skel, motion = load_bvh(path)
    assert static_channels(skel, motion) == {}, why


@pytest.mark.skipif(len(CMU_CLIPS) < 2, reason=f"CMU clips not found in {CMU_DIR}")
def test_cmu_rig_channels_that_never_move_are_the_same_for_every_performer():
    # two performers (subjects 07 and 35): what convert holds is the rig's, not one performance's (20 of
    # the 96 channels; 22 without the rest pose of frame 0, which turns the hand tips once)
    held = [
        convert_bvh(CMU_DIR / f"{clip}.bvh", CMU_SCALE, hold_static=True)[3] for clip in ("07_01", "35_02")
    ]
    assert held[0].keys() == held[1].keys() and len(held[0]) == 20
    assert held[0] == pytest.approx(held[1], abs=1e-12)
    assert {n.rsplit("_", 1)[0] for n in held[0]} == {
        "LHipJoint", "RHipJoint", "LeftShoulder", "RightShoulder",
        "LeftHand", "RightHand", "LeftHandIndex1", "RightHandIndex1",
    }  # fmt: skip


def test_end_site_names_are_unique(tmp_path):
    h = """
ROOT A
{
  OFFSET 0 0 0
  CHANNELS 1 Yrotation
  JOINT A_end
  {
    OFFSET 1 0 0
    CHANNELS 0
    End Site
    {
      OFFSET 1 0 0
    }
  }
  End Site
  {
    OFFSET 0 1 0
  }
}
"""
    path = tmp_path / "e.bvh"
    path.write_text(_bvh(h, [[0.0]]))
    assert [j.name for j in read_bvh(path).joints] == ["A", "A_end", "A_end_end", "A_end_2"]


# ------------------------------------------------------------------------------------------------ property
AXES = "XYZ"


@st.composite
def random_bvh(draw):
    """A random hierarchy (any Euler orders, position channels anywhere), frames, line ends and spacing."""
    n = draw(st.integers(1, 6))
    parents = [-1] + [draw(st.integers(0, k - 1)) for k in range(1, n)]
    coord = st.floats(-20, 20, allow_nan=False).map(lambda v: round(v, 4))
    channels = []
    for k in range(n):
        rot = draw(st.permutations(AXES).map(lambda p: [f"{a}rotation" for a in p]))
        rot = rot[: draw(st.integers(0 if k else 1, 3))]
        pos = [f"{a}position" for a in AXES if k == 0 or draw(st.booleans())]
        if k and draw(st.booleans()):
            pos = pos[:1]
        # Mix the order: positions are translations whatever their place in the list.
        chans = draw(st.permutations(rot + pos)) if k else pos + rot
        channels.append(chans)
    indent = draw(st.sampled_from(["\t", "  "]))
    newline = draw(st.sampled_from(["\n", "\r\n"]))

    def block(k, depth):
        pad = indent * depth
        kw = "ROOT" if k == 0 else "JOINT"
        off = " ".join(str(draw(coord)) for _ in range(3))
        lines = [f"{pad}{kw} J{k}", f"{pad}{{", f"{pad}{indent}OFFSET {off}"]
        lines.append(f"{pad}{indent}CHANNELS {len(channels[k])} {' '.join(channels[k])}")
        kids = [c for c in range(n) if parents[c] == k]
        for c in kids:
            lines += block(c, depth + 1)
        if not kids or draw(st.booleans()):
            end = " ".join(str(draw(coord)) for _ in range(3))
            lines += [
                f"{pad}{indent}End Site",
                f"{pad}{indent}{{",
                f"{pad}{indent * 2}OFFSET {end}",
                f"{pad}{indent}}}",
            ]
        lines.append(f"{pad}}}")
        return lines

    hierarchy = "\n".join(block(0, 0))
    T = draw(st.integers(1, 4))
    K = sum(len(c) for c in channels)
    frames = [[draw(st.floats(-400, 400, allow_nan=False)) for _ in range(K)] for _ in range(T)]
    return _bvh(hierarchy, frames, newline=newline)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=random_bvh(), scale=st.sampled_from([1.0, 0.056444, 2.5]))
def test_random_hierarchies_match_reference(tmp_path, text, scale):
    path = tmp_path / "random.bvh"
    path.write_bytes(text.encode())
    err, _, _ = fk_error(path, scale)
    joints, _, values = ref_parse(text)
    extent = max(1.0, max(float(np.abs(p).max()) for p in ref_positions(joints, values, scale).values()))
    assert err < 1e-6 * extent  # float32 offsets in the pytorch-kinematics chain: ~1e-7 relative


# ------------------------------------------------------------------------------------------------ bad input
GOOD = _bvh(TWO_BONES, [[0, 1, 2, 3, 4, 5, 6, 7], [1, 1, 2, 3, 4, 5, 6, 7]])


def _error(tmp_path, text) -> MocapFormatError:
    path = tmp_path / "bad.bvh"
    path.write_bytes(text.encode())
    with pytest.raises(MocapFormatError) as info:
        load_bvh(path, scale=CMU_SCALE)
    assert str(path) in str(info.value)
    return info.value


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        (GOOD[: GOOD.index("End Site")], 9, "ends inside the HIERARCHY"),  # truncated in the hierarchy
        (GOOD.rsplit("1.0 1.0", 1)[0], 19, "file ends after 1 frame lines"),  # a frame missing
        (GOOD.replace("Frames: 2", "Frames: 1"), 20, "more frame lines"),
        (GOOD.replace("4.0 5.0 6.0 7.0\n", "4.0 5.0 6.0\n", 1), 19, "expected 8 numbers"),
        (GOOD.replace("2 Zrotation Xrotation", "2 Zrotation Wrotation"), 9, "unknown channel 'Wrotation'"),
        (
            GOOD.replace("2 Zrotation Xrotation", "3 Zrotation Xrotation"),
            10,
            "declares 3 channels but lists 2",
        ),
        (GOOD.replace("OFFSET 0 1 0", "OFFSET 0 one 0"), 8, "not a number: 'one'"),
        (GOOD.replace("JOINT Chest", "JOINT Hips"), 6, "duplicate joint name"),
        (GOOD.replace("Frame Time: 0.01", "Frame Time: 0"), 18, "Frame Time must be a number of seconds in"),
        (GOOD.split("MOTION")[0], 15, "no MOTION"),
        (GOOD.replace("Frame Time: 0.01\n", ""), 18, "expected 'Frame Time"),
        (GOOD.replace("Frame Time: 0.01", "Frame Time: 1e-320"), 18, "Frame Time must be a number of"),
        (GOOD.replace("OFFSET 0 1 0", "OFFSET 0 1_000 0"), 8, "not a number: '1_000'"),
        (GOOD.replace("OFFSET 0 1 0", "OFFSET 0 \u0661 0"), 8, "not a number"),
        (GOOD.replace("Frames: 2", "Frames: 0_2"), 17, "Frames must be an integer"),
        (GOOD.replace("OFFSET 0 1 0", "OFFSET 0 1e200 0"), 6, "OFFSET 5.6444e+198 m at scale 0.056444"),
        (GOOD.replace("4.0 5.0 6.0 7.0\n", "4.0 5.0 6.0 7.0e300\n", 1), None, "frame 1: 7e+300 is"),
        (GOOD.replace("4.0 5.0 6.0 7.0\n", "4.0 5.0 6.0 \u0667\n", 1), 19, "not a plain decimal number"),
    ],
)
def test_bvh_errors_name_file_and_line(tmp_path, text, line, words):
    err = _error(tmp_path, text)
    assert err.line == line, str(err)
    assert words in str(err)


def test_deep_hierarchy_is_a_clear_error(tmp_path):
    depth = 1200
    lines = ["HIERARCHY", "ROOT J0", "{", "OFFSET 0 0 0", "CHANNELS 1 Xrotation"]
    for k in range(1, depth):
        lines += [f"JOINT J{k}", "{", "OFFSET 0 1 0", "CHANNELS 1 Xrotation"]
    lines += ["}"] * depth + ["MOTION", "Frames: 1", "Frame Time: 0.01", " ".join(["0"] * depth)]
    err = _error(tmp_path, "\n".join(lines) + "\n")
    assert "more than 256 joints deep" in str(err) and err.line == 2 + 4 * 256  # JOINT J256


def test_zero_frames_read_but_do_not_convert(tmp_path):
    path = tmp_path / "empty.bvh"
    path.write_text(_bvh(TWO_BONES, []))
    assert read_bvh(path).n_frames == 0
    with pytest.raises(MocapFormatError, match="empty.bvh: 'Frames: 0': the file has no motion"):
        load_bvh(path)


@pytest.mark.parametrize("bad", ["nan", "inf", "1e999", "x"])
def test_bvh_bad_values_name_line_and_column(tmp_path, bad):
    text = GOOD.replace("1.0 1.0 2.0 3.0", f"1.0 1.0 {bad} 3.0")
    err = _error(tmp_path, text)
    assert (err.line, err.column) == (20, "3 ('Hips_Zposition')")


def test_empty_and_crlf_files(tmp_path):
    err = _error(tmp_path, "")
    assert "HIERARCHY" in str(err)
    path = tmp_path / "crlf.bvh"
    path.write_bytes(GOOD.replace("\n", "\r\n").encode())
    assert read_bvh(path).values.shape == (2, 8)


# ------------------------------------------------------------------------------------------------ Motion
def test_motion_validation_and_helpers():
    m = Motion(["a", "b"], 50, np.arange(6.0).reshape(3, 2), name="x")
    assert m.angles.dtype == torch.float64 and len(m) == 3 and m.duration == pytest.approx(0.04)
    torch.testing.assert_close(m.times, torch.tensor([0.0, 0.02, 0.04], dtype=torch.float64))
    s = m.select(["b", "a"])
    assert s.dof_names == ["b", "a"] and s.angles[:, 0].tolist() == [1.0, 3.0, 5.0]
    assert m.to(torch.float32).angles.dtype == torch.float32
    sub = m[1::2]
    assert sub.angles.tolist() == [[2.0, 3.0]] and sub.fps == 25.0 and sub.name == "x"
    with pytest.raises(KeyError, match="'c'"):
        m.select(["c"])
    with pytest.raises(ValueError, match=r"shape \(T, 3\)"):
        Motion(["a", "b", "c"], 50, torch.zeros(3, 2))
    with pytest.raises(ValueError, match="duplicate"):
        Motion(["a", "a"], 50, torch.zeros(3, 2))
    with pytest.raises(ValueError, match="fps"):
        Motion(["a"], 0, torch.zeros(3, 1))


def test_control_characters_in_joint_names_name_the_file(tmp_path):
    err = _error(tmp_path, GOOD.replace("JOINT Chest", "JOINT Chest\x12"))
    assert "holds control characters" in str(err) and err.line == 6
