"""Command line: ``python -m torchpf track`` and ``python -m torchpf evaluate``.

    python -m torchpf track SEQ_DIR --skeleton S.urdf [--action walk.npz] --filter apf --particles 500 \\
        --out track.csv [--init auto|truth|POSE.csv]
    python -m torchpf evaluate track.csv [run2.csv ...] --truth truth.csv --skeleton S.urdf
    python -m torchpf calibrate SEQ_DIR --skeleton S.urdf --out FITTED.urdf [--frames K] \\
        [--init auto|truth|POSE.csv]

``track`` reads a sequence directory (DESIGN.md: cameras.yaml, masks/, optional points/, truth.csv), builds a
:class:`~torchpf.tracker.Tracker` and writes the estimated motion as mocap CSV. ``evaluate`` compares one or
several tracks (several runs of a stochastic tracker) with the ground truth: Fontmarty's RMSE, bias,
dispersion and failure rate (eq. 3-6), MPJPE and the angle MSE. ``calibrate`` fits the body's capsule radii
and scale to the first frames' masks (:func:`torchpf.calibrate.fit_body`), writes the fitted URDF and an
overlay PNG (masks against the fitted model) next to it. Bad input ends with a one-line error and
exit status 2.
"""

from __future__ import annotations

import argparse
import os
import sys

import torch


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m torchpf", description=__doc__.splitlines()[0], allow_abbrev=False
    )
    sub = ap.add_subparsers(dest="command", required=True)

    tr = sub.add_parser(
        "track", help="track a sequence directory, write the estimated motion as CSV", allow_abbrev=False
    )
    tr.add_argument("sequence", help="sequence directory (cameras.yaml, masks/, points/, truth.csv)")
    tr.add_argument("--skeleton", required=True, help="URDF of the tracked body")
    tr.add_argument("--out", required=True, help="output mocap CSV")
    tr.add_argument("--config", help="YAML with Tracker keywords (command-line options override it)")
    tr.add_argument("--action", help="action model (.npz) for the action-constrained prior (Rius)")
    tr.add_argument(
        "--dynamics",
        help="registered motion prior (default random_walk, or action with --action), or a FILE.npz of "
        "'python -m training fit-dynamics' (the 'learned' prior)",
    )
    tr.add_argument("--filter", help="sir, qrs, partitioned, partitioned_qrs, apf, mcmc (default apf)")
    tr.add_argument("--particles", type=int, help="likelihood evaluations per frame (default 500)")
    tr.add_argument(
        "--likelihood",
        action="append",
        help="likelihood term, repeatable; NAME or NAME=WEIGHT (default silhouette and dual_silhouette)",
    )
    tr.add_argument(
        "--temperature",
        help="exponent on the log-likelihood: a number, or auto (set on the first frame for ESS/N = 0.2)",
    )
    tr.add_argument("--init-spread", type=float, help="std of the initial particles (rad / m)")
    tr.add_argument(
        "--init",
        help="initial pose: truth (truth.csv frame 0; the default when present), auto (found from the "
        "masks alone; an uncalibrated body is fitted, its URDF written next to --out), or a mocap CSV",
    )
    tr.add_argument("--no-recovery", action="store_true", help="do not re-acquire a lost track")
    tr.add_argument("--device", help="cpu or cuda")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--no-progress", action="store_true")

    ev = sub.add_parser("evaluate", help="compare tracks with the ground truth")
    ev.add_argument("tracks", nargs="+", help="track CSVs (several = several runs on one sequence)")
    ev.add_argument("--truth", required=True, help="ground-truth mocap CSV")
    ev.add_argument("--skeleton", required=True, help="URDF used for the joint positions")
    ev.add_argument("--threshold", type=float, default=0.25, help="T_failure (m), Fontmarty eq. 6")

    ca = sub.add_parser("calibrate", help="fit the body's radii and scale to the masks, write a URDF")
    ca.add_argument("sequence", help="sequence directory (cameras.yaml, masks/, truth.csv)")
    ca.add_argument("--skeleton", required=True, help="URDF of the body to fit")
    ca.add_argument("--out", required=True, help="fitted URDF (the overlay PNG is written next to it)")
    ca.add_argument("--frames", type=int, default=8, help="number of first frames fitted (default 8)")
    ca.add_argument(
        "--init",
        default="auto",
        help="initial poses: truth (truth.csv), a mocap CSV of poses (one row per frame, or one row for "
        "all), or auto (truth.csv when present, else found from the masks: torchpf.detect)",
    )
    ca.add_argument("--fit-lengths", action="store_true", help="also fit one length factor per bone group")
    ca.add_argument("--iterations", type=int, default=400, help="most optimiser steps (default 400)")
    ca.add_argument("--no-progress", action="store_true")
    return ap


