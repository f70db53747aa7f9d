"""Cost and effect of the gradient refinement (:mod:`torchpf.refine`).

1. Cost: the refinement cue's forward pass (no grad) against forward + backward (a gradient step) for ``K``
   poses, the ratio that :attr:`torchpf.refine.Refiner.cost_per_step` charges per step in the equal-budget
   accounting, and the wall time of one :class:`~torchpf.refine.Refiner` call.
2. Effect (``--clips``): on foreign renders (:mod:`benchmarks.foreign`, real CMU clips, a body that is not
   torchpf's capsules), the body calibrated on the first 8 frames (:func:`torchpf.calibrate.fit_body`), poses
   = truth + noise (0.15 rad per revolute DOF, 4 cm per prismatic one), MPJPE before and after refinement.

    python -m benchmarks.refine                               # cost table
    python -m benchmarks.refine --clips 07_01 35_24 --steps 20 40 --clock cpu
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from benchmarks.likelihoods import machine
from torchpf import assets
from torchpf.camera import camera_ring
from torchpf.likelihoods import SilhouetteDistanceLikelihood
from torchpf.observations import Silhouettes
from torchpf.refine import Refiner
from torchpf.skeleton import Skeleton

CMU_DIR = (Path(__file__).resolve().parents[1] / ".." / "shared" / "mocap" / "cmu").resolve()


def _clock(kind: str):
    return time.process_time if kind == "cpu" else time.perf_counter


def _median_time(fn, repeat: int, clock) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return statistics.median(times)


def cost_table(ks, steps: int, repeat: int, clock) -> str:
    from tests.torchpf._masks import render_masks  # the independent OpenCV renderer of the test suite

    skel = Skeleton.from_urdf(assets.path("human.urdf"))
    rig = camera_ring(3, radius=3.0, height=1.5, target=(0, 0, 0.85), width=160, height_px=120)
    truth = torch.zeros(len(skel.dof_names), dtype=torch.float64)
    truth[skel.dof_names.index("Hips_Yposition")] = 0.95
    obs = Silhouettes(render_masks(skel.fk(truth), skel.tree.bones, skel.radii, rig.cameras))
    cue = SilhouetteDistanceLikelihood(skel, rig)
    refiner = Refiner(skel, rig, steps=steps)
    g = torch.Generator().manual_seed(0)
    lines = [
        "| K poses | forward (ms) | forward + backward (ms) | ratio | Refiner call, "
        f"{steps} steps (ms) | ms per pose-step |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for k in ks:
        x = (truth + 0.1 * torch.randn(k, len(truth), generator=g, dtype=torch.float64)).float()

        def forward(x=x):
            with torch.no_grad():
                cue(x, obs)

        def backward(x=x):
            xr = x.clone().requires_grad_(True)
            cue(xr, obs).sum().backward()

        f = _median_time(forward, repeat, clock)
        b = _median_time(backward, repeat, clock)
        r = _median_time(lambda x=x: refiner(x, obs), max(1, repeat // 2), clock)
        per_step = r * 1e3 / (k * steps)
        lines.append(
            f"| {k} | {f * 1e3:.2f} | {b * 1e3:.2f} | {b / f:.2f} | {r * 1e3:.0f} | {per_step:.3f} |"
        )
    return "\n".join(lines)


def effect_table(clips, steps_list, n_poses: int, frames: int, work: Path, clock) -> str:
    from benchmarks.foreign import body_plan, build_sequence
    from torchpf.calibrate import fit_body
    from torchpf.sequence import read_sequence

    lines = [
        "| clip | steps | MPJPE before (mm) | after (mm) | ms per frame |",
        "|---|---:|---:|---:|---:|",
    ]
    for clip in clips:
        out = work / f"{clip}-clean"
        if not (out / "truth.csv").exists():
            build_sequence(CMU_DIR / f"{clip}.bvh", out, defects="clean", frames=frames)
        skel = Skeleton.from_urdf(str(out / "skeleton.urdf"))
        seq = read_sequence(out)
        truth = seq.truth.double()
        fitted, _ = fit_body(skel, seq.cameras, seq.masks[:8], truth[:8], frames_used=8, progress=False)
        joints = body_plan(skel).eval_joints()
        g = torch.Generator().manual_seed(0)
        ts = list(range(0, len(truth), max(1, len(truth) // 10)))
        noise = torch.randn(len(ts), n_poses, truth.shape[-1], generator=g, dtype=torch.float64)
        start = fitted.clamp(truth[ts, None] + noise * torch.where(skel.dof_revolute, 0.15, 0.04))

        def mpjpe(x, fitted=fitted, joints=joints, truth=truth, ts=ts):
            with torch.no_grad():
                err = fitted.fk(x)[..., joints, :] - fitted.fk(truth[ts])[:, None, joints, :]
            return float(err.norm(dim=-1).mean()) * 1e3

        for steps in steps_list:
            refiner = Refiner(fitted, seq.cameras, steps=steps).double()
            t0 = clock()
            done = torch.stack([refiner(start[i], seq.frame(t).silhouettes).x for i, t in enumerate(ts)])
            dt = (clock() - t0) / len(ts)
            lines.append(f"| {clip} | {steps} | {mpjpe(start):.0f} | {mpjpe(done):.0f} | {dt * 1e3:.0f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--k", type=int, nargs="+", default=[1, 4, 16, 100], help="poses per call")
    p.add_argument("--steps", type=int, nargs="+", default=[20], help="refinement steps")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--clips", nargs="*", default=[], help="CMU clips for the effect table")
    p.add_argument("--poses", type=int, default=4, help="noisy poses per frame (effect table)")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--work", default="out/refine", help="where the foreign sequences are written")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--clock", choices=["wall", "cpu"], default="wall")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    clock = _clock(args.clock)
    print(f"machine: {machine()}; clock: {args.clock}\n")
    print(cost_table(args.k, args.steps[0], args.repeat, clock))
    if args.clips:
        print()
        print(effect_table(args.clips, args.steps, args.poses, args.frames, Path(args.work), clock))


if __name__ == "__main__":
    main()
