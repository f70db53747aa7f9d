"""Seeded mutation fuzzing of the file loaders (issue 16): the shared mutations, loaders and property.

Property, for every mutated file: **a clear error naming the file, or a correct result**. Never another
exception type, never a non-finite result, never more memory (numpy, traced) than the input justifies.

The tests (``test_fuzz_*.py``) draw mutation plans with hypothesis (``derandomize=True``; the number of
examples is ``FUZZ_EXAMPLES``, raised by the environment variable ``TORCHPF_FUZZ_EXAMPLES``). Counting the
failing mutations of a loader, e.g. before and after a fix::

    PYTHONPATH=. python -m tests.fuzzing bvh csv urdf action keypoints --n 500
"""

from __future__ import annotations

import io
import math
import os
import random
import re
import sys
import tempfile
import tracemalloc
import zipfile
from collections import Counter
from collections.abc import Callable

import numpy as np

#: Examples per fuzz test in the suite; ``TORCHPF_FUZZ_EXAMPLES=500`` for a full run.
FUZZ_EXAMPLES = int(os.environ.get("TORCHPF_FUZZ_EXAMPLES", "0") or 0) or 40

#: Traced (numpy / Python) bytes a load may peak at: a fixed allowance plus this many times the file size.
MEMORY_BASE, MEMORY_PER_BYTE = 64 * 2**20, 256

NUMBERS = [
    "nan", "inf", "-inf", "1e308", "1e-320", "0", "-0", "-1", "1e200", "-1e200", "1_000", "\u0661\u0662",
    "99999999999", "0x10", "1e", ".", "", "3.5", "1e6", "123456789012345678901234567890",
]  # fmt: skip
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
N_OPS = 8


def random_plan(rng: random.Random) -> list[tuple[int, int, int, int]]:
    """1-3 mutations: (operator, and three free integers the operator reduces modulo what it needs)."""
    return [
        (rng.randrange(N_OPS), rng.randrange(2**31), rng.randrange(2**31), rng.randrange(2**31))
        for _ in range(rng.randint(1, 3))
    ]


def plans():
    """The hypothesis strategy of mutation plans (same shape as :func:`random_plan`)."""
    from hypothesis import strategies as st

    word = st.integers(0, 2**31 - 1)
    return st.lists(st.tuples(st.integers(0, N_OPS - 1), word, word, word), min_size=1, max_size=3)


def mutate(data: bytes, plan, tokens: list[str]) -> bytes:
    """``data`` with the mutations of ``plan`` applied in order; ``tokens`` are format words to insert."""
    for op, a, b, _ in plan:
        if not data:
            data = tokens[a % len(tokens)].encode()
            continue
        n = len(data)
        if op == 0:  # replace a number by a nasty one
            found = list(_NUMBER.finditer(data))
            if found:
                m = found[a % len(found)]
                data = data[: m.start()] + NUMBERS[b % len(NUMBERS)].encode() + data[m.end() :]
        elif op in (1, 2, 3):  # delete, duplicate or swap lines
            lines = data.split(b"\n")
            i, j = a % len(lines), b % len(lines)
            if op == 1:
                del lines[i]
            elif op == 2:
                lines.insert(i, lines[j])
            else:
                lines[i], lines[j] = lines[j], lines[i]
            data = b"\n".join(lines)
        elif op == 4:  # one byte
            data = data[: a % n] + bytes([b % 256]) + data[a % n + 1 :]
        elif op == 5:  # truncate
            data = data[: a % n]
        elif op == 6:  # insert a format word
            data = data[: a % n] + tokens[b % len(tokens)].encode() + data[a % n :]
        else:  # delete a span
            data = data[: a % n] + data[a % n + 1 + b % 20 :]
    return data


def mutate_npz(data: bytes, plan) -> bytes:
    """An ``.npz`` mutated inside one member (re-zipped with valid CRCs, so the mutation reaches the array
    parser) or, for an odd first word, in the raw zip bytes."""
    if plan[0][1] % 5 == 0:
        return mutate(data, plan, NPY_TOKENS)
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        members = [(info, zf.read(info)) for info in zf.infolist()]
    k = plan[0][2] % len(members)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for i, (info, raw) in enumerate(members):
            if i == k:
                # most mutations in the .npy header, where the shape and dtype live
                head, body = raw[:128], raw[128:]
                raw = (
                    mutate(head, plan, NPY_TOKENS) + body if plan[0][3] % 3 else mutate(raw, plan, NPY_TOKENS)
                )
            zf.writestr(info.filename, raw)
    return out.getvalue()


BVH_TOKENS = ["JOINT X {", "End Site", "{", "}", "OFFSET", "CHANNELS 3", "Xrotation", "ROOT", "MOTION",
              "Frames:", "Frame Time:", " ", "\t", "\r", "\n"]  # fmt: skip
