"""Command line: ``python -m torchpf track`` and ``python -m torchpf evaluate``.

    python -m torchpf track SEQ_DIR --skeleton S.urdf [--action walk.npz [--action run.npz]] --filter apf \\
        --particles 500 --out track.csv [--init auto|truth|POSE.csv] [--fps F]
    python -m torchpf evaluate track.csv [run2.csv ...] --truth truth.csv --skeleton S.urdf
    python -m torchpf calibrate SEQ_DIR --skeleton S.urdf --out FITTED.urdf [--frames K] \\
        [--init auto|truth|POSE.csv] [--outline-offsets PX] [--radius-sigma SIGMA]
    python -m torchpf masks VIDEO_OR_FOLDER... --cameras cameras.yaml --out SEQ_DIR \\
        [--background-frames N | --clean-plate IMG...]
    python -m torchpf render TRACK.csv --skeleton S.urdf --sequence SEQ_DIR --out overlay.mp4
    python -m torchpf cameras merge CAM1.yml CAM2.yml ... --out cameras.yaml

``track`` reads a sequence directory (DESIGN.md: cameras.yaml, masks/, optional points/, truth.csv), builds a
:class:`~torchpf.tracker.Tracker` and writes the estimated motion as mocap CSV. ``evaluate`` compares one or
several tracks (several runs of a stochastic tracker) with the ground truth: Fontmarty's RMSE, bias,
dispersion and failure rate (eq. 3-6), MPJPE and the angle MSE. ``calibrate`` fits the body's capsule radii
and scale to the first frames' masks (:func:`torchpf.calibrate.fit_body`), writes the fitted URDF and an
overlay PNG (masks against the fitted model) next to it. ``masks`` segments synchronised videos (one per
camera) by background subtraction into a sequence directory (:mod:`torchpf.video`); ``render`` draws a
track's body model over each camera's video frame or mask, side by side (:mod:`torchpf.render`);
``cameras merge`` writes one ``cameras.yaml`` from per-camera OpenCV calibration files. Bad input
ends with a one-line error and exit status 2, Ctrl-C with ``interrupted`` and status 130 (``--debug`` or
``TORCHPF_DEBUG=1``: the traceback); ``--threads N`` sets torch's threads (:mod:`torchpf.cli`).
"""

from __future__ import annotations

import argparse
import os
import sys

import torch

from torchpf.cli import CliError, add_runtime_options, check_memory, check_output_file, run_command

#: Memory per simultaneously scored particle and capsule (bytes), measured with the default cues (SIR, human
#: skeleton, 27 capsules: ~35 KiB per particle): what ``--particles`` is checked against before the run.
_BYTES_PER_PARTICLE_CAPSULE = 1400


