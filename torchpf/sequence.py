"""The sequence directory read by ``python -m torchpf track`` (DESIGN.md "File formats"), and its in-memory
form :class:`SequenceData`.

Layout::

    SEQ/cameras.yaml                  cameras (torchpf.camera format), depth_camera when points exist
    SEQ/masks/<camera>/<frame:06d>.png   silhouettes, 0/255 (a missing file is a missing frame)
    SEQ/points/<frame:06d>.npy        (K, 3) float32 world points (m)
    SEQ/truth.csv                     header ``time,<dof names...>``, one row per frame
    SEQ/keypoints.npz                 (extension) uv (T, V, J, 2) NaN = missing, joints, cameras
    SEQ/video/<camera>.mp4            optional: the frames the masks were segmented from (frame t = mask t)

Sequences are made by :func:`torchpf.synth.synthesize` (synthetic) or by background subtraction of videos
(:func:`torchpf.video.segment_videos`, ``python -m torchpf masks``).

Example::

    from torchpf.sequence import read_sequence, write_sequence
    seq = read_sequence("data/seq")
    frame = seq.frame(0)             # torchpf.observations.Frame for the likelihoods
    write_sequence("out/seq", seq)
"""

from __future__ import annotations

import io
import math
import operator
import os
import re
import struct
import tokenize
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from torchpf.camera import Camera, CameraRig, load_cameras, save_cameras, single_camera_advice
from torchpf.io import read_mocap_csv, read_npz, write_atomic, write_mocap_csv
from torchpf.observations import Frame, Keypoints2D, PointCloud, Silhouettes, binary_mask

__all__ = [
    "LazyFrames",
    "SequenceData",
    "SequenceError",
    "format_frames",
    "load_truth_csv",
    "read_sequence",
    "save_truth_csv",
    "write_mask",
    "write_sequence",
]


# ---------------------------------------------------------------------- truth.csv
def save_truth_csv(path, angles, dof_names, times=None) -> None:
    """Write angles (T, D) as mocap CSV (DESIGN.md; :func:`torchpf.io.write_mocap_csv`), atomically."""
    write_mocap_csv(path, dof_names, angles, times=times)


def load_truth_csv(path) -> tuple[torch.Tensor, list[str], np.ndarray | None]:
    """Read a mocap CSV (:func:`torchpf.io.read_mocap_csv`).

    Returns:
        angles (T, D) float64 tensor, dof names, times (T,) or None when there is no ``time`` column.
    """
    names, times, values = read_mocap_csv(path)
    return torch.from_numpy(np.ascontiguousarray(values)), names, times


