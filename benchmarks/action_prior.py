"""Do learned priors pay off on people they were not trained on? Random walk vs the action model's priors on
the foreign renderer, at equal likelihood evaluations (issue 14; Rius et al. Fig. 3).

    python -m benchmarks.action_prior [--rw 500 2500 10000] [--learned 500 2000] [--seeds 3] [--frames 30]

Set-up (printed at the start of the run):

* *Action model*: fitted (:mod:`training.fit`, ``n_components="auto"``: D and n_sigma by
  leave-one-performer-out validation) on the CMU walks of subjects 07, 08 and 16 (``../shared/mocap/cmu``;
  frame 0, a rest pose, dropped) at ``--fps``; the validation curve is printed.
* *Test sequences*: held-out subject-35 clips (``--test``, default the walk 35_30), rendered by the foreign
  renderer (:mod:`benchmarks.foreign`: a body the tracker's capsules have never seen, ``--defects`` noisy
  masks, 3 cameras) at ``--fps``, ``--frames`` frames, on the clip's own skeleton; never drawn with
  :mod:`torchpf.synth`.
* *Priors*, each in :class:`torchpf.Tracker` with the default bidirectional silhouette likelihood and the
  ``--filter`` (default ``sir``, whose ``n_particles`` is the likelihood evaluations per frame):
  ``random_walk`` (the structural random walk, the tracker's default, at ``--rw`` evaluations),
  ``rius`` (eq. 6 0/1 rejection around that random walk), ``soft`` (the soft aSpace prior) and
  ``proposal`` (:class:`priors.action.ActionProposal`, phase advance along ĝ with its p/q correction), at
  ``--learned`` evaluations.
* *Figures* per prior and N, mean over ``--seeds``: MPJPE (mm), failure rate (Fontmarty eq. 6, share of
  (frame, joint) errors > 25 cm), mean ESS, seconds per frame, and for the action priors the mean share of
  particles the model accepts and the frames that fell back to the plain dynamics.

The run ends with the comparison of the issue: the best learned prior at the smallest ``--learned`` N
against the random walk at each ``--rw`` N.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from priors.action import ActionProposal
from priors.factories import action as action_prior
from priors.factories import random_walk
from torchpf import metrics
from torchpf.tracker import Tracker
from training.fit import ActionModelFitter
from training.mocap import CMU_SCALE, bvh_motion, read_bvh

CMU = Path(__file__).resolve().parents[1].parent / "shared" / "mocap" / "cmu"
TRAIN = ("07_01", "07_06", "08_09", "08_10", "16_21", "16_31")
PRIORS = ("random_walk", "rius", "soft", "proposal")


def fit_walk_model(cmu: Path, fps: float, components, progress: bool = False):
    """The walk model of subjects 07, 08, 16 and its fitter (``validation_curve_`` for ``"auto"``)."""
    train = [bvh_motion(read_bvh(cmu / f"{c}.bvh"), CMU_SCALE)[1:] for c in TRAIN]
    fitter = ActionModelFitter(n_components=components, action="walk", fps=fps, progress=progress).fit(train)
    return fitter.model_, fitter


def fit_run_model(cmu: Path, fps: float, components: int = 6, n_sigma: float = 4.0):
    """A run model from the one run of a training subject (16_46); one performer: no validation."""
    run = [bvh_motion(read_bvh(cmu / "16_46.bvh"), CMU_SCALE)[1:]]
    return ActionModelFitter(n_components=components, n_sigma=n_sigma, action="run", fps=fps).fit(run).model_


def recognise(seq, models, n: int, seed: int, filter_name: str, fps: float) -> tuple[list[str], dict]:
    """Track ``seq`` with an :class:`priors.bank.ActionBank` of ``models``: per-frame action labels (argmax
    of the posterior) and the figures of :func:`run_one`."""
    from priors.bank import ActionBank

    skel = seq.skeleton
    bank = ActionBank(models, random_walk(skel, fps=fps), fps=fps, skeleton=skel)
    tracker = Tracker(
        skel, seq.cameras, dynamics=bank, filter=filter_name, n_particles=n, fps=fps, progress=False
    )
    result = tracker.track(str(seq.path), seed=seed)
    truth, est = skel.fk(seq.angles.to(torch.float64)), skel.fk(result.angles)
    labels = [bank.actions[int(i)] for i in result.stats["action_posterior"].argmax(-1)]
    return labels, {"mpjpe_mm": 1000 * float(metrics.mpjpe(truth, est))}


def build_prior(name: str, skel, model, fps: float):
    """``(dynamics, proposal)`` of one prior for ``skel`` at ``fps``."""
    if name == "random_walk":
        return random_walk(skel, fps=fps), None
    if name in ("rius", "soft"):
        return action_prior(skel, model=model, fps=fps, mode=name), None
    if name == "proposal":
        dyn = random_walk(skel, fps=fps)
        return dyn, ActionProposal(model, dyn, fps=fps, skeleton=skel)
    raise ValueError(f"unknown prior {name!r}; choose from {PRIORS}")


def run_one(seq, name: str, model, n: int, seed: int, filter_name: str, fps: float) -> dict[str, float]:
    """Track ``seq`` (a :class:`benchmarks.foreign.ForeignSequence`) once; the figures of one cell."""
    skel = seq.skeleton
    dyn, proposal = build_prior(name, skel, model, fps)
    tracker = Tracker(
        skel, seq.cameras, dynamics=dyn, proposal=proposal, filter=filter_name, n_particles=n, fps=fps,
        progress=False,
    )  # fmt: skip
    result = tracker.track(str(seq.path), seed=seed)
    truth = skel.fk(seq.angles.to(torch.float64))
    est = skel.fk(result.angles)
    out = {
        "mpjpe_mm": 1000 * float(metrics.mpjpe(truth, est)),
        "failure": float(metrics.failure_rate(truth, est)),
        "ess": float(result.ess.mean()),
        "s_per_frame": result.seconds / len(result.angles),
        "evaluations": tracker.likelihood_evaluations,
    }
    if "action_accepted" in result.stats:
        out["accepted"] = float(result.stats["action_accepted"].float().mean())
        out["fallback"] = float(result.stats["action_fallback"].float().mean())
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cmu", type=Path, default=CMU, help="folder of the CMU BVH clips")
    ap.add_argument("--test", nargs="+", default=["35_30"], help="held-out clips (subject 35)")
    ap.add_argument("--rw", type=int, nargs="+", default=[500, 2500, 10000], help="random-walk evaluations")
    ap.add_argument("--learned", type=int, nargs="+", default=[500, 2000], help="learned-prior evaluations")
    ap.add_argument("--priors", nargs="+", default=list(PRIORS[1:]), choices=PRIORS[1:])
    ap.add_argument("--frames", type=int, default=30, help="frames tracked (at --fps)")
    ap.add_argument("--fps", type=float, default=30.0, help="tracking and model frame rate")
    ap.add_argument("--components", default="auto", help="aSpace dimension D or 'auto'")
    ap.add_argument("--defects", default="noisy", help="foreign-renderer mask defects preset")
    ap.add_argument("--filter", default="sir", help="filter (n_particles = evaluations per frame)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument(
        "--bank",
        nargs="*",
        metavar="CLIP:ACTION",
        help="also track these clips (e.g. 35_30:walk 35_24:run) with a walk + run ActionBank at the "
        "smallest "
        "--learned N and report how often the action posterior names the right action",
    )
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if not args.cmu.is_dir():
        raise SystemExit(f"error: CMU clips not found at {args.cmu} (pass --cmu)")
    from benchmarks.foreign import build_sequence

    t0 = time.perf_counter()
    components = args.components if args.components == "auto" else int(args.components)
    model, fitter = fit_walk_model(args.cmu, args.fps, components)
    if fitter.validation_curve_ is not None:
        print(fitter.validation_curve_.table())
    print(
        f"action model: walks {', '.join(TRAIN)} at {args.fps:g} fps: D={model.n_components}, "
        f"n_sigma={model.n_sigma:g}, K={model.n_postures}; fit {time.perf_counter() - t0:.0f}s"
    )
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for clip in args.test:
            seq = build_sequence(
                args.cmu / f"{clip}.bvh", Path(tmp) / clip, defects=args.defects, fps=args.fps,
                frames=args.frames,
            )  # fmt: skip
            accept = float(model.accept_probability(seq.angles.to(torch.float64)).mean())
            print(
                f"test {clip}: {len(seq.angles)} frames, {args.defects} masks; eq. 6 accepts the truth "
                f"p={accept:.2f}"
            )
            # cheapest first, so that a run cut short has the comparison at small N
            cells = sorted(
                [("random_walk", n) for n in args.rw] + [(p, n) for p in args.priors for n in args.learned],
                key=lambda cell: cell[1],
            )
            for name, n in cells:
                runs = [run_one(seq, name, model, n, s, args.filter, args.fps) for s in range(args.seeds)]
                mean = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
                rows.append((clip, name, n, mean))
                extra = (
                    f" accepted {100 * mean['accepted']:5.1f}% fallback {100 * mean['fallback']:5.1f}%"
                    if "accepted" in mean
                    else ""
                )
                print(
                    f"{clip} {name:>11} N={n:>6}: MPJPE {mean['mpjpe_mm']:6.1f} mm  failure "
                    f"{100 * mean['failure']:5.1f}%  ESS {mean['ess']:7.1f}  "
                    f"{mean['s_per_frame']:.2f} s/frame" + extra,
                    flush=True,
                )
    print()
    print("| clip | prior | N | MPJPE (mm) | failure (%) | ESS | s/frame | accepted (%) | fallback (%) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for clip, name, n, m in rows:
        acc = f"{100 * m['accepted']:.1f} | {100 * m['fallback']:.1f}" if "accepted" in m else "- | -"
        print(
            f"| {clip} | {name} | {n} | {m['mpjpe_mm']:.1f} | {100 * m['failure']:.1f} | {m['ess']:.1f} | "
            f"{m['s_per_frame']:.2f} | {acc} |"
        )
    n0 = min(args.learned)
    for clip in args.test:
        learned = [
            (m["mpjpe_mm"], name) for c, name, n, m in rows if c == clip and n == n0 and name != "random_walk"
        ]
        if not learned:
            continue
        best, which = min(learned)
        rw = [(n, m["mpjpe_mm"]) for c, name, n, m in rows if c == clip and name == "random_walk"]
        beaten = [n for n, e in rw if best <= e]
        print(
            f"{clip}: best learned prior at N={n0}: {which} {best:.1f} mm; the random walk is no better "
            "up to " + (f"N={max(beaten)}" if beaten else f"none of N={[n for n, _ in rw]}")
        )
    if args.bank:
        models = [model, fit_run_model(args.cmu, args.fps)]
        n0 = min(args.learned)
        with tempfile.TemporaryDirectory() as tmp:
            for spec in args.bank:
                clip, _, truth_action = spec.partition(":")
                seq = build_sequence(
                    args.cmu / f"{clip}.bvh", Path(tmp) / clip, defects=args.defects, fps=args.fps,
                    frames=args.frames,
                )  # fmt: skip
                for s in range(args.seeds):
                    labels, figures = recognise(seq, models, n0, s, args.filter, args.fps)
                    right = float(np.mean([a == truth_action for a in labels]))
                    print(
                        f"bank walk+run on {clip} ({truth_action}), N={n0}, seed {s}: right action on "
                        f"{100 * right:.0f}% of frames, MPJPE {figures['mpjpe_mm']:.1f} mm",
                        flush=True,
                    )
    print(f"total {time.perf_counter() - t0:.0f}s")


if __name__ == "__main__":
    main()
