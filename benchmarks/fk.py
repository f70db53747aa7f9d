"""Forward-kinematics throughput: torchpf's fused kernel vs pytorch-kinematics, measured in one run.

    python -m benchmarks.fk [--sizes 1000 10000] [--repeats 15] [--device cpu]

Skeleton: ``torchpf/assets/human.urdf`` (the CMU joint tree: floating root + 30 ball joints, 96 DOFs,
38 body-joint positions, 104 pytorch-kinematics frames). Both sides get the same random in-limit poses;
timings interleave the two implementations and report the best of ``--repeats`` (the least disturbed run) so
that machine noise hits both alike.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import torch

from torchpf import Skeleton
from torchpf.assets import path


def _time(fn, sync) -> float:
    t0 = time.perf_counter()
    fn()
    sync()
    return time.perf_counter() - t0


def _passes(skel, chain, theta):
    """name -> (ours, theirs): zero-argument callables timing one FK pass on ``theta``."""
    th_grad = theta.clone().requires_grad_(True)
    return {
        "forward": (lambda: skel.fk(theta), lambda: chain.forward_kinematics_tensor(theta)),
        "forward+backward": (
            lambda: skel.fk(th_grad).sum().backward(),
            lambda: chain.forward_kinematics_tensor(th_grad)[..., :3, 3].sum().backward(),
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    skel = Skeleton.from_urdf(path("human.urdf")).to(device)
    chain = skel.chain.to(dtype=dtype, device=device)
    gen = torch.Generator().manual_seed(0)
    lo, hi = skel.lower.clamp(min=-1.0), skel.upper.clamp(max=1.0)

    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{os.cpu_count()} CPU cores"
    print(
        f"# FK throughput, {where}, torch {torch.__version__} ({torch.get_num_threads()} threads), "
        f"{platform.python_implementation()} {platform.python_version()}, {args.dtype}"
    )
    print(
        f"# skeleton: D={len(skel.dof_names)} DOFs, J={len(skel.joint_names)} joints, "
        f"{len(chain.get_frame_names(exclude_fixed=False))} pytorch-kinematics frames"
    )
    print()
    print("| poses | pass | torchpf poses/s | pytorch-kinematics poses/s | ratio | max abs diff (m) |")
    print("|---:|---|---:|---:|---:|---:|")
    for n in args.sizes:
        theta = lo + torch.rand(n, len(skel.dof_names), generator=gen, dtype=torch.float64) * (hi - lo)
        theta = theta.to(device=device, dtype=dtype)
        ref = chain.forward_kinematics_tensor(theta)[skel.pk_frame_indices.to(device), :, :3, 3].transpose(
            0, 1
        )
        diff = (skel.fk(theta) - ref).abs().max().item()

        passes = _passes(skel, chain, theta)
        for name, (ours, theirs) in passes.items():
            ours(), theirs()  # warm-up
            a, b = [], []
            for _ in range(args.repeats):
                a.append(_time(ours, sync))
                b.append(_time(theirs, sync))
            ta, tb = min(a), min(b)
            print(f"| {n:,} | {name} | {n / ta:,.0f} | {n / tb:,.0f} | {tb / ta:.1f}x | {diff:.1e} |")


if __name__ == "__main__":
    main()
