"""The sequence directory read by ``python -m torchpf track`` (DESIGN.md "File formats"), and its in-memory
form :class:`SequenceData`.

Layout::

    SEQ/cameras.yaml                  cameras (torchpf.camera format), depth_camera when points exist
    SEQ/masks/<camera>/<frame:06d>.png   silhouettes, 0/255 (a missing file is a missing frame)
    SEQ/points/<frame:06d>.npy        (K, 3) float32 world points (m)
    SEQ/truth.csv                     header ``time,<dof names...>``, one row per frame
    SEQ/keypoints.npz                 (extension) uv (T, V, J, 2) NaN = missing, joints, cameras

Sequences are made by :func:`torchpf.synth.synthesize` (synthetic) or by background subtraction of videos
(:func:`torchpf.sensors.silhouettes_from_video`).

Example::

    from torchpf.sequence import read_sequence, write_sequence
    seq = read_sequence("data/seq")
    frame = seq.frame(0)             # torchpf.observations.Frame for the likelihoods
    write_sequence("out/seq", seq)
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, field

import numpy as np
import torch

from torchpf.camera import Camera, CameraRig, load_cameras, save_cameras
from torchpf.io import read_mocap_csv, read_npz, write_atomic, write_mocap_csv
from torchpf.observations import Frame, Keypoints2D, PointCloud, Silhouettes

__all__ = [
    "SequenceData",
    "load_truth_csv",
    "read_sequence",
    "save_truth_csv",
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
    """A multi-camera sequence in memory (synthetic or read from disk).

    Fields:
        cameras: :class:`~torchpf.camera.CameraRig` of the mask cameras (``V``), in mask order.
        masks: T lists of V uint8 (H, W) 0/255 arrays, None for a missing frame.
        points: T arrays (K, 3) float32 world points, or None (no depth data).
        depth_camera: the depth sensor (None without points).
        keypoints: (T, V, J, 2) float pixels in the mask grid, NaN = missing, or None;
            ``keypoint_joints`` their names.
        truth: (T, D) angles or None; ``dof_names``; ``times`` (T,) seconds or None.
    """

    cameras: CameraRig
    masks: list = field(default_factory=list)
    points: list | None = None
    depth_camera: Camera | None = None
    keypoints: np.ndarray | None = None
    keypoint_joints: list[str] | None = None
    truth: torch.Tensor | None = None
    dof_names: list[str] | None = None
    times: np.ndarray | None = None

    def __len__(self) -> int:
        for x in (self.masks, self.points, self.truth, self.keypoints):
            if x is not None and len(x):
                return len(x)
        return 0

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
        """The observations of frame ``t`` as a :class:`~torchpf.observations.Frame`."""
        sil = None
        if self.masks and t < len(self.masks):
            row = self.masks[t]
            shape = next((m.shape for m in row if m is not None), None)
            if shape is not None:
                stack = np.stack([m if m is not None else np.zeros(shape, np.uint8) for m in row])
                valid = torch.tensor([m is not None for m in row])
                sil = Silhouettes(torch.from_numpy(stack > 127).float(), valid)
        pts = None
        if self.points is not None and t < len(self.points) and self.points[t] is not None:
            pts = PointCloud(torch.from_numpy(np.asarray(self.points[t], dtype=np.float32)))
        kp = None
        if self.keypoints is not None and t < len(self.keypoints):
            kp = Keypoints2D(torch.from_numpy(np.asarray(self.keypoints[t], dtype=np.float32)))
        return Frame(silhouettes=sil, points=pts, keypoints=kp)


# ---------------------------------------------------------------------- directory I/O
def write_sequence(path, seq: SequenceData) -> None:
    """Write ``seq`` as a sequence directory (module docstring); every file is written atomically."""
    import cv2

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
            if m is None:
                continue
            ok, buf = cv2.imencode(".png", np.where(np.asarray(m) > 127, 255, 0).astype(np.uint8))
            if not ok:
                raise OSError(f"cannot encode mask {name}/{t:06d}.png")
            write_atomic(os.path.join(root, "masks", name, f"{t:06d}.png"), buf.tobytes())
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


def _frame_index(name: str, path: str) -> int:
    stem = os.path.splitext(name)[0]
    if not stem.isdigit():
        raise ValueError(f"{path}: unexpected file {name!r} (frames are named <frame:06d>)")
    return int(stem)


def read_sequence(path) -> SequenceData:
    """Read a sequence directory (module docstring). The frame count is the largest frame index found in
    ``masks/``, ``points/`` or ``truth.csv``; a missing mask or point file reads as None. A
    ``video/<camera>.mp4`` without masks is not segmented here: use
    :func:`torchpf.sensors.silhouettes_from_video`.
    """
    import cv2

    root = os.fspath(path)
    cam_file = os.path.join(root, "cameras.yaml")
    if not os.path.isfile(cam_file):
        raise FileNotFoundError(f"{root}: not a sequence directory (no cameras.yaml)")
    rig = load_cameras(cam_file)
    depth = rig[rig.depth_camera] if rig.depth_camera else None
    mask_dir = os.path.join(root, "masks")
    names = [n for n in rig if os.path.isdir(os.path.join(mask_dir, n))]
    if not names:
        names = [n for n in rig if n != rig.depth_camera]
    files: dict[str, dict[int, str]] = {}
    T = 0
    for n in names:
        d = os.path.join(mask_dir, n)
        files[n] = {}
        if os.path.isdir(d):
            for fn in os.listdir(d):
                if fn.endswith(".png"):
                    files[n][_frame_index(fn, d)] = os.path.join(d, fn)
            T = max([T] + [i + 1 for i in files[n]])
    pts_files: dict[int, str] = {}
    pdir = os.path.join(root, "points")
    if os.path.isdir(pdir):
        for fn in os.listdir(pdir):
            if fn.endswith(".npy"):
                pts_files[_frame_index(fn, pdir)] = os.path.join(pdir, fn)
        T = max([T] + [i + 1 for i in pts_files])
    truth = dof = times = None
    tpath = os.path.join(root, "truth.csv")
    if os.path.isfile(tpath):
        truth, dof, times = load_truth_csv(tpath)
        T = max(T, truth.shape[0])
    masks = []
    for t in range(T):
        row = []
        for n in names:
            f = files[n].get(t)
            if f is None:
                row.append(None)
                continue
            m = cv2.imread(f, cv2.IMREAD_GRAYSCALE)
            if m is None:
                raise OSError(f"{f}: cannot read as an image")
            row.append(m)
        masks.append(row)
    points = None
    if pts_files:
        points = []
        for t in range(T):
            f = pts_files.get(t)
            if f is None:
                points.append(None)
                continue
            arr = np.load(f)
            if arr.ndim != 2 or arr.shape[1] != 3:
                raise ValueError(f"{f}: expected a (K, 3) array, got shape {arr.shape}")
            points.append(arr.astype(np.float32))
    kps = kj = None
    kpath = os.path.join(root, "keypoints.npz")
    if os.path.isfile(kpath):
        z = read_npz(kpath, "keypoints")
        kps, kj = z.get("uv"), z.get("joints")
        if kps is None or kj is None or kps.dtype.kind not in "fiu" or kps.shape[2:] != (kj.size, 2):
            raise ValueError(f"{kpath}: expected a float array uv (T, V, J, 2) and joints (J,)")
        if np.isinf(kps).any():
            raise ValueError(f"{kpath}: uv holds infinite values (NaN marks a missing point)")
        kj = [str(j) for j in kj.reshape(-1)]
    mask_cams = CameraRig([rig[n] for n in names])
    return SequenceData(
        cameras=mask_cams,
        masks=masks,
        points=points,
        depth_camera=depth,
        keypoints=kps,
        keypoint_joints=kj,
        truth=truth,
        dof_names=dof,
        times=times,
    )
