"""``make demo``: the main job end to end on the embedded default data, on a fresh machine.

1. generate walking performances of several performers with the procedural generator and write them as
   mocap CSV (plus each performer's URDF), with a look at the other actions;
2. train a walk action model (Rius eq. 1-5) from those CSV files, and check that it accepts a held-out
   performer's walk but not bending or waving;
3. synthesise a multi-camera sequence of the held-out performer (silhouettes with segmentation noise);
4. track it with several filters at the same number of likelihood evaluations per frame: CONDENSATION, the
   annealed and the partitioned particle filter with the angular random walk, CONDENSATION with the
   action model's soft aSpace prior (the best learned prior under it in ``benchmarks/action_prior.py``),
   and ``track``'s default hybrid filter (APF + gradient refinement) with the random walk, with the walk
   model (eq. 6), whose refinement then stays in the action's aSpace, and with a bank of the walk, bend and
   wave models (the best learned prior of ``benchmarks/action_prior.py``), whose posterior over the actions
   names what the person does;
5. print a metrics table (Fontmarty eq. 3-6 on the tracks ``track`` returns, smoothed by default; the MPJPE of
   the filter's own estimates beside it; ESS, time) and save plots and mask overlays under ``--out``.

    python -m training.demo --out out [--particles 600] [--frames 24] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from priors.bank import ActionBank
from priors.factories import random_walk
from torchpf import Skeleton, metrics
from torchpf.camera import camera_ring
from torchpf.distributions import as_generator
from torchpf.sequence import write_sequence
from torchpf.synth import SynthOptions, synthesize
from torchpf.tracker import Tracker
from training.fit import fit_action_model
from training.mocap import load_csv
from training.synthetic import ACTIONS, generate_dataset

_TRACES = ("LeftUpLeg_Xrotation", "LeftLeg_Xrotation", "RightArm_Zrotation", "Spine1_Xrotation")


def _plot_performances(plt, csv_by_action: dict[str, list[Path]], out: Path) -> Path:
    fig, axes = plt.subplots(2, len(csv_by_action), figsize=(5 * len(csv_by_action), 8), squeeze=False)
    for col, (action, csvs) in enumerate(csv_by_action.items()):
        for k, csv in enumerate(csvs):
            motion = load_csv(csv)
            if k == 0:
                skel = Skeleton.from_urdf(csv.with_suffix(".urdf"))
                pos = skel.fk(motion.angles)
                step = max(1, motion.n_frames // 6)
                for i, f in enumerate(range(0, motion.n_frames, step)):
                    for p, c in skel.bones:
                        axes[0, col].plot(
                            pos[f, [p, c], 1], pos[f, [p, c], 2], color=plt.cm.viridis(i / 6), lw=1.2
                        )
                axes[0, col].set_title(f"{action}: {csv.name} (side view, every {step} frames)")
                axes[0, col].set_xlabel("y (m, forward is -y)")
                axes[0, col].set_ylabel("z (m)")
                axes[0, col].set_aspect("equal")
            for c, dof in enumerate(_TRACES):
                axes[1, col].plot(
                    motion.times,
                    torch.rad2deg(motion.angles[:, motion.dof_names.index(dof)]),
                    color=f"C{c}",
                    alpha=0.8 if k == 0 else 0.3,
                    label=dof if k == 0 else None,
                )
        axes[1, col].set_xlabel("time (s)")
        axes[1, col].set_ylabel("angle (deg)")
        axes[1, col].legend(fontsize=7)
    fig.tight_layout()
    path = out / "performances.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _overlay(plt, skel, cams, seq, truth, estimates: dict[str, torch.Tensor], out: Path) -> Path:
    """Masks of camera 0 at a few frames with the true and estimated skeletons projected on them."""
    cam_name = next(iter(cams.keys()))
    cam = cams[cam_name]
    T = truth.shape[0]
    frames = sorted({0, T // 3, 2 * T // 3, T - 1})
    fig, axes = plt.subplots(1, len(frames), figsize=(3.2 * len(frames), 3), squeeze=False)
    mask_h, mask_w = seq.masks[0][0].shape
    scale = torch.tensor([mask_w / cam.width, mask_h / cam.height])
    poses = {"truth": truth, **estimates}
    for ax, f in zip(axes[0], frames, strict=True):
        ax.imshow(seq.masks[f][0], cmap="gray")
        for i, (name, angles) in enumerate(poses.items()):
            uv = cam.project(skel.fk(angles[f]).to(torch.float64)) * scale
            for p, c in skel.bones:
                ax.plot(
                    uv[[p, c], 0],
                    uv[[p, c], 1],
                    color="lime" if i == 0 else f"C{i}",
                    lw=1.5 if i == 0 else 1,
                    label=name if (p, c) == skel.bones[0] else None,
                )
        ax.set_title(f"{cam_name}, frame {f}")
        ax.set_axis_off()
    axes[0, 0].legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    path = out / "overlay.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out"))
    ap.add_argument("--performers", type=int, default=6, help="walk performers (the last one is held out)")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=30.0, help="mocap frame rate")
    ap.add_argument("--track-fps", type=float, default=15.0, help="camera frame rate of the tracked sequence")
    ap.add_argument("--frames", type=int, default=24, help="frames to track")
    ap.add_argument("--particles", type=int, default=600, help="likelihood evaluations per frame")
    ap.add_argument("--components", type=int, default=6, help="aSpace dimension of the action model")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    import matplotlib

    matplotlib.use("Agg")  # files only, no display on CI or servers
    import matplotlib.pyplot as plt

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    # 1. performances as mocap CSV
    print(f"1. generating performances under {out / 'data'}")
    csvs = {
        action: generate_dataset(
            out / "data" / action,
            action,
            args.performers if action == "walk" else 2,
            args.seconds,
            args.fps,
            args.seed,
        )
        for action in ACTIONS
    }
    print(f"   {sum(len(v) for v in csvs.values())} CSV files; plot: {_plot_performances(plt, csvs, out)}")

    # 2. the action model, trained from the CSV files
    walks = [load_csv(p) for p in csvs["walk"]]
    train, held_out = walks[:-1], walks[-1]
    # a training performer's body: its joint types say which DOFs are angles
    performer = Skeleton.from_urdf(csvs["walk"][0].with_suffix(".urdf"))
    model = fit_action_model(train, n_components=args.components, action="walk", skeleton=performer)
    model_path = out / "walk.npz"
    model.save(model_path)
    gen = as_generator(args.seed)
    rates = {
        "training walks": float(torch.cat([model.accepts(m.angles, gen).double() for m in train]).mean()),
        "held-out walk": float(model.accepts(held_out.angles, gen).double().mean()),
        "bend": float(model.accepts(load_csv(csvs["bend"][0]).angles, gen).double().mean()),
        "wave": float(model.accepts(load_csv(csvs["wave"][0]).angles, gen).double().mean()),
    }
    print(f"2. action model ({args.components} aSpace dims, {len(train)} performers) -> {model_path}")
    # the other actions' models, for the bank (two performers each)
    others = [
        fit_action_model(
            [load_csv(p) for p in csvs[a]], n_components=args.components, action=a, skeleton=performer
        )
        for a in ACTIONS
        if a != "walk"
    ]
    print("   acceptance (Rius eq. 6): " + ", ".join(f"{k} {v:.2f}" for k, v in rates.items()))

    # 3. a held-out multi-camera sequence
    skel = Skeleton.from_urdf(csvs["walk"][-1].with_suffix(".urdf"))  # the held-out performer's body
    step = max(1, int(round(args.fps / args.track_fps)))
    angles = held_out.angles[::step][: args.frames].clone()
    cams = camera_ring(3, radius=4.5, width=640, height_px=480, target=(0.0, -0.6, 0.9), start_deg=-60.0)
    angles[:, [0, 2]] -= angles[0, [0, 2]].clone()  # the walk starts at the origin, in view of the cameras
    noise = SynthOptions(morph_px=1, speckle=0.002)
    seq = synthesize(
        skel, angles, cams, mask_size=(160, 120), options=noise, fps=args.track_fps, seed=args.seed
    )
    write_sequence(out / "sequence", seq)
    print(f"3. sequence: {len(angles)} frames, 3 cameras, 160x120 masks -> {out / 'sequence'}")

    # 4. tracking at an equal budget of likelihood evaluations per frame
    rw = {"fps": args.track_fps}
    setups = {
        "CONDENSATION + random walk": dict(filter="sir", dynamics="random_walk", dynamics_options=rw),
        "APF + random walk": dict(filter="apf", dynamics="random_walk", dynamics_options=rw),
        "PARTITIONED + random walk": dict(filter="partitioned", dynamics="random_walk", dynamics_options=rw),
        # the best learned prior of benchmarks/action_prior.py (BENCHMARKS.md, issue 14): soft aSpace prior
        "CONDENSATION + action model (soft)": dict(
            filter="sir", dynamics="action", dynamics_options={"model": model_path, "mode": "soft", **rw}
        ),
        # track's default filter: APF layers, then gradient refinement, which an action model keeps on the
        # action's manifold (its aSpace, priors.action.ActionSubspace)
        "HYBRID + random walk": dict(filter="hybrid", dynamics="random_walk", dynamics_options=rw),
        "HYBRID + action model": dict(
            filter="hybrid", dynamics="action", dynamics_options={"model": model_path, **rw}
        ),
        # the best learned prior of benchmarks/action_prior.py under the hybrid: a bank of action models,
        # whose per-frame posterior over the actions recognises what the person does
        "HYBRID + action bank": dict(
            filter="hybrid",
            dynamics=ActionBank(
                [model, *others], random_walk(skel, fps=args.track_fps), fps=args.track_fps, skeleton=skel
            ),
        ),
    }
    truth = skel.fk(angles)
    rows, estimates, errors = [], {}, {}
    print(f"4. tracking with {args.particles} likelihood evaluations per frame")
    for name, setup in setups.items():
        tracker = Tracker(
            skel,
            cams,
            likelihood={"silhouette": 1.0, "dual_silhouette": 1.0},
            n_particles=args.particles,
            progress=False,
            **setup,
        )
        result = tracker.track(seq, seed=args.seed)
        if "action_posterior" in result.stats:
            labels = [setup["dynamics"].actions[int(i)] for i in result.stats["action_posterior"].argmax(-1)]
            recognised = {a: labels.count(a) / len(labels) for a in dict.fromkeys(labels)}
            print(f"   {name}: action posterior " + ", ".join(f"{a} {p:.0%}" for a, p in recognised.items()))
        est = skel.fk(result.angles)
        estimates[name] = result.angles
        errors[name] = (est - truth).norm(dim=-1).mean(-1)
        table = metrics.evaluate(truth, est)
        # the filter's own estimates, before track's smoothing (torchpf.smooth): what the filters compare
        own = result.filtered_angles if result.filtered_angles is not None else result.angles
        table["filter_mpjpe"] = float(metrics.mpjpe(truth, skel.fk(own)))
        rows.append(
            (name, table, float(result.ess.mean()), result.seconds / len(angles), int(result.failed.sum()))
        )
    print()
    print(
        "| tracker | RMSE (cm) | bias (cm) | MPJPE (cm) | failure rate | MPJPE unsmoothed (cm) | mean ESS "
        "| s/frame |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, t, ess, spf, _ in rows:
        print(
            f"| {name} | {t['rmse'] * 100:.1f} | {t['bias'] * 100:.1f} | {t['mpjpe'] * 100:.1f} | "
            f"{t['failure_rate']:.3f} | {t['filter_mpjpe'] * 100:.1f} | {ess:.1f} | {spf:.2f} |"
        )
    print()

    # 5. plots
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, err in errors.items():
        ax.plot(np.arange(len(err)) / args.track_fps, err * 100, label=name)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mean joint error (cm)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "error_per_frame.png", dpi=100)
    plt.close(fig)
    overlay = _overlay(plt, skel, cams, seq, angles, estimates, out)
    print(f"5. plots: {out / 'error_per_frame.png'}, {overlay}")
    print(f"done in {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