def _temperature(value: str | None) -> float | str | None:
    """``--temperature``: ``auto`` or a positive number."""
    if value is None or value == "auto":
        return value
    try:
        beta = float(value)
    except ValueError:
        raise CliError(f"--temperature must be a number or auto, got {value!r}") from None
    if not (beta > 0 and beta < float("inf")):
        raise CliError(f"--temperature must be positive and finite, got {value}")
    return beta


def _likelihood_spec(items):
    if not items:
        return None
    spec = {}
    for item in items:
        name, _, weight = item.partition("=")
        try:
            spec[name] = float(weight) if weight else 1.0
        except ValueError:
            raise CliError(f"--likelihood {item!r}: the weight must be a number") from None
    return spec


def _require_file(path: str, what: str) -> str:
    if not os.path.isfile(path):
        raise CliError(f"{what} not found: {path}")
    return path


def _track(args) -> int:
    from torchpf.sequence import read_sequence
    from torchpf.skeleton import Skeleton
    from torchpf.tracker import Tracker

    skel = Skeleton.from_urdf(_require_file(args.skeleton, "skeleton"))
    if not os.path.isdir(args.sequence):
        raise CliError(f"sequence directory not found: {args.sequence}")
    seq = read_sequence(args.sequence)
    if args.device and args.device.startswith("cuda") and not torch.cuda.is_available():
        raise CliError("--device cuda: no CUDA device is available")
    kwargs = {}
    if args.config:
        import yaml

        with open(_require_file(args.config, "config"), encoding="utf-8") as f:
            kwargs = dict(yaml.safe_load(f) or {})
        kwargs.pop("skeleton", None)
    if args.action:
        kwargs["dynamics"] = args.dynamics or "action"
        kwargs["dynamics_options"] = {
            **kwargs.get("dynamics_options", {}),
            "model": _require_file(args.action, "action model"),
        }
    elif args.dynamics and args.dynamics.lower().endswith(".npz"):  # learned stds: the file is an option
        kwargs["dynamics"] = "learned"
        kwargs["dynamics_options"] = {
            **kwargs.get("dynamics_options", {}),
            "path": _require_file(args.dynamics, "dynamics file"),
        }
    elif args.dynamics:
        kwargs["dynamics"] = args.dynamics
    for key, value in (
        ("filter", args.filter),
        ("n_particles", args.particles),
        ("likelihood", _likelihood_spec(args.likelihood)),
        ("temperature", _temperature(args.temperature)),
        ("init_spread", args.init_spread),
        ("device", args.device),
        ("recovery", False if args.no_recovery else None),
    ):
        if value is not None:
            kwargs[key] = value
    kwargs["progress"] = not args.no_progress
    if seq.times is not None and len(seq.times) > 1 and "fps" not in kwargs:
        kwargs["fps"] = 1.0 / float(seq.times[1] - seq.times[0])
    tracker = Tracker.from_config(kwargs, skeleton=skel, cameras=seq.cameras)
    init = args.init
    if init not in (None, "auto", "truth"):
        init = _require_file(init, "--init pose CSV")
    elif init is None and seq.truth is None:
        raise CliError(
            f"{args.sequence}: no truth.csv for the initial pose; pass --init auto or --init POSE.csv"
        )
    result = tracker.track(seq, seed=args.seed, init=init)
    result.save_csv(args.out)
    n_failed = int(result.failed.sum())
    print(
        f"tracked {len(result.angles)} frames with {tracker.filter_name} ({tracker.n_particles} likelihood "
        f"evaluations/frame) in {result.seconds:.1f} s: mean ESS {float(result.ess.mean()):.1f}, "
        f"{n_failed} failed frames, log-evidence {result.log_evidence:.1f}; wrote {args.out}"
    )
    if n_failed or bool(result.recovered.any()):
        failed, recovered = _frame_list(result.failed), _frame_list(result.recovered)
        print(f"failed frames: {failed}; recovered at frames: {recovered}")
    if result.skeleton is not skel:  # init auto fitted the body: the track's angles belong to it
        fitted = os.path.splitext(args.out)[0] + "_fitted.urdf"
        result.skeleton.save_urdf(fitted)
        print(f"init auto: fitted the body to frame 0's masks; wrote {fitted} (the track's skeleton)")
    if seq.truth is not None:
        from torchpf import metrics

        truth = skel.fk(seq.truth.to(torch.float64))
        est = result.skeleton.fk(result.angles)
        print(
            f"vs truth.csv: RMSE {float(metrics.rmse(truth, est)) * 100:.1f} cm, MPJPE "
            f"{float(metrics.mpjpe(truth, est)) * 100:.1f} cm"
        )
    return 0


