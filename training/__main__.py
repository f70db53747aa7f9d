"""Command line of the training package: ``python -m training <command> ...``.

Commands::

    python -m training convert FILE.bvh --scale S --out-dir DIR    # -> DIR/skeleton.urdf + DIR/FILE.csv

``convert`` turns a BVH file into a torchpf skeleton (URDF, z up, metres) and a mocap CSV of its angle
tracks in the skeleton's ``dof_names`` order (see :mod:`training.mocap`). Bad input ends with a one-line
``error:`` message on stderr and exit status 2. Each command is one subparser with its own ``--help``;
more commands (``fit``) plug in the same way through :func:`build_parser`.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

PROG = "python -m training"


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def _convert(args: argparse.Namespace) -> int:
    # Imported here so that `--help` answers without loading torch.
    from torchpf.io import write_text_atomic
    from torchpf.skeleton import Skeleton
    from training.mocap import bvh_motion, bvh_to_urdf, read_bvh, save_csv

    bvh = read_bvh(args.file)
    urdf = bvh_to_urdf(bvh, args.scale)
    skel = Skeleton.from_urdf(urdf)
    motion = bvh_motion(bvh, args.scale, dof_names=skel.dof_names)
    out = Path(args.out_dir)
    urdf_path, csv_path = out / "skeleton.urdf", out / f"{Path(args.file).stem}.csv"
    write_text_atomic(urdf_path, urdf)
    save_csv(csv_path, motion)
    print(
        f"wrote {urdf_path} ({len(skel.joint_names)} joints, {len(skel.dof_names)} DOFs) and {csv_path} "
        f"({motion.n_frames} frames at {motion.fps:.6g} fps)"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``python -m training`` parser; each subcommand sets ``func(args) -> exit status``."""
    parser = argparse.ArgumentParser(prog=PROG, description="Mocap conversion and action-model training.")
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
        default=1.0,
        help="metres per file unit (CMU clips: 0.056444; default 1)",
    )
    convert.add_argument("--out-dir", required=True, metavar="DIR", help="output folder (created if missing)")
    convert.set_defaults(func=_convert)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)  # exits with status 2 and a usage line on malformed arguments
    try:
        return args.func(args)
    except OSError as e:  # missing file, unwritable folder: "path: reason" rather than "[Errno 2] ..."
        where = f"{e.filename}: " if e.filename is not None else ""
        print(f"{PROG} {args.command}: error: {where}{e.strerror or e}", file=sys.stderr)
    except ValueError as e:  # MocapFormatError included: its message names file, line and column
        message = " ".join(str(e).split())  # one line, whatever the message
        print(f"{PROG} {args.command}: error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