def _parser() -> argparse.ArgumentParser:
    from torchpf._version import __version__

    ap = argparse.ArgumentParser(
        prog="python -m torchpf", description=__doc__.splitlines()[0], allow_abbrev=False
    )
    ap.add_argument("--version", action="version", version=f"torchpf {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)

    tr = sub.add_parser(
        "track", help="track a sequence directory, write the estimated motion as CSV", allow_abbrev=False
    )
    tr.add_argument("sequence", help="sequence directory (cameras.yaml, masks/, points/, truth.csv)")
    tr.add_argument("--skeleton", required=True, help="URDF of the tracked body")
    tr.add_argument("--out", required=True, help="output mocap CSV")
    tr.add_argument("--config", help="YAML with Tracker keywords (command-line options override it)")
    tr.add_argument(
        "--action",
        action="append",
        help="action model (.npz of 'python -m training fit') for the action-constrained prior (Rius); "
        "repeat it for a bank of actions (e.g. a walk and a run), the action then a state of each particle",
    )
    tr.add_argument("--name-map", help="YAML 'model DOF: skeleton DOF' names, where the skeleton's differ")
    tr.add_argument(
        "--dynamics",
        help="registered motion prior (default random_walk, or action with --action), or a FILE.npz of "
        "'python -m training fit-dynamics' (the 'learned' prior)",
    )
    tr.add_argument(
        "--filter",
        help="sir, qrs, partitioned, partitioned_qrs, apf, mcmc, hybrid (APF + gradient refinement on the "
        "silhouettes), auto (default: hybrid where silhouettes and cameras are given, else apf)",
    )
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
        "--fps",
        type=float,
        help="frame rate of the sequence (Hz), for the motion prior and the output's time column "
        "(default: truth.csv's time column; without one 30, said on stderr)",
    )
    tr.add_argument(
        "--init",
        help="initial pose: truth (truth.csv frame 0; the default when present), auto (found from the "
        "masks alone; an uncalibrated body is fitted, its URDF written next to --out), or a mocap CSV",
    )
    tr.add_argument(
        "--no-calibrate",
        action="store_true",
        help="track on the skeleton as given, even when its body looks uncalibrated (by default such a "
        "body is fitted to the first frames' masks first, its URDF written next to --out)",
    )
    tr.add_argument("--no-recovery", action="store_true", help="do not re-acquire a lost track")
    tr.add_argument(
        "--boundary-offset",
        action="store_true",
        help="measure per camera and frame how far the masks' outline lies outside the body's (a "
        "segmentation that fattens or thins the person) and widen or thin the model by it",
    )
    tr.add_argument(
        "--torso-limit",
        metavar="RAD",
        help="hold each unlimited rotation of the skeleton's torso chain (spine, neck, head, found from the "
        "tree; a converted BVH has no limits) within RAD of the rest pose, e.g. 0.5 (default: none, the "
        "skeleton as given)",
    )
    tr.add_argument(
        "--hold-thin-arms",
        metavar="PX",
        help="when the body is fitted, keep the arms' capsule widths as the skeleton has them if the arms "
        "project thinner than PX pixels (radius) in frame 0's masks and those masks' outlines stray more "
        "than half a pixel from the body fitted to them: noisy masks cannot measure an arm a pixel or two "
        "across; none: fit the arms like the rest (default: 2)",
    )
    tr.add_argument(
        "--no-smooth",
        action="store_true",
        help="write the filter's own estimates (each frame's from the frames up to it) instead of the track "
        "smoothed over the whole sequence (torchpf.smooth, the default with silhouettes)",
    )
    tr.add_argument("--device", help="cpu or cuda")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--no-progress", action="store_true")
    add_runtime_options(tr)

    ev = sub.add_parser("evaluate", help="compare tracks with the ground truth")
    ev.add_argument("tracks", nargs="+", help="track CSVs (several = several runs on one sequence)")
    ev.add_argument("--truth", required=True, help="ground-truth mocap CSV")
    ev.add_argument("--skeleton", required=True, help="URDF used for the joint positions")
    ev.add_argument("--threshold", type=float, default=0.25, help="T_failure (m), Fontmarty eq. 6")
    add_runtime_options(ev)

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
    ca.add_argument(
        "--outline-offsets",
        type=float,
        metavar="PX",
        help="also fit each mask's outline offset (px added to every projected radius, held near 0 by "
        "this std: a segmenter that thins or fattens one camera's masks), so that it does not thin or "
        "fatten the body (torchpf.calibrate.fit_body view_offset_sigma; default: masks as they are)",
    )
    ca.add_argument(
        "--radius-sigma",
        type=float,
        metavar="SIGMA",
        help="hold the bone groups' log radii near their mean with this std (a prior on the spread of the "
        "body's widths, for masks with defects or poses that are off, e.g. 0.25; "
        "torchpf.calibrate.fit_body radius_sigma; default: each radius free)",
    )
    ca.add_argument("--no-progress", action="store_true")
    add_runtime_options(ca)

    ma = sub.add_parser("masks", help="videos or image folders -> silhouettes -> a sequence directory")
    ma.add_argument("sources", nargs="+", help="one video file or image folder per camera (named after it)")
    ma.add_argument("--cameras", required=True, help="cameras.yaml (or an OpenCV calibration file)")
    ma.add_argument("--out", required=True, help="sequence directory to write")
    bg = ma.add_mutually_exclusive_group()
    bg.add_argument(
        "--background-frames",
        type=int,
        default=0,
        help="background = median of the first N frames (also segmented)",
    )
    bg.add_argument(
        "--clean-plate",
        nargs="+",
        help="one image of the empty scene per camera, in source order (after the videos)",
    )
    ma.add_argument("--start", type=int, default=0, help="first frame written as mask 0 (default 0)")
    ma.add_argument("--frames", type=int, help="at most this many frames")
    ma.add_argument("--method", default="mog2", choices=["mog2", "knn"], help="background model (mog2)")
    ma.add_argument("--history", type=int, default=200, help="frames the background model remembers")
    ma.add_argument("--threshold", type=float, help="model threshold (MOG2 16, KNN 400)")
    ma.add_argument("--no-shadows", action="store_true", help="keep shadows as foreground")
    ma.add_argument("--open-px", type=int, default=3, help="opening kernel (px), removes speckle (3)")
    ma.add_argument("--close-px", type=int, default=7, help="closing kernel (px), bridges gaps (7)")
    ma.add_argument("--min-area", type=float, default=0.002, help="smallest blob kept, share of image")
    ma.add_argument("--no-fill-holes", action="store_true")
    ma.add_argument("--learning-rate", type=float, help="model adaptation per frame (0 freezes; -1 auto)")
    ma.add_argument("--size", help="WxH of the written masks, e.g. 160x120 (default: the video's size)")
    ma.add_argument("--no-video", action="store_true", help="do not write video/<camera>.mp4")
    ma.add_argument("--fps", type=float, help="frame rate of the written videos (default: the input's)")
    ma.add_argument("--no-progress", action="store_true")
    add_runtime_options(ma)

    re_ = sub.add_parser("render", help="draw a track's body model over the sequence, cameras side by side")
    re_.add_argument("track", help="track CSV (python -m torchpf track --out)")
    re_.add_argument("--skeleton", required=True, help="URDF of the tracked body")
    re_.add_argument("--sequence", required=True, help="sequence directory (cameras.yaml, masks/, video/)")
    re_.add_argument("--out", required=True, help="overlay video (.mp4, .avi) or a folder for PNG frames")
    re_.add_argument(
        "--background", default="auto", choices=["auto", "video", "masks"], help="draw over (default auto)"
    )
    re_.add_argument("--fps", type=float, help="video frame rate (default: the track's time column, else 30)")
    re_.add_argument("--min-height", type=int, default=240, help="enlarge smaller tiles to this height (px)")
    re_.add_argument("--no-progress", action="store_true")
    add_runtime_options(re_)

    cm = sub.add_parser("cameras", help="camera files: merge per-camera OpenCV calibrations (cameras merge)")
    cm_sub = cm.add_subparsers(dest="cameras_command", required=True)
    mg = cm_sub.add_parser(
        "merge", help="per-camera OpenCV calibration files (or cameras.yaml files) -> one cameras.yaml"
    )
    mg.add_argument(
        "files", nargs="+", help="camera files in camera order; a one-camera file names its camera"
    )
    mg.add_argument("--out", required=True, help="cameras.yaml to write")
    mg.add_argument("--depth-camera", help="name of the depth sensor (points/ of a sequence)")
    add_runtime_options(mg)
    return ap