@dataclass(eq=False)
class SequenceData:
    """A multi-camera sequence (synthetic in memory, or read from disk by :func:`read_sequence`).

    Attributes:
        cameras: :class:`~torchpf.camera.CameraRig` of the mask cameras (``V``), in mask order.
        masks: T rows of V (H, W) masks (uint8 0/255; 0/1, bool and 16-bit are read alike by
            :func:`~torchpf.observations.binary_mask`), None for a missing mask. A list, or the
            :class:`LazyFrames` of :func:`read_sequence` that reads a row when it is indexed.
        points: T arrays (K, 3) float32 world points or None per frame (list or :class:`LazyFrames`), or
            None (no depth data).
        depth_camera: the depth sensor (None without points).
        keypoints: (T, V, J, 2) float pixels in the mask grid, NaN = missing, or None;
            ``keypoint_joints`` their names.
        truth: (T, D) angles or None; ``dof_names``; ``times`` (T,) seconds or None.
        mask_size: (width, height) of the masks, the pixel grid of the keypoints too (masks may be smaller
            than the camera images: 160x120 masks of 640x480 cameras), or None (the cameras' own).
    """

    cameras: CameraRig
    masks: Sequence = field(default_factory=list)
    points: Sequence | None = None
    depth_camera: Camera | None = None
    keypoints: np.ndarray | None = None
    keypoint_joints: list[str] | None = None
    truth: torch.Tensor | None = None
    dof_names: list[str] | None = None
    times: np.ndarray | None = None
    mask_size: tuple[int, int] | None = None

    def __len__(self) -> int:
        for x in (self.masks, self.points, self.truth, self.keypoints):
            if x is not None and len(x):
                return len(x)
        return 0

    def has_observations(self, fields=None) -> bool:
        """Whether any frame has a mask, a point file or a keypoint (without, there is nothing to track).
        ``fields``: only these :class:`~torchpf.observations.Frame` fields count (``"silhouettes"``,
        ``"points"``, ``"keypoints"``: the ones a likelihood reads); default all."""

        def any_in(frames) -> bool:
            if frames is None:
                return False
            if isinstance(frames, LazyFrames):
                return frames.n_files > 0
            return any(
                x is not None for row in frames for x in (row if isinstance(row, list | tuple) else [row])
            )

        def wanted(name: str) -> bool:
            return fields is None or name in fields

        kp = self.keypoints is not None and bool(np.isfinite(np.asarray(self.keypoints)).any())
        return (
            (wanted("silhouettes") and any_in(self.masks))
            or (wanted("points") and any_in(self.points))
            or (wanted("keypoints") and kp)
        )

    def truth_in(self, dof_names) -> torch.Tensor | None:
        """The ground truth (T, D) with its columns in ``dof_names`` order (a skeleton's; truth.csv may
        list them in any order), or None; a ValueError when the columns are not the same set of DOFs."""
        if self.truth is None or self.dof_names is None or list(self.dof_names) == list(dof_names):
            return self.truth
        have, want = list(self.dof_names), list(dof_names)
        if sorted(have) != sorted(want):
            extra, missing = sorted(set(have) - set(want)), sorted(set(want) - set(have))
            raise ValueError(
                f"truth.csv columns do not match the skeleton: unknown {extra}, missing {missing}"
            )
        return self.truth[:, [have.index(n) for n in want]]

    def frame(self, t: int) -> Frame:
        """The observations of frame ``t`` as a :class:`~torchpf.observations.Frame` (read from disk for a
        sequence read by :func:`read_sequence`)."""
        sil = None
        if self.masks is not None and t < len(self.masks):
            row = self.masks[t]
            present = [binary_mask(m) if m is not None else None for m in row]
            shape = next((m.shape for m in present if m is not None), None)
            if shape is not None:
                if any(m is not None and m.shape != shape for m in present):
                    raise ValueError(f"frame {t}: the cameras' masks differ in size")
                stack = np.stack([m if m is not None else np.zeros(shape, bool) for m in present])
                valid = torch.tensor([m is not None for m in present])
                sil = Silhouettes(torch.from_numpy(stack).float(), valid)
        pts = None
        if self.points is not None and t < len(self.points):
            p = self.points[t]
            if p is not None:
                pts = PointCloud(torch.from_numpy(np.asarray(p, dtype=np.float32)))
        kp = None
        if self.keypoints is not None and t < len(self.keypoints):
            uv = torch.from_numpy(np.asarray(self.keypoints[t], dtype=np.float32))
            kp = Keypoints2D(uv, image_size=self.mask_size)
        return Frame(silhouettes=sil, points=pts, keypoints=kp)


# ---------------------------------------------------------------------- directory I/O
def write_sequence(path, seq: SequenceData) -> None:
    """Write ``seq`` as a sequence directory (module docstring); every file is written atomically. Masks are
    stored 0/255 (:func:`write_mask`); camera names must be safe identifiers
    (:func:`~torchpf.camera.check_camera_name`)."""
    root = os.fspath(path)
    cams = CameraRig(seq.cameras.cameras)
    depth_name = None
    if seq.points is not None and seq.depth_camera is not None:
        depth_name = seq.depth_camera.name
        if depth_name not in cams:
            cams = CameraRig(list(cams.values()) + [seq.depth_camera])
    save_cameras(os.path.join(root, "cameras.yaml"), cams, depth_camera=depth_name)
    names = list(seq.cameras.keys())
    for t, row in enumerate(seq.masks):
        for name, m in zip(names, row, strict=True):
            if m is not None:
                write_mask(root, name, t, m)
    if seq.points is not None:
        for t, pts in enumerate(seq.points):
            if pts is None:
                continue
            b = io.BytesIO()
            np.save(b, np.asarray(pts, dtype=np.float32))
            write_atomic(os.path.join(root, "points", f"{t:06d}.npy"), b.getvalue())
    if seq.truth is not None:
        save_truth_csv(os.path.join(root, "truth.csv"), seq.truth, seq.dof_names, seq.times)
    if seq.keypoints is not None:
        b = io.BytesIO()
        np.savez(
            b,
            uv=np.asarray(seq.keypoints, dtype=np.float32),
            joints=np.asarray(seq.keypoint_joints or []),
            cameras=np.asarray(names),
        )
        write_atomic(os.path.join(root, "keypoints.npz"), b.getvalue())


