"""FK, likelihood and tracking-step timings on a device next to the CPU, measured in one run (issue 15).

    python -m benchmarks.device --device cuda                 # N in {500, 10000}, float32
    python -m benchmarks.device --device cpu --n 500          # a CPU-only smoke run

Set-up: ``human.urdf`` (96 DOFs, 27 capsules), 3 cameras at 160x120 around a synthetic pose, a depth camera
giving a 1,000-point cloud, particles spread around the true pose. Each row times the same call on the CPU
and on ``--device`` (the median of ``--repeat`` synchronised calls after a warm-up); a tracking step is one
frame of the default tracker's filter (the hybrid: APF layers, then gradient refinement of 4 poses;
silhouette x dual silhouette, random walk) at an equal likelihood budget of N evaluations; with
``--sequences B`` also one step of B independent sequences at once ((B, N, D) particles, (B, V, H, W)
masks; at the smallest N). The first line names the device (GPU model) for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.likelihoods import machine, setup
from torchpf.likelihoods import (
    DualSilhouetteLikelihood,
    Keypoints2DLikelihood,
    PointCloudLikelihood,
    ProductLikelihood,
    SilhouetteLikelihood,
)
from torchpf.observations import Frame, PointCloud, Silhouettes
from torchpf.tracker import Tracker, _to_device


def _timer(device: torch.device, repeat: int):
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def run(fn) -> float:
        with torch.no_grad():
            fn()  # warm-up: caches, allocator, kernels
            sync()
            times = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                fn()
                sync()
                times.append(time.perf_counter() - t0)
        return statistics.median(times)

    return run


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--n", type=int, nargs="+", default=[500, 10000], help="particle counts")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument(
        "--sequences", type=int, nargs="*", default=[16], help="also time B sequences in one tracking step"
    )
    args = p.parse_args(argv)
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("benchmarks.device: no CUDA device here")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"# device: {name}; host: {machine()}; {args.dtype}")
    skel, truth, rig, depth, frame = setup(1000)
    frame.points = PointCloud(frame.points.points[:1000])
    sil, dual = SilhouetteLikelihood(skel, rig), DualSilhouetteLikelihood(skel, rig)
    cases = {
        "silhouette (3 cams)": sil,
        "dual silhouette (3 cams)": dual,
        "silhouette x dual (3 cams)": ProductLikelihood([sil, dual]),
        "point cloud K=1000": PointCloudLikelihood(skel),
        "2D keypoints (3 cams)": Keypoints2DLikelihood(skel, rig),
    }
    frames = {dev: _to_device(frame, dev, dtype) for dev in (torch.device("cpu"), device)}  # moved once
    batched = {  # B sequences' masks (B, V, H, W): the same frame B times costs what B different ones do
        b: {
            dev: _to_device(
                Frame(silhouettes=Silhouettes(frame.silhouettes.masks.expand(b, -1, -1, -1))), dev, dtype
            )
            for dev in (torch.device("cpu"), device)
        }
        for b in args.sequences
    }
    g = torch.Generator().manual_seed(0)
    print()
    print(f"| call | N | CPU ms | {name} ms | speed-up |")
    print("|---|---:|---:|---:|---:|")
    for n in args.n:
        theta = truth + 0.05 * torch.randn(n, len(truth), generator=g, dtype=torch.float64)
        rows = {"forward kinematics": lambda dev, th: skel.to(dev).fk(th)}
        for label, lik in cases.items():
            rows[label] = lambda dev, th, lik=lik: lik.to(dev)(th, frames[dev])
        tracker = Tracker(skel, rig, n_particles=n, fps=15.0, progress=False)
        rows[f"tracking step ({tracker.filter_name})"] = lambda dev, th, tr=tracker: _step(
            tr, dev, dtype, th, frames[dev]
        )
        # independent sequences in one call, what a GPU is for (one call's ms), at the smallest N only
        for b in args.sequences if n == min(args.n) else ():
            rows[f"tracking step ({tracker.filter_name}), {b} sequences"] = lambda dev, th, tr=tracker, b=b: (
                _step(tr, dev, dtype, th, batched[b][dev], sequences=b)
            )
        for label, fn in rows.items():
            timings = []
            for dev in (torch.device("cpu"), device):
                th = theta.to(dev, dtype)
                timings.append(_timer(dev, args.repeat)(lambda fn=fn, dev=dev, th=th: fn(dev, th)))
            cpu, other = (1000 * t for t in timings)
            print(f"| {label} | {n:,} | {cpu:.1f} | {other:.1f} | {cpu / other:.1f}x |", flush=True)
    skel.to("cpu")


def _step(tracker: Tracker, device, dtype, theta, frame, sequences: int | None = None):
    """One frame of the tracker's filter (on ``device``) from particles around the pose; with
    ``sequences`` B, one call for B independent sequences ((B, N, D) particles, ``frame``'s masks (B, V, H,
    W))."""
    tracker.to(device).to(dtype)
    filt = tracker.filter
    x0 = theta[: filt.n_particles]
    if len(x0) < filt.n_particles:
        x0 = x0.repeat(-(-filt.n_particles // len(x0)), 1)[: filt.n_particles]
    if sequences is not None:
        x0 = x0.expand(sequences, -1, -1)
    generator = torch.Generator(device=device).manual_seed(0)
    return filt.step(filt.init(x0), frame, generator)


if __name__ == "__main__":
    main()
