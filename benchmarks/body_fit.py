"""How well ``track``'s body fit recovers a foreign body's widths from masks with defects (issue 12).

On noisy foreign renders ``track`` is 19 mm better on the body it fits to the *clean* masks of a clip than
on the one it fits to the noisy masks (BENCHMARKS.md, "Which joint limits carry the gain"); this measures
the body fit alone, with no tracking and no randomness but the defects' seed: for each clip, render the
first ``--frames`` frames with the foreign renderer (:mod:`benchmarks.foreign`) clean and with each
``--defects`` set, fit the converted skeleton's body as ``track`` does
(:func:`torchpf.detect.fit_body_to_frame` on frame 0, then again on all the frames) but at the *true* poses,
and score the fitted body

* ``IoU``: its silhouettes at the true poses against the *clean* masks (mean over cameras and frames);
* ``|log r|``: the mean absolute log ratio of each bone's radius to the radius the same fit gives on the
  clean masks (bones thinner than 5 mm on the clean fit left out), and the mean signed log ratio per bone,
  labelled by the bone's child joint (display only).

Defect sets are :data:`benchmarks.foreign.PRESETS` names or fields of :class:`benchmarks.foreign.Defects`::

    python -m benchmarks.body_fit --defects noisy morph_px=1 ragged=0.25 holes=3 merge=0.3 --jobs 2

``--fit`` passes keywords to the fit (``view_offset_sigma=1``, ``radius_sigma=0.25``,
``iterations=100``); ``--hold-arms`` keeps the arms' radii out of the defect sets' fits (``fit_body(fixed=)``;
``track`` instead fits them and puts them back after each fit on such masks, ``Tracker.hold_thin_arms``):
their rows then show what the other capsules do with the arms held.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import fields
from functools import partial
from pathlib import Path

import numpy as np
import torch

from benchmarks.cue_bias import parse_setting
from benchmarks.evaluate import CMU_DIR
from benchmarks.foreign import (
    CMU_SCALE,
    PRESETS,
    Defects,
    ForeignRenderer,
    centre_root,
    place_cameras,
    resample,
)


def parse_defects(text: str) -> Defects:
    """``"noisy"`` (a preset) or ``"morph_px=1,merge=0.3"`` (:class:`Defects` fields) -> :class:`Defects`."""
    if text in PRESETS:
        return PRESETS[text]
    types = {f.name: f.type for f in fields(Defects)}
    out = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in types or key == "dropout_frames":
            raise ValueError(
                f"--defects {text!r}: {item!r} is not a preset ({', '.join(PRESETS)}) nor key=value with a "
                f"key of {', '.join(k for k in types if k != 'dropout_frames')}"
            )
        out[key] = int(value) if types[key] in (int, "int") else float(value)
    return Defects(**out)


#: the integer keywords of :func:`torchpf.calibrate.fit_body` (``--fit``)
FIT_INTS = ("iterations", "max_size", "patience", "refresh_every", "frames_used")


def parse_fit(text: str) -> dict[str, float | int]:
    """``"view_offset_sigma=1,iterations=50"`` -> keywords of :func:`torchpf.calibrate.fit_body`
    (:func:`benchmarks.cue_bias.parse_setting` with :data:`FIT_INTS`)."""
    return parse_setting(text, FIT_INTS)


def clip_bodies(
    clip: Path, defect_sets: list[Defects], *, frames: int, seed: int, fit: dict, hold_arms: bool = False
) -> list[dict]:
    """One row per defect set (the clean fit first, always fitting every capsule): ``iou`` (float),
    ``radii`` (C,) m, and ``groups`` (the fit's bone groups, :func:`torchpf.calibrate.bone_groups`) labelled
    by their first bone's child joint. ``hold_arms``: the defect sets' fits keep the arms' radii as the
    converted skeleton has them (``fixed=arm_bones(skeleton)``)."""
    from torchpf.calibrate import _iou, _model_masks, bone_groups
    from torchpf.camera import CameraRig
    from torchpf.detect import fit_body_to_frame
    from torchpf.kinematics.anatomy import arm_bones
    from training.mocap import convert_bvh

    _, skel, motion, _ = convert_bvh(clip, CMU_SCALE)
    angles = centre_root(skel, resample(motion.angles[1:], motion.fps, 30.0, skel.dof_revolute)[:frames])
    renderer = ForeignRenderer(skel, performer_seed=sum(ord(ch) for ch in clip.stem.split("_")[0]))
    rig, _ = place_cameras(renderer.joints(angles), n=3, size=(160, 120), radius=4.0)
    rig = CameraRig(rig)
    clean = renderer.render_sequence(angles, rig, defects="clean", seed=seed) > 0
    truth = angles.double()
    groups = {skel.joint_names[skel.bones[g[0]][1]]: g[0] for g in bone_groups(skel)}
    rows = []
    for k, defects in enumerate([Defects(), *defect_sets]):
        masks = clean if k == 0 else renderer.render_sequence(angles, rig, defects=defects, seed=seed) > 0
        options = {**fit, "fixed": arm_bones(skel) if hold_arms and k > 0 else ()}
        first, _ = fit_body_to_frame(skel, rig, torch.from_numpy(masks[0]), truth[0], **options)
        body, _ = fit_body_to_frame(first, rig, [torch.from_numpy(m) for m in masks], truth, **options)
        with torch.no_grad():
            model = _model_masks(
                body, rig, body.fk(truth.to(body.radii.dtype)), body.radii, *clean.shape[-2:]
            )
        iou = _iou(model, clean, np.ones(clean.shape[:2], dtype=bool), rig.names)
        rows.append(
            {"iou": float(np.mean(list(iou.values()))), "radii": body.radii.double(), "groups": groups}
        )
    return rows


def _clip_rows(clip: Path, *, threads: int, **options) -> list[dict]:
    """:func:`clip_bodies` in a worker process (its own torch thread count)."""
    torch.set_num_threads(threads)
    return clip_bodies(clip, **options)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--defects", nargs="+", default=["noisy"], help="presets or Defects fields k=v")
    parser.add_argument("--clips", nargs="*", default=None, help="CMU clip stems (default: all in --cmu)")
    parser.add_argument("--cmu", type=Path, default=CMU_DIR)
    parser.add_argument("--frames", type=int, default=30, help="frames fitted (track's refit uses 30)")
    parser.add_argument("--seed", type=int, default=0, help="the defects' seed")
    parser.add_argument("--fit", default="", help="fit_body keywords, e.g. view_offset_sigma=1")
    parser.add_argument(
        "--hold-arms",
        action="store_true",
        help="the defect sets' fits keep the arms' radii (fit_body's fixed)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads per process")
    parser.add_argument("--jobs", type=int, default=1, help="clips fitted at a time (processes)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    defect_sets = [parse_defects(d) for d in args.defects]
    fit = parse_fit(args.fit)
    clips = (
        [args.cmu / f"{c}.bvh" for c in args.clips] if args.clips else sorted(Path(args.cmu).glob("*.bvh"))
    )
    for clip in clips:
        if not clip.exists():
            raise SystemExit(f"body_fit: no clip {clip}")
    t0 = time.perf_counter()
    work = partial(_clip_rows, defect_sets=defect_sets, frames=args.frames, seed=args.seed, fit=fit)
    work = partial(work, threads=args.threads, hold_arms=args.hold_arms)
    if args.jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.jobs) as pool:
            per_clip = list(pool.map(work, clips))
    else:
        per_clip = [work(c) for c in clips]
    names = ["clean (the reference)", *args.defects]
    groups = per_clip[0][0]["groups"]
    shared = all(rows[0]["groups"] == groups for rows in per_clip)
    print(
        f"Body fit at the true poses, {len(clips)} clips, {args.frames} frames, defects seed {args.seed}"
        + (f", fit {fit}" if fit else "")
        + (", the arms' radii held in the defect sets' fits" if args.hold_arms else "")
    )
    print("\n| masks | IoU vs clean masks | mean abs log radius ratio to the clean fit |\n|---|---:|---:|")
    signed = []
    for k, name in enumerate(names):
        ious, logs = [], []
        for rows in per_clip:
            ref, got = rows[0]["radii"], rows[k]["radii"]
            keep = ref > 0.005
            ious.append(rows[k]["iou"])
            logs.append((got.clamp_min(1e-4).log() - ref.clamp_min(1e-4).log()) * keep)
        lr = torch.stack(logs)  # (clips, C), 0 where the clean bone is thinner than 5 mm
        kept = torch.stack([rows[0]["radii"] > 0.005 for rows in per_clip])
        signed.append(lr.sum(0) / kept.sum(0).clamp_min(1))
        mean_abs = float(lr.abs().sum() / kept.sum().clamp_min(1))
        print(f"| {name} | {np.mean(ious):.3f} | {mean_abs:.3f} |")
    if shared:  # the same skeleton in every clip: the signed ratio per bone group
        thick = torch.stack([rows[0]["radii"] > 0.005 for rows in per_clip]).all(0)
        cols = {label: k for label, k in groups.items() if bool(thick[k])}
        print("\nMean log radius ratio to the clean fit per bone group (its first bone's child joint):\n")
        print("| masks | " + " | ".join(cols) + " |")
        print("|---|" + "---:|" * len(cols))
        for name, row in zip(names, signed, strict=True):
            print(f"| {name} | " + " | ".join(f"{float(row[k]):+.2f}" for k in cols.values()) + " |")
    print(f"\n{time.perf_counter() - t0:.0f} s")
    return 0 if all(math.isfinite(r["iou"]) for rows in per_clip for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
