"""Command line of the training package: ``python -m training <command> ...``.

Commands::

    python -m training convert FILE.bvh [--scale S] --out-dir DIR  # -> DIR/skeleton.urdf + DIR/FILE.csv
    python -m training fit --action walk --skeleton S.urdf --out walk.npz DATA/*.csv
    python -m training inspect walk.npz --out DIR                  # -> DIR/synchronisation.png, ...; curve
    python -m training fit-dynamics DATA/*.csv --skeleton S.urdf --out dyn.npz [--fps 30]
    python -m training fit-limits DATA/*.csv --skeleton S.urdf --out limited.urdf [--margin 0.15]
    python -m training export TRACK.csv --skeleton S.urdf --out track.bvh [--scale S]

``convert`` turns a BVH file into a torchpf skeleton (URDF, z up, metres) and a mocap CSV of its angle
tracks in the skeleton's ``dof_names`` order (see :mod:`training.mocap`; ``--hold-static`` holds the
rotation channels the file never moves at their value). ``fit`` learns an action model (Rius eq. 1-3,
:mod:`training.fit`) from performances of one action and saves it as ``.npz`` (:mod:`priors.action`);
``inspect`` prints its summary and saves the plots of Rius Fig. 1 (:mod:`training.plots`). ``fit-dynamics``
learns per-DOF step stds and the constant-velocity α (:mod:`training.dynamics`) for ``python -m torchpf
track --dynamics dyn.npz``. ``fit-limits`` writes the skeleton again with joint limits learned from the
performances' range of motion (:mod:`training.limits`; a converted BVH has none) for ``track --skeleton
limited.urdf``. ``export`` writes a track (or any mocap CSV of the skeleton) as BVH for Blender /
MotionBuilder (:func:`training.mocap.save_bvh`). Bad input ends with a one-line ``error:`` message on stderr
and exit status 2, Ctrl-C with ``interrupted`` and status 130; every command takes ``--threads N`` and
``--debug`` (:mod:`torchpf.cli`). Each command is one subparser with its own ``--help``; more commands plug
in the same way through :func:`build_parser`.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from torchpf.cli import add_runtime_options, check_output_dir, check_output_file, int_at_least, run_command

PROG = "python -m training"


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def _add_skip_first(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--skip-first",
        type=int_at_least(0),
        default=0,
        metavar="N",
        help="drop the first N frames of every file (CMU conversions: 1, a rest pose)",
    )


#: Units a BVH file is written in, metres per file unit, tried by ``convert`` when ``--scale`` is missing.
#: CMU's unit is 1/0.45 inch (its ASF files' ``length 0.45``). A body size decides between them: the ranges
#: of rest-pose extents that each gives a :data:`_BODY_SIZE_M` body do not overlap.
_UNITS = {"metres": 1.0, "centimetres": 0.01, "millimetres": 0.001, "inches": 0.0254, "CMU units": 0.056444}
#: Plausible largest rest-pose extent (height or arm span) of a person, metres.
_BODY_SIZE_M = (1.0, 2.2)


def _infer_scale(bvh, file: str) -> float:
    """Metres per file unit for a BVH without ``--scale``: the unit of :data:`_UNITS` that makes the rest
    pose's largest extent a person's size, with a warning naming it; a CliError when none does."""
    import numpy as np

    from torchpf.cli import CliError

    rest = np.zeros((len(bvh.joints), 3))
    for i, joint in enumerate(bvh.joints):  # parents come first in a BVH hierarchy
        if joint.parent >= 0:
            rest[i] = rest[joint.parent] + np.asarray(joint.offset, dtype=np.float64)
    size = float(np.ptp(rest, axis=0).max())
    lo, hi = _BODY_SIZE_M
    fits = [(name, s) for name, s in _UNITS.items() if lo <= size * s <= hi]
    if not fits:
        raise CliError(
            f"{file}: no --scale, and the rest pose spans {size:.4g} file units, which no usual unit "
            f"({', '.join(_UNITS)}) makes a {lo:g}-{hi:g} m person: pass --scale (metres per file unit)"
        )
    name, scale = fits[0]
    print(
        f"warning: no --scale: {file}'s rest pose spans {size:.4g} file units, read as {name} (--scale "
        f"{scale:g}, a {size * scale:.2f} m body); pass --scale to set the units",
        file=sys.stderr,
    )
    return scale


def _convert(args: argparse.Namespace) -> int:
    # Imported here so that `--help` answers without loading torch.
    from torchpf.io import write_text_atomic
    from training.mocap import convert_bvh, read_bvh, save_csv

    check_output_dir(args.out_dir, "--out-dir")
    bvh = read_bvh(args.file)
    if args.scale is None:
        args.scale = _infer_scale(bvh, args.file)
    urdf, skel, motion, static = convert_bvh(bvh, args.scale, hold_static=args.hold_static)
    out = Path(args.out_dir)
    urdf_path, csv_path = out / "skeleton.urdf", out / f"{Path(args.file).stem}.csv"
    write_text_atomic(urdf_path, urdf)
    save_csv(csv_path, motion)
    print(
        f"wrote {urdf_path} ({len(skel.joint_names)} joints, {len(skel.dof_names)} DOFs) and {csv_path} "
        f"({motion.n_frames} frames at {motion.fps:.6g} fps)"
    )
    if static:
        what = "held at their values" if args.hold_static else "left free (--hold-static holds them)"
        print(
            f"{len(static)} rotation channels never move in this file (the rig does not animate them, e.g. "
            f"{', '.join(list(static)[:3])}): {what}"
        )
    print(
        "the skeleton has no joint limits (BVH has none): 'python -m training fit-limits' learns them from "
        "mocap CSVs of the action you will track"
    )
    return 0


def _components(text: str) -> int | float | str:
    """``--components``: ``auto``, an int >= 1 (count) or a float in (0, 1) (fraction of variance)."""
    if text == "auto":
        return text
    try:
        value: int | float = int(text)
    except ValueError:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if isinstance(value, int) and value < 1 or isinstance(value, float) and not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1 or a fraction in (0, 1), got {text!r}")
    return value


def _fit(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from priors.diffusion import alpha_summary
    from torchpf.skeleton import Skeleton
    from training.fit import HAND_PATTERNS, ActionModelFitter
    from training.mocap import load_csv

    if args.out.suffix != ".npz":
        raise ValueError(f"--out must name a .npz file, got {str(args.out)!r}")
    check_output_file(args.out)
    skeleton = Skeleton.from_urdf(args.skeleton) if args.skeleton else None
    dof_names = skeleton.dof_names if skeleton is not None else None
    motions = []
    for path in tqdm(args.files, desc="reading", unit="file", disable=args.quiet or len(args.files) < 2):
        motion = load_csv(
            path, dof_names=dof_names
        )  # a CSV of another skeleton fails, naming file and column
        if args.skip_first:
            motion = motion[args.skip_first :]
        motions.append(motion)
    negatives = [load_csv(p, dof_names=dof_names)[args.skip_first :] for p in args.negatives or []]
    if args.components == "auto" and len(motions) < 2:
        # the validation leaves one performance out; say so in the command's own terms
        raise ValueError(
            f"--components auto (the default) chooses the aSpace by leaving one performance out, and "
            f"{args.files[0]} is the only one: give another performer's clip of the action, or --components "
            "D (a model of one performance may not fit another performer's style: BENCHMARKS.md, "
            "'A learned prior')"
        )
    fitter = ActionModelFitter(
        negatives=negatives or None,
        n_components=args.components,
        action=args.action,
        fps=args.fps,
        cyclic=args.cyclic,
        n_postures=args.postures,
        exclude_root=args.exclude_root,
        exclude=HAND_PATTERNS if args.exclude is None else tuple(args.exclude),
        max_iter=args.max_iter,
        n_sigma=args.n_sigma,
        alpha=args.alpha,
        validate=args.validate,
        progress=not args.quiet,
    ).fit(motions, skeleton=skeleton)
    model = fitter.model_
    model.save(args.out)
    if fitter.validation_curve_ is not None:
        print(fitter.validation_curve_.table())
    rate = fitter.train_acceptance_  # how often eq. 6 accepts the training frames themselves
    print(
        f"wrote {args.out}: action {args.action!r} from {len(motions)} performances, "
        f"{len(model.posture_dofs)} posture DOFs -> D={model.n_components} "
        f"({100 * float(model.explained_variance_ratio.sum()):.1f}% variance), "
        f"K={model.n_postures} {'cyclic' if model.cyclic else 'acyclic'} mean postures at {model.fps:g} fps, "
        f"synchronisation {'converged' if fitter.converged_ else 'stopped'} after {fitter.n_iter_} "
        f"iterations, "
        f"alpha={alpha_summary(model.alpha)}; accepts {100 * rate:.1f}% of the training frames"
    )
    if fitter.validation_acceptance_ is not None:
        held = fitter.validation_acceptance_
        print(
            f"leave-one-performance-out: accepts {100 * held.mean():.1f}% of the left-out frames "
            f"(worst {100 * held.min():.1f}%); if far below the training rate, lower --components"
        )
    return 0


def _inspect(args: argparse.Namespace) -> int:
    from priors.action import ActionModel
    from training.plots import describe, plot_explained_variance, plot_synchronisation

    check_output_dir(args.out)
    model = ActionModel.load(args.model)
    print(describe(model))
    curve = (model.training_data or {}).get("info", {}).get("validation")
    if curve:
        from training.fit import ValidationCurve

        print(ValidationCurve.from_dict(curve).table())
    paths = [
        plot_synchronisation(model, args.out, n_dims=args.dims),
        plot_explained_variance(model, args.out),
    ]
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def _fit_dynamics(args: argparse.Namespace) -> int:
    from priors.diffusion import alpha_summary, sigma_summary
    from torchpf.skeleton import Skeleton
    from training.dynamics import learn_from_files

    if args.out.suffix != ".npz":
        raise ValueError(f"--out must name a .npz file, got {str(args.out)!r}")
    check_output_file(args.out)
    skeleton = Skeleton.from_urdf(args.skeleton)
    stats = learn_from_files(args.files, skeleton, fps=args.fps, alpha=args.alpha, skip_first=args.skip_first)
    stats.save(args.out)
    print(
        f"wrote {args.out}: {len(stats.dof_names)} DOFs from {len(args.files)} files "
        f"({stats.info['frames']} frames) at {stats.fps:g} fps, alpha={alpha_summary(stats.alpha)}"
    )
    print(sigma_summary(skeleton, stats.step_std, fps=stats.fps, source="learned"))
    return 0


def _fit_limits(args: argparse.Namespace) -> int:
    from torchpf.skeleton import Skeleton
    from training.limits import fit_limits
    from training.mocap import load_csv

    if args.out.suffix != ".urdf":
        raise ValueError(f"--out must name a .urdf file, got {str(args.out)!r}")
    if not (math.isfinite(args.margin) and args.margin >= 0):
        raise ValueError(f"--margin must be a number of radians >= 0, got {args.margin}")
    check_output_file(args.out)
    skeleton = Skeleton.from_urdf(args.skeleton)
    motions = [load_csv(p, dof_names=skeleton.dof_names)[args.skip_first :] for p in args.files]
    lower, upper, report = fit_limits(motions, skeleton, margin=args.margin)
    skeleton.with_limits(lower, upper).save_urdf(args.out)
    print(f"wrote {args.out}: joint limits from {len(args.files)} files, margin {args.margin:g} rad")
    print(report.summary())
    return 0


def _export(args: argparse.Namespace) -> int:
    from torchpf.skeleton import Skeleton
    from training.mocap import load_csv, save_bvh

    skeleton = Skeleton.from_urdf(args.skeleton)
    motion = load_csv(args.track, fps=args.fps, dof_names=skeleton.dof_names)
    save_bvh(args.out, skeleton, motion, scale=args.scale, euler_order=args.euler_order)
    print(
        f"wrote {args.out}: {motion.n_frames} frames at {motion.fps:g} fps, {len(skeleton.joint_names)} "
        f"joints, {args.scale:g} m per file unit"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``python -m training`` parser; each subcommand sets ``func(args) -> exit status``."""
    from torchpf._version import __version__

    parser = argparse.ArgumentParser(prog=PROG, description="Mocap conversion and action-model training.")
    parser.add_argument("--version", action="version", version=f"torchpf {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    convert = commands.add_parser(
        "convert",
        help="BVH -> skeleton.urdf + mocap CSV",
        description="Convert a BVH file to DIR/skeleton.urdf (z up, metres) and DIR/<stem>.csv (time column, "
        "then one column per DOF in the skeleton's dof_names order, radians / metres).",
    )
    convert.add_argument("file", metavar="FILE.bvh", help="BVH motion-capture file")
    convert.add_argument(
        "--scale",
        type=_positive_float,
        default=None,
        help="metres per file unit (CMU clips: 0.056444); default: inferred from the body's size "
        "(metres, cm, mm, inches or CMU units), with a warning",
    )
    convert.add_argument("--out-dir", required=True, metavar="DIR", help="output folder (created if missing)")
    convert.add_argument(
        "--hold-static",
        action="store_true",
        help="hold the rotation channels the file never moves (the rig does not animate them) at their value "
        "in the URDF (training.mocap.static_channels); default: every channel free",
    )
    add_runtime_options(convert)
    convert.set_defaults(func=_convert)

    fit = commands.add_parser(
        "fit",
        help="mocap CSV performances -> action model .npz",
        description="Learn an action model (aSpace PCA, DTW-synchronised mean performance and per-posture "
        "std, "
        "constant-velocity sigma_phi and alpha; Rius et al. eq. 1-3) from performances of one action, "
        "one mocap CSV each, and save it as .npz.",
    )
    fit.add_argument("files", nargs="+", metavar="FILE.csv", help="performances of the action (mocap CSV)")
    fit.add_argument("--action", required=True, help="action name stored in the model, e.g. walk")
    fit.add_argument("--out", required=True, type=Path, metavar="MODEL.npz", help="output file")
    fit.add_argument(
        "--skeleton",
        metavar="S.urdf",
        help="skeleton the CSVs must match (its dof_names are the pose layout)",
    )
    fit.add_argument(
        "--components",
        type=_components,
        default="auto",
        metavar="D",
        help="aSpace dimensions: 'auto' (default: leave-one-performer-out validation, also of n_sigma), a "
        "count (13 as Rius) or a variance fraction such as 0.9",
    )
    fit.add_argument(
        "--negatives",
        nargs="+",
        metavar="OTHER.csv",
        help="performances of other actions the model must reject (scored by --components auto)",
    )
    fit.add_argument("--fps", type=_positive_float, help="model frame rate; default: the files' rate")
    fit.add_argument(
        "--cyclic",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="periodic action (walk) or not (one bend); default: detected from the data",
    )
    fit.add_argument("--postures", type=int, metavar="K", help="mean-performance length (default: from data)")
    fit.add_argument(
        "--exclude-root",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="leave the root's translation and orientation out of the posture (default: yes)",
    )
    fit.add_argument(
        "--exclude",
        action="append",
        metavar="REGEX",
        help="leave DOFs matching REGEX out of the posture (repeatable; replaces the default "
        "hand|finger|thumb)",
    )
    fit.add_argument(
        "--n-sigma", type=_positive_float, default=2.0, help="acceptance width in sigma (2; auto: validated)"
    )
    fit.add_argument("--alpha", type=float, help="fix the velocity smoothing alpha instead of fitting it")
    fit.add_argument("--max-iter", type=int, default=30, help="most synchronisation iterations (30)")
    _add_skip_first(fit)
    fit.add_argument(
        "--validate",
        action="store_true",
        help="also measure, for each performance, how often a model fitted without it accepts its frames",
    )
    fit.add_argument("--quiet", action="store_true", help="no progress bars")
    add_runtime_options(fit)
    fit.set_defaults(func=_fit)

    inspect = commands.add_parser(
        "inspect",
        help="summary and plots of an action model",
        description="Print a summary of an action model and save the plots of Rius Fig. 1 (first aSpace "
        "dimensions of the training performances before and after synchronisation, mean +- 3 sigma) and the "
        "explained variance to DIR.",
    )
    inspect.add_argument("model", metavar="MODEL.npz", help="action model written by 'fit'")
    inspect.add_argument("--out", required=True, metavar="DIR", help="folder for the PNG files")
    inspect.add_argument("--dims", type=int, default=4, help="aSpace dimensions to plot (4)")
    add_runtime_options(inspect)
    inspect.set_defaults(func=_inspect)

    dyn = commands.add_parser(
        "fit-dynamics",
        help="mocap CSVs -> learned per-DOF step stds and constant-velocity alpha (.npz)",
        description="Learn per-DOF random-walk step stds (1.4826 x median |step|) and the constant-velocity "
        "alpha of Rius eq. 3 from mocap CSVs of a skeleton, and save them as .npz for "
        "'python -m torchpf track --dynamics FILE.npz'.",
    )
    dyn.add_argument("files", nargs="+", metavar="FILE.csv", help="performances (mocap CSV)")
    dyn.add_argument("--skeleton", required=True, metavar="S.urdf", help="skeleton the CSVs must match")
    dyn.add_argument("--out", required=True, type=Path, metavar="DYN.npz", help="output file")
    dyn.add_argument(
        "--fps", type=_positive_float, help="rate of the statistics (track at it); default: the files' rate"
    )
    dyn.add_argument("--alpha", type=float, help="fix the velocity smoothing alpha instead of fitting it")
    _add_skip_first(dyn)
    add_runtime_options(dyn)
    dyn.set_defaults(func=_fit_dynamics)

    lim = commands.add_parser(
        "fit-limits",
        help="mocap CSVs -> the skeleton with joint limits from their range of motion (.urdf)",
        description="Learn per-DOF joint limits from the range of motion of mocap CSVs of a skeleton (the "
        "shortest arc holding every frame, widened by --margin; the root's DOFs and prismatic ones keep "
        "theirs) and write the skeleton with them as URDF for "
        "'python -m torchpf track --skeleton FILE.urdf'. Learn them from the actions you will track.",
    )
    lim.add_argument("files", nargs="+", metavar="FILE.csv", help="performances (mocap CSV)")
    lim.add_argument("--skeleton", required=True, metavar="S.urdf", help="skeleton the CSVs must match")
    lim.add_argument("--out", required=True, type=Path, metavar="LIMITED.urdf", help="output file")
    lim.add_argument(
        "--margin", type=float, default=0.15, metavar="RAD", help="widening of each range on each side (0.15)"
    )
    _add_skip_first(lim)
    add_runtime_options(lim)
    lim.set_defaults(func=_fit_limits)

    export = commands.add_parser(
        "export",
        help="track / mocap CSV -> BVH (Blender, MotionBuilder)",
        description="Write a mocap CSV of a skeleton (e.g. the output of 'python -m torchpf track') as a BVH "
        "file: y up, one joint per body joint, 6-channel ROOT, Frame Time from the CSV's time column. DOFs "
        "along coordinate axes become one channel each; other joints are re-decomposed into Euler angles.",
    )
    export.add_argument("track", metavar="TRACK.csv", help="mocap CSV in the skeleton's DOF names")
    export.add_argument("--skeleton", required=True, metavar="S.urdf", help="skeleton of the track")
    export.add_argument("--out", required=True, type=Path, metavar="OUT.bvh", help="output BVH file")
    export.add_argument(
        "--scale",
        type=_positive_float,
        default=1.0,
        help="metres per file unit (CMU: 0.056444; default 1: the file is in metres)",
    )
    export.add_argument("--fps", type=_positive_float, help="frame rate when the CSV has no time column")
    export.add_argument(
        "--euler-order", default="ZXY", help="channel order of re-decomposed joints (default ZXY)"
    )
    add_runtime_options(export)
    export.set_defaults(func=_export)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 bad input, 130 interrupted)."""
    parser = build_parser()
    args = parser.parse_args(argv)  # exits with status 2 and a usage line on malformed arguments
    # MocapFormatError's message names file, line and column; an OSError prints as "path: reason"
    return run_command(PROG, args, args.func)


if __name__ == "__main__":
    sys.exit(main())
