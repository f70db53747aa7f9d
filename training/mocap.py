"""Motion capture in and out: BVH files to URDF skeletons and angle tracks, and the mocap CSV format.

Recommended use::

    from training.mocap import load_bvh, save_csv, load_csv
    skel, motion = load_bvh("07_01.bvh", scale=CMU_SCALE)   # torchpf Skeleton, Motion (T, D) rad / m
    joints = skel.fk(motion.angles)                          # (T, J, 3) world positions, metres, z up
    save_csv("07_01.csv", motion); motion = load_csv("07_01.csv")
    save_bvh("07_01_out.bvh", skel, motion, scale=CMU_SCALE)  # back to BVH (Blender, MotionBuilder)

or from a shell: ``python -m training convert 07_01.bvh --scale 0.056444 --out-dir data/``.

**BVH semantics.** A BVH file is a HIERARCHY of joints (``ROOT``/``JOINT``, each with an ``OFFSET`` from its
parent and ``CHANNELS``, leaves closed by an ``End Site``) followed by a MOTION section: ``Frames: T``,
``Frame Time: dt`` and one line of channel values per frame, in hierarchy order. A joint's frame is::

    T_joint = T_parent @ Trans(offset + position channels) @ R_c1(a1) @ R_c2(a2) @ R_c3(a3)

where the rotation channels multiply in the order they are listed (``Zrotation Yrotation Xrotation`` means
``Rz @ Ry @ Rx``), angles in degrees. Any Euler order per joint is allowed, and position channels on any
joint (normally only the root has them).

**Conversion to torchpf conventions** (z up, metres, radians). BVH is y up; the world frame is obtained with
``C`` = rotation about x by +90 degrees, ``(x, y, z)_bvh -> (x, -z, y)_world``. Conjugating every joint frame
by ``C`` (and scaling translations by ``scale``, metres per file unit) turns the formula above into the URDF
one of :class:`torchpf.kinematics.urdf.BodyJoint`, term by term:

* offsets become ``scale * C @ offset``;
* a rotation about BVH axis ``e`` by ``a`` degrees becomes a revolute DOF about ``C @ e`` (X -> (1, 0, 0),
  Y -> (0, 0, 1), Z -> (0, -1, 0)) with value ``radians(a)``;
* a position channel along ``e`` becomes a prismatic DOF along ``C @ e`` with value ``scale * v``.

So the angle tracks are the file's numbers times a per-column constant: no Euler-angle re-decomposition, no
loss, and FK of the converted skeleton reproduces the BVH joint positions (to ~1e-8 relative: the URDF keeps 9
significant digits of the offsets and pytorch-kinematics parses them in float32).

**Names and order.** Each BVH channel is one DOF named ``f"{joint}_{channel}"`` with the channel spelled as in
the file (``Hips_Xposition``, ``LeftUpLeg_Zrotation``); within a joint the position DOFs come first, then the
rotations in channel order (the same as channel order in every common file, and what the formula above says
when a file lists a position after a rotation). BVH joint names are kept as body-joint names; an End Site
becomes a fixed body joint ``f"{parent}_end"``.

**Root OFFSET.** It is added to the root's position channels (``Hips_Xposition = scale * (offset_x + v)``)
wherever the root has a position channel for that axis, and left out of the URDF: same FK, root translation
DOFs that are the root's world position, and a URDF whose base link ``world`` stays hidden
(``Skeleton.from_urdf`` would otherwise list it as a body joint with a bone to the root). CMU files have a
zero root OFFSET, so there the values are only scaled.

**Limits.** BVH has none. Revolute DOFs get ``[-2 pi, 2 pi]`` (real Euler tracks may exceed +-180 degrees
slightly, e.g. a wrist that wraps, and FK is periodic anyway), prismatic ones
``+-torchpf.kinematics.urdf.ROOT_TRANSLATION_LIMIT``. Values are never wrapped or clipped here.

**Channels the rig does not animate.** A BVH exporter writes three rotation channels for every joint, and a
rig animates only some: in every CMU clip the same 20 of the 96 channels (the hip and collar bones, two of
each wrist's three, the hand tips) hold one value for the whole file, whoever the performer.
:func:`convert_bvh` with ``hold_static=True`` (``python -m training convert --hold-static``) finds them in the
file's own motion (:func:`static_channels`: posture DOFs only, at least :data:`STATIC_MIN_FRAMES` frames,
never all of them) and writes each as a limit range of one value, which the filters, the refinement and the
smoothing hold (a DOF with ``lower == upper`` is frozen). Not the default: on the foreign renders of the 11
CMU clips (``track``'s defaults) it changed the noisy error by nothing measurable (84.1 -> 83.9 mm) and made
the tracker lose a hand or a limb on clean masks more often (2.7-3.8 % of frames failed against 0 % with the
same tracker seeds; BENCHMARKS.md), presumably because the collar and hip rotations let the capsule body,
fitted on one frame, make up for its differences from the performer's.

**Capsules.** Each bone gets radius ``0.15 x`` its length clipped to ``[0.01, 0.08]`` m unless ``radii``
(child joint name -> radius in m) says otherwise.

Errors in the input (truncated file, wrong number of values on a motion line, unknown channel, NaN, CSV
columns that do not match) raise :class:`torchpf.io.MocapFormatError` naming file, line and column.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchpf.io import (
    MocapFormatError,
    parse_float_table,
    plain_float,
    plain_int,
    read_mocap_csv,
    write_mocap_csv,
)
from torchpf.kinematics.urdf import (
    MAX_COORDINATE,
    MAX_TREE_DEPTH,
    ROOT_TRANSLATION_LIMIT,
    BodyJoint,
    Dof,
    build_urdf,
    relimit_urdf,
)
from torchpf.skeleton import Skeleton

#: Metres per file unit of the CMU BVH conversions (``load_bvh(path, scale=CMU_SCALE)``).
CMU_SCALE = 0.056444

#: Joint limits (rad) given to every revolute DOF of a converted BVH.
REVOLUTE_LIMIT = 2.0 * math.pi

#: Default capsule radius: ``RADIUS_FRACTION x`` bone length, clipped to ``[RADIUS_MIN, RADIUS_MAX]`` m.
RADIUS_FRACTION, RADIUS_MIN, RADIUS_MAX = 0.15, 0.01, 0.08

#: Accepted ``Frame Time`` (s): a 1 MHz to one-frame-a-day clip; outside it, a corrupted header (1e-320 gives
#: an infinite frame rate).
MIN_FRAME_TIME, MAX_FRAME_TIME = 1e-6, 86400.0

#: Relative tolerance on the spacing of a CSV time column (e.g. times rounded to 1e-5 s at 120 fps pass).
TIME_RTOL = 1e-3

#: ``C``: BVH (y up) to world (z up), rotation about x by +90 degrees: (x, y, z) -> (x, -z, y).
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

# channel (lower case) -> (kind, BVH axis index)
_CHANNELS = {f"{axis}{kind}": (kind, i) for i, axis in enumerate("xyz") for kind in ("position", "rotation")}
_CHANNEL_SPELLING = "Xposition, Yposition, Zposition, Xrotation, Yrotation, Zrotation"
_KEYWORDS = {"OFFSET", "CHANNELS", "JOINT", "END", "ROOT", "{", "}", "MOTION"}


# ================================================================================================ Motion
@dataclass(eq=False)
class Motion:
    """A mocap performance: DOF tracks sampled at a constant frame rate.

    Attributes:
        dof_names: (D,) names of the columns of ``angles`` (a skeleton's ``dof_names`` or a subset).
        fps: frames per second (> 0).
        angles: (T, D) tensor, radians (revolute) / metres (prismatic). Loaders give float64 on the CPU; any
            floating dtype and device is kept as given (see :meth:`to`).
        name: optional label, e.g. the file stem.
    """

    dof_names: list[str]
    fps: float
    angles: torch.Tensor
    name: str | None = None

    def __post_init__(self):
        self.dof_names = [str(n) for n in self.dof_names]
        if len(set(self.dof_names)) != len(self.dof_names):
            dup = sorted({n for n in self.dof_names if self.dof_names.count(n) > 1})
            raise ValueError(f"Motion: duplicate DOF names {dup}")
        if not isinstance(self.angles, torch.Tensor):
            self.angles = torch.as_tensor(np.asarray(self.angles, dtype=np.float64))
        if not self.angles.is_floating_point():
            self.angles = self.angles.to(torch.float64)
        if self.angles.ndim != 2 or self.angles.shape[1] != len(self.dof_names):
            raise ValueError(
                f"Motion: angles must have shape (T, {len(self.dof_names)}) to match dof_names, "
                f"got {tuple(self.angles.shape)}"
            )
        self.fps = float(self.fps)
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"Motion: fps must be finite and > 0, got {self.fps}")

    @property
    def n_frames(self) -> int:
        """T."""
        return self.angles.shape[0]

    def __len__(self) -> int:
        return self.n_frames

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame, ``(T - 1) / fps``."""
        return max(self.n_frames - 1, 0) / self.fps

    @property
    def times(self) -> torch.Tensor:
        """(T,) float64 time (s) of each frame, starting at 0, on the device of ``angles``."""
        return torch.arange(self.n_frames, dtype=torch.float64, device=self.angles.device) / self.fps

    def __getitem__(self, frames: slice) -> Motion:
        """A new Motion with a slice of the frames, e.g. ``motion[1:]`` (CMU clips start with a rest pose)."""
        if not isinstance(frames, slice):
            raise TypeError(f"Motion frames are selected with a slice, got {type(frames).__name__}")
        step = frames.step if frames.step is not None else 1
        return Motion(list(self.dof_names), self.fps / abs(step), self.angles[frames], self.name)

    def select(self, dof_names: Sequence[str]) -> Motion:
        """A new Motion with only these DOF columns, in this order (e.g. another skeleton's ``dof_names``)."""
        index = {n: i for i, n in enumerate(self.dof_names)}
        missing = [n for n in dof_names if n not in index]
        if missing:
            raise KeyError(f"Motion {self.name or ''}: no DOF(s) {missing}")
        cols = torch.tensor([index[n] for n in dof_names], dtype=torch.long, device=self.angles.device)
        return Motion(list(dof_names), self.fps, self.angles.index_select(1, cols), self.name)

    def to(self, *args, **kwargs) -> Motion:
        """A new Motion with ``angles.to(*args, **kwargs)`` (device and/or dtype)."""
        return Motion(list(self.dof_names), self.fps, self.angles.to(*args, **kwargs), self.name)

    def __repr__(self) -> str:
        return (
            f"Motion(name={self.name!r}, T={self.n_frames}, D={len(self.dof_names)}, fps={self.fps:g}, "
            f"dtype={self.angles.dtype}, device={self.angles.device})"
        )


# ================================================================================================ CSV
def save_csv(path: str | os.PathLike, motion: Motion) -> None:
    """Write ``motion`` as a mocap CSV (``time`` column ``i / fps`` s, then one column per DOF), atomically.

    Values keep full float64 precision, so :func:`load_csv` reads back the same angles.
    """
    angles = motion.angles.detach().to("cpu", torch.float64).numpy()
    write_mocap_csv(path, motion.dof_names, angles, times=motion.times.cpu().numpy())


def load_csv(
    path: str | os.PathLike,
    fps: float | None = None,
    dof_names: Sequence[str] | None = None,
) -> Motion:
    """Read a mocap CSV into a :class:`Motion` (float64, CPU).

    Args:
        path: the CSV file.
        fps: frame rate. Taken from the ``time`` column when the file has one (it must then agree within
            ``TIME_RTOL``); required when the file has no time column or a single frame.
        dof_names: if given, the file must have exactly these DOF columns (any order); the Motion has them in
            this order (pass ``skel.dof_names`` to check a file against a skeleton).

    Returns:
        Motion with ``name`` = file stem; the time column's start is dropped (Motion times start at 0).

    Raises:
        MocapFormatError: malformed file (see :func:`torchpf.io.read_mocap_csv`), a value beyond
            +-``MAX_COORDINATE`` (1e6 rad or m), or time steps that are not uniform (within ``TIME_RTOL``),
            naming file, line and column.
        ValueError: no frame rate available, or ``fps`` disagrees with the time column.
    """
    path = os.fspath(path)
    names, times, values = read_mocap_csv(path, expected_dof_names=dof_names)
    too_big = np.argwhere(~(np.abs(values) <= MAX_COORDINATE))
    if len(too_big):  # a corrupted number: its square would overflow the fit's statistics
        r, c = (int(v) for v in too_big[0])
        raise MocapFormatError(
            f"|value| must be at most {MAX_COORDINATE:g} rad or m, got {float(values[r, c])!r}",
            path=path,
            line=r + 2,
            column=repr(names[c]),
        )
    if times is not None and len(times) >= 2:
        steps = np.diff(times)
        dt = (times[-1] - times[0]) / (len(times) - 1)
        off = np.abs(steps - dt) > TIME_RTOL * dt
        if off.any():
            r = int(np.argmax(off)) + 1  # frame index of the row that ends the first bad step
            raise MocapFormatError(
                f"time steps are not uniform: {float(steps[r - 1])!r} s here, {float(dt)!r} s on average; "
                "resample, or drop the time column and pass fps",
                path=path,
                line=r + 2,
                column="1 ('time')",
            )
        file_fps = 1.0 / dt
        if fps is not None and not math.isclose(fps, file_fps, rel_tol=TIME_RTOL):
            raise ValueError(f"{path}: fps={fps} disagrees with the time column ({file_fps:.6g} fps)")
        fps = file_fps
    if fps is None:
        why = "has no time column" if times is None else "has a single frame"
        raise ValueError(f"{path}: {why}, so the frame rate is unknown; pass fps=")
    return Motion(names, fps, torch.from_numpy(values), name=Path(path).stem)


# ================================================================================================ BVH parsing
@dataclass(frozen=True)
class BvhJoint:
    """One joint (or End Site) of a BVH hierarchy, as in the file.

    Attributes:
        name: BVH joint name; End Sites get ``f"{parent}_end"`` (made unique with ``_2``, ``_3``, ...).
        parent: index of the parent in ``BvhData.joints``; -1 for the root.
        offset: (3,) offset from the parent in file units, BVH frame (y up).
        channels: channel names as spelled in the file, in file order (empty for End Sites).
        end_site: whether this is an End Site.
        line: line of the file where it is declared.
    """

    name: str
    parent: int
    offset: tuple[float, float, float]
    channels: tuple[str, ...] = ()
    end_site: bool = False
    line: int = 0


@dataclass(frozen=True, eq=False)
class BvhData:
    """A parsed BVH file, raw: file units, degrees, y up. Convert with :func:`bvh_to_urdf`/:func:`bvh_motion`.

    Attributes:
        path: the file it was read from.
        joints: hierarchy in file order (parents before children), End Sites included.
        frame_time: seconds per frame (``Frame Time``).
        values: (T, K) channel values per frame, columns in ``channel_names`` order (file order).
    """

    path: str
    joints: list[BvhJoint]
    frame_time: float
    values: np.ndarray

    @property
    def channel_names(self) -> list[str]:
        """(K,) ``f"{joint}_{channel}"`` for every channel, in file (column) order."""
        return [f"{j.name}_{c}" for j in self.joints for c in j.channels]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def n_frames(self) -> int:
        return self.values.shape[0]


class _Tokens:
    """Whitespace-separated hierarchy tokens with their line numbers."""

    def __init__(self, lines: list[str], path: str):
        self.items: list[tuple[str, int]] = []
        for ln, line in enumerate(lines, 1):
            # Braces glued to a name ("Hips{") are split off; BVH names never contain braces.
            for tok in line.replace("{", " { ").replace("}", " } ").split():
                self.items.append((tok, ln))
        self.pos = 0
        self.path = path
        self.last_line = max((ln for ln, line in enumerate(lines, 1) if line.strip()), default=1)

    def error(self, message: str, line: int | None = None) -> MocapFormatError:
        return MocapFormatError(message, path=self.path, line=line)

    def peek(self) -> tuple[str, int] | None:
        return self.items[self.pos] if self.pos < len(self.items) else None

    def next(self, expected: str) -> tuple[str, int]:
        """The next token; ``expected`` describes it for the truncation message."""
        if self.pos >= len(self.items):
            raise self.error(
                f"file ends inside the HIERARCHY (truncated?); expected {expected}", self.last_line
            )
        item = self.items[self.pos]
        self.pos += 1
        return item

    def expect(self, word: str) -> int:
        tok, ln = self.next(repr(word))
        if tok.upper() != word.upper():
            raise self.error(f"expected {word!r}, got {tok!r}", ln)
        return ln

    def number(self, what: str) -> float:
        tok, ln = self.next(what)
        try:
            value = plain_float(tok)
        except ValueError:
            raise self.error(f"{what}: not a number: {tok!r}", ln) from None
        if not math.isfinite(value):
            raise self.error(f"{what}: must be finite, got {tok!r}", ln)
        return value


def _parse_hierarchy(tokens: _Tokens) -> list[dict]:
    # An explicit stack of the open joints, not recursion: a file 1,200 joints deep must end in the
    # MAX_TREE_DEPTH error, not a RecursionError.
    joints: list[dict] = []
    stack: list[tuple[int, str, int]] = []  # (index in joints, label, line of its keyword)

    def open_joint(parent: int, keyword_line: int, end_site: bool) -> None:
        if end_site:
            name = None
            tokens.expect("{")
        else:
            name, ln = tokens.next("a joint name")
            if name in ("{", "}"):
                raise tokens.error(f"missing joint name before {name!r}", ln)
            if not name.isprintable():  # control characters cannot go into the URDF (XML) it becomes
                raise tokens.error(f"joint name {name!r} holds control characters", ln)
        label = "End Site" if end_site else f"joint {name!r}"
        if len(stack) >= MAX_TREE_DEPTH:
            raise tokens.error(
                f"{label}: the hierarchy is more than {MAX_TREE_DEPTH} joints deep", keyword_line
            )
        joints.append({"name": name, "parent": parent, "offset": None, "channels": (), "end": end_site})
        joints[-1]["line"] = keyword_line
        if not end_site:
            tokens.expect("{")
        stack.append((len(joints) - 1, label, keyword_line))

    tokens.expect("HIERARCHY")
    open_joint(-1, tokens.expect("ROOT"), end_site=False)
    while stack:
        index, label, keyword_line = stack[-1]
        me = joints[index]
        end_site = me["end"]
        tok, ln = tokens.next(f"'}}' closing {label} (line {keyword_line})")
        word = tok.upper()
        if word == "OFFSET":
            if me["offset"] is not None:
                raise tokens.error(f"{label}: second OFFSET", ln)
            me["offset"] = tuple(tokens.number(f"{label}: OFFSET {a}") for a in "xyz")
        elif word == "CHANNELS" and not end_site:
            if me["channels"]:
                raise tokens.error(f"{label}: second CHANNELS", ln)
            me["channels"] = _parse_channels(tokens, label, ln)
        elif word == "JOINT" and not end_site:
            open_joint(index, ln, end_site=False)
        elif word == "END" and not end_site:
            tokens.expect("Site")
            open_joint(index, ln, end_site=True)
        elif tok == "}":
            if me["offset"] is None:
                raise tokens.error(f"{label} has no OFFSET", keyword_line)
            stack.pop()
        else:
            raise tokens.error(f"{label}: unexpected {tok!r}", ln)
    extra = tokens.peek()
    if extra is not None:
        what = "a second ROOT (several skeletons in one file are not supported)"
        raise tokens.error(
            what if extra[0].upper() == "ROOT" else f"unexpected {extra[0]!r} after the ROOT", extra[1]
        )
    return joints


def _parse_channels(tokens: _Tokens, label: str, line: int) -> tuple[str, ...]:
    tok, ln = tokens.next("the number of channels")
    try:
        n = plain_int(tok)
    except ValueError:
        raise tokens.error(f"{label}: CHANNELS count must be an integer, got {tok!r}", ln) from None
    if n < 0:
        raise tokens.error(f"{label}: CHANNELS count must be >= 0, got {n}", ln)
    channels: list[str] = []
    for k in range(n):
        tok, ln = tokens.next(f"channel {k + 1} of {n}")
        if tok.upper() in _KEYWORDS:
            raise tokens.error(f"{label}: CHANNELS declares {n} channels but lists {k}", ln)
        if tok.lower() not in _CHANNELS:
            raise tokens.error(f"{label}: unknown channel {tok!r} (expected one of {_CHANNEL_SPELLING})", ln)
        if tok.lower() in (c.lower() for c in channels):
            raise tokens.error(f"{label}: channel {tok!r} listed twice", ln)
        channels.append(tok)
    return tuple(channels)


def _name_end_sites(raw: list[dict]) -> None:
    """End Sites -> ``f"{parent}_end"``, unique among all joint names."""
    taken = {j["name"] for j in raw if not j["end"]}
    for j in raw:
        if j["end"]:
            base = f"{raw[j['parent']]['name']}_end"
            name, k = base, 2
            while name in taken:
                name, k = f"{base}_{k}", k + 1
            j["name"] = name
            taken.add(name)


_FRAMES_RE = re.compile(r"^\s*Frames\s*:\s*(\S+)\s*$", re.IGNORECASE)
_FRAME_TIME_RE = re.compile(r"^\s*Frame\s+Time\s*:\s*(\S+)\s*$", re.IGNORECASE)


def read_bvh(path: str | os.PathLike) -> BvhData:
    """Parse a BVH file (LF or CRLF line ends, tabs or spaces).

    Returns:
        :class:`BvhData` with the raw hierarchy and the (T, K) channel values in file units and degrees.

    Raises:
        MocapFormatError: malformed or truncated file, naming file, line and (for motion values) column.
        FileNotFoundError: no such file.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            text = f.read()
    except UnicodeDecodeError as e:
        raise MocapFormatError(f"not a text file ({e.reason} at byte {e.start})", path=path) from None
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    motion_at = next((i for i, line in enumerate(lines) if line.strip().upper() == "MOTION"), None)
    tokens = _Tokens(lines if motion_at is None else lines[:motion_at], path)
    raw = _parse_hierarchy(tokens)
    if motion_at is None:
        raise MocapFormatError("no MOTION section (truncated file?)", path=path, line=tokens.last_line)
    first_seen: dict[str, int] = {}
    for j in raw:
        if not j["end"]:
            if j["name"] in first_seen:
                raise MocapFormatError(
                    f"duplicate joint name {j['name']!r} (also line {first_seen[j['name']]})",
                    path=path,
                    line=j["line"],
                )
            first_seen[j["name"]] = j["line"]
    _name_end_sites(raw)
    joints = [BvhJoint(j["name"], j["parent"], j["offset"], j["channels"], j["end"], j["line"]) for j in raw]
    channel_names = [f"{j.name}_{c}" for j in joints for c in j.channels]
    n_ch = len(channel_names)
    if n_ch == 0:
        raise MocapFormatError("the hierarchy has no channels", path=path, line=motion_at + 1)

    # MOTION header: "Frames: T" then "Frame Time: dt" on the next non-blank lines.
    rest = [(i + 1, line) for i, line in enumerate(lines) if i > motion_at and line.strip()]
    header = []
    for regex, what in ((_FRAMES_RE, "'Frames: <count>'"), (_FRAME_TIME_RE, "'Frame Time: <seconds>'")):
        if len(header) >= len(rest):
            raise MocapFormatError(f"file ends before {what} (truncated?)", path=path, line=len(lines))
        ln, line = rest[len(header)]
        m = regex.match(line)
        if not m:
            raise MocapFormatError(f"expected {what}, got {line.strip()[:40]!r}", path=path, line=ln)
        header.append((ln, m.group(1)))
    (frames_ln, frames_tok), (ft_ln, ft_tok) = header
    try:
        n_frames = plain_int(frames_tok)
    except ValueError:
        n_frames = -1
    if n_frames < 0:
        raise MocapFormatError(
            f"Frames must be an integer >= 0, got {frames_tok!r}", path=path, line=frames_ln
        )
    try:
        frame_time = plain_float(ft_tok)
    except ValueError:
        frame_time = float("nan")
    if not (math.isfinite(frame_time) and MIN_FRAME_TIME <= frame_time <= MAX_FRAME_TIME):
        raise MocapFormatError(
            f"Frame Time must be a number of seconds in [{MIN_FRAME_TIME:g}, {MAX_FRAME_TIME:g}], "
            f"got {ft_tok!r}",
            path=path,
            line=ft_ln,
        )

    data_lines = rest[2:]
    if len(data_lines) < n_frames:
        last = data_lines[-1][0] if data_lines else ft_ln
        raise MocapFormatError(
            f"'Frames: {n_frames}' but the file ends after {len(data_lines)} frame lines (truncated?)",
            path=path,
            line=last,
        )
    if len(data_lines) > n_frames:
        raise MocapFormatError(
            f"more frame lines than 'Frames: {n_frames}' declares", path=path, line=data_lines[n_frames][0]
        )
    fields: list[str] = []
    for ln, line in data_lines:
        row = line.split()
        if len(row) != n_ch:
            raise MocapFormatError(
                f"expected {n_ch} numbers (one per channel), got {len(row)}", path=path, line=ln
            )
        fields.extend(row)
    values = parse_float_table(fields, n_ch, channel_names, path, [ln for ln, _ in data_lines])
    bad = np.argwhere(~np.isfinite(values))
    if len(bad):
        r, c = (int(v) for v in bad[0])
        raise MocapFormatError(
            f"value must be finite, got {fields[r * n_ch + c]!r}",
            path=path,
            line=data_lines[r][0],
            column=f"{c + 1} ({channel_names[c]!r})",
        )
    return BvhData(path=path, joints=joints, frame_time=frame_time, values=values)


# ================================================================================================ conversion
def _as_bvh(bvh: BvhData | str | os.PathLike) -> BvhData:
    return bvh if isinstance(bvh, BvhData) else read_bvh(bvh)


def _check_scale(scale: float) -> float:
    scale = float(scale)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale (metres per file unit) must be finite and > 0, got {scale}")
    return scale


def _dof_order(joint: BvhJoint) -> list[str]:
    """Channels of one joint in DOF order: positions first (translation precedes rotation), then rotations."""
    pos = [c for c in joint.channels if _CHANNELS[c.lower()][0] == "position"]
    return pos + [c for c in joint.channels if _CHANNELS[c.lower()][0] == "rotation"]


def _root_shift(bvh: BvhData) -> np.ndarray:
    """(3,) part of the root OFFSET (file units, BVH frame) folded into the root's position channels."""
    root = bvh.joints[0]
    covered = [_CHANNELS[c.lower()][1] for c in root.channels if _CHANNELS[c.lower()][0] == "position"]
    shift = np.zeros(3)
    shift[covered] = np.asarray(root.offset, dtype=np.float64)[covered]
    return shift


def default_radii(bvh: BvhData | str | os.PathLike, scale: float = 1.0) -> dict[str, float]:
    """Capsule radius (m) of the bone ending at each non-root joint: ``0.15 x`` length in ``[0.01, 0.08]``."""
    bvh, scale = _as_bvh(bvh), _check_scale(scale)
    out = {}
    for j in bvh.joints:
        if j.parent >= 0:
            length = scale * math.sqrt(sum(v * v for v in j.offset))
            out[j.name] = min(max(RADIUS_FRACTION * length, RADIUS_MIN), RADIUS_MAX)
    return out


def bvh_to_urdf(
    bvh: BvhData | str | os.PathLike,
    scale: float = 1.0,
    radii: Mapping[str, float] | None = None,
    robot_name: str | None = None,
) -> str:
    """URDF text of a BVH hierarchy in torchpf conventions (z up, metres; see the module docstring).

    Args:
        bvh: a parsed file or a path.
        scale: metres per file unit (CMU: ``CMU_SCALE`` = 0.056444).
        radii: capsule radius (m) per child joint name; overrides :func:`default_radii`.
        robot_name: ``<robot name>``; default the file stem.

    Returns:
        URDF XML text: one DOF per channel named ``f"{joint}_{channel}"``, End Sites as fixed joints.
    """
    bvh, scale = _as_bvh(bvh), _check_scale(scale)
    root = bvh.joints[0]
    if not root.channels and any(root.offset):
        # build_urdf makes a channel-less root the fixed base link at the origin: its OFFSET has no place.
        warnings.warn(
            f"{bvh.path}: root {root.name!r} has no channels; its OFFSET {root.offset} is ignored",
            stacklevel=2,
        )
    body = []
    for j in bvh.joints:
        raw = np.asarray(j.offset, dtype=np.float64) - (_root_shift(bvh) if j.parent < 0 else 0.0)
        offset = tuple(float(v) for v in scale * (Y_UP_TO_Z_UP @ raw))
        if not max(abs(v) for v in offset) <= MAX_COORDINATE:
            raise MocapFormatError(
                f"joint {j.name!r}: OFFSET {max(abs(v) for v in offset):g} m at scale {scale:g}, more than "
                f"{MAX_COORDINATE:g} m (a corrupted number?)",
                path=bvh.path,
                line=j.line,
            )
        dofs = []
        for c in _dof_order(j):
            kind, axis_index = _CHANNELS[c.lower()]
            axis = tuple(float(v) for v in Y_UP_TO_Z_UP[:, axis_index])
            if kind == "rotation":
                dofs.append(Dof(f"{j.name}_{c}", "revolute", axis, -REVOLUTE_LIMIT, REVOLUTE_LIMIT))
            else:
                dofs.append(
                    Dof(f"{j.name}_{c}", "prismatic", axis, -ROOT_TRANSLATION_LIMIT, ROOT_TRANSLATION_LIMIT)
                )
        parent = bvh.joints[j.parent].name if j.parent >= 0 else None
        body.append(BodyJoint(j.name, parent, offset, dofs))
    table = default_radii(bvh, scale)
    table.update(radii or {})
    name = robot_name if robot_name is not None else (Path(bvh.path).stem or "bvh")
    return build_urdf(name, body, radii=table)


def bvh_motion(
    bvh: BvhData | str | os.PathLike,
    scale: float = 1.0,
    dof_names: Sequence[str] | None = None,
) -> Motion:
    """The BVH channel tracks as a :class:`Motion` in radians / metres (float64).

    Args:
        bvh: a parsed file or a path.
        scale: metres per file unit; multiplies the position channels.
        dof_names: column order (e.g. ``skel.dof_names`` of :func:`bvh_to_urdf`'s skeleton); must name every
            channel exactly once. Default: file order.

    Returns:
        Motion with ``fps = 1 / Frame Time`` and ``name`` = file stem; ``angles`` (T, D).
    """
    bvh, scale = _as_bvh(bvh), _check_scale(scale)
    if bvh.n_frames == 0:
        raise MocapFormatError("'Frames: 0': the file has no motion to convert", path=bvh.path)
    names = bvh.channel_names
    kinds = [_CHANNELS[c.lower()][0] for j in bvh.joints for c in j.channels]
    # The conjugation by C leaves the values untouched (see the module docstring): one factor per column.
    factor = np.array([scale if k == "position" else math.pi / 180.0 for k in kinds])
    shift = np.zeros(len(names))  # the root OFFSET folded into the root's position channels
    root_shift = _root_shift(bvh)
    for k, c in enumerate(bvh.joints[0].channels):
        kind, axis = _CHANNELS[c.lower()]
        if kind == "position":
            shift[k] = scale * root_shift[axis]
    angles = bvh.values * factor + shift  # (T, K), all frames at once
    too_big = np.argwhere(~(np.abs(angles) <= MAX_COORDINATE))
    if len(too_big):
        r, c = (int(v) for v in too_big[0])
        raise MocapFormatError(
            f"frame {r + 1}: {bvh.values[r, c]:g} is {abs(float(angles[r, c])):g} rad or m, more than "
            f"{MAX_COORDINATE:g} (a corrupted number?)",
            path=bvh.path,
            column=f"{c + 1} ({names[c]!r})",
        )
    if dof_names is not None:
        index = {n: i for i, n in enumerate(names)}
        if sorted(dof_names) != sorted(names):
            unknown, missing = sorted(set(dof_names) - set(names)), sorted(set(names) - set(dof_names))
            raise ValueError(
                f"{bvh.path}: dof_names must name each BVH channel once; unknown {unknown}, missing {missing}"
            )
        angles = angles[:, [index[n] for n in dof_names]]
        names = list(dof_names)
    return Motion(names, bvh.fps, torch.from_numpy(np.ascontiguousarray(angles)), name=Path(bvh.path).stem)


def skeleton_from_urdf(bvh: BvhData, urdf: str) -> Skeleton:
    """:meth:`Skeleton.from_urdf` of :func:`bvh_to_urdf`'s text; an error names the BVH file, not the URDF
    string (e.g. a joint name the URDF cannot carry)."""
    try:
        return Skeleton.from_urdf(urdf)
    except ValueError as e:
        reason = " ".join(str(e).split())
        raise MocapFormatError(f"the converted skeleton is invalid ({reason})", path=bvh.path) from None


#: Fewest frames in which a channel that never moves is taken for one the rig does not animate rather than a
#: joint the performer held still (a second at 30 fps; CMU clips have hundreds at 120 fps).
STATIC_MIN_FRAMES = 30


def static_channels(
    skeleton: Skeleton, motion: Motion, *, min_frames: int = STATIC_MIN_FRAMES, tol: float = 1e-9
) -> dict[str, float]:
    """The posture DOFs (:attr:`~torchpf.skeleton.Skeleton.posture_dofs`: revolute, not the root's) that
    ``motion`` never moves, with the value they hold (rad): the channels the rig that wrote the file does not
    animate (module docstring).

    Args:
        skeleton: the motion's skeleton (its tree says which DOFs shape the posture).
        motion: a performance on it (columns by name; DOFs it lacks are not judged).
        min_frames: a shorter motion returns ``{}``: a few frames cannot tell a channel the rig never moves
            from a joint held still.
        tol: the largest spread (rad) of a channel still taken for constant.

    Returns:
        ``{dof name: value}``; ``{}`` as well where *every* posture DOF is constant (a file of one still pose
        says nothing about which channels move).
    """
    if motion.n_frames < int(min_frames):
        return {}
    column = {n: i for i, n in enumerate(motion.dof_names)}
    posture = skeleton.posture_dofs.cpu().tolist()
    names = [n for n, p in zip(skeleton.dof_names, posture, strict=True) if p and n in column]
    if not names:
        return {}
    angles = motion.angles[:, [column[n] for n in names]].detach().double().cpu()
    still = (angles.amax(0) - angles.amin(0)) <= tol
    if bool(still.all()):
        return {}
    return {n: float(angles[0, k]) for k, n in enumerate(names) if bool(still[k])}


def convert_bvh(
    bvh: BvhData | str | os.PathLike,
    scale: float = 1.0,
    *,
    radii: Mapping[str, float] | None = None,
    hold_static: bool = False,
) -> tuple[str, Skeleton, Motion, dict[str, float]]:
    """A BVH file as ``python -m training convert`` turns it into a tracking skeleton.

    Args:
        bvh: a parsed file or a path.
        scale: metres per file unit (CMU: ``CMU_SCALE``).
        radii: as :func:`bvh_to_urdf`.
        hold_static: write the channels the file never moves (:func:`static_channels`) as limits of one
            value, so that a tracker holds them (module docstring); default False: every channel free.

    Returns:
        ``(urdf, skel, motion, static)``: the URDF text, its skeleton, the motion in ``skel.dof_names`` order
        (:func:`bvh_motion`) and ``{dof name: value}`` of the channels the file never moves (held in the URDF
        only with ``hold_static``).
    """
    bvh = _as_bvh(bvh)
    urdf = bvh_to_urdf(bvh, scale, radii=radii)
    skel = skeleton_from_urdf(bvh, urdf)
    motion = bvh_motion(bvh, scale, dof_names=skel.dof_names)
    static = static_channels(skel, motion)
    if static and hold_static:
        urdf = relimit_urdf(urdf, {n: (v, v) for n, v in static.items()}, source=str(bvh.path))
        skel = skeleton_from_urdf(bvh, urdf)
    return urdf, skel, motion, static


def load_bvh(
    path: str | os.PathLike,
    scale: float = 1.0,
    *,
    radii: Mapping[str, float] | None = None,
    hold_static: bool = False,
) -> tuple[Skeleton, Motion]:
    """Read a BVH file as a torchpf skeleton and its motion.

    Args:
        path: the BVH file.
        scale: metres per file unit (CMU: ``CMU_SCALE`` = 0.056444).
        radii: capsule radius (m) per child joint name (default: :func:`default_radii`).
        hold_static: hold the channels the file never moves at their value (:func:`convert_bvh`,
            ``python -m training convert --hold-static``); default False: the file's rig as it is.

    Returns:
        ``(skel, motion)``: ``skel`` a :class:`torchpf.Skeleton` whose ``joint_names`` are the BVH joints and
        End Sites (``f"{parent}_end"``); ``motion.angles`` (T, D) float64 in ``skel.dof_names`` order
        (radians / metres), ``motion.fps = 1 / Frame Time``. ``skel.fk(motion.angles)`` (T, J, 3) are the BVH
        joint positions in metres, z up.

    Raises:
        MocapFormatError: malformed file, naming file, line and column.
    """
    _, skel, motion, _ = convert_bvh(read_bvh(path), scale, radii=radii, hold_static=hold_static)
    return skel, motion


# ================================================================================================ BVH export
#: Euler order (BVH channel order) of the joints :func:`save_bvh` re-decomposes; Blender's default.
BVH_EULER_ORDER = "ZXY"


@dataclass(frozen=True)
class _BvhOut:
    """One exported joint: name, parent index, OFFSET (file units, y up), channels and how to fill them.

    ``direct``: per channel ``(dof index, factor)`` (value = factor * theta[dof]), or None when the joint's
    rotation (and position) is re-decomposed from the FK transforms (:func:`_euler_from_matrix`).
    """

    name: str
    parent: int
    offset: np.ndarray
    channels: tuple[str, ...]
    direct: tuple[tuple[int, float], ...] | None
    positions: bool = False
    end_site: bool = False


def _unit_axis(v: np.ndarray, tol: float = 1e-9) -> tuple[int, float] | None:
    """(axis index, sign) when ``v`` is +-e_k, else None."""
    k = int(np.argmax(np.abs(v)))
    if abs(abs(v[k]) - 1.0) > tol or np.abs(np.delete(v, k)).max() > tol:
        return None
    return k, float(np.sign(v[k]))


def _direct_channels(run, scale: float, is_root: bool):
    """Channels of a run of URDF frames mapped one DOF -> one BVH channel, or None when they cannot be.

    The map exists when every origin in the run is a pure translation, translations (origins and prismatic
    DOFs) all come before the first revolute DOF, each DOF axis is a coordinate axis after the y-up change
    (``C^T axis = +-e_k``) and no axis repeats within rotations or within positions; a root must then have
    exactly 3 positions and 3 rotations (Blender's ROOT). Returns ``(offset, channels, direct)``.
    """
    offset = np.zeros(3)
    channels, direct, kinds, seen = [], [], [], set()
    for f in run:
        static = f.static.numpy()
        if not np.allclose(static[:3, :3], np.eye(3), atol=1e-9):
            return None
        if np.abs(static[:3, 3]).max() > 0 and "revolute" in kinds:
            return None
        offset += static[:3, 3]
        if f.dof < 0:
            continue
        if f.joint_type == "prismatic" and "revolute" in kinds:
            return None
        axis = _unit_axis(Y_UP_TO_Z_UP.T @ f.axis.numpy())
        kind = "rotation" if f.joint_type == "revolute" else "position"
        if axis is None or (kind, axis[0]) in seen:
            return None
        seen.add((kind, axis[0]))
        kinds.append(f.joint_type)
        channels.append(f"{'XYZ'[axis[0]]}{kind}")
        direct.append((f.dof, axis[1] * (180.0 / math.pi if kind == "rotation" else 1.0 / scale)))
    if is_root and (kinds.count("prismatic"), kinds.count("revolute")) != (3, 3):
        return None
    return Y_UP_TO_Z_UP.T @ offset / scale, tuple(channels), tuple(direct)


def _euler_from_matrix(R: np.ndarray, order: str) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) angles (rad) ``a`` with ``R = R_o0(a0) @ R_o1(a1) @ R_o2(a2)`` for
    ``order = o0 o1 o2`` (BVH channel order: intrinsic), any of the 6 Tait-Bryan orders. At gimbal lock
    (middle angle +-90 deg) the last angle is 0."""
    i, j, k = ("XYZ".index(c) for c in order)
    s = 1.0 if (j - i) % 3 == 1 else -1.0  # +1 for the cyclic orders XYZ, YZX, ZXY
    # atan2 with cos b = |row i off the k column| keeps b accurate near +-90 deg, where arcsin is not
    cos_b = np.hypot(R[..., i, i], R[..., i, j])
    b = np.arctan2(s * R[..., i, k], cos_b)
    a = np.arctan2(-s * R[..., j, k], R[..., k, k])
    c = np.arctan2(-s * R[..., i, j], R[..., i, i])
    lock = cos_b < 1e-10
    a = np.where(lock, np.arctan2(s * R[..., k, j], R[..., j, j]), a)
    c = np.where(lock, 0.0, c)
    return np.stack([a, b, c], -1)


def _bvh_plan(skeleton: Skeleton, scale: float, order: str) -> list[_BvhOut]:
    """The exported hierarchy: one BVH joint per body joint, its channels direct or re-decomposed."""
    from torchpf.kinematics.urdf import flatten_chain

    frames = flatten_chain(skeleton.chain)
    index = {f.name: i for i, f in enumerate(frames)}
    rest = skeleton.transforms(torch.zeros(len(skeleton.dof_names), dtype=torch.float64)).numpy()
    kids = [[c for c, p in enumerate(skeleton.parents) if p == j] for j in range(len(skeleton.parents))]
    out = []
    for j, (name, parent) in enumerate(zip(skeleton.joint_names, skeleton.parents, strict=True)):
        stop = index[skeleton.joint_names[parent]] if parent >= 0 else -1
        run, f = [], index[name]
        while f != stop:
            run.append(frames[f])
            f = frames[f].parent
        run.reverse()
        has_dofs = any(fr.dof >= 0 for fr in run)
        if parent >= 0:  # OFFSET: the rest-pose position in the parent's frame
            T_p = rest[parent]
            local = T_p[:3, :3].T @ (rest[j, :3, 3] - T_p[:3, 3])
        else:
            local = rest[j, :3, 3]
        offset = Y_UP_TO_Z_UP.T @ local / scale
        if not has_dofs and not kids[j] and parent >= 0:
            out.append(_BvhOut(name, parent, offset, (), None, end_site=True))
            continue
        direct = _direct_channels(run, scale, parent < 0) if has_dofs else None
        if direct is not None:
            out.append(_BvhOut(name, parent, direct[0], direct[1], direct[2]))
            continue
        # Re-decomposed: the translation varies along the run (a prismatic DOF) or it is the root.
        moves = parent < 0 or any(fr.joint_type == "prismatic" for fr in run)
        pos = ("Xposition", "Yposition", "Zposition") if moves else ()
        rot = tuple(f"{c}rotation" for c in order)
        out.append(_BvhOut(name, parent, np.zeros(3) if parent < 0 else offset, pos + rot, None, moves))
    return out


def _bvh_values(
    plan: list[_BvhOut], skeleton: Skeleton, angles: torch.Tensor, scale: float, order: str
) -> dict[int, np.ndarray]:
    """Channel values (file units, degrees) of ``angles`` (T, D) in ``skeleton.dof_names`` order: joint
    index -> (T, channels of that joint), End Sites left out."""
    theta = angles.detach().to("cpu", torch.float64)
    T = len(theta)
    need = any(p.direct is None and not p.end_site for p in plan)
    transforms = skeleton.transforms(theta).numpy() if need and T else None
    th = theta.numpy()
    blocks = {}
    C = Y_UP_TO_Z_UP
    for j, p in enumerate(plan):
        if p.end_site:
            continue
        cols: list[np.ndarray] = []
        blocks[j] = cols
        if T == 0:
            cols.extend(np.zeros(0) for _ in p.channels)
            continue
        if p.direct is not None:
            cols.extend(factor * th[:, dof] for dof, factor in p.direct)
            continue
        if p.parent >= 0:
            Rp, tp = transforms[:, p.parent, :3, :3], transforms[:, p.parent, :3, 3]
        else:
            Rp, tp = np.eye(3), np.zeros(3)
        Tj = transforms[:, j]
        R_local = np.swapaxes(Rp, -1, -2) @ Tj[:, :3, :3]
        if p.positions:
            local = (np.swapaxes(Rp, -1, -2) @ (Tj[:, :3, 3] - tp)[..., None])[..., 0]
            cols.extend((local @ C / scale - p.offset).T)  # (C^T x) for each row
        # BVH frame = C^T (URDF frame) C; angles unwrapped over time so that players interpolate smoothly
        euler = _euler_from_matrix(C.T @ R_local @ C, order)
        cols.extend(np.degrees(np.unwrap(euler, axis=0)).T)
    return {j: np.stack(cols, 1) if cols else np.zeros((T, 0)) for j, cols in blocks.items()}


def save_bvh(
    path: str | os.PathLike,
    skeleton: Skeleton,
    motion: Motion,
    *,
    scale: float = 1.0,
    euler_order: str = BVH_EULER_ORDER,
) -> None:
    """Write ``motion`` on ``skeleton`` as a BVH file (Blender, MotionBuilder), atomically.

    The inverse of :func:`load_bvh` (module docstring: ``C`` y up -> z up, ``scale`` metres per file unit):
    one BVH joint per body joint (``skeleton.joint_names``, parents first), a DOF-less leaf is an
    ``End Site``; ``OFFSET`` is the rest-pose position in the parent's frame, ``C^T offset / scale``; the
    ``MOTION`` section has ``Frames: T`` and ``Frame Time: 1 / fps``; values in degrees and file units,
    in each joint's declared channel order.

    Two ways to fill a joint's channels:

    * **one channel per DOF** (exact, and :func:`load_bvh` gives back the same ``dof_names`` when they are
      spelled ``f"{joint}_{channel}"``, as a converted BVH or ``torchpf/assets/human.urdf`` are): when the
      URDF run of the joint has pure-translation origins, translations before rotations, DOF axes along
      coordinate axes (``+-x, +-y, +-z``, the sign goes into the value) with none repeated, and, for the
      root, 3 positions + 3 rotations (Blender's 6-channel ROOT);
    * otherwise **re-decomposed**: the joint's rotation relative to its parent (from
      :meth:`Skeleton.transforms`) as Euler angles in ``euler_order`` (BVH channel order, unwrapped over
      time), plus 3 position channels for the root and for a joint with a prismatic DOF. The joint
      positions and orientations are those of the skeleton (to rounding: ~1e-9 relative), the DOF values
      are not kept; near gimbal lock (middle angle +-90 deg) the angles are exact but jump.

    What a BVH cannot hold, and so is lost: capsule radii and joint limits (:func:`load_bvh` re-derives
    defaults), the names of DOF-less leaves (read back as ``f"{parent}_end"``) and frames that are not body
    joints. A skeleton with several root body joints cannot be written (BVH has one ROOT): ValueError.

    Args:
        path: output ``.bvh`` file.
        skeleton: the :class:`torchpf.Skeleton` of the motion.
        motion: :class:`Motion` with every DOF of ``skeleton`` (any column order; extra columns ignored).
        scale: metres per file unit (``CMU_SCALE`` writes CMU units; default 1: metres).
        euler_order: a permutation of ``"XYZ"``: channel order of re-decomposed joints.

    Raises:
        ValueError: several roots, a motion lacking DOFs of the skeleton, non-finite values, bad order.
    """
    from torchpf.io import write_text_atomic

    scale = _check_scale(scale)
    order = euler_order.upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"euler_order must be a permutation of XYZ, got {euler_order!r}")
    roots = [n for n, p in zip(skeleton.joint_names, skeleton.parents, strict=True) if p < 0]
    if len(roots) != 1:
        raise ValueError(f"a BVH file has one ROOT; this skeleton has {len(roots)} root joints {roots}")
    missing = [n for n in skeleton.dof_names if n not in motion.dof_names]
    if missing:
        raise ValueError(
            f"the motion lacks DOF(s) of the skeleton: {missing[:5]}{' ...' if len(missing) > 5 else ''}"
        )
    angles = motion.select(skeleton.dof_names).angles
    if not bool(torch.isfinite(angles).all()):
        raise ValueError("the motion has non-finite values")
    plan = _bvh_plan(skeleton, scale, order)
    blocks = _bvh_values(plan, skeleton, angles, scale, order)

    kids: dict[int, list[int]] = {}
    for j, p in enumerate(plan):
        kids.setdefault(p.parent, []).append(j)
    lines, visited = ["HIERARCHY"], []

    def num(v) -> str:
        return f"{float(v):.10g}"

    def off(v) -> str:  # the chain holds the URDF offsets in float32: 7 digits give them back unpadded
        return " ".join(f"{float(x):.7g}" for x in v)

    def write(j: int, depth: int) -> None:
        p, pad = plan[j], "  " * depth
        if p.end_site:
            lines.extend([f"{pad}End Site", f"{pad}{{", f"{pad}  OFFSET {off(p.offset)}", f"{pad}}}"])
            return
        lines.append(f"{pad}{'ROOT' if p.parent < 0 else 'JOINT'} {p.name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {off(p.offset)}")
        lines.append(f"{pad}  CHANNELS {len(p.channels)} {' '.join(p.channels)}".rstrip())
        visited.append(j)  # motion columns follow the hierarchy as written
        for c in kids.get(j, []):
            write(c, depth + 1)
        lines.append(f"{pad}}}")

    write(kids[-1][0], 0)
    values = np.concatenate([blocks[j] for j in visited], 1)
    lines += ["MOTION", f"Frames: {len(values)}", f"Frame Time: {1.0 / motion.fps:.10g}"]
    lines.extend(" ".join(num(v) for v in row) for row in values)
    write_text_atomic(path, "\n".join(lines) + "\n")
