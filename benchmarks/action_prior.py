"""Rius et al. Fig. 3: tracking error vs number of particles, 1st-order motion model with and without the
action constraint, on a held-out real walk seen through synthetic silhouettes.

    python -m benchmarks.action_prior [--particles 100 300 1000 3000 10000] [--frames 15] [--seeds 2]

Set-up (everything printed at the start of the run):

* *Action model*: fitted (:mod:`training.fit`) on the CMU walks of ``../shared/mocap/cmu`` except the test
  clip (subjects 07, 08, 16 and 35; frame 0, a rest pose, dropped), resampled to ``--fps``; α fixed to 0.5
  as in the paper's experiments, so that σ_φ is the constant-velocity residual at the α we track with.
  ``--components`` defaults to 8: with four training subjects, the paper's D = 13 accepts few frames of a new
  performance (the model then overfits, as Rius §4 warns); pass ``--components 13`` to see it.
* *Test sequence*: ``--frames`` frames (default 15 at 15 fps: one gait cycle) of the held-out walk
  ``--test`` (default 35_30) at ``--fps``, on that subject's own skeleton; ``--cameras`` cameras on a ring
  around the walk render clean silhouettes (:func:`torchpf.synth.synthesize`) at ``--size`` pixels.
* *Likelihood*: :class:`torchpf.likelihoods.SilhouetteLikelihood` (Fontmarty eq. 2; ``--likelihood overlap``
  for Rius eq. 7, four times slower) with 6 model points per capsule, finger/thumb capsules left out
  (sub-pixel at this resolution).
* *Filters*: :class:`torchpf.filters.ParticleFilter` (resampling when ESS < N/2) with the same
  constant-velocity prior (Rius eq. 3, α = 0.5, σ_φ from the model), once plain and
  once wrapped in :class:`priors.action.ActionConstrained` (eq. 6 rejection, at most 20 draws). Particles
  start at the true first pose with the true first velocity. The velocity of eq. 3 is, as in the paper,
  smoothed from the filter's estimates and shared by all particles (``--velocity particle``: each particle
  smooths its own displacements, which turns the diffusion into a random walk of the velocity).
* *Error*: per frame, the MMSE estimate against the truth: RMS over the 66 posture DOFs of the wrapped angle
  error (degrees; Rius report the MSE of the relative angles) and the mean 3D joint-position error (cm),
  averaged over frames 1..T-1 and over ``--seeds``.

Runtime is dominated by the likelihood: about ``frames x 2 x sum(particles)`` pose evaluations.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from priors.action import ActionConstrained
from priors.motion import ConstantVelocity
from torchpf.camera import camera_ring
from torchpf.filters import ParticleFilter
from torchpf.likelihoods import OverlapLikelihood, SilhouetteLikelihood
from torchpf.synth import synthesize
from training.align import resample
from training.fit import ActionModelFitter
from training.mocap import CMU_SCALE, bvh_motion, load_bvh, read_bvh

CMU = Path(__file__).resolve().parents[1].parent / "shared" / "mocap" / "cmu"
WALKS = ("07_01", "07_06", "08_09", "08_10", "16_21", "16_31", "35_02", "35_30")


def _posture_rmse_deg(estimates: torch.Tensor, truth: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(T,) RMS over the posture DOFs of the wrapped angle error, degrees."""
    diff = torch.remainder(estimates[:, index] - truth[:, index] + math.pi, 2 * math.pi) - math.pi
    return torch.rad2deg(diff.square().mean(-1).sqrt())


