"""How far from the truth the refinement's cue has its optimum, on foreign renders (issues 11 and 12).

A tracking run on noisy masks is bimodal (a track holds or loses a limb for good), so comparing cue
settings by tracking needs many seeds. This measures what the hybrid filter's local optimisation does to a
pose it is handed, with no randomness: every ``--every``-th frame of each clip, start
:class:`~torchpf.refine.Refiner` at the *true* pose and run ``--steps`` gradient steps on the cue; report
how far the refined pose ends from the truth (MPJPE, mm, the evaluated joints of
:func:`benchmarks.foreign.body_plan`). A cue whose optimum lies at the truth leaves it there; mask defects
move that optimum, and the tracker follows it (it recentres its particles on the refined pose every frame).
The body is what ``track`` uses: the converted skeleton fitted to frame 0's masks at the true pose
(:func:`torchpf.detect.fit_body_to_frame`); ``floor`` is the error of the true angles on that body.

Settings are keywords of :class:`~torchpf.likelihoods.SilhouetteDistanceLikelihood`::

    python -m benchmarks.cue_bias --settings "tau=6,despeckle=3" "tau=6" "tau=3" --presets clean noisy

prints one row per setting with the mean drift per preset and per clip.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from benchmarks.evaluate import CMU_DIR
from benchmarks.foreign import body_plan, build_sequence


def parse_setting(
    text: str, ints: tuple[str, ...] = ("despeckle", "n_samples", "n_body", "n_cap")
) -> dict[str, float | int]:
    """``"tau=6,despeckle=3"`` -> ``{"tau": 6.0, "despeckle": 3}`` (``""``: the defaults): keywords, ints
    for the keys in ``ints`` (the cue's by default), floats for the others."""
    out: dict[str, float | int] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"setting {text!r}: {item!r} is not key=value")
        out[key.strip()] = int(value) if key.strip() in ints else float(value)
    return out


def drift(seq_dir: Path, settings: list[str], *, steps: int, every: int) -> tuple[float, dict[str, float]]:
    """``(floor, {setting: mean drift})`` in mm for one sequence directory."""
    from torchpf.detect import fit_body_to_frame
    from torchpf.likelihoods import SilhouetteDistanceLikelihood
    from torchpf.refine import Refiner
    from torchpf.sequence import load_truth_csv, read_sequence
    from torchpf.skeleton import Skeleton

    skel = Skeleton.from_urdf(str(seq_dir / "skeleton.urdf"))
    truth, _, _ = load_truth_csv(seq_dir / "truth.csv")
    seq = read_sequence(seq_dir)
    joints = body_plan(skel).eval_joints()
    body, _ = fit_body_to_frame(skel, seq.cameras, seq.frame(0), truth[0])
    body = body.float()
    frames = list(range(1, len(seq), every))
    x = truth[frames].float()
    with torch.no_grad():
        want = skel.fk(truth[frames]).float()[:, joints]
        floor = float((body.fk(x)[:, joints] - want).norm(dim=-1).mean()) * 1000
    out = {}
    for text in settings:
        cue = SilhouetteDistanceLikelihood(body, seq.cameras, **parse_setting(text))
        refiner = Refiner(body, seq.cameras, cue=cue, steps=steps)
        refined = torch.stack(
            [refiner(x[k : k + 1], seq.frame(t).silhouettes).x[0] for k, t in enumerate(frames)]
        )
        with torch.no_grad():
            out[text] = float((body.fk(refined)[:, joints] - want).norm(dim=-1).mean()) * 1000
    return floor, out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--settings", nargs="+", default=["despeckle=3", ""], help="cue keyword sets")
    parser.add_argument("--clips", default="07_01,35_02,16_46,35_24,08_09,16_21", help="CMU clips")
    parser.add_argument("--presets", nargs="+", default=["clean", "noisy"])
    parser.add_argument("--steps", type=int, default=40, help="gradient steps from the truth")
    parser.add_argument("--every", type=int, default=4, help="every k-th frame")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--cmu-dir", default=str(CMU_DIR))
    parser.add_argument("--work", default="out/cue_bias", help="where the rendered sequences go")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    clips = [c.strip() for c in args.clips.split(",") if c.strip()]
    rows: dict[tuple[str, str], dict[str, float]] = {}
    floors: dict[str, list[float]] = {p: [] for p in args.presets}
    for clip in clips:
        for preset in args.presets:
            seq = build_sequence(
                Path(args.cmu_dir) / f"{clip}.bvh",
                Path(args.work) / f"{clip}-{preset}",
                defects=preset,
                frames=args.frames,
            )
            floor, got = drift(seq.path, args.settings, steps=args.steps, every=args.every)
            floors[preset].append(floor)
            for text, value in got.items():
                rows.setdefault((text, preset), {})[clip] = value
            print(
                f"{clip} {preset}: floor {floor:.0f} mm, "
                + ", ".join(f"[{k}] {v:.0f}" for k, v in got.items()),
                file=sys.stderr,
                flush=True,
            )
    print(
        f"Drift of the refined pose from the truth (MPJPE, mm; {args.steps} steps from the true pose, every "
        f"{args.every}th frame, body fitted to frame 0), {len(clips)} clips:\n"
    )
    print(
        "| Cue setting | "
        + " | ".join(f"{p} (mean)" for p in args.presets)
        + " | "
        + " | ".join(f"{c} {p}" for p in args.presets for c in clips)
        + " |"
    )
    print("|---|" + "---:|" * (len(args.presets) * (len(clips) + 1)))
    print(
        "| (floor: the true angles on the fitted body) | "
        + " | ".join(f"{sum(floors[p]) / len(floors[p]):.0f}" for p in args.presets)
        + " | "
        + " | ".join(f"{floors[p][i]:.0f}" for p in args.presets for i in range(len(clips)))
        + " |"
    )
    for text in args.settings:
        means = [sum(rows[(text, p)].values()) / len(clips) for p in args.presets]
        print(
            f"| `{text or 'defaults'}` | "
            + " | ".join(f"{m:.0f}" for m in means)
            + " | "
            + " | ".join(f"{rows[(text, p)][c]:.0f}" for p in args.presets for c in clips)
            + " |"
        )
    print(f"\n{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
