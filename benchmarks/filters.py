"""Throughput of the particle filters: time per frame for a 30-D state and 1e3 / 1e4 / 1e5 particles.

Every filter gets the same budget of ``N`` likelihood evaluations per frame (Fontmarty §3.3.2): SIR and QRS
with ``N`` particles, the APF with 3 layers of ``N/3`` (Fontmarty's schedule), the partitioned filters with 2
stages of ``N/2`` (6 "torso" DOFs, then 24 "limb" DOFs). The MCMC filter runs ``N`` particles plus one HMC
move of 3 leapfrog steps, i.e. 4 extra likelihood *gradient* evaluations per particle. The likelihood is a
cheap synthetic Gaussian around the observed pose, so the figures measure the engine (sampling, weighting,
resampling, Sobol noise, autograd), not an image likelihood.

    python -m benchmarks.filters                    # CPU, all sizes
    python -m benchmarks.filters --device cuda --sizes 1000 100000
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import torch

from torchpf.filters import (
    AnnealedParticleFilter,
    MCMCParticleFilter,
    ParticleFilter,
    PartitionedParticleFilter,
)
from torchpf.proposals import GaussianRandomWalk

DIM = 30
TORSO = list(range(6))
LIMBS = list(range(6, DIM))


def gaussian_loglik(x: torch.Tensor, z: torch.Tensor, dims=slice(None)) -> torch.Tensor:
    """``log N(z; x, 0.1^2 I)`` + const over the DOFs ``dims``: ``(..., N, D), (..., D) -> (..., N)``."""
    r = (x[..., dims] - z.unsqueeze(-2)[..., dims]) / 0.1
    return -0.5 * (r * r).sum(-1)


def make_filters(dynamics) -> dict[str, tuple[object, int]]:
    """Name -> (filter, number of layers / stages that share the budget N)."""
    partial = [lambda x, z: gaussian_loglik(x, z, TORSO), lambda x, z: gaussian_loglik(x, z, LIMBS)]
    common = {"progress": False}
    return {
        "SIR": (ParticleFilter(dynamics, gaussian_loglik, **common), 1),
        "APF (3 layers)": (AnnealedParticleFilter(dynamics, gaussian_loglik, **common), 3),
        "PARTITIONED (2)": (PartitionedParticleFilter(dynamics, partial, [TORSO, LIMBS], **common), 2),
        "QRS": (ParticleFilter(dynamics, gaussian_loglik, sampling="qrs", **common), 1),
        "PARTITIONED QRS": (
            PartitionedParticleFilter(dynamics, partial, [TORSO, LIMBS], sampling="qrs", **common),
            2,
        ),
        "MCMC (1 HMC x 3)": (
            MCMCParticleFilter(dynamics, gaussian_loglik, n_moves=1, n_leapfrog=3, step_size=0.02, **common),
            1,
        ),
    }


def time_per_step(pf, n: int, device: str, dtype: torch.dtype, frames: int) -> float:
    g = torch.Generator(device=device).manual_seed(0)
    truth = torch.zeros(1, DIM, device=device, dtype=dtype)
    state = pf.init(torch.zeros(1, n, DIM, device=device, dtype=dtype))
    with torch.no_grad():
        for _ in range(2):  # warm-up (allocator, Sobol engine, autograd)
            truth = truth + 0.05 * torch.randn(truth.shape, generator=g, device=device, dtype=dtype)
            state = pf.step(state, truth, g)
        if device == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(frames):
            truth = truth + 0.05 * torch.randn(truth.shape, generator=g, device=device, dtype=dtype)
            state = pf.step(state, truth, g)
        if device == "cuda":
            torch.cuda.synchronize()
    return (time.perf_counter() - start) / frames


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 10_000, 100_000], help="budgets N")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    dynamics = GaussianRandomWalk(torch.full((DIM,), 0.05)).to(args.device)

    print(f"machine: {cpu_name()}, {os.cpu_count()} cores visible, torch {torch.__version__}")
    print(f"torch threads {torch.get_num_threads()}, device {args.device}, {args.dtype}, state dim {DIM}")
    if args.device.startswith("cuda"):
        print(f"GPU: {torch.cuda.get_device_name()}")
    header = f"{'filter':<20}" + "".join(f"{f'N={n:,}':>14}" for n in args.sizes)
    print(header + "\n" + "-" * len(header) + "   (ms per frame, N likelihood evaluations per frame)")
    for name, (pf, per) in make_filters(dynamics).items():
        cells = []
        for n in args.sizes:
            frames = max(3, min(30, 300_000 // n))
            cells.append(f"{1e3 * time_per_step(pf, n // per, args.device, dtype, frames):>14.2f}")
        print(f"{name:<20}" + "".join(cells), flush=True)


if __name__ == "__main__":
    main()