def _positive(option: str, value: str, other: str) -> float:
    """``value`` of ``option`` as a positive finite number; the error names the other word it takes."""
    try:
        number = float(value)
    except ValueError:
        raise CliError(f"{option} must be a number or {other}, got {value!r}") from None
    if not (number > 0 and number < float("inf")):
        raise CliError(f"{option} must be positive and finite, got {value}")
    return number


def _temperature(value: str | None) -> float | str | None:
    """``--temperature``: ``auto`` or a positive number."""
    if value is None or value == "auto":
        return value
    return _positive("--temperature", value, "auto")


def _positive_or_none(option: str, value: str) -> float | None:
    """``--torso-limit`` (rad), ``--hold-thin-arms`` (px): ``none`` or a positive number."""
    return None if value.lower() == "none" else _positive(option, value, "none")


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


#: What ``track`` assumes for a sequence without timestamps and without ``--fps`` (and says so).
_DEFAULT_FPS = 30.0


def _frame_rate(args, seq, configured) -> float:
    """The tracking frame rate (Hz): ``--fps``, else the config's ``fps``, else the sequence's timestamps,
    else :data:`_DEFAULT_FPS` with a warning on stderr (the prior's per-frame stds and the output's time
    column depend on it: never assumed silently)."""
    fps = args.fps if args.fps is not None else configured
    times = seq.times if seq.times is not None and len(seq.times) > 1 else None
    from_times = 1.0 / float(times[1] - times[0]) if times is not None else None
    if fps is None:
        if from_times is not None:
            return from_times
        print(
            f"warning: {args.sequence} has no timestamps (no time column in truth.csv) and no --fps was "
            f"given: assuming {_DEFAULT_FPS:g} fps for the motion prior and the output",
            file=sys.stderr,
        )
        return _DEFAULT_FPS
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        raise CliError(f"fps must be a number of frames per second, got {fps!r}") from None
    if not (0 < fps < float("inf")):
        raise CliError(f"--fps must be positive and finite, got {fps:g}")
    if from_times is not None and abs(fps - from_times) > 1e-3 * from_times:
        print(
            f"warning: --fps {fps:g} overrides the {from_times:g} fps of {args.sequence}'s timestamps for "
            "the motion prior",
            file=sys.stderr,
        )
    return fps


