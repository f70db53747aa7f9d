"""Seeded mutations of the sequence-side loaders and the property they must keep (issue 16).

Loaders: a sequence directory (:func:`torchpf.sequence.read_sequence`, every frame read), ``cameras.yaml``
and OpenCV FileStorage files (:func:`torchpf.camera.load_cameras`), ``keypoints.npz`` (read with its
sequence). Property: a ValueError (CameraFileError, SequenceError, MocapFormatError...) or OSError whose
message names the file or folder, or a correct result; never another exception type, never a non-finite
value, never more memory than the input justifies (frame count within the files and rows given, traced
peak within a multiple of the input's size).

``mutate_*(rng, ...)`` make one mutated input from ``random.Random(seed)``; ``check_*`` return None when the
property holds, else a one-line description. The tests draw seeds with hypothesis; run this file to count
failures over many seeds (also against an older checkout, it imports nothing from the tests)::

    PYTHONPATH=. python tests/torchpf/_fuzz.py --n 500
"""

from __future__ import annotations

import io
import os
import random
import shutil
import tracemalloc

import numpy as np

W, H, N_FRAMES = 16, 12, 4
NUMBERS = [
    "0",
    "-1",
    "-0.0",
    "1e400",
    "-1e400",
    ".inf",
    ".nan",
    "nan",
    "1e300",
    "99999999999",
    "1_000",
    "٣",
    "abc",
    "",
    "[]",
    "{}",
    "null",
    "true",
    "~",
    "[1, 2]",
    "0x10",
    "1e-320",
    "3.5",
    "-640",
]
NAMES = ["../../outside", "/tmp/abs", "a b", "", ".hidden", "..", "cam0", "x" * 200, "c/d", "-x", "ü"]


# ------------------------------------------------------------------------------------------- text mutations
def mutate_text(rng: random.Random, text: str, n_ops: int | None = None) -> bytes:
    """1-3 edits: a number or a name replaced, a line deleted/duplicated/swapped/re-indented, a truncation,
    inserted or flipped bytes (maybe invalid UTF-8)."""
    import re

    data = text
    for _ in range(n_ops or rng.randint(1, 3)):
        lines = data.split("\n")
        op = rng.randrange(9)
        if op in (0, 1):  # a number
            spans = [m.span() for m in re.finditer(r"-?\d+(\.\d+)?(e[-+]?\d+)?", data)]
            if spans:
                a, b = rng.choice(spans)
                data = data[:a] + rng.choice(NUMBERS) + data[b:]
        elif op == 2:  # a name (camera keys are the words before ':' at the start of a line)
            spans = [m.span(1) for m in re.finditer(r"^\s*([A-Za-z_][\w]*)\s*:", data, re.M)]
            if spans:
                a, b = rng.choice(spans)
                data = data[:a] + repr(rng.choice(NAMES)) + data[b:]
        elif op == 3 and len(lines) > 1:
            del lines[rng.randrange(len(lines))]
            data = "\n".join(lines)
        elif op == 4:
            i = rng.randrange(len(lines))
            lines.insert(i, lines[i])
            data = "\n".join(lines)
        elif op == 5 and len(lines) > 1:
            i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
            data = "\n".join(lines)
        elif op == 6:
            i = rng.randrange(len(lines))
            lines[i] = " " * rng.randint(0, 5) + lines[i].lstrip()
            data = "\n".join(lines)
        elif op == 7:
            data = data[: rng.randrange(len(data) + 1)]
        else:
            raw = bytearray(data.encode("utf-8", "surrogateescape"))
            i = rng.randrange(len(raw) + 1)
            raw[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 4)))
            return bytes(raw)
    return data.encode("utf-8")


def mutate_bytes(rng: random.Random, data: bytes) -> bytes:
    raw = bytearray(data)
    op = rng.randrange(3)
    if op == 0:
        for _ in range(rng.randint(1, 8)):
            raw[rng.randrange(len(raw))] = rng.randrange(256)
    elif op == 1:
        del raw[rng.randrange(len(raw)) :]
    else:
        i = rng.randrange(len(raw))
        raw[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    return bytes(raw)


# ------------------------------------------------------------------------------------------- valid inputs
def cameras_yaml(n: int = 2) -> str:
    from torchpf.camera import camera_ring, save_cameras

    path = os.path.join(_scratch(), "cams.yaml")
    save_cameras(path, camera_ring(n, width=W, height_px=H))
    with open(path, encoding="utf-8") as f:
        return f.read()


def filestorage_yaml() -> str:
    import cv2

    path = os.path.join(_scratch(), "calib.yml")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[500.0, 0, 8], [0, 500, 6], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[0.1, -0.05, 0.0, 0.0, 0.01]]))
    fs.write("R", np.eye(3))
    fs.write("T", np.array([[0.0], [0.0], [3.0]]))
    fs.write("image_width", W)
    fs.write("image_height", H)
    fs.release()
    with open(path, encoding="utf-8") as f:
        return f.read()


