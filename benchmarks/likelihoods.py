"""Throughput of the observation likelihoods: poses per second at N particles (forward kinematics included).

Set-up: ``human.urdf`` (93 DOFs, 27 capsules), 3 cameras at 160x120 around a synthetic pose, a depth camera
giving the point cloud (subsampled to K points), particles spread around the true pose.

    python -m benchmarks.likelihoods                 # N in {100, 1000, 10000}
    python -m benchmarks.likelihoods --n 1000 --repeat 5 --threads 1 --clock cpu

Goals on the 2-core CPU: point cloud >= 10,000 poses/s at K=1,000; three-camera silhouette >= 5,000 poses/s.
Rows marked "tensor version" run a computation that has a fused CPU kernel without it (``TORCHPF_FUSED=0``).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from unittest import mock

import cv2
import numpy as np
import torch

from torchpf import assets
from torchpf.camera import camera_ring, look_at
from torchpf.likelihoods import (
    ChamferLikelihood,
    DualSilhouetteLikelihood,
    Keypoints2DLikelihood,
    OverlapLikelihood,
    PointCloudLikelihood,
    ProductLikelihood,
    SilhouetteLikelihood,
    SkinBlobLikelihood,
)
from torchpf.observations import DistanceMaps, PointCloud
from torchpf.skeleton import Skeleton
from torchpf.synth import SynthOptions, synthesize


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return (
        f"{cpu}; {os.cpu_count()} logical cores; torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads; OpenCV {cv2.__version__}; Python {platform.python_version()}"
    )


#: a row's environment for the tensor version of a computation that has a fused CPU kernel
TENSOR = {"TORCHPF_FUSED": "0"}


def setup(n_points: int):
    skel = Skeleton.from_urdf(assets.path("human.urdf"))
    names = skel.dof_names
    truth = torch.zeros(len(names), dtype=torch.float64)
    for k, v in {"Hips_Yposition": 1.0, "LeftArm_Yrotation": 0.6, "RightForeArm_Zrotation": -0.5}.items():
        truth[names.index(k)] = v
    rig = camera_ring(3, radius=4.0, height=1.5, target=(0, 0, 0.8), width=160, height_px=120)
    depth = look_at((0.6, -3.0, 1.4), (0, 0, 0.8), width=320, height=240, name="depth")
    seq = synthesize(
        skel, truth[None], rig, depth_camera=depth, options=SynthOptions(n_points=n_points), seed=0
    )
    frame = seq.frame(0)
    frame.skin = DistanceMaps.from_features([cv2.Canny(m, 50, 150) for m in seq.masks[0]])
    frame.edges = frame.skin
    return skel, truth, rig, depth, frame


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--n", type=int, nargs="+", default=[100, 1000, 10000], help="particle counts")
    p.add_argument("--repeat", type=int, default=3, help="timed calls per entry (the median is reported)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument(
        "--clock",
        choices=["wall", "cpu"],
        default="wall",
        help="wall time, or process CPU time (with --threads 1: robust on a machine shared with other jobs)",
    )
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print(machine())
    skel, truth, rig, depth, frame = setup(2000)
    cloud = frame.points.points
    print(
        f"cameras: 3 x 160x120; cloud: {len(cloud)} points; capsules: {len(skel.bones)}; DOFs: {len(truth)}"
    )
    sil = SilhouetteLikelihood(skel, rig)
    dual = DualSilhouetteLikelihood(skel, rig)
    dual512 = DualSilhouetteLikelihood(skel, rig, n_samples=512)
    cases = {
        "point cloud K=1000": (PointCloudLikelihood(skel), PointCloud(cloud[:1000])),
        "point cloud K=1000, compile=True": (
            PointCloudLikelihood(skel, compile=True),
            PointCloud(cloud[:1000]),
        ),
        "point cloud K=2000": (PointCloudLikelihood(skel), PointCloud(cloud)),
        "point cloud half-capsules K=1000": (
            PointCloudLikelihood(skel, view_point=depth),
            PointCloud(cloud[:1000]),
        ),
        "silhouette (3 cams)": (sil, frame),
        "silhouette, tensor version": (sil, frame, TENSOR),
        "silhouette union-weighted (3 cams)": (SilhouetteLikelihood(skel, rig, union=True), frame),
        "dual silhouette N_s=128 (3 cams)": (dual, frame),
        "dual N_s=128, tensor version": (dual, frame, TENSOR),
        "dual silhouette N_s=512 (3 cams)": (dual512, frame),
        "dual N_s=512, tensor version": (dual512, frame, TENSOR),
        "silhouette x dual (3 cams)": (ProductLikelihood([sil, dual]), frame),
        "silhouette x dual, tensor version": (ProductLikelihood([sil, dual]), frame, TENSOR),
        "silhouette x dual N_s=512 (3 cams)": (ProductLikelihood([sil, dual512]), frame),
        "overlap ratio (3 cams)": (OverlapLikelihood(skel, rig), frame),
        "2D keypoints (3 cams)": (Keypoints2DLikelihood(skel, rig), frame),
        "skin blobs (3 cams)": (SkinBlobLikelihood(skel, rig), frame),
        "Chamfer edges (3 cams)": (ChamferLikelihood(skel, rig), frame),
    }
    g = torch.Generator().manual_seed(0)
    header = f"{'likelihood':38s}" + "".join(f"{f'N={n}':>14s}" for n in args.n)
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    print(f"{header}   (poses/s, float32, {args.clock} clock, median of {args.repeat})")
    print("-" * len(header))
    for name, (lik, obs, *env) in cases.items():
        row = f"{name:38s}"
        for n in args.n:
            theta = (truth + 0.05 * torch.randn(n, len(truth), generator=g, dtype=torch.float64)).float()
            with torch.no_grad(), mock.patch.dict(os.environ, env[0] if env else {}):
                lik(theta, obs)  # warm-up (caches, allocator)
                times = []
                for _ in range(args.repeat):
                    t0 = clock()
                    lik(theta, obs)
                    times.append(clock() - t0)
            row += f"{n / float(np.median(times)):14,.0f}"
        print(row, flush=True)
    with torch.no_grad():
        theta = (truth + 0.05 * torch.randn(10000, len(truth), generator=g, dtype=torch.float64)).float()
        t0 = clock()
        for _ in range(args.repeat):
            skel.capsules(theta)
        fk = (clock() - t0) / args.repeat
    print(f"(forward kinematics alone, included above: {10000 / fk:,.0f} poses/s at N=10000)")


if __name__ == "__main__":
    main()
