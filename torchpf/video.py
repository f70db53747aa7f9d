"""Real video in: synchronised per-camera videos (or image folders) -> silhouettes -> a sequence directory.

``python -m torchpf masks VIDEO... --cameras cameras.yaml --out SEQ`` runs :func:`segment_videos`: one source
per camera, read in lock step (frame ``t`` of every camera is one instant; the shortest source ends the
sequence), each frame segmented by the library's background subtraction
(:class:`torchpf.sensors.BackgroundSubtractor`: MOG2 or KNN per pixel, shadows dropped, then opening,
closing, small blobs dropped and holes filled, Brubaker et al. §3.2 / Fig. 3), written as the sequence
directory of DESIGN.md (``cameras.yaml``, ``masks/<camera>/<frame:06d>.png``, ``video/<camera>.mp4``).

The background model comes from one of:

* a **clean plate** per camera (an image of the empty scene): the model starts from it;
* the **first N frames** (``background_frames``): their per-pixel median (:func:`background_plate`) is the
  plate, so a person walking through those frames does not stay in it (a person who stands still in
  more than half of them does); those frames are segmented too;
* neither: the adaptive model learns from the video itself as it goes (the person must move).

With a plate the model is frozen by default (``learning_rate=0``): MOG2 learns a plate as one mixture
component, whose weight adaptation decays below the model's background ratio (0.9) within about 20 frames
at ``1 / history``, after which anything seen twice becomes background. Pass a small ``learning_rate`` for
slow lighting changes. The plate is fed once: the per-pixel variance stays at the model's initial value
(MOG2: 15 grey levels squared), which covers sensor and compression noise; repeated feeds would shrink it.

Sources (:class:`FrameReader`): a video file (anything OpenCV reads: mp4, avi, mov, ...) or a folder of
images (png, jpg, bmp, tif, sorted by name); a folder holding only videos stands for those videos. Sources
are matched to cameras by name (file stem or folder name = camera name in ``cameras.yaml``), else in order.

Example::

    from torchpf.video import segment_videos
    report = segment_videos(["cam0.mp4", "cam1.mp4", "cam2.mp4"], "cameras.yaml", "seq",
                            clean_plates=["cam0.png", "cam1.png", "cam2.png"])
    print(report.summary())             # frames, foreground share per camera
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from torchpf.camera import CameraRig, load_cameras, save_cameras
from torchpf.sensors import BackgroundSubtractor
from torchpf.sequence import write_mask

__all__ = [
    "FrameReader",
    "SegmentReport",
    "background_plate",
    "expand_sources",
    "match_cameras",
    "read_image",
    "segment_videos",
]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv")


def read_image(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) BGR uint8 image (grey images are expanded); OSError naming the file when unreadable."""
    import cv2

    img = cv2.imread(os.fspath(path), cv2.IMREAD_COLOR)
    if img is None:
        raise OSError(f"{os.fspath(path)}: cannot read as an image")
    return img


class FrameReader:
    """The BGR uint8 frames (H, W, 3) of one camera: a video file or a folder of images.

    Iterating opens the source afresh each time (the background pass and the segmentation pass read the
    same frames). ``name``: the file stem or folder name; ``len()``: the frame count (a video's container
    count, which some formats only estimate); ``fps``: a video's frame rate, None for images.
    """

    def __init__(self, source: str | os.PathLike):
        import cv2

        self.path = os.fspath(source)
        self.name = os.path.splitext(os.path.basename(os.path.normpath(self.path)))[0]
        self.fps: float | None = None
        if os.path.isdir(self.path):
            self.images = sorted(
                os.path.join(self.path, f)
                for f in os.listdir(self.path)
                if f.lower().endswith(IMAGE_EXTENSIONS)
            )
            if not self.images:
                raise OSError(f"{self.path}: no images ({', '.join(IMAGE_EXTENSIONS)}) in this folder")
            self._count = len(self.images)
        elif os.path.isfile(self.path):
            self.images = None
            cap = cv2.VideoCapture(self.path)
            if not cap.isOpened():
                raise OSError(f"{self.path}: OpenCV cannot open this video")
            self._count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            self.fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
            cap.release()
        else:
            raise FileNotFoundError(f"{self.path}: cannot open: no such video file or image folder")

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[np.ndarray]:
        import cv2

        if self.images is not None:
            for f in self.images:
                yield read_image(f)
            return
        cap = cv2.VideoCapture(self.path)
        try:
            while True:
                ok, frame = cap.read()
                if not ok:
                    return
                yield frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        finally:
            cap.release()

    def __repr__(self) -> str:
        kind = "images" if self.images is not None else "video"
        return f"FrameReader({self.path!r}, {kind}, {len(self)} frames)"


