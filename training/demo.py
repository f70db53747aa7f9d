"""``make demo``: the main job on the embedded default data, end to end, on a fresh machine.

Today it generates performances of each action with the procedural generator, writes them as mocap CSV (and
each performer's URDF), reads them back, runs forward kinematics on the performers' skeletons, prints a
table of what the motions do and saves plots under ``--out``. Tracking and action models join as they land.

    python -m training.demo --out out [--performers 4] [--seconds 4] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from torchpf import Skeleton
from training.mocap import load_csv
from training.synthetic import ACTIONS, generate_dataset

_TRACES = ("LeftUpLeg_Xrotation", "LeftLeg_Xrotation", "RightArm_Zrotation", "Spine1_Xrotation")


def _summary(skel: Skeleton, motion) -> dict[str, float]:
    pos = skel.fk(motion.angles)
    j = {n: pos[:, i] for i, n in enumerate(skel.joint_names)}
    hips = j["Hips"]
    seconds = max(motion.duration, 1e-9)
    return {
        "frames": motion.n_frames,
        "speed m/s": float((hips[-1, :2] - hips[0, :2]).norm()) / seconds,
        "head z min..max": (float(j["Head_end"][:, 2].min()), float(j["Head_end"][:, 2].max())),
        "r. hand z max": float(j["RightHandIndex1_end"][:, 2].max()),
        "knee max deg": float(
            torch.rad2deg(motion.angles[:, motion.dof_names.index("LeftLeg_Xrotation")]).max()
        ),
    }


def _draw(ax, skel: Skeleton, pos: torch.Tensor, colour) -> None:
    for p, c in skel.bones:
        seg = pos[[p, c]]
        ax.plot(seg[:, 1], seg[:, 2], color=colour, lw=1.2)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out"))
    ap.add_argument("--performers", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")  # files only, no display on CI or servers
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    rows = []
    fig, axes = plt.subplots(2, len(ACTIONS), figsize=(5 * len(ACTIONS), 8))
    for col, action in enumerate(ACTIONS):
        csvs = generate_dataset(
            args.out / "data" / action, action, args.performers, args.seconds, args.fps, args.seed
        )
        for k, csv in enumerate(csvs):
            motion = load_csv(csv)  # what a user's own mocap CSV would go through
            skel = Skeleton.from_urdf(csv.with_suffix(".urdf"))
            rows.append((action, csv.name, _summary(skel, motion)))
            if k == 0:
                pos = skel.fk(motion.angles)
                ax = axes[0, col]
                for i, f in enumerate(range(0, motion.n_frames, max(1, motion.n_frames // 6))):
                    _draw(ax, skel, pos[f], plt.cm.viridis(i / 6))
                ax.set_title(f"{action}: {csv.name} (side view, every {motion.n_frames // 6} frames)")
                ax.set_xlabel("y (m, forward is -y)")
                ax.set_ylabel("z (m)")
                ax.set_aspect("equal")
            ax = axes[1, col]
            for c, dof in enumerate(_TRACES):
                ax.plot(
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
    plot = args.out / "performances.png"
    fig.savefig(plot, dpi=90)
    plt.close(fig)

    print("| action | file | frames | speed (m/s) | head z (m) | right hand z max (m) | knee max (deg) |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for action, name, s in rows:
        lo, hi = s["head z min..max"]
        print(
            f"| {action} | {name} | {s['frames']} | {s['speed m/s']:.2f} | {lo:.2f}..{hi:.2f} "
            f"| {s['r. hand z max']:.2f} | {s['knee max deg']:.1f} |"
        )
    elapsed = time.perf_counter() - t0
    print(f"\nwrote {len(rows)} performances under {args.out / 'data'} and {plot} in {elapsed:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