def _track(pf, dyn, observations, x0, v0, alpha, velocity, generator):
    """Run the filter frame by frame; returns estimates (T, D) and the mean share of particles eq. 6 accepts.

    ``velocity="estimate"`` is Rius' eq. 3: one velocity ``V_t = α V_{t-1} + (1-α)(φ̂_t - φ̂_{t-1})`` from the
    MMSE estimates, given to every particle; ``"particle"`` keeps each particle's own smoothed velocity.
    """
    state = pf.init(x0, extras={"velocity": v0.expand_as(x0).clone()})
    estimates, accepted, v = [x0[0]], [], v0
    for obs in observations[1:]:
        state = pf.step(state, obs, generator)
        estimates.append(state.mean())
        if isinstance(dyn, ActionConstrained):
            accepted.append(float(state.extras["accepted"].float().mean()))
        if velocity == "estimate":
            v = alpha * v + (1 - alpha) * (estimates[-1] - estimates[-2])
            state = state.replace(extras={"velocity": v.expand_as(state.particles).clone()})
    return torch.stack(estimates), (float(np.mean(accepted)) if accepted else float("nan"))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cmu", type=Path, default=CMU, help="folder of the CMU BVH clips")
    ap.add_argument("--test", default="35_30", help="held-out walk clip")
    ap.add_argument("--particles", type=int, nargs="+", default=[100, 300, 1000, 3000, 10000])
    ap.add_argument("--frames", type=int, default=15, help="frames tracked (at --fps)")
    ap.add_argument("--start", type=int, default=0, help="first frame of the test clip (at --fps)")
    ap.add_argument("--fps", type=float, default=15.0, help="tracking and model frame rate (CMU: 120)")
    ap.add_argument("--components", type=int, default=8, help="aSpace dimension D (Rius: 13)")
    ap.add_argument("--cameras", type=int, default=3)
    ap.add_argument("--size", type=int, nargs=2, default=[80, 60], metavar=("W", "H"))
    ap.add_argument("--likelihood", choices=["silhouette", "overlap"], default="silhouette")
    ap.add_argument("--sigma-scale", type=float, default=1.0, help="multiplies the fitted sigma_phi")
    ap.add_argument(
        "--velocity",
        choices=["estimate", "particle"],
        default="estimate",
        help="velocity of eq. 3 from the MMSE estimates (Rius) or per particle",
    )
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if not args.cmu.is_dir():
        raise SystemExit(f"error: CMU clips not found at {args.cmu} (pass --cmu)")

    # ---------------------------------------------------------------------------------- action model
    t0 = time.perf_counter()
    train = [bvh_motion(read_bvh(args.cmu / f"{s}.bvh"), CMU_SCALE)[1:] for s in WALKS if s != args.test]
    fitter = ActionModelFitter(n_components=args.components, action="walk", fps=args.fps, alpha=0.5).fit(
        train
    )
    model = fitter.model_
    print(
        f"action model: {len(train)} walks ({', '.join(m.name for m in train)}), D={model.n_components} "
        f"({100 * float(model.explained_variance_ratio.sum()):.1f}% variance), "
        f"K={model.n_postures} postures, "
        f"alpha={model.alpha}, fit {time.perf_counter() - t0:.1f}s"
    )

    # ---------------------------------------------------------------------------------- test sequence
    skel, motion = load_bvh(args.cmu / f"{args.test}.bvh", CMU_SCALE)
    if skel.dof_names != model.dof_names:
        raise SystemExit("error: the test clip's DOFs differ from the training clips'")
    angles = torch.from_numpy(resample(motion[1:].angles.numpy(), motion.fps, args.fps))
    truth = angles[args.start : args.start + args.frames]
    T = len(truth)
    hips = skel.fk(truth)[:, skel.joint_names.index("Hips")]
    centre = hips.mean(0).tolist()
    rig = camera_ring(
        args.cameras,
        radius=5.0,
        height=1.5,
        target=(centre[0], centre[1], 0.9),
        width=args.size[0],
        height_px=args.size[1],
        fov_deg=60.0,
    )
    seq = synthesize(skel, truth, rig, fps=args.fps, seed=0)
    observations = [seq.frame(t) for t in range(T)]
    joints = skel.joint_names
    bones = [
        c
        for c, (_, child) in enumerate(skel.bones)
        if not any(k in joints[child].lower() for k in ("finger", "thumb", "handindex"))
    ]
    Lik = SilhouetteLikelihood if args.likelihood == "silhouette" else OverlapLikelihood
    likelihood = Lik(skel, rig, bones=bones, n_body=4, n_cap=1)  # 6 model points per capsule
    truth_accept = float(model.accept_probability(truth).mean())
    print(
        f"test: {args.test} frames {args.start}..{args.start + T - 1} at {args.fps:g} fps "
        f"({hips[-1].sub(hips[0]).norm():.2f} m walked), "
        f"{args.cameras} cameras {args.size[0]}x{args.size[1]}, "
        f"{type(likelihood).__name__} on {len(bones)} capsules; eq. 6 accepts the true poses with p="
        f"{truth_accept:.2f}; torch threads {torch.get_num_threads()}"
    )

    # ---------------------------------------------------------------------------------- filters
    sigma = model.sigma_phi * args.sigma_scale
    index = model.posture_index
    v0 = (angles[args.start + 1] - angles[args.start]) if T > 1 else torch.zeros_like(truth[0])
    rows = []
    header = (
        f"{'N':>6} | {'1st order: RMSE deg':>19} {'joints cm':>9} {'s/frame':>7} | "
        f"{'+ action model: RMSE deg':>24} {'joints cm':>9} {'s/frame':>7} {'accepted':>8}"
    )
    print(header)
    print("-" * len(header))
    for n in args.particles:
        result = {}
        for name in ("plain", "action"):
            base = ConstantVelocity(sigma, alpha=model.alpha)
            dyn = base if name == "plain" else ActionConstrained(model, base)
            pf = ParticleFilter(dyn, likelihood, n_particles=n, progress=False)
            errs, cms, acc, secs = [], [], [], 0.0
            for seed in range(args.seeds):
                g = torch.Generator().manual_seed(1000 * seed + n)
                t1 = time.perf_counter()
                with torch.no_grad():
                    x0 = truth[:1].expand(n, -1).clone()
                    est, a = _track(pf, dyn, observations, x0, v0, model.alpha, args.velocity, g)
                secs += (time.perf_counter() - t1) / max(T - 1, 1)
                errs.append(_posture_rmse_deg(est, truth, index)[1:].mean())
                cms.append((skel.fk(est) - skel.fk(truth)).norm(dim=-1).mean(-1)[1:].mean() * 100)
                acc.append(a)
            result[name] = (float(np.mean(errs)), float(np.mean(cms)), secs / args.seeds, float(np.mean(acc)))
        (e0, c0, s0, _), (e1, c1, s1, a1) = result["plain"], result["action"]
        rows.append((n, e0, c0, e1, c1))
        print(f"{n:>6} | {e0:>19.2f} {c0:>9.2f} {s0:>7.2f} | {e1:>24.2f} {c1:>9.2f} {s1:>7.2f} {a1:>8.2f}")
    print(
        "RMSE: posture angles (66 DOFs, degrees); joints: mean 3D joint error; accepted: share of the "
        "frame's particles that eq. 6 accepts"
    )
    if len(rows) > 1:
        best_plain = rows[-1][1]
        match = next((n for n, _, _, e1, _ in rows if e1 <= best_plain), None)
        print(
            f"plain filter with {rows[-1][0]} particles: {best_plain:.2f} deg; the action-constrained filter "
            + (f"reaches it with {match} particles" if match else "does not reach it in this range")
        )
    print(f"total {time.perf_counter() - t0:.0f}s")


if __name__ == "__main__":
    main()