def expand_sources(paths: Sequence[str | os.PathLike]) -> list[str]:
    """The per-camera sources named by ``paths``: a video file or an image folder is one camera; a folder
    with videos and no images (e.g. a sequence's ``video/``) stands for its videos, sorted by name."""
    out = []
    for p in map(os.fspath, paths):
        if os.path.isdir(p):
            names = sorted(os.listdir(p))
            videos = [f for f in names if f.lower().endswith(VIDEO_EXTENSIONS)]
            if videos and not any(f.lower().endswith(IMAGE_EXTENSIONS) for f in names):
                out.extend(os.path.join(p, f) for f in videos)
                continue
        out.append(p)
    return out


def match_cameras(source_names: Sequence[str], rig: CameraRig) -> list[str]:
    """Camera name of each source: by name when every source is named after a camera of ``rig``, else in
    ``rig``'s order when there are as many cameras as sources; ValueError otherwise."""
    names = list(source_names)
    if all(n in rig for n in names) and len(set(names)) == len(names):
        return names
    usable = [n for n in rig if n != rig.depth_camera]
    if len(usable) == len(names):
        return usable
    raise ValueError(
        f"{len(names)} source(s) {names} for cameras {usable}: name each video or folder after its camera, "
        "or give one source per camera in cameras.yaml order"
    )


def background_plate(frames: Iterable[np.ndarray]) -> np.ndarray:
    """Per-pixel temporal median of ``frames`` (each (H, W, 3) or (H, W) uint8) -> a clean plate of the same
    shape: the background wherever the scene shows it in more than half of the frames."""
    stack = np.stack(list(frames))
    if len(stack) == 0:
        raise ValueError("background_plate: no frames")
    return np.median(stack, axis=0).round().astype(np.uint8)


@dataclass
class SegmentReport:
    """What :func:`segment_videos` did: ``n_frames`` written, ``cameras`` (names, source order), ``sources``
    (paths), ``foreground`` (camera -> mean foreground share of the masks), ``background`` ("plate",
    "first N frames" or "adaptive"), ``seconds``, ``path`` of the sequence directory."""

    path: str
    n_frames: int
    cameras: list[str]
    sources: list[str]
    foreground: dict[str, float] = field(default_factory=dict)
    background: str = "adaptive"
    seconds: float = 0.0

    def summary(self) -> str:
        share = ", ".join(f"{c} {100 * f:.1f}%" for c, f in self.foreground.items())
        return (
            f"segmented {self.n_frames} frames x {len(self.cameras)} cameras in {self.seconds:.1f} s "
            f"(background: {self.background}); foreground share: {share}; wrote {self.path}"
        )