CSV_TOKENS = [",", "time", "\n", "\r", '"', "\ufeff", " ", "a", "Hips_Xposition"]
URDF_TOKENS = ['<link name="x"/>', "</joint>", 'xyz="', 'link="', 'type="fixed"', "<", ">", '"', "<robot>",
               '<joint name="j" type="revolute"><parent link="base"/><child link="x"/></joint>']  # fmt: skip
NPY_TOKENS = ["'shape': (", "'descr': '|O'", "'fortran_order': True", "<f8", "<i8", "|S3", "(1000000000,",
              "{", "}", "(", ")", "\n", "\x93NUMPY", '"version": 9', '"dof_names": 1']  # fmt: skip


# ------------------------------------------------------------------------------------------------ seeds
SEED_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 0 5 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0 4 0.5
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 2 0
      }
    }
  }
  JOINT LeftUpLeg
  {
    OFFSET 1.5 -1 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 -8 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0083333
0.5 17.2 -3.1 10 -5 2 1 2 3 -4 5 6 30 -10 5
0.6 17.3 -3.0 11 -5 2 1 2 3 -4 5 6 31 -10 5
0.7 17.4 -2.9 12 -5 2 1 2 3 -4 5 6 32 -10 5
"""

SEED_CSV = """time,Hips_Xposition,Hips_Zrotation,Knee_Xrotation
0.0,0.5,0.1,1.2
0.0333333333,0.51,0.11,1.1
0.0666666667,0.52,0.12,1.0
0.1,0.53,0.13,0.9
"""


def seed_urdf() -> str:
    """``tests/data/odd.urdf``: prismatic root, fixed joints mid-chain, odd axes, several geometries."""
    return open(os.path.join(os.path.dirname(__file__), "data", "odd.urdf"), encoding="utf-8").read()


def seed_action_model() -> bytes:
    """The small action model of the action-model tests (5 DOFs, D=2, K=4) as file bytes."""
    from .priors.test_action import tiny_model

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "seed.npz")
        tiny_model().save(path)
        with open(path, "rb") as f:
            return f.read()


# ------------------------------------------------------------------------------------------------ loaders
def _finite(*tensors) -> bool:
    import torch

    return all(bool(torch.isfinite(torch.as_tensor(t)).all()) for t in tensors)


def load_bvh(path: str) -> str | None:
    from training.mocap import CMU_SCALE, load_bvh

    skel, motion = load_bvh(path, scale=CMU_SCALE)
    if not (math.isfinite(motion.fps) and motion.fps > 0):
        return f"fps {motion.fps}"
    if not _finite(motion.angles, skel.fk(motion.angles)):
        return "non-finite angles or joint positions"
    return None


def load_csv(path: str) -> str | None:
    from training.mocap import load_csv

    motion = load_csv(path)
    if not (math.isfinite(motion.fps) and motion.fps > 0):
        return f"fps {motion.fps}"
    if not _finite(motion.angles) or not bool((motion.angles.abs() <= 1e6).all()):
        return "non-finite or absurd angles"
    return None


def load_urdf(path: str) -> str | None:
    import torch

    from torchpf import Skeleton

    skel = Skeleton.from_urdf(path)
    D = len(skel.dof_names)
    theta = skel.clamp(torch.randn(8, D, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))
    if skel.lower.isnan().any() or skel.upper.isnan().any() or bool((skel.lower > skel.upper).any()):
        return "NaN or crossed limits"
    if not _finite(skel.fk(torch.zeros(D)), skel.fk(theta), skel.radii) or bool((skel.radii <= 0).any()):
        return "non-finite FK or radii"
    return None


def load_action(path: str) -> str | None:
    import torch

    from priors.action import ActionModel

    model = ActionModel.load(path)
    arrays = [model.center, model.pca_mean, model.components, model.mean_performance, model.std, model.delta]
    if not _finite(*arrays, model.sigma_phi, model.alpha, model.fps):
        return "non-finite model arrays"
    accepted = model.accepts(torch.zeros(3, len(model.dof_names), dtype=torch.float64))
    if accepted.shape != (3,):
        return f"accepts() shape {tuple(accepted.shape)}"
    return None


def seed_keypoints() -> bytes:
    """A ``keypoints.npz`` of a sequence directory: uv (T=3, V=1, J=2, 2) with a missing point, joints."""
    uv = np.array(
        [[[[10.0, 20.0], [np.nan, np.nan]]], [[[11.0, 21.0], [30.0, 40.0]]], [[[12, 22], [31, 41]]]]
    )
    b = io.BytesIO()
    np.savez(b, uv=uv.astype(np.float32), joints=np.array(["Head", "Hips"]), cameras=np.array(["cam0"]))
    return b.getvalue()


def load_keypoints(path: str) -> str | None:
    from torchpf.camera import camera_ring, save_cameras
    from torchpf.sequence import read_sequence

    folder = os.path.dirname(path)
    if not os.path.exists(os.path.join(folder, "cameras.yaml")):
        save_cameras(os.path.join(folder, "cameras.yaml"), camera_ring(1, width=64, height_px=48))
    seq = read_sequence(folder)
    uv = seq.keypoints
    if uv is None or uv.ndim != 4 or uv.shape[-2:] != (len(seq.keypoint_joints), 2):
        return "keypoints missing or of the wrong shape"
    if np.isinf(uv).any():
        return "infinite keypoints"
    return None


#: name -> (seed bytes factory, file name ending, mutate(data, plan), loader(path) -> failure or None)
LOADERS: dict[str, tuple[Callable[[], bytes], str, Callable, Callable[[str], str | None]]] = {
    "bvh": (lambda: SEED_BVH.encode(), ".bvh", lambda d, p: mutate(d, p, BVH_TOKENS), load_bvh),
    "csv": (lambda: SEED_CSV.encode(), ".csv", lambda d, p: mutate(d, p, CSV_TOKENS), load_csv),
    "urdf": (lambda: seed_urdf().encode(), ".urdf", lambda d, p: mutate(d, p, URDF_TOKENS), load_urdf),
    "action": (seed_action_model, ".npz", mutate_npz, load_action),
    "keypoints": (seed_keypoints, "/keypoints.npz", mutate_npz, load_keypoints),
}


def outcome(loader: Callable[[str], str | None], path: str) -> str:
    """``"ok"``, ``"error"`` (a ValueError naming the file) or a description of the broken property."""
    import warnings

    size = os.path.getsize(path)
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            failure = loader(path)
    except ValueError as e:  # the loaders' error types (MocapFormatError, ...) are ValueErrors
        if os.path.basename(path) not in str(e):
            return f"ValueError without the file name: {' '.join(str(e).split())[:120]}"
        return "error"
    except Exception as e:  # any other type breaks the property (MemoryError, RecursionError, ...)
        return f"{type(e).__name__}: {' '.join(str(e).split())[:120]}"
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    if peak > MEMORY_BASE + MEMORY_PER_BYTE * size:
        return f"memory: peak {peak} bytes for a {size}-byte file"
    return failure or "ok"


def check(name: str, plan, folder: str) -> str:
    """Mutate the seed of loader ``name`` with ``plan``, write it into ``folder`` and load it."""
    seed, suffix, mutator, loader = LOADERS[name]
    data = mutator(_seed_bytes(name, seed), plan)
    path = os.path.join(folder, suffix.lstrip("/") if suffix.startswith("/") else f"mutant{suffix}")
    with open(path, "wb") as f:
        f.write(data)
    return outcome(loader, path)


_SEEDS: dict[str, bytes] = {}


def _seed_bytes(name: str, factory) -> bytes:
    if name not in _SEEDS:
        _SEEDS[name] = factory()
    return _SEEDS[name]


def fuzz_test(name: str):
    """The hypothesis test of loader ``name``: ``FUZZ_EXAMPLES`` derandomized mutation plans, each ending in
    ``"ok"`` or ``"error"`` (``test_bvh_mutations = fuzz_test("bvh")`` in the package's test folder)."""
    from hypothesis import HealthCheck, given, settings

    @settings(
        derandomize=True, max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck)
    )
    @given(plan=plans())
    def test(plan):
        with tempfile.TemporaryDirectory() as folder:
            assert check(name, plan, folder) in ("ok", "error")

    test.__name__ = f"test_{name}_mutations"
    return test


def count(name: str, n: int, seed: int = 0) -> Counter:
    """Outcomes of ``n`` seeded random mutations of loader ``name`` (``"ok"``, ``"error"``, failures)."""
    rng = random.Random(f"{name}-{seed}")
    tally: Counter = Counter()
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(n):
            result = check(name, random_plan(rng), folder)
            tally[result if result in ("ok", "error") else result.split(":")[0]] += 1
    return tally


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="count failing mutations per loader")
    ap.add_argument("loaders", nargs="*", default=list(LOADERS))
    ap.add_argument("--n", type=int, default=500)
    args = ap.parse_args()
    np.seterr(all="ignore")
    for name in args.loaders:
        tally = count(name, args.n)
        failing = sum(v for k, v in tally.items() if k not in ("ok", "error"))
        details = ", ".join(f"{k}: {v}" for k, v in sorted(tally.items(), key=lambda kv: -kv[1]))
        print(f"{name}: {failing}/{args.n} failing ({details})", flush=True)
    sys.exit(0)