def _check_config_keys(config: dict, path: str) -> None:
    import inspect

    from torchpf.tracker import Tracker

    allowed = [p for p in inspect.signature(Tracker.__init__).parameters if p not in ("self", "skeleton")]
    unknown = sorted(str(k) for k in config if k not in allowed)
    if unknown:
        raise CliError(f"{path}: unknown key(s) {unknown}; a tracker config takes {allowed}")


def _track(args) -> int:
    from torchpf.sequence import read_sequence
    from torchpf.skeleton import Skeleton
    from torchpf.tracker import Tracker

    check_output_file(args.out)
    skel = Skeleton.from_urdf(_require_file(args.skeleton, "skeleton"))
    if not os.path.isdir(args.sequence):
        raise CliError(f"sequence directory not found: {args.sequence}")
    if os.path.isdir(args.out):
        raise CliError(f"--out {args.out} is a directory; give the CSV file to write")
    seq = read_sequence(args.sequence)  # lazy: frames are read one at a time while tracking
    if args.device and args.device.startswith("cuda") and not torch.cuda.is_available():
        raise CliError("--device cuda: no CUDA device is available")
    kwargs = {}
    if args.config:
        import yaml

        from torchpf.io import load_yaml

        with open(_require_file(args.config, "config"), encoding="utf-8") as f:
            try:
                loaded = load_yaml(f.read()) or {}  # plain numbers only (no "1_000")
            except yaml.YAMLError as e:
                raise CliError(f"{args.config}: invalid YAML ({' '.join(str(e).split())})") from None
        if not isinstance(loaded, dict):
            raise CliError(f"{args.config}: a tracker config must be a mapping of Tracker keywords")
        kwargs = dict(loaded)
        kwargs.pop("skeleton", None)
        _check_config_keys(kwargs, args.config)
    if args.action:
        models = [_require_file(a, "action model") for a in args.action]
        bank = len(models) > 1
        kwargs["dynamics"] = args.dynamics or ("bank" if bank else "action")
        kwargs["dynamics_options"] = {
            **kwargs.get("dynamics_options", {}),
            **({"models": models} if bank else {"model": models[0]}),
        }
        if args.name_map:
            kwargs["dynamics_options"]["name_map"] = _require_file(args.name_map, "name map")
    elif args.name_map:
        raise CliError("--name-map renames an action model's DOFs; it needs --action")
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
        ("boundary_offset", True if args.boundary_offset else None),
        ("smooth", False if args.no_smooth else None),
    ):
        if value is not None:
            kwargs[key] = value
    if args.torso_limit is not None:  # None is a value here: 'none' turns the guess off
        kwargs["torso_limit"] = _positive_or_none("--torso-limit", args.torso_limit)
    kwargs["progress"] = not args.no_progress
    n = int(kwargs.get("n_particles", 500))
    if not str(kwargs.get("device") or "cpu").startswith("cuda"):
        check_memory(n * _BYTES_PER_PARTICLE_CAPSULE * max(len(skel.bones), 1), f"--particles {n}")
    kwargs["fps"] = _frame_rate(args, seq, kwargs.get("fps"))
    tracker = Tracker.from_config(kwargs, skeleton=skel, cameras=seq.cameras)
    if args.hold_thin_arms is not None:  # a Tracker attribute (the body fits'), not a constructor keyword
        tracker.hold_thin_arms = _positive_or_none("--hold-thin-arms", args.hold_thin_arms)
    init = args.init
    if init not in (None, "auto", "truth"):
        init = _require_file(init, "--init pose CSV")
    elif init is None and seq.truth is None:
        raise CliError(
            f"{args.sequence}: no truth.csv for the initial pose; pass --init auto or --init POSE.csv"
        )
    # the CSV is written as frames are tracked: OUT.partial keeps the finished frames if the run stops
    calibrate = False if args.no_calibrate else None
    result = tracker.track(seq, seed=args.seed, init=init, out=args.out, calibrate=calibrate)
    n_failed = int(result.failed.sum())
    blind = result.no_evidence.nonzero().flatten().tolist()
    smoothed = (
        " (smoothed; --no-smooth for the filter's own estimates)"
        if result.filtered_angles is not None
        else ""
    )
    print(
        f"tracked {len(result.angles)} frames with {tracker.filter_name} ({tracker.n_particles} likelihood "
        f"evaluations/frame) in {result.seconds:.1f} s: mean ESS {float(result.ess.mean()):.1f}, "
        f"{n_failed} failed frames, {len(blind)} frames without evidence, log-evidence "
        f"{result.log_evidence:.1f}; wrote {args.out}{smoothed}"
    )
    from torchpf.sequence import format_frames

    free = tracker.skeleton.free_rotations()  # the torso's may have been limited by the tracker's guess
    if len(free) > len(skel.dof_names) // 4:  # a converted BVH: no joint limits at all
        print(
            f"note: {len(free)} joint rotations of {args.skeleton} have no limits (BVH has none), so the "
            "track may bend a knee sideways or cross the legs; 'python -m training fit-limits' learns "
            "limits from mocap of the action (foreign renders, noisy masks: 67 -> 51 mm; with walk and run "
            "models of 'python -m training fit' as --action walk.npz --action run.npz, 47; BENCHMARKS.md)"
        )
    if blind:
        print(f"frames without evidence (no usable mask, point or keypoint): {format_frames(blind)}")
    if "action_fallback" in result.stats:  # a learned prior says when it gave up on the sequence
        fell, accepted = result.stats["action_fallback"], result.stats["action_accepted"]
        print(
            f"action prior: accepted {100 * float(accepted.float().mean()):.0f}% of the particles; fell back "
            f"to its plain dynamics on {int(fell.sum())} of {fell.numel()} frames"
        )
    names = getattr(tracker.dynamics, "actions", None)
    if "action_posterior" in result.stats and names:  # a bank of actions: which one, frame by frame
        label = result.stats["action_posterior"].argmax(-1)
        print(
            "actions: "
            + "; ".join(
                f"{name} on frames {format_frames((label == a).nonzero().flatten().tolist())}"
                for a, name in enumerate(names)
                if bool((label == a).any())
            )
        )
    if n_failed or bool(result.recovered.any()):
        failed, recovered = (
            format_frames(f.nonzero().flatten().tolist()) or "none" for f in (result.failed, result.recovered)
        )
        print(f"failed frames: {failed}; recovered at frames: {recovered}")
    if result.skeleton is not skel:  # the body was fitted first: the track's angles belong to it
        fitted = os.path.splitext(args.out)[0] + "_fitted.urdf"
        result.skeleton.save_urdf(fitted)
        print(f"fitted the body to the first frames' masks; wrote {fitted} (the track's skeleton)")
    if seq.truth is not None:
        from torchpf import metrics

        truth = skel.fk(seq.truth_in(skel.dof_names).to(torch.float64))
        est = result.skeleton.fk(result.angles)
        print(
            f"vs truth.csv: RMSE {float(metrics.rmse(truth, est)) * 100:.1f} cm, MPJPE "
            f"{float(metrics.mpjpe(truth, est)) * 100:.1f} cm"
        )
    return 0