def write_mask(path, camera: str, t: int, mask) -> None:
    """Write one silhouette (H, W) (bool, 0/1, 0/255 or 16-bit: :func:`~torchpf.observations.binary_mask`)
    as ``masks/<camera>/<t:06d>.png`` (0/255) of the sequence directory ``path``, atomically: what
    :func:`write_sequence` does per mask, for writers that stream frames (:mod:`torchpf.video`)."""
    import cv2

    ok, buf = cv2.imencode(".png", np.where(binary_mask(mask), 255, 0).astype(np.uint8))
    if not ok:
        raise OSError(f"cannot encode mask {camera}/{t:06d}.png")
    write_atomic(os.path.join(os.fspath(path), "masks", camera, f"{t:06d}.png"), buf.tobytes())


class SequenceError(ValueError):
    """A sequence directory that cannot be read as one; the message starts with the file or folder at
    fault."""


class LazyFrames(Sequence):
    """Per-frame data read from disk when asked for: ``frames[t]`` reads frame ``t`` and keeps nothing, a
    slice reads a list, iteration reads one frame at a time. What :func:`read_sequence` puts in
    ``SequenceData.masks`` and ``.points``, so that tracking holds one frame in memory, not the sequence.

    ``n_files`` counts the files behind it (0: no observations of this kind)."""

    def __init__(self, n: int, load, n_files: int):
        self._n, self._load, self.n_files = int(n), load, int(n_files)

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, t):
        if isinstance(t, slice):
            return [self._load(i) for i in range(*t.indices(self._n))]
        t = operator.index(t)
        if t < 0:
            t += self._n
        if not 0 <= t < self._n:
            raise IndexError(f"frame {t} out of range (0..{self._n - 1})")
        return self._load(t)

    def __repr__(self) -> str:
        return f"LazyFrames({self._n} frames, {self.n_files} files)"


_DIGITS = re.compile(r"[0-9]{1,12}")


def _frame_index(name: str, folder: str) -> int:
    stem = os.path.splitext(name)[0]
    if not _DIGITS.fullmatch(stem):  # ASCII digits only: str.isdigit() also takes '²' and Arabic-Indic digits
        raise SequenceError(f"{os.path.join(folder, name)}: unexpected file (frames are named <frame:06d>)")
    return int(stem)


def _index_folder(folder: str, ext: str) -> dict[int, str]:
    """frame index -> path of the ``*.ext`` files in ``folder``."""
    out: dict[int, str] = {}
    for fn in sorted(os.listdir(folder)):
        if fn.endswith(ext) and not fn.startswith("."):
            i = _frame_index(fn, folder)
            if i in out:
                raise SequenceError(f"{os.path.join(folder, fn)}: frame {i} also in {out[i]}")
            out[i] = os.path.join(folder, fn)
    return out


def _format_runs(runs: list[tuple[int, int]], limit: int = 6) -> str:
    """'3, 5-9, 12' for inclusive runs (the first ``limit``, then how many more)."""
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:limit])
    return text + (f" and {len(runs) - limit} more" if len(runs) > limit else "")


def format_frames(frames: list[int], limit: int = 6) -> str:
    """Sorted frame numbers as runs, '3, 5-9, 12 and 4 more' (messages and reports)."""
    return _format_runs(_runs(frames), limit)


def _runs(idx: list[int]) -> list[tuple[int, int]]:
    """Sorted ints -> inclusive runs of consecutive values."""
    runs: list[list[int]] = []
    for i in idx:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return [(a, b) for a, b in runs]


def _frame_count(root: str, sources: dict[str, dict[int, str]], listed: tuple[int, str] | None) -> int:
    """The number of frames. ``listed``: (count, file) from truth.csv or keypoints.npz, which list one row
    per frame; every file must then be inside it. Otherwise the frames are the files 0..T-1 and must be
    contiguous: a stray ``masks/cam0/99999999.png`` is an error, not a hundred million missing frames.
    Checked on the indices alone, before anything is allocated per frame."""
    if listed is not None:
        T, what = listed
        for folder, files in sources.items():
            late = [i for i in files if i >= T]
            if late:
                raise SequenceError(
                    f"{files[max(late)]}: frame {max(late)} is past the {T} frames that {what} lists "
                    f"({len(late)} file(s) in {folder} are: frames {format_frames(sorted(late))})"
                )
        return T
    present = sorted(set().union(*[files.keys() for files in sources.values()]))
    if not present:
        return 0
    # the gaps between the present indices, never the (possibly huge) range of missing ones
    gaps = [(a + 1, b - 1) for a, b in zip([-1, *present[:-1]], present, strict=True) if b > a + 1]
    if gaps:
        last = next(files[present[-1]] for files in sources.values() if present[-1] in files)
        raise SequenceError(
            f"{root}: frame numbers are not contiguous: no file for frame(s) {_format_runs(gaps)} (the last "
            f"file is {last}); number the frames 0..T-1, or add truth.csv with one row per frame to list them"
        )
    return present[-1] + 1