def segment_videos(
    sources: Sequence[str | os.PathLike],
    cameras: str | os.PathLike | CameraRig,
    out: str | os.PathLike,
    *,
    background_frames: int = 0,
    clean_plates: Sequence[str | os.PathLike | np.ndarray] | None = None,
    start: int = 0,
    max_frames: int | None = None,
    learning_rate: float | None = None,
    size: tuple[int, int] | None = None,
    subtractor: Mapping | None = None,
    write_video: bool = True,
    fps: float | None = None,
    progress: bool = True,
) -> SegmentReport:
    """Segment synchronised per-camera videos into silhouettes and write a sequence directory.

    Args:
        sources: one video file or image folder per camera (:func:`expand_sources`, :func:`match_cameras`).
        cameras: ``cameras.yaml`` (or an OpenCV calibration file, :func:`torchpf.camera.load_cameras`) or a
            :class:`~torchpf.camera.CameraRig`; the used cameras are written to ``out/cameras.yaml``.
        out: the sequence directory to write (created; existing masks of the same frames are replaced).
        background_frames: learn the background from the per-pixel median of the first N frames.
        clean_plates: one empty-scene image (path or BGR array) per source; excludes ``background_frames``.
        start: first frame written as mask 0 (earlier frames, e.g. an empty lead-in, are only read).
        max_frames: at most this many frames written.
        learning_rate: per-frame adaptation of the model in [0, 1] (0 freezes it); default 0 after a plate
            (module docstring), automatic (-1, ``1 / min(frames seen, history)``) without one.
        size: ``(width, height)`` of the written masks (segmented at the video's size, then resampled by
            area: a pixel is foreground when at least half of it is), e.g. the tracker's working size.
        subtractor: keywords of :class:`~torchpf.sensors.BackgroundSubtractor` (method, history,
            threshold, detect_shadows, open_px, close_px, min_area, fill_holes).
        write_video: also write the frames from ``start`` on as ``out/video/<camera>.mp4`` (mask ``t`` is
            video frame ``t``) for ``python -m torchpf render``.
        fps: frame rate of the written videos (default: the first video's, else 30).
        progress: a tqdm bar over the frames.

    Returns:
        :class:`SegmentReport`.

    Raises:
        ValueError: bad options, sources that do not match the cameras, a plate whose size is not the
            frames'. OSError / FileNotFoundError: unreadable sources.
    """
    import cv2
    from tqdm.auto import tqdm

    if size is not None and (len(size) != 2 or min(size) < 1):
        raise ValueError(f"size must be (width, height) >= 1, got {size}")
    if background_frames < 0 or start < 0 or (max_frames is not None and max_frames < 0):
        raise ValueError("background_frames, start and max_frames must be >= 0")
    if background_frames and clean_plates is not None:
        raise ValueError("give either background_frames or clean_plates, not both")
    if learning_rate is not None and not (learning_rate == -1 or 0.0 <= learning_rate <= 1.0):
        raise ValueError(f"learning_rate must be in [0, 1] or -1 (automatic), got {learning_rate}")
    t0 = time.perf_counter()
    rig = cameras if isinstance(cameras, CameraRig) else load_cameras(cameras)
    readers = [FrameReader(s) for s in expand_sources(sources)]
    if not readers:
        raise ValueError("no video or image folder given")
    names = match_cameras([r.name for r in readers], rig)
    options = dict(subtractor or {})
    subs = [BackgroundSubtractor(**options) for _ in readers]

    background = "adaptive"
    plates: list[np.ndarray] | None = None
    if clean_plates is not None:
        if len(clean_plates) != len(readers):
            raise ValueError(f"{len(clean_plates)} clean plate(s) for {len(readers)} camera(s)")
        plates = [read_image(p) if not isinstance(p, np.ndarray) else p for p in clean_plates]
        background = "clean plate"
    elif background_frames:
        plates = []
        for r in readers:
            first = [f for _, f in zip(range(background_frames), r, strict=False)]
            plates.append(background_plate(first))
        background = f"median of the first {background_frames} frames"
    if plates is not None:
        for sub, plate in zip(subs, plates, strict=True):
            sub.learn([plate])
        if learning_rate is None:
            learning_rate = 0.0
    if learning_rate is None:
        learning_rate = -1.0

    root = os.fspath(out)
    used = CameraRig([rig[n] for n in names])
    save_cameras(os.path.join(root, "cameras.yaml"), used)
    total = min(len(r) for r in readers) - start
    if max_frames is not None:
        total = min(total, max_frames)
    fps = fps or next((r.fps for r in readers if r.fps), None) or 30.0
    writers: list = [None] * len(readers)
    fg = np.zeros(len(readers))
    n = 0
    bar = tqdm(total=max(total, 0), desc="masks", unit="frame", disable=not progress)
    try:
        for i, row in enumerate(zip(*readers, strict=False)):
            if max_frames is not None and n >= max_frames:
                break
            write = i >= start
            for v, (frame, sub) in enumerate(zip(row, subs, strict=True)):
                if plates is not None and frame.shape[:2] != plates[v].shape[:2]:
                    h, w = plates[v].shape[:2]
                    raise ValueError(
                        f"{readers[v].path}: frame {i} is {frame.shape[1]}x{frame.shape[0]}, the background "
                        f"plate {w}x{h}"
                    )
                mask = sub.apply(frame, learning_rate=learning_rate)
                if not write:
                    continue
                if size is not None and mask.shape[::-1] != tuple(size):
                    mask = np.where(
                        cv2.resize(mask, tuple(size), interpolation=cv2.INTER_AREA) >= 128, 255, 0
                    )
                write_mask(root, names[v], n, mask)
                fg[v] += float((mask > 0).mean())
                if write_video:
                    writers[v] = writers[v] or _video_writer(root, names[v], frame, fps)
                    writers[v].write(frame)
            if write:
                n += 1
                bar.update(1)
    finally:
        bar.close()
        for w in writers:
            if w is not None:
                w.release()
    if write_video:  # the writers wrote into temporary names: publish complete files only
        for name in names:
            tmp = os.path.join(root, "video", f".{name}.tmp.mp4")
            if os.path.exists(tmp):
                os.replace(tmp, os.path.join(root, "video", f"{name}.mp4"))
    return SegmentReport(
        path=root,
        n_frames=n,
        cameras=names,
        sources=[r.path for r in readers],
        foreground={c: float(f / max(n, 1)) for c, f in zip(names, fg, strict=True)},
        background=background,
        seconds=time.perf_counter() - t0,
    )


def _video_writer(root: str, name: str, frame: np.ndarray, fps: float):
    import cv2

    os.makedirs(os.path.join(root, "video"), exist_ok=True)
    path = os.path.join(root, "video", f".{name}.tmp.mp4")
    h, w = frame.shape[:2]
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not writer.isOpened():
        raise OSError(f"{path}: OpenCV cannot write an mp4 video here")
    return writer