def _evaluate(args) -> int:
    from torchpf import metrics
    from torchpf.io import read_mocap_csv
    from torchpf.skeleton import Skeleton

    if not (0 < args.threshold < float("inf")):
        raise CliError(f"--threshold must be a positive number of metres, got {args.threshold}")
    skel = Skeleton.from_urdf(_require_file(args.skeleton, "skeleton"))
    names = skel.dof_names
    _, _, truth_angles = read_mocap_csv(_require_file(args.truth, "truth"), expected_dof_names=names)
    truth_angles = torch.as_tensor(truth_angles, dtype=torch.float64)
    if truth_angles.shape[0] == 0:
        raise CliError(f"{args.truth}: no frames to evaluate")
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

    check_output_file(args.out)
    skel = Skeleton.from_urdf(_require_file(args.skeleton, "skeleton"))
    if not os.path.isdir(args.sequence):
        raise CliError(f"sequence directory not found: {args.sequence}")
    if args.frames < 1:
        raise CliError(f"--frames must be >= 1, got {args.frames}")
    if args.outline_offsets is not None and not args.outline_offsets > 0:
        raise CliError(f"--outline-offsets must be > 0 px, got {args.outline_offsets}")
    if args.radius_sigma is not None and not args.radius_sigma > 0:
        raise CliError(f"--radius-sigma must be > 0, got {args.radius_sigma}")
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
        poses = seq.truth_in(skel.dof_names).to(torch.float64)
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
        view_offset_sigma=args.outline_offsets,
        radius_sigma=args.radius_sigma,
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