def _png_size(path: str) -> tuple[int, int]:
    """(width, height) from a PNG header, without decoding the image."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise SequenceError(f"{path}: not a PNG file")
    w, h = struct.unpack(">II", head[16:24])
    return w, h


def _check_mask_sizes(files: dict[str, dict[int, str]], rig: CameraRig) -> tuple[int, int] | None:
    """Every mask has one size (the V axis of Silhouettes), with its camera's aspect ratio: a mask smaller
    than the camera image is scored with the camera rescaled to it (``CameraRig.resized``), but a mask
    whose aspect differs (transposed, cropped) cannot be the camera's view and is refused, not rescaled."""
    size, first = None, None
    for name, frames in files.items():
        W, H = rig[name].width, rig[name].height
        for path in frames.values():
            wh = _png_size(path)
            if size is None:
                size, first = wh, path
            elif wh != size:
                raise SequenceError(
                    f"{path}: mask is {wh[0]}x{wh[1]} pixels but {first} is {size[0]}x{size[1]}; all masks "
                    f"of a sequence have one size"
                )
            if W > 0 and H > 0 and abs(wh[0] * H - wh[1] * W) > max(W, H):
                raise SequenceError(
                    f"{path}: mask is {wh[0]}x{wh[1]} pixels, camera {name!r} images are {W}x{H}: the aspect "
                    f"ratios differ (transposed or cropped mask?)"
                )
    return size


def _read_mask(path: str, size: tuple[int, int]) -> np.ndarray:
    """(H, W) uint8 0/255 from a mask PNG stored 0/1, 0/255, bool or 16-bit, grey or colour."""
    import cv2

    m = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if m is None:
        raise SequenceError(f"{path}: cannot read as an image")
    if m.shape[1::-1] != size:
        raise SequenceError(f"{path}: decoded size {m.shape[1]}x{m.shape[0]} differs from its header")
    return np.where(binary_mask(m), np.uint8(255), np.uint8(0))


# What numpy's .npy header parser raises on a damaged header (it tokenizes the header's Python literal).
_NPY_ERRORS = (ValueError, OSError, EOFError, SyntaxError, tokenize.TokenError)