def _frame_list(flags) -> str:
    """``"3-12, 40"``: the indices of the True entries of a (T,) bool tensor as ranges (``"none"``)."""
    idx = flags.nonzero().flatten().tolist()
    runs: list[list[int]] = []
    for i in idx:
        if runs and i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else str(r[0]) for r in runs) or "none"


def _evaluate(args) -> int:
    from torchpf import metrics
    from torchpf.io import read_mocap_csv
    from torchpf.skeleton import Skeleton

    skel = Skeleton.from_urdf(_require_file(args.skeleton, "skeleton"))
    names = skel.dof_names
    _, _, truth_angles = read_mocap_csv(_require_file(args.truth, "truth"), expected_dof_names=names)
    truth_angles = torch.as_tensor(truth_angles, dtype=torch.float64)
    runs = []
    for path in args.tracks:
        _, _, angles = read_mocap_csv(_require_file(path, "track"), expected_dof_names=names)
        angles = torch.as_tensor(angles, dtype=torch.float64)
        if angles.shape != truth_angles.shape:
            raise CliError(f"{path}: {angles.shape[0]} frames, the truth has {truth_angles.shape[0]}")
        runs.append(angles)
    est_angles = torch.stack(runs)
    truth, est = skel.fk(truth_angles), skel.fk(est_angles)
    table = metrics.evaluate(truth, est, args.threshold)
    revolute = skel.dof_revolute
    table["angle_mse"] = float(metrics.angle_mse(truth_angles, est_angles, revolute))
    units = {"angle_mse": "rad^2", "failure_rate": ""}
    print(f"{len(runs)} run(s), {truth_angles.shape[0]} frames, {len(skel.joint_names)} joints")
    print("| criterion | value |")
    print("|---|---:|")
    for key, value in table.items():
        unit = units.get(key, "cm")
        shown = value * 100 if unit == "cm" else value
        print(f"| {key} | {shown:.3f} {unit} |")
    return 0


def _calibrate(args) -> int:
    import numpy as np

    from torchpf.calibrate import fit_body, overlay_image
    from torchpf.io import read_mocap_csv, write_atomic
    from torchpf.sequence import read_sequence
    from torchpf.skeleton import Skeleton

    skel = Skeleton.from_urdf(_require_file(args.skeleton, "skeleton"))
    if not os.path.isdir(args.sequence):
        raise CliError(f"sequence directory not found: {args.sequence}")
    if args.frames < 1:
        raise CliError(f"--frames must be >= 1, got {args.frames}")
    seq = read_sequence(args.sequence)
    k = min(args.frames, len(seq.masks))
    if k == 0:
        raise CliError(f"{args.sequence}: no masks to calibrate on")
    if args.init == "auto" and seq.truth is None:  # no ground truth: the person found from the masks
        from torchpf.detect import PersonDetector

        try:
            pose, _, _ = PersonDetector(skel, seq.cameras).fit(seq.frame(0))
        except ValueError as e:
            raise CliError(f"--init auto: {e}") from None
        poses = pose[None]
    elif args.init in ("auto", "truth"):
        if seq.truth is None:
            raise CliError(f"{args.sequence}: no truth.csv for the initial poses; pass --init POSE.csv")
        if list(seq.dof_names) != list(skel.dof_names):
            _, _, values = read_mocap_csv(
                os.path.join(args.sequence, "truth.csv"), expected_dof_names=skel.dof_names
            )
            poses = torch.as_tensor(values, dtype=torch.float64)
        else:
            poses = seq.truth.to(torch.float64)
    else:
        _, _, values = read_mocap_csv(_require_file(args.init, "--init pose CSV"), skel.dof_names)
        poses = torch.as_tensor(values, dtype=torch.float64)
    if len(poses) == 0:
        raise CliError("the initial pose CSV has no rows")
    if len(poses) < k:  # one pose (or too few) for all frames: repeat the last
        poses = torch.cat([poses, poses[-1:].expand(k - len(poses), -1)])
    fitted, report = fit_body(
        skel,
        seq.cameras,
        seq.masks[:k],
        poses[:k],
        frames_used=k,
        fit_lengths=args.fit_lengths,
        iterations=args.iterations,
        progress=not args.no_progress,
    )
    fitted.save_urdf(args.out)
    import cv2

    overlay = overlay_image(fitted, seq.cameras, seq.masks[0], report.poses[0])
    png = os.path.splitext(args.out)[0] + "_overlay.png"
    ok, data = cv2.imencode(".png", overlay)
    if not ok:
        raise CliError("cannot encode the overlay PNG")
    write_atomic(png, np.asarray(data).tobytes())
    print(report.table())
    print(f"wrote {args.out} and {png}")
    return 0


_COMMANDS = {"track": _track, "evaluate": _evaluate, "calibrate": _calibrate}


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _COMMANDS[args.command](args)
    except (CliError, ValueError, FileNotFoundError, OSError) as e:
        print(f"python -m torchpf {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
