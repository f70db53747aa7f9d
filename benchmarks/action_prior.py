"""Do learned priors pay off on people they were not trained on? Random walk vs the action model's priors on
the foreign renderer, at equal likelihood evaluations (issue 14; Rius et al. Fig. 3).

    python -m benchmarks.action_prior [--rw 500 2500 10000] [--learned 500 2000] [--seeds 3] [--frames 30]
        [--test 35_02:walk 35_30:walk 35_24:run 35_26:run] [--filter auto]
        [--plot benchmarks/figures/action_prior.png] [--threads 1]

Set-up (printed at the start of the run):

* *Action models*: the walk model is fitted (:mod:`training.fit`, ``n_components="auto"``: D and n_sigma by
  leave-one-performer-out validation) on the CMU walks of subjects 07, 08 and 16 (``../shared/mocap/cmu``;
  frame 0, a rest pose, dropped) at ``--fps``; the validation curve is printed. The bank's run model comes
  from the one run of a training subject (16_46, D = 6, n_sigma = 4; one performer: no validation).
* *Test sequences*: held-out subject-35 clips (``--test CLIP:ACTION``, default all four: the walks 35_02
  and 35_30, the runs 35_24 and 35_26), rendered by the foreign renderer (:mod:`benchmarks.foreign`: a body
  the tracker's capsules have never seen, ``--defects`` noisy masks, 3 cameras placed to see all
  ``--frames`` frames, so a longer cut shows a smaller person) at ``--fps``, on the clip's own skeleton;
  never drawn with :mod:`torchpf.synth`.
* *Priors*, each in :class:`torchpf.Tracker` with the default bidirectional silhouette likelihood and the
  ``--filter`` (default ``auto``, ``track``'s: the hybrid, whose refinement an action model keeps in its
  aSpace, :class:`priors.action.ActionSubspace`; ``n_particles`` is the likelihood evaluations per frame):
  ``random_walk`` (the structural random walk, the tracker's default, at ``--rw`` evaluations),
  ``rius`` (eq. 6 0/1 rejection around that random walk), ``soft`` (the soft aSpace prior),
  ``proposal`` (:class:`priors.action.ActionProposal`, phase advance along ĝ with its p/q correction) and
  ``bank`` (:class:`priors.bank.ActionBank` of the walk and run models, soft mode, switching 0.05 per
  frame), at ``--learned`` evaluations.
* *Figures* per clip, prior and N, mean over ``--seeds`` (with the seeds' standard deviation of the MPJPE):
  MPJPE (mm), failure rate (Fontmarty eq. 6, share of (frame, joint) errors > 25 cm), mean ESS, seconds per
  frame, for ``rius``/``soft`` the mean share of particles the model accepts and the frames that fell back to
  the plain dynamics, and for ``bank`` the share of frames whose action posterior names the clip's action.

The run ends with the comparison of the issue (the best learned prior at the smallest ``--learned`` N
against the random walk at each ``--rw`` N, per clip and over all clips) and writes the plot (MPJPE against
N per prior, one panel per clip) and the rows as JSON beside it.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from priors.action import ActionProposal
from priors.bank import ActionBank
from priors.factories import action as action_prior
from priors.factories import random_walk
from torchpf import metrics
from torchpf.tracker import Tracker
from training.fit import ActionModelFitter
from training.mocap import CMU_SCALE, bvh_motion, read_bvh

CMU = Path(__file__).resolve().parents[1].parent / "shared" / "mocap" / "cmu"
FIGURE = Path(__file__).resolve().parent / "figures" / "action_prior.png"
TRAIN = ("07_01", "07_06", "08_09", "08_10", "16_21", "16_31")
PRIORS = ("random_walk", "rius", "soft", "proposal", "bank")


def fit_walk_model(cmu: Path, fps: float, components, progress: bool = False):
    """The walk model of subjects 07, 08, 16 and its fitter (``validation_curve_`` for ``"auto"``)."""
    train = [bvh_motion(read_bvh(cmu / f"{c}.bvh"), CMU_SCALE)[1:] for c in TRAIN]
    fitter = ActionModelFitter(n_components=components, action="walk", fps=fps, progress=progress).fit(train)
    return fitter.model_, fitter


def fit_run_model(cmu: Path, fps: float, components: int = 6, n_sigma: float = 4.0):
    """A run model from the one run of a training subject (16_46); one performer: no validation."""
    run = [bvh_motion(read_bvh(cmu / "16_46.bvh"), CMU_SCALE)[1:]]
    return ActionModelFitter(n_components=components, n_sigma=n_sigma, action="run", fps=fps).fit(run).model_


def build_prior(name: str, skel, model, fps: float, others=()):
    """``(dynamics, proposal)`` of one prior for ``skel`` at ``fps``; ``bank`` switches between ``model``
    and the action models ``others``."""
    if name == "random_walk":
        return random_walk(skel, fps=fps), None
    if name in ("rius", "soft"):
        return action_prior(skel, model=model, fps=fps, mode=name), None
    if name == "proposal":
        dyn = random_walk(skel, fps=fps)
        return dyn, ActionProposal(model, dyn, fps=fps, skeleton=skel)
    if name == "bank":
        return ActionBank([model, *others], random_walk(skel, fps=fps), fps=fps, skeleton=skel), None
    raise ValueError(f"unknown prior {name!r}; choose from {PRIORS}")


def run_one(
    seq,
    name: str,
    model,
    n: int,
    seed: int,
    filter_name: str,
    fps: float,
    others=(),
    action: str | None = None,
) -> dict[str, float]:
    """Track ``seq`` (a :class:`benchmarks.foreign.ForeignSequence` of ``action``) once; the figures of one
    cell."""
    skel = seq.skeleton
    dyn, proposal = build_prior(name, skel, model, fps, others)
    tracker = Tracker(
        skel, seq.cameras, dynamics=dyn, proposal=proposal, filter=filter_name, n_particles=n, fps=fps,
        progress=False,
    )  # fmt: skip
    result = tracker.track(str(seq.path), seed=seed)
    truth = skel.fk(seq.angles.to(torch.float64))
    est = (result.skeleton or skel).fk(result.angles)  # the body track fitted to frame 0, if it did
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
    if "action_posterior" in result.stats and action is not None:
        labels = [dyn.actions[int(i)] for i in result.stats["action_posterior"].argmax(-1)]
        out["right_action"] = float(np.mean([a == action for a in labels]))
    return out


def plot(rows: list[dict], path: Path) -> None:
    """MPJPE against evaluations per frame for each prior, one panel per clip (seed sd as error bars)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clips = list(dict.fromkeys(r["clip"] for r in rows))
    fig, axes = plt.subplots(1, len(clips), figsize=(5.5 * len(clips), 4.2), squeeze=False)
    for ax, clip in zip(axes[0], clips, strict=True):
        for name in PRIORS:
            cells = sorted(
                (r["n"], r["mpjpe_mm"], r["mpjpe_sd"])
                for r in rows
                if r["clip"] == clip and r["prior"] == name
            )
            if not cells:
                continue
            n, e, sd = (np.array(v) for v in zip(*cells, strict=True))
            style = {"lw": 2.5, "color": "k"} if name == "random_walk" else {"marker": "o"}
            ax.errorbar(n, e, yerr=sd, capsize=3, label=name, **style)
        ax.set_xscale("log")
        ax.set_xlabel("likelihood evaluations per frame (N)")
        ax.set_ylabel("MPJPE (mm)")
        action = next(r["action"] for r in rows if r["clip"] == clip)
        ax.set_title(f"{clip} ({action}), held-out subject 35")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def compare(rows: list[dict], n0: int) -> None:
    """Print the issue's comparison: best learned prior at ``n0`` against the random walk at each N."""
    clips = list(dict.fromkeys(r["clip"] for r in rows))
    groups = [(c, [r for r in rows if r["clip"] == c]) for c in clips]
    if len(clips) > 1:  # the mean over clips, per (prior, N)
        keys = list(dict.fromkeys((r["prior"], r["n"]) for r in rows))
        mean = [
            {
                "prior": p,
                "n": n,
                "mpjpe_mm": float(np.mean([r["mpjpe_mm"] for r in rows if (r["prior"], r["n"]) == (p, n)])),
            }
            for p, n in keys
        ]
        groups.append(("all clips", mean))
    for label, cells in groups:
        learned = [(r["mpjpe_mm"], r["prior"]) for r in cells if r["n"] == n0 and r["prior"] != "random_walk"]
        if not learned:
            continue
        best, which = min(learned)
        rw = [(r["n"], r["mpjpe_mm"]) for r in cells if r["prior"] == "random_walk"]
        beaten = [n for n, e in rw if best <= e]
        print(
            f"{label}: best learned prior at N={n0}: {which} {best:.1f} mm; random walk "
            + ", ".join(f"N={n}: {e:.1f} mm" for n, e in rw)
            + "; no better up to "
            + (f"N={max(beaten)}" if beaten else "none of them")
        )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cmu", type=Path, default=CMU, help="folder of the CMU BVH clips")
    ap.add_argument(
        "--test",
        nargs="+",
        default=["35_02:walk", "35_30:walk", "35_24:run", "35_26:run"],
        help="held-out clips CLIP:ACTION (subject 35)",
    )
    ap.add_argument("--rw", type=int, nargs="+", default=[500, 2500, 10000], help="random-walk evaluations")
    ap.add_argument("--learned", type=int, nargs="+", default=[500, 2000], help="learned-prior evaluations")
    ap.add_argument("--priors", nargs="+", default=list(PRIORS[1:]), choices=PRIORS[1:])
    ap.add_argument("--frames", type=int, default=30, help="frames tracked (at --fps)")
    ap.add_argument("--fps", type=float, default=30.0, help="tracking and model frame rate")
    ap.add_argument("--components", default="auto", help="aSpace dimension D or 'auto'")
    ap.add_argument("--defects", default="noisy", help="foreign-renderer mask defects preset")
    ap.add_argument(
        "--filter", default="auto", help="filter (default: track's; n_particles = evaluations per frame)"
    )
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument(
        "--plot",
        type=lambda s: Path(s) if s else None,
        default=FIGURE,
        help="PNG of MPJPE against N (rows as .json beside); '' for none",
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
    others = [fit_run_model(args.cmu, args.fps)] if "bank" in args.priors else []
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.test:
            clip, _, truth_action = spec.partition(":")
            seq = build_sequence(
                args.cmu / f"{clip}.bvh", Path(tmp) / clip, defects=args.defects, fps=args.fps,
                frames=args.frames,
            )  # fmt: skip
            accept = float(model.accept_probability(seq.angles.to(torch.float64)).mean())
            print(
                f"test {clip} ({truth_action or '?'}): {len(seq.angles)} frames, {args.defects} masks; "
                f"the walk model's eq. 6 accepts the truth p={accept:.2f}"
            )
            # cheapest first, so that a run cut short has the comparison at small N
            cells = sorted(
                [("random_walk", n) for n in args.rw] + [(p, n) for p in args.priors for n in args.learned],
                key=lambda cell: cell[1],
            )
            for name, n in cells:
                runs = [
                    run_one(seq, name, model, n, s, args.filter, args.fps, others, truth_action or None)
                    for s in range(args.seeds)
                ]
                mean = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
                mean["mpjpe_sd"] = float(np.std([r["mpjpe_mm"] for r in runs]))
                rows.append({"clip": clip, "action": truth_action, "prior": name, "n": n, **mean})
                extra = (
                    f" accepted {100 * mean['accepted']:5.1f}% fallback {100 * mean['fallback']:5.1f}%"
                    if "accepted" in mean
                    else ""
                )
                if "right_action" in mean:
                    extra += f" right action {100 * mean['right_action']:5.1f}%"
                print(
                    f"{clip} {name:>11} N={n:>6}: MPJPE {mean['mpjpe_mm']:6.1f} "
                    f"± {mean['mpjpe_sd']:4.1f} mm  failure {100 * mean['failure']:5.1f}%  "
                    f"ESS {mean['ess']:7.1f}  {mean['s_per_frame']:.2f} s/frame" + extra,
                    flush=True,
                )
    print()
    print(
        "| clip | prior | N | MPJPE (mm) | failure (%) | ESS | s/frame | accepted (%) | fallback (%) "
        "| right action (%) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")

    def pct(m, key):
        return f"{100 * m[key]:.1f}" if key in m else "-"

    for m in rows:
        print(
            f"| {m['clip']} | {m['prior']} | {m['n']} | {m['mpjpe_mm']:.1f} ± {m['mpjpe_sd']:.1f} | "
            f"{100 * m['failure']:.1f} | {m['ess']:.1f} | {m['s_per_frame']:.2f} | {pct(m, 'accepted')} | "
            f"{pct(m, 'fallback')} | {pct(m, 'right_action')} |"
        )
    compare(rows, min(args.learned))
    bank = [m["right_action"] for m in rows if "right_action" in m]
    if bank:
        print(
            f"action posterior: right action on {100 * float(np.mean(bank)):.1f}% of frames (all bank runs)"
        )
    if args.plot:
        plot(rows, args.plot)
        args.plot.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
        print(f"wrote {args.plot} and {args.plot.with_suffix('.json')}")
    print(f"total {time.perf_counter() - t0:.0f}s")


if __name__ == "__main__":
    main()
