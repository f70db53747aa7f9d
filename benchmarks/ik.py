"""IK projection throughput and accuracy: ``torchpf.ik.project`` on the full-body skeleton (Hauberg eq. 7).

    python -m benchmarks.ik [--sizes 1000 10000] [--noise 0.01] [--repeats 3] [--dtype float32]

Skeleton ``torchpf/assets/human.urdf`` (96 DOFs, 38 joints). Poses are real: frames of the CMU walk
``35_02.bvh`` from ``../shared/mocap/cmu`` (random in-limit poses when the clip is missing). Each problem is
the particle-filter situation: start ``θ_init`` = the previous frame, targets = FK of the next frame plus
isotropic Gaussian noise of ``--noise`` metres per coordinate. Reported per method and batch size: median
wall time of ``--repeats`` runs, mean/max iterations, fraction converged, and the median RMS joint residual
next to two references: the residual of the true pose (``≈ noise·√3``) and the least-squares noise floor
``noise·√(3 - p/J)``, ``p`` the rank of the Jacobian (the DOFs that joint positions determine), which a
least-squares fit attains on average. Three solvers, timed in the same run: ``tree`` (the default: tree
Jacobian, articulated-body solve in the fused CPU kernel), ``tree-eager`` (the same with the solve as tensor
operations, ``TORCHPF_FUSED=0``, what CUDA runs) and ``autograd`` (dense autograd Jacobian + Cholesky, on 200
poses of the smallest size only); ``speed-up`` is each one's time per pose against ``tree-eager``. Times are
wall clock, the minimum and the median of ``--repeats`` runs (a shared VM: the minimum is the machine's
speed, the median what a busy neighbour leaves). Single-threaded by default (``--threads``).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from torchpf import Skeleton, ik
from torchpf.assets import path
from torchpf.kinematics.jacobian import tree_jacobian

CLIP = Path(__file__).resolve().parents[2] / "shared" / "mocap" / "cmu" / "35_02.bvh"


def _poses(skel: Skeleton, n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, str]:
    """``(θ_{t-1}, θ_t)`` pairs ``(n, D)`` from the CMU clip, else random in-limit poses."""
    if CLIP.is_file():
        from training.mocap import load_bvh

        _, motion = load_bvh(CLIP, scale=0.056444)
        ang = skel.clamp(motion.select(skel.dof_names).angles[1:].float())  # frame 0 is a rest pose
        i = torch.randint(0, ang.shape[0] - 1, (n,), generator=g)
        return ang[i], ang[i + 1], f"CMU {CLIP.name} ({ang.shape[0]} frames)"
    lo, hi = skel.lower.float().clamp(-0.5, 0.5), skel.upper.float().clamp(-0.5, 0.5)
    prev = lo + (hi - lo) * torch.rand(n, len(skel.dof_names), generator=g)
    return prev, skel.clamp(prev + 0.02 * torch.randn(prev.shape, generator=g)), "random in-limit poses"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    ap.add_argument("--noise", type=float, default=0.01, help="target noise std per coordinate (m)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch's default)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    skel = Skeleton.from_urdf(path("human.urdf"))
    J, D = len(skel.joint_names), len(skel.dof_names)
    g = torch.Generator().manual_seed(0)

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, dtype {args.dtype}"
    )
    print(f"skeleton: human.urdf, D={D}, J={J}; noise {args.noise * 1000:.0f} mm per coordinate")
    rows = []
    for size in args.sizes:
        prev, truth, source = _poses(skel, size, g)
        prev, truth = prev.to(dtype), truth.to(dtype)
        targets = skel.fk(truth) + args.noise * torch.randn(size, J, 3, generator=g, dtype=dtype)
        truth_res = (skel.fk(truth) - targets).norm(dim=-1).square().mean(-1).sqrt().median().item()
        for label, method, fused in (
            ("tree", "tree", "1"),
            ("tree-eager", "tree", "0"),
            ("autograd", "autograd", "1"),
        ):
            if method == "autograd" and size != min(args.sizes):
                continue
            n = size if method == "tree" else min(size, 200)
            os.environ["TORCHPF_FUSED"] = fused
            ik.project(skel, targets[: min(n, 8)], prev[: min(n, 8)], method=method)  # compile / warm up
            times = []
            for _ in range(args.repeats if method == "tree" else 1):
                t0 = time.perf_counter()
                res = ik.project(skel, targets[:n], prev[:n], method=method, return_result=True)
                times.append(time.perf_counter() - t0)
            rows.append(
                (
                    label,
                    n,
                    min(times),
                    statistics.median(times),
                    res.iterations.float().mean().item(),
                    int(res.iterations.max()),
                    res.converged.float().mean().item(),
                    res.residual.median().item(),
                    truth_res,
                )
            )
        os.environ.pop("TORCHPF_FUSED")
    print(f"poses: {source}; start = previous frame, targets = FK(next frame) + noise")
    # DOFs that joint positions determine: the rank of the Jacobian at a typical pose
    rank = int(torch.linalg.matrix_rank(tree_jacobian(skel, prev[0].double()).reshape(3 * J, D)))
    floor = args.noise * (3 - rank / J) ** 0.5
    print(f"least-squares noise floor: noise * sqrt(3 - rank/J) = {floor * 1000:.2f} mm (rank {rank})")
    eager = {n: t / n for label, n, t, *_ in rows if label == "tree-eager"}
    head = (
        f"{'method':>10} {'poses':>6} {'min s':>7} {'median s':>8} {'ms/1k':>7} {'speed-up':>8} {'iters':>6}"
    )
    print(head + f" {'max':>4} {'conv':>6} {'median res mm':>14} {'truth res mm':>13}")
    for label, n, t, tmed, it, itmax, conv, res, tres in rows:
        base = eager.get(n, eager[min(eager)])
        print(
            f"{label:>10} {n:>6} {t:>7.3f} {tmed:>8.3f} {1000 * t / n * 1000:>7.1f} {base / (t / n):>7.2f}x"
            f" {it:>6.2f} {itmax:>4} {conv:>6.3f} {res * 1000:>14.2f} {tres * 1000:>13.2f}"
        )


if __name__ == "__main__":
    main()