_SCRATCH: list[str] = []


def _scratch() -> str:
    import tempfile

    if not _SCRATCH:
        import atexit

        _SCRATCH.append(tempfile.mkdtemp(prefix="torchpf-fuzz-"))
        atexit.register(shutil.rmtree, _SCRATCH[0], True)
    return _SCRATCH[0]


def _png(mask: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", mask)
    assert ok
    return buf.tobytes()


def _npy(arr) -> bytes:
    b = io.BytesIO()
    np.save(b, arr)
    return b.getvalue()


def _npz(**arrays) -> bytes:
    b = io.BytesIO()
    np.savez(b, **arrays)
    return b.getvalue()


def write_base_sequence(root: str, keypoints: bool = True) -> None:
    """2 cameras x 4 frames of 16x12 masks, points, truth.csv and keypoints.npz."""
    os.makedirs(root, exist_ok=True)
    with open(os.path.join(root, "cameras.yaml"), "w", encoding="utf-8") as f:
        f.write(cameras_yaml(2))
    m = np.zeros((H, W), np.uint8)
    m[3:8, 4:9] = 255
    for c in ("cam0", "cam1"):
        os.makedirs(os.path.join(root, "masks", c))
        for t in range(N_FRAMES):
            with open(os.path.join(root, "masks", c, f"{t:06d}.png"), "wb") as f:
                f.write(_png(m))
    os.makedirs(os.path.join(root, "points"))
    for t in range(N_FRAMES):
        with open(os.path.join(root, "points", f"{t:06d}.npy"), "wb") as f:
            f.write(_npy(np.full((5, 3), 0.5, np.float32)))
    with open(os.path.join(root, "truth.csv"), "w", encoding="utf-8") as f:
        f.write("time,a,b\n" + "".join(f"{t / 30!r},0.0,{t * 0.1!r}\n" for t in range(N_FRAMES)))
    if keypoints:
        uv = np.full((N_FRAMES, 2, 3, 2), 4.0, np.float32)
        uv[1, 0, 1] = np.nan
        with open(os.path.join(root, "keypoints.npz"), "wb") as f:
            f.write(_npz(uv=uv, joints=np.array(["a", "b", "c"]), cameras=np.array(["cam0", "cam1"])))


def _files(root: str) -> list[str]:
    return sorted(os.path.join(d, f) for d, _, fs in os.walk(root) for f in fs)


def _weird_mask(rng: random.Random) -> np.ndarray:
    kind = rng.randrange(7)
    m = np.zeros((H, W), bool)
    m[2:9, 3:10] = True
    if kind == 0:
        return m.astype(np.uint8)  # 0/1
    if kind == 1:
        return (m * 65535).astype(np.uint16)
    if kind == 2:
        return np.repeat((m * 255).astype(np.uint8)[..., None], 3, -1)  # colour
    if kind == 3:
        return (m * 255).astype(np.uint8).T.copy()  # transposed
    if kind == 4:
        return np.zeros((rng.randint(1, 40), rng.randint(1, 40)), np.uint8)
    if kind == 5:
        return np.zeros((H, W), np.uint8)  # empty
    return (m * 255).astype(np.uint8)[: H // 2, : W // 2].copy()  # same aspect, half size


_BLOCK = np.zeros((H, W), np.uint8)
_BLOCK[3:8, 4:9] = 255


def _put(path: str, data: bytes) -> None:
    """Write ``data``, creating the folder (an earlier mutation may have removed it)."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(data)


def mutate_sequence(rng: random.Random, root: str) -> None:
    """Write the base sequence to ``root`` and apply 1-3 directory-level mutations."""
    write_base_sequence(root)
    for _ in range(rng.randint(1, 3)):
        files = _files(root)
        op = rng.randrange(12)
        cam = rng.choice(["cam0", "cam1"])
        if op == 0:  # a stray frame file
            idx = rng.choice([4, 5, 7, 100, 1000000, 99999999, 10**12 - 1])
            _put(os.path.join(root, "masks", cam, f"{idx}.png"), _png(_BLOCK))
        elif op == 1 and files:  # a file removed
            os.remove(rng.choice(files))
        elif op == 2:  # a mask stored otherwise
            _put(
                os.path.join(root, "masks", cam, f"{rng.randrange(N_FRAMES):06d}.png"), _png(_weird_mask(rng))
            )
        elif op == 3:  # a corrupted file
            victims = [f for f in files if f.endswith((".png", ".npy", ".npz", ".csv", ".yaml"))]
            if victims:
                v = rng.choice(victims)
                with open(v, "rb") as f:
                    data = f.read()
                with open(v, "wb") as f:
                    f.write(mutate_bytes(rng, data))
        elif op in (4, 5):  # cameras.yaml or truth.csv edited
            name = "cameras.yaml" if op == 4 else "truth.csv"
            p = os.path.join(root, name)
            if os.path.exists(p):
                with open(p, encoding="utf-8", errors="surrogateescape") as f:
                    text = f.read()
                with open(p, "wb") as f:
                    f.write(mutate_text(rng, text))
        elif op == 6:  # stray names
            name = rng.choice(["cam7", "notes.txt", "0001.png", "1e3.png", "²³.png", ".DS_Store", "-1.png"])
            target = (
                os.path.join(root, "masks", name)
                if name == "cam7"
                else os.path.join(root, "masks", cam, name)
            )
            if name == "cam7":
                os.makedirs(target, exist_ok=True)
            else:
                _put(target, b"")
        elif op == 7:  # points with odd content
            arr = rng.choice(
                [
                    np.full((3, 3), np.nan, np.float32),
                    np.full((3, 3), np.inf),
                    np.zeros((3, 2)),
                    np.zeros(3),
                    np.array(["a", "b", "c"]),
                    np.zeros((0, 3), np.float32),
                    np.zeros((2, 3), np.complex64),
                ]
            )
            _put(os.path.join(root, "points", f"{rng.randrange(N_FRAMES + 2):06d}.npy"), _npy(arr))
        elif op == 8:  # a .npy header promising more than the file holds
            b = io.BytesIO()
            np.lib.format.write_array_header_1_0(
                b, {"descr": "<f4", "fortran_order": False, "shape": (10**10, 3)}
            )
            _put(
                os.path.join(root, "points", "000000.npy"),
                b.getvalue() + np.zeros((5, 3), np.float32).tobytes(),
            )
        elif op == 9:
            mutate_keypoints_file(rng, os.path.join(root, "keypoints.npz"))
        elif op == 10:  # a whole folder gone
            shutil.rmtree(
                os.path.join(root, rng.choice(["masks", "points", "masks/cam1"])), ignore_errors=True
            )
        else:  # a camera renamed in cameras.yaml
            p = os.path.join(root, "cameras.yaml")
            with open(p, encoding="utf-8", errors="surrogateescape") as f:
                text = f.read()
            with open(p, "w", encoding="utf-8", errors="surrogateescape") as f:
                f.write(text.replace(f"{cam}:", f"{rng.choice(NAMES)!r}:", 1))


def mutate_keypoints_file(rng: random.Random, path: str) -> None:
    """Replace ``path`` by a keypoints.npz with odd arrays, or flip its bytes."""
    good = np.full((N_FRAMES, 2, 3, 2), 4.0, np.float32)
    op = rng.randrange(8)
    if op == 0 and os.path.exists(path):
        with open(path, "rb") as f:
            data = f.read()
        blob = mutate_bytes(rng, data)
    else:
        arrays = {"uv": good, "joints": np.array(["a", "b", "c"]), "cameras": np.array(["cam0", "cam1"])}
        if op == 1:
            arrays["uv"] = rng.choice(
                [good[..., :1], good[0], good.astype(object), good.astype(str), good[:, :1]]
            )
        elif op == 2:
            arrays["uv"] = np.where(good > 0, rng.choice([np.inf, -np.inf, np.nan, 1e30]), good).astype(
                np.float32
            )
        elif op == 3:
            del arrays[rng.choice(list(arrays))]
        elif op == 4:
            arrays["cameras"] = np.array(
                rng.choice([["cam1", "cam0"], ["cam0"], ["x", "y"], ["cam0", "cam0"]])
            )
        elif op == 5:
            arrays["joints"] = np.array(rng.choice([["a"], [], ["a", "b", "c", "d"]]))
        elif op == 6:
            arrays["uv"] = np.zeros((rng.choice([0, 1, 3, 5, 1000]), 2, 3, 2), np.float32)
        if op == 7:
            blob = _npz(**arrays).replace(
                b"(4, 2, 3, 2)", b"(9999,2,3,2)"
            )  # same length: only the shape lies
        else:
            blob = _npz(**{k: v for k, v in arrays.items() if v is not None})
    with open(path, "wb") as f:
        f.write(blob)


# ------------------------------------------------------------------------------------------- the property
def _size(paths) -> int:
    return sum(os.path.getsize(p) for p in paths if os.path.isfile(p))


def _classify(e: BaseException, names: list[str]) -> str | None:
    """None for a clear error (ValueError/OSError naming one of ``names``), else a description."""
    text = str(e)
    if isinstance(e, (ValueError, OSError)) and not isinstance(e, (UnicodeError, MemoryError)):
        if any(n and n in text for n in names):
            return None
        return f"{type(e).__name__} without the file name: {text.splitlines()[0][:160] if text else ''}"
    return f"{type(e).__name__}: {text.splitlines()[0][:160] if text else ''}"


def _finite(x) -> bool:
    arr = np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)
    return bool(np.isfinite(arr).all())


def _check_rig(rig) -> str | None:
    import torch

    for name in rig:
        cam = rig[name]
        if not (_finite(cam.K) and _finite(cam.R) and _finite(cam.t)) or (
            cam.dist is not None and not _finite(cam.dist)
        ):
            return f"camera {name!r}: non-finite parameters"
        if not (0 < cam.width <= 1 << 20 and 0 < cam.height <= 1 << 20):
            return f"camera {name!r}: size {cam.width}x{cam.height}"
        if "/" in name or name in (".", "..") or name.startswith("."):
            return f"unsafe camera name {name!r} accepted"
        uv = cam.project(cam.center.double() + 2.0 * cam.R[2].double())
        if not bool(torch.isfinite(uv).all()):
            return f"camera {name!r}: projection not finite"
    return None


def _with_limits(fn, input_bytes: int):
    """``(fn() or the exception it raised, problem)``, run under tracemalloc; ``problem`` says when the peak
    is above 64 MiB + 50 x the input (more memory than the input justifies), else None."""
    tracemalloc.start()
    try:
        try:
            out = fn()
        except Exception as e:  # noqa: BLE001 (classified by the caller)
            out = e
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    if peak > 64 * 2**20 + 50 * input_bytes:
        return out, f"memory: peak traced {peak / 2**20:.0f} MiB for {input_bytes} input bytes"
    return out, None


def check_cameras_file(path: str) -> str | None:
    from torchpf.camera import load_cameras

    out, memory = _with_limits(lambda: load_cameras(path), _size([path]))
    if memory is not None:
        return memory
    if isinstance(out, BaseException):
        return _classify(out, [path])
    return _check_rig(out)


def check_sequence(root: str) -> str | None:
    from torchpf.sequence import read_sequence

    files = _files(root)

    def run():
        seq = read_sequence(root)
        n = len(seq)
        rows = 0 if seq.truth is None else len(seq.truth)
        kp = 0 if seq.keypoints is None else len(seq.keypoints)
        if n > max(len(files), rows, kp):
            return f"{n} frames from {len(files)} files"
        if (problem := _check_rig(seq.cameras)) is not None:
            return problem
        if seq.keypoints is not None and np.isinf(np.asarray(seq.keypoints, dtype=np.float64)).any():
            return "keypoints hold infinite values"
        for t in range(n):
            fr = seq.frame(t)
            for part in (
                fr.silhouettes and fr.silhouettes.masks,
                fr.points and fr.points.points,
                fr.keypoints and fr.keypoints.uv,
            ):
                if part is not None and not _finite(part):
                    return f"frame {t}: non-finite observations"
            if fr.silhouettes is not None and fr.silhouettes.masks.shape[0] != len(seq.cameras):
                return f"frame {t}: {fr.silhouettes.masks.shape[0]} masks for {len(seq.cameras)} cameras"
        return None

    out, memory = _with_limits(run, _size(files))
    if memory is not None:
        return memory
    if isinstance(out, BaseException):
        return _classify(out, [root])
    return out


# ------------------------------------------------------------------------------------------- one example
def run_example(loader: str, seed: int, workdir: str) -> str | None:
    """Mutate with ``seed``, load, check: None when the property holds."""
    rng = random.Random(f"{loader}:{seed}")
    shutil.rmtree(workdir, ignore_errors=True)
    os.makedirs(workdir)
    if loader == "cameras_yaml":
        path = os.path.join(workdir, "cameras.yaml")
        with open(path, "wb") as f:
            f.write(mutate_text(rng, _BASE.setdefault("cams", cameras_yaml(2))))
        return check_cameras_file(path)
    if loader == "filestorage":
        path = os.path.join(workdir, "calib.yml")
        with open(path, "wb") as f:
            f.write(mutate_text(rng, _BASE.setdefault("fs", filestorage_yaml())))
        return check_cameras_file(path)
    root = os.path.join(workdir, "seq")
    if loader == "keypoints_npz":
        write_base_sequence(root)
        mutate_keypoints_file(rng, os.path.join(root, "keypoints.npz"))
    else:
        mutate_sequence(rng, root)
    return check_sequence(root)


_BASE: dict[str, str] = {}
LOADERS = ("sequence_dir", "cameras_yaml", "filestorage", "keypoints_npz")


SECONDS_PER_EXAMPLE = 30


class _TooSlow(BaseException):  # not an Exception: the property check must not classify it
    pass


def _child(loader: str, start: int, stop: int) -> None:
    """Print ``seed<TAB>problem`` (empty when the property holds) for each seed, flushed line by line."""
    import resource
    import signal
    import sys
    import tempfile

    # a loader that tries to allocate gigabytes fails with MemoryError here instead of taking the machine,
    # one that loops over a hundred million frames is stopped after SECONDS_PER_EXAMPLE
    resource.setrlimit(resource.RLIMIT_AS, (3 * 2**30, resource.getrlimit(resource.RLIMIT_AS)[1]))

    def too_slow(signum, frame):
        raise _TooSlow(f"time: no answer within {SECONDS_PER_EXAMPLE} s")

    signal.signal(signal.SIGALRM, too_slow)
    work = tempfile.mkdtemp(prefix="torchpf-fuzz-")
    for seed in range(start, stop):
        signal.alarm(SECONDS_PER_EXAMPLE)
        try:
            problem = run_example(loader, seed, os.path.join(work, "x"))
        except _TooSlow as e:
            problem = str(e)
        finally:
            signal.alarm(0)
        line = (problem or "").replace("\n", " ")
        sys.stdout.write(f"{seed}\t{line}\n")
        sys.stdout.flush()
    shutil.rmtree(work, ignore_errors=True)


def count(loader: str, n: int, timeout_s: float = 120.0) -> dict[int, str]:
    """Problems over seeds 0..n-1, each child process running seeds until one kills it (an abort in a C
    library, or ``timeout_s`` without an answer): that seed is counted as a crash and the next child goes
    on after it."""
    import subprocess
    import sys

    problems: dict[int, str] = {}
    seed = 0
    while seed < n:
        cmd = [sys.executable, os.path.abspath(__file__), "--child", loader, str(seed), str(n)]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            out, _ = proc.communicate(timeout=timeout_s * (n - seed))
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        done = [line.split("\t", 1) for line in out.splitlines() if "\t" in line]
        for s_, problem in done:
            if problem.strip():
                problems[int(s_)] = problem.strip()
        seed = int(done[-1][0]) + 1 if done else seed
        if proc.returncode != 0 and seed < n:
            problems[seed] = f"crash: process ended with status {proc.returncode} (abort/segfault/timeout)"
            seed += 1
    return problems


def main(argv=None) -> int:
    import argparse
    import collections
    import sys

    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        _child(argv[1], int(argv[2]), int(argv[3]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=500)
    ap.add_argument("loaders", nargs="*", default=list(LOADERS))
    args = ap.parse_args(argv)
    for loader in args.loaders:
        problems = count(loader, args.n)
        kinds = collections.Counter(p.split(":")[0] for p in problems.values())
        print(f"{loader}: {len(problems)} of {args.n} mutations break the property", flush=True)
        for kind, k in kinds.most_common():
            seed = min(s for s, p in problems.items() if p.split(":")[0] == kind)
            print(f"    {k:4d}  {problems[seed][:150]}  (seed {seed})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