def _read_npy_header(f, path: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype from the header of the ``.npy`` data open in ``f`` (left at the data)."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = fmt.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _, dtype = fmt.read_array_header_2_0(f)
        else:
            raise SequenceError(f"{path}: unsupported .npy version {version}")
    except SequenceError:
        raise
    except _NPY_ERRORS as e:
        raise SequenceError(f"{path}: not a readable .npy header ({type(e).__name__}: {e})") from None
    return shape, dtype


def _npy_header(path: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of a ``.npy`` file, checked against the file's size before anything is read."""
    with open(path, "rb") as f:
        shape, dtype = _read_npy_header(f, path)
        offset = f.tell()
    if dtype.hasobject or dtype.kind not in "fiu":
        raise SequenceError(f"{path}: expected numbers, the file holds {dtype}")
    if math.prod(shape) * dtype.itemsize > os.path.getsize(path) - offset:
        raise SequenceError(f"{path}: header says {shape} {dtype}, more data than the file holds")
    return shape, dtype


def _read_points(path: str) -> np.ndarray:
    """(K, 3) float32 finite world points from ``points/<frame>.npy``."""
    try:
        shape, _ = _npy_header(path)
        if len(shape) != 2 or shape[1] != 3:
            raise SequenceError(f"{path}: expected a (K, 3) array, got shape {shape}")
        arr = np.load(path, allow_pickle=False)
    except SequenceError:
        raise
    except _NPY_ERRORS as e:
        raise SequenceError(f"{path}: not a readable .npy file ({type(e).__name__}: {e})") from None
    arr = arr.astype(np.float32)
    if not np.isfinite(arr).all():
        raise SequenceError(f"{path}: holds non-finite points")
    return arr


def _read_keypoints(path: str, names: list[str]) -> tuple[np.ndarray, list[str]]:
    """uv (T, V, J, 2) float32 in the order of ``names`` (NaN = missing) and the joint names."""
    z = read_npz(path, "keypoints", SequenceError)  # sizes checked before allocating, nothing unpickled
    if "uv" not in z:
        raise SequenceError(f"{path}: no 'uv' array")
    uv = np.asarray(z["uv"])
    joints = [str(j) for j in z["joints"].reshape(-1)] if "joints" in z else []
    cams = [str(c) for c in z["cameras"].reshape(-1)] if "cameras" in z else None
    if uv.dtype.kind not in "fiu" or uv.ndim != 4 or uv.shape[-1] != 2:
        raise SequenceError(
            f"{path}: 'uv' must be a (T, V, J, 2) array of numbers, got {uv.shape} {uv.dtype}"
        )
    uv = uv.astype(np.float32)
    if np.isinf(uv).any():
        raise SequenceError(f"{path}: 'uv' holds infinite values (NaN marks a missing point)")
    if len(joints) != uv.shape[2]:
        raise SequenceError(f"{path}: {len(joints)} joint names for {uv.shape[2]} joints in 'uv'")
    if cams is None:
        cams = names
    if len(cams) != uv.shape[1] or sorted(cams) != sorted(names):
        raise SequenceError(f"{path}: keypoints of cameras {cams}, the masks' cameras are {names}")
    return uv[:, [cams.index(n) for n in names]], joints


def read_sequence(path) -> SequenceData:
    """Read a sequence directory (module docstring), lazily: ``masks`` and ``points`` are
    :class:`LazyFrames` that read a frame when it is asked for, so tracking holds one frame at a time.

    Checked here, before any frame is read (errors are :class:`SequenceError`, a ValueError naming the file):
    camera names and geometry (:func:`~torchpf.camera.load_cameras`); frame numbering: the frame count is
    the number of rows of ``truth.csv`` (or of ``keypoints.npz``) when there is one, and every file must be
    inside it, else the mask and point files must be numbered 0..T-1 without gaps; every mask has one size
    and its camera's aspect ratio (read from the PNG headers). A missing mask or point file of a listed
    frame reads as None. Masks read as uint8 0/255 whatever they were stored as (0/1, 0/255, bool, 16-bit).
    A ``video/<camera>.mp4`` without masks is not segmented here: use
    :func:`torchpf.sensors.silhouettes_from_video`.
    """
    root = os.fspath(path)
    cam_file = os.path.join(root, "cameras.yaml")
    if not os.path.isfile(cam_file):
        raise FileNotFoundError(f"{root}: not a sequence directory (no cameras.yaml)")
    rig = load_cameras(cam_file)
    depth = rig[rig.depth_camera] if rig.depth_camera else None
    mask_dir = os.path.join(root, "masks")
    if os.path.isdir(mask_dir):
        stray = sorted(n for n in os.listdir(mask_dir) if n not in rig and not n.startswith("."))
        if stray:
            advice = single_camera_advice(cam_file)
            raise SequenceError(
                f"{os.path.join(mask_dir, stray[0])}: no camera {stray[0]!r} in {cam_file}"
                + (f"; {advice}" if advice else "")
            )
    names = [n for n in rig if os.path.isdir(os.path.join(mask_dir, n))]
    if not names:
        names = [n for n in rig if n != rig.depth_camera]
    files = {
        n: _index_folder(os.path.join(mask_dir, n), ".png")
        for n in names
        if os.path.isdir(os.path.join(mask_dir, n))
    }
    pdir = os.path.join(root, "points")
    pts_files = _index_folder(pdir, ".npy") if os.path.isdir(pdir) else {}
    truth = dof = times = None
    tpath = os.path.join(root, "truth.csv")
    if os.path.isfile(tpath):
        truth, dof, times = load_truth_csv(tpath)
    kps = kj = None
    kpath = os.path.join(root, "keypoints.npz")
    if os.path.isfile(kpath):
        kps, kj = _read_keypoints(kpath, names)
    listed = None
    if truth is not None:
        listed = (truth.shape[0], tpath)
        if kps is not None and len(kps) != truth.shape[0]:
            raise SequenceError(f"{kpath}: {len(kps)} frames, {tpath} has {truth.shape[0]}")
    elif kps is not None:
        listed = (len(kps), kpath)
    sources = {os.path.join(mask_dir, n): f for n, f in files.items()}
    if pts_files:
        sources[pdir] = pts_files
    T = _frame_count(root, sources, listed)
    size = _check_mask_sizes(files, rig)

    def mask_row(t: int) -> list:
        return [None if n not in files or t not in files[n] else _read_mask(files[n][t], size) for n in names]

    def point_frame(t: int):
        return None if t not in pts_files else _read_points(pts_files[t])

    n_masks = sum(len(f) for f in files.values())
    return SequenceData(
        cameras=CameraRig([rig[n] for n in names]),
        masks=LazyFrames(T, mask_row, n_masks),
        points=LazyFrames(T, point_frame, len(pts_files)) if pts_files else None,
        depth_camera=depth,
        keypoints=kps,
        keypoint_joints=kj,
        truth=truth,
        dof_names=dof,
        times=times,
        mask_size=size,
    )