def _size(value: str | None) -> tuple[int, int] | None:
    """``--size WxH`` -> (W, H)."""
    if value is None:
        return None
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise CliError(f"--size must be WIDTHxHEIGHT, e.g. 160x120, got {value!r}") from None
    return w, h


def _masks(args) -> int:
    from torchpf.camera import single_camera_advice
    from torchpf.video import segment_videos

    advice = single_camera_advice(_require_file(args.cameras, "cameras file"))
    if advice and len(args.sources) > 1:
        raise CliError(f"--cameras: {len(args.sources)} sources for one camera; {advice}")
    report = segment_videos(
        args.sources,
        _require_file(args.cameras, "cameras file"),
        args.out,
        background_frames=args.background_frames,
        clean_plates=args.clean_plate,
        start=args.start,
        max_frames=args.frames,
        learning_rate=args.learning_rate,
        size=_size(args.size),
        subtractor={
            "method": args.method,
            "history": args.history,
            "threshold": args.threshold,
            "detect_shadows": not args.no_shadows,
            "open_px": args.open_px,
            "close_px": args.close_px,
            "min_area": args.min_area,
            "fill_holes": not args.no_fill_holes,
        },
        write_video=not args.no_video,
        fps=args.fps,
        progress=not args.no_progress,
    )
    if report.n_frames == 0:
        raise CliError(f"no frame written (sources shorter than --start {args.start}?)")
    print(report.summary())
    return 0


def _render(args) -> int:
    from torchpf.io import read_mocap_csv
    from torchpf.render import render_track
    from torchpf.skeleton import Skeleton

    skel = Skeleton.from_urdf(_require_file(args.skeleton, "skeleton"))
    if not os.path.isdir(args.sequence):
        raise CliError(f"sequence directory not found: {args.sequence}")
    _, times, values = read_mocap_csv(_require_file(args.track, "track"), expected_dof_names=skel.dof_names)
    fps = args.fps
    if fps is None:
        fps = 1.0 / float(times[1] - times[0]) if times is not None and len(times) > 1 else 30.0
    n = render_track(
        skel,
        torch.as_tensor(values, dtype=torch.float64),
        args.sequence,
        args.out,
        fps=fps,
        background=args.background,
        min_height=args.min_height,
        progress=not args.no_progress,
    )
    print(f"rendered {n} frames at {fps:g} fps; wrote {args.out}")
    return 0


def _cameras(args) -> int:
    from torchpf.camera import merge_camera_files, save_cameras

    check_output_file(args.out)
    rig = merge_camera_files([_require_file(p, "camera file") for p in args.files], args.depth_camera)
    save_cameras(args.out, rig)
    sizes = ", ".join(f"{name} {w}x{h}" for name, (w, h) in zip(rig.names, rig.sizes, strict=True))
    depth = f", depth camera {rig.depth_camera}" if rig.depth_camera else ""
    print(f"wrote {args.out}: {len(rig)} cameras ({sizes}){depth}")
    return 0


_COMMANDS = {
    "track": _track,
    "evaluate": _evaluate,
    "calibrate": _calibrate,
    "masks": _masks,
    "render": _render,
    "cameras": _cameras,
}


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    return run_command("python -m torchpf", args, _COMMANDS[args.command])


if __name__ == "__main__":
    raise SystemExit(main())
