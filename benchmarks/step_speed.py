"""Speed of one tracking step on a foreign render (issues 11 and 12: ">= 10 fps" at 500 likelihood
evaluations per frame, 3 cameras, 160x120 masks, one torch thread).

One CMU clip is rendered by the foreign renderer (:func:`benchmarks.foreign.build_sequence`, as
``python -m benchmarks.evaluate --renderer foreign`` does), the converted skeleton's body is fitted to frame
0 once (:func:`torchpf.detect.fit_body_to_frame`, what ``track`` would do at its start: outside the timing,
so the rows are the per-frame step) and, in one process, the script times per frame:

* ``apf``: ``Tracker(skel, cameras, n_particles=500, fps=30, filter="apf")`` (APF, ``silhouette`` +
  ``dual_silhouette``, structural random walk, recovery on), the whole :meth:`~torchpf.Tracker.track`
  loop (masks read from disk included); ``apf, no recovery``: the same without the lost-track detector;
* ``hybrid``: ``filter="hybrid"``, the default of ``track`` (APF layers, then projected Adam on ``K = 4``
  poses, limb swaps tried; the finished track smoothed, :mod:`torchpf.smooth`, its cost spread over the
  frames); ``hybrid, no smoothing``: the filter alone (``smooth=False``); ``hybrid, no recovery``: without
  the lost-track detector (its periodic visual hull); ``hybrid, no limb swaps``: without the swapped
  candidates (``filter_options={"swaps": ()}``);
* ``bank``: the hybrid with a bank of walk and run models learned from the other performers' CMU clips
  (``python -m benchmarks.evaluate --setups action_bank``), and with their joint limits too
  (``action_bank_limits``): what a learned prior costs per frame (the models' fit outside the timing);
* ``refine``: :class:`~torchpf.refine.Refiner` alone (the hybrid's default: 20 steps, ``K = 4`` poses near
  the truth; ``--refine-steps 10,15`` adds rows with other step counts, for the hybrid too, at the same
  budget) on each frame's fresh observation (its per-frame caches, the despeckled masks and distance
  images, built inside the timing as in tracking);
* one likelihood evaluation of 500 particles for each image cue (caches warm, as in the 2nd-Lth APF layer),
  median over the frames.

Figures are per frame (per evaluation for the cues) in CPU time of this process (``--clock cpu``, the default:
the machine is shared, and one torch thread makes CPU time the time a quiet core would take) or wall time.
``--save FILE.json`` keeps the figures, ``--baseline FILE.json`` prints the ratio to a run saved earlier,
e.g. at another commit::

    git stash; python -m benchmarks.step_speed --save out/before.json; git stash pop
    python -m benchmarks.step_speed --baseline out/before.json

``--device cuda --paths apf,hybrid,bank`` runs the trackers on a GPU (wall clock: a GPU's work is
asynchronous); ``--particles`` sets the evaluations per frame; ``--cmu-dir`` finds the clips where
``../shared`` is not beside the checkout (a GPU machine; the bank's models read ``../shared`` itself). The
rendering and the body fit come first: give a GPU run a minute.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from benchmarks.likelihoods import machine

CMU_DIR = (Path(__file__).resolve().parents[1] / ".." / "shared" / "mocap" / "cmu").resolve()

#: image cues timed one evaluation at a time (all read the silhouettes)
CUES = ("silhouette", "dual_silhouette", "silhouette_distance", "overlap")


class _Clocks:
    """CPU and wall time of a block: ``with clocks: ...`` adds to ``cpu`` and ``wall`` (seconds)."""

    def __init__(self):
        self.cpu = self.wall = 0.0

    def __enter__(self):
        self._c, self._w = time.process_time(), time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.cpu += time.process_time() - self._c
        self.wall += time.perf_counter() - self._w


def _track_row(tracker, seq_dir: Path, frames: int, warmup) -> dict:
    tracker.track(warmup["frames"], init=warmup["init"], seed=0)  # first-call costs out of the timing
    clocks = _Clocks()
    with clocks:
        result = tracker.track(seq_dir, seed=0)
    return {"cpu": clocks.cpu / frames, "wall": clocks.wall / frames, "evals": result.likelihood_evaluations}


def measure(
    clip: str,
    work: Path,
    frames: int,
    repeat: int,
    paths,
    refine_steps=(),
    *,
    cmu_dir: Path = CMU_DIR,
    device: str = "cpu",
    particles: int = 500,
) -> dict[str, dict]:
    """Per-frame seconds ``{path: {"cpu", "wall", "evals"}}`` of the paths named in ``paths``; the hybrid
    and the refinement also with each number of gradient steps in ``refine_steps`` (default 20). The
    trackers run on ``device`` with ``particles`` likelihood evaluations per frame."""
    from benchmarks.foreign import build_sequence
    from torchpf.detect import fit_body_to_frame
    from torchpf.likelihoods import LIKELIHOODS
    from torchpf.refine import Refiner
    from torchpf.sequence import read_sequence
    from torchpf.skeleton import Skeleton
    from torchpf.tracker import Tracker

    bvh = Path(cmu_dir) / f"{clip}.bvh"
    seq = build_sequence(bvh, work / f"{clip}-clean", defects="clean", frames=frames)
    data = read_sequence(seq.path)
    T = len(data)
    # the body track() would fit to frame 0 (the converted skeleton looks uncalibrated), fitted once here so
    # that the rows time the per-frame step, not the fit, and every row runs on the same body
    skel = Skeleton.from_urdf(str(seq.skeleton_path))
    skel, _ = fit_body_to_frame(skel, data.cameras, data.frame(0), data.truth_in(skel.dof_names)[0].double())
    truth = data.truth_in(skel.dof_names).float()
    warmup = {"frames": [data.frame(t) for t in range(2)], "init": truth[0].double()}
    rows: dict[str, dict] = {}

    def tracker(**options):
        return Tracker(
            skel, data.cameras, n_particles=particles, fps=30, progress=False, device=device, **options
        )

    if "apf" in paths:
        rows["apf"] = _track_row(tracker(filter="apf"), seq.path, T, warmup)
        rows["apf, no recovery"] = _track_row(tracker(filter="apf", recovery=False), seq.path, T, warmup)
    if "hybrid" in paths:
        rows["hybrid"] = _track_row(tracker(filter="hybrid"), seq.path, T, warmup)
        rows["hybrid, no smoothing"] = _track_row(tracker(filter="hybrid", smooth=False), seq.path, T, warmup)
        rows["hybrid, no recovery"] = _track_row(
            tracker(filter="hybrid", recovery=False), seq.path, T, warmup
        )
        rows["hybrid, no limb swaps"] = _track_row(
            tracker(filter="hybrid", filter_options={"swaps": ()}), seq.path, T, warmup
        )
        for steps in refine_steps:  # the same budget: fewer steps leave the APF layers more particles
            options = {"filter_options": {"refine_options": {"steps": steps}}}
            rows[f"hybrid, {steps} steps"] = _track_row(
                tracker(filter="hybrid", **options), seq.path, T, warmup
            )
    if "bank" in paths:  # a learned prior (issue 12's noisy goal): the bank, then the bank with limits
        from benchmarks.evaluate import action_bank_setup

        for name, limits in (("hybrid, action bank", None), ("hybrid, action bank + limits", 0.15)):
            made = action_bank_setup(limits=limits, device=device)(seq.path, skel, n_particles=particles)
            rows[name] = _track_row(made, seq.path, T, warmup)
    g = torch.Generator().manual_seed(0)
    spread = torch.where(skel.dof_revolute, 0.05, 0.02).float()
    for steps in (20, *refine_steps) if "refine" in paths else ():
        refiner = Refiner(skel, data.cameras, steps=steps)
        refiner(truth[:1].expand(4, -1).clone(), data.frame(0).silhouettes)  # warm-up
        clocks = _Clocks()
        for t in range(T):
            x = skel.clamp(truth[t] + spread * torch.randn(4, truth.shape[-1], generator=g))
            obs = data.frame(t).silhouettes  # fresh: its caches are built inside the timing, as in tracking
            with clocks:
                refiner(x, obs)
        rows[f"refine (K=4, {steps} steps)"] = {
            "cpu": clocks.cpu / T,
            "wall": clocks.wall / T,
            "evals": refiner.evaluations(4),
        }
    if "cues" in paths:
        for name in CUES:
            cue = LIKELIHOODS.get(name)(skel, data.cameras)
            cpu, wall = [], []
            for t in range(0, T, max(1, T // 5)):
                x = skel.clamp(truth[t] + spread * torch.randn(500, truth.shape[-1], generator=g))
                obs = data.frame(t).silhouettes
                with torch.no_grad():
                    cue(x, obs)  # fills the observation's caches, as the first APF layer does
                    for _ in range(repeat):
                        clocks = _Clocks()
                        with clocks:
                            cue(x, obs)
                        cpu.append(clocks.cpu)
                        wall.append(clocks.wall)
            rows[f"cue {name} (500 poses)"] = {
                "cpu": statistics.median(cpu),
                "wall": statistics.median(wall),
                "evals": 500,
            }
    return rows


def table(rows: dict[str, dict], clock: str, baseline: dict[str, dict] | None = None) -> str:
    """Markdown table: ms per frame (per evaluation for the cues) and fps on ``clock``, the other clock's ms,
    and the ratio baseline / now (> 1: faster now) where a baseline row of the same name exists."""
    other = "wall" if clock == "cpu" else "cpu"
    head = f"| path | ms/frame ({clock}) | fps ({clock}) | ms/frame ({other}) | evaluations/frame |"
    rule = "|---|---:|---:|---:|---:|"
    if baseline is not None:
        head += f" baseline ms ({clock}) | speed-up |"
        rule += "---:|---:|"
    lines = [head, rule]
    for name, r in rows.items():
        line = (
            f"| {name} | {r[clock] * 1e3:.1f} | {1.0 / max(r[clock], 1e-12):.1f} | {r[other] * 1e3:.1f} | "
            f"{r['evals']} |"
        )
        if baseline is not None:
            b = baseline.get(name)
            line += " - | - |" if b is None else f" {b[clock] * 1e3:.1f} | {b[clock] / r[clock]:.2f}x |"
        lines.append(line)
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--clip", default="07_01", help="CMU clip stem (clean masks)")
    p.add_argument("--frames", type=int, default=60, help="frames of the clip before resampling to 30 fps")
    p.add_argument(
        "--paths", default="apf,hybrid,refine,cues", help="comma list of apf, hybrid, bank, refine, cues"
    )
    p.add_argument("--repeat", type=int, default=3, help="timed evaluations per frame (cues)")
    p.add_argument(
        "--refine-steps",
        default="",
        help="comma list of refinement step counts timed besides the default 20 (hybrid and refine rows)",
    )
    p.add_argument("--work", default="out/step_speed", help="where the sequence directory is written")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--clock", choices=["cpu", "wall"], help="default: cpu on the CPU, wall on a GPU")
    p.add_argument(
        "--device", default="cpu", help="where the trackers run (cuda: the apf, hybrid and bank rows)"
    )
    p.add_argument("--particles", type=int, default=500, help="likelihood evaluations per frame")
    p.add_argument("--cmu-dir", default=str(CMU_DIR), help="folder of the CMU BVH clips")
    p.add_argument("--save", help="write the figures to this JSON file")
    p.add_argument("--baseline", help="JSON file of an earlier --save: adds its ms and the speed-up")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    paths = {s.strip() for s in args.paths.split(",") if s.strip()}
    unknown = paths - {"apf", "hybrid", "bank", "refine", "cues"}
    if unknown:
        p.error(f"unknown path(s) {sorted(unknown)}")
    if args.device != "cpu":
        if not paths <= {"apf", "hybrid", "bank"}:
            p.error(
                f"--device {args.device} times the apf, hybrid and bank rows only (--paths apf,hybrid,bank)"
            )
        if args.device.startswith("cuda") and not torch.cuda.is_available():
            p.error(f"--device {args.device}: no CUDA device is available")
    # a GPU's work is asynchronous and runs beside the CPU: only wall time measures it
    clock = args.clock or ("cpu" if args.device == "cpu" else "wall")
    baseline = None
    if args.baseline:
        with open(args.baseline, encoding="utf-8") as f:
            baseline = json.load(f)["rows"]
    gpu = f"; device: {torch.cuda.get_device_name(args.device)}" if args.device.startswith("cuda") else ""
    print(f"machine: {machine()}{gpu}; load average {os.getloadavg()[0]:.2f}; clock: {clock}")
    refine_steps = [int(x) for x in args.refine_steps.split(",") if x.strip()]
    rows = measure(
        args.clip,
        Path(args.work),
        args.frames,
        args.repeat,
        paths,
        refine_steps,
        cmu_dir=Path(args.cmu_dir),
        device=args.device,
        particles=args.particles,
    )
    print(
        f"clip {args.clip} (clean), 3 cameras, 160x120 masks, {args.particles} evaluations/frame on "
        f"{args.device}; load average now {os.getloadavg()[0]:.2f}\n"
    )
    print(table(rows, clock, baseline))
    if args.save:
        Path(args.save).parent.mkdir(parents=True, exist_ok=True)
        with open(args.save, "w", encoding="utf-8") as f:
            json.dump({"machine": machine(), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
