"""Hauberg's claim, reproduced: data-driven importance distributions vs the angular prior (Hauberg §6).

    python -m benchmarks.importance [--particles 25 50 150 300 500] [--runs 2] [--frames 10] [--step 8]

Sequence: the real CMU walk ``35_02.bvh`` (``../shared/mocap/cmu``; frame 0 is a rest pose and is skipped),
whose angles drive ``torchpf/assets/human.urdf`` directly, walked in place (the root keeps its first
horizontal position, like the paper's subject standing in front of the camera; a zero-mean spatial prior
cannot follow a 1.4 m/s translation), subsampled every ``--step`` frames (120 fps / 8 = 15 fps).
Observations from :func:`torchpf.synth.synthesize`: silhouettes (80x60) from a front and a side camera, and
a point cloud from a depth sensor at the front camera (Hauberg's stereo camera), subsampled to at most
``--points`` points. Likelihood: the point-cloud model of Hauberg eq. 15 on half-capsules facing the sensor
(:class:`torchpf.likelihoods.PointCloudLikelihood`) with ``σ = --lik-sigma``; a much sharper one makes every
filter's ESS collapse to ~1 (nothing left to compare). Finger, thumb and toe DOFs are frozen at the first
frame (joint positions hardly constrain them). All filters start from the true first pose and resample
every frame (SIR).

Importance distributions (the filter's dynamics in brackets):

* ``angular``: the angular prior itself, Hauberg eq. 3 (:class:`priors.AngularRandomWalk`, Fontmarty Table 5
  std rescaled to the frame rate), bootstrap weights;
* ``projected``: the projected prior of eq. 6 on its own (reference: same prior as the two below, no data);
* ``silhouette``: eq. 12 (:class:`priors.SilhouetteGuided`) [projected prior];
* ``depth``: eq. 13-14 (:class:`priors.DepthGuided`) [projected prior].

Weights follow the paper's approximation (the correction factor of eq. 2 treated as constant). Reported per
method and N (mean ± sd over ``--runs`` runs): tracking error (mean 3-D joint error of the weighted mean
joint positions, cm), time-averaged effective number of samples ``1 / Σ w²`` (Hauberg eq. 17 with squared
weights, Brubaker eq. 18) before resampling, time per frame, and, for the guided proposals, mean rejections
per joint. The paper: silhouette 1.6-2.2x, depth 2.3-3.6x the effective samples of the angular prior, at
about 10 % extra time. Runs single-threaded by default (``--threads``): on a small shared CPU the
second intra-op thread makes the IK's many small tensor operations several times slower.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from priors.motion import AngularRandomWalk, ProjectedGaussian
from priors.proposals import DepthGuided, SilhouetteGuided
from priors.table5 import table5_sigma
from torchpf import Skeleton, ik
from torchpf.assets import path
from torchpf.camera import look_at
from torchpf.filters import ParticleFilter
from torchpf.kinematics.jacobian import tree_jacobian
from torchpf.likelihoods import PointCloudLikelihood
from torchpf.observations import Frame, PointCloud
from torchpf.synth import synthesize

CLIP = Path(__file__).resolve().parents[2] / "shared" / "mocap" / "cmu" / "35_02.bvh"
FROZEN = ["Finger", "Thumb", "HandIndex", "ToeBase"]


class _Recording:
    """Proposal wrapper that keeps the mean rejections per joint of every draw (benchmark bookkeeping)."""

    def __init__(self, proposal):
        self.proposal, self.rejections = proposal, []

    def sample(self, state, obs, generator=None):
        d = self.proposal.draw(state, obs, generator)
        self.rejections.append(d.rejections.float().mean().item())
        return d.x, d.log_q


def _sequence(skel: Skeleton, frames: int, step: int, start: int, n_points: int):
    from training.mocap import load_bvh

    if not CLIP.is_file():
        raise SystemExit(f"CMU clip not found: {CLIP}")
    _, motion = load_bvh(CLIP, scale=0.056444)
    ang = skel.clamp(motion.select(skel.dof_names).angles[1:])  # frame 0 of a CMU clip is a rest pose
    truth = ang[start : start + step * (frames + 1) : step][: frames + 1].clone()
    # In place, like the paper's subject standing in front of the camera: the root translation DOFs that move
    # the root horizontally (BVH is y-up: X and Z) keep their first value; the vertical bob, the pelvis
    # rotations and all limb motion stay.
    jac = tree_jacobian(skel, truth[0])[0]  # (3, D) at the root joint
    for name in ("Hips_Xposition", "Hips_Yposition", "Hips_Zposition"):
        d = skel.dof_names.index(name)
        if jac[2, d].abs() < 0.5:
            truth[:, d] = truth[0, d]
    root = skel.fk(truth)[:, 0]
    c = root.mean(0).tolist()
    cams = [
        look_at((c[0], c[1] - 4.0, 1.3), (c[0], c[1], 0.9), width=160, height=120, fov_deg=65, name="front"),
        look_at((c[0] + 4.0, c[1], 1.3), (c[0], c[1], 0.9), width=160, height=120, fov_deg=65, name="side"),
    ]
    seq = synthesize(skel, truth, cams, depth_camera=cams[0], mask_size=(80, 60), seed=0)
    obs = []
    for t in range(len(seq)):
        f = seq.frame(t)
        pts = f.points.points
        if pts.shape[0] > n_points:
            pts = pts[torch.linspace(0, pts.shape[0] - 1, n_points).long()]
        obs.append(Frame(silhouettes=f.silhouettes, points=PointCloud(pts)))
    return truth.float(), cams, obs


def _run(skel, method, n, truth, cams, obs, fps, joint_sigma, lik_sigma, seed, ik_iters=None):
    D = len(skel.dof_names)
    free = ik.frozen_mask(skel, FROZEN)
    sig = table5_sigma(skel, fps=fps) * free
    lik = PointCloudLikelihood(skel, sigma=lik_sigma, view_point=cams[0])
    ik_options = {"free": free} if ik_iters is None else {"free": free, "iters": ik_iters}
    projected = ProjectedGaussian(skel, joint_sigma, ik_options=ik_options)
    proposal = None
    if method == "angular":
        dynamics = AngularRandomWalk(sig, skel.lower, skel.upper)
    else:
        dynamics = projected
        if method == "silhouette":
            proposal = _Recording(SilhouetteGuided(skel, cams, joint_sigma, prior=projected, dilate_px=1))
        elif method == "depth":
            proposal = _Recording(DepthGuided(skel, cams, joint_sigma, prior=projected, dilate_px=1))
    pf = ParticleFilter(dynamics, lik, proposal, n_particles=n, ess_threshold=1.0, progress=False)
    g = torch.Generator().manual_seed(seed)
    state = pf.init(truth[:1].expand(n, D).clone())
    true_joints = skel.fk(truth)
    errs, ess, times = [], [], []
    for t in range(1, truth.shape[0]):
        t0 = time.perf_counter()
        state = pf.step(state, obs[t], generator=g)
        times.append(time.perf_counter() - t0)
        ess.append(state.ess().item())
        w = state.weights()
        est = (w[:, None, None] * skel.fk(state.particles)).sum(0)
        errs.append((est - true_joints[t]).norm(dim=-1).mean().item())
    rej = statistics.mean(proposal.rejections) if proposal is not None else float("nan")
    return statistics.mean(errs), statistics.mean(ess), statistics.mean(times), rej


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--particles", type=int, nargs="+", default=[25, 50, 150, 300, 500])
    ap.add_argument("--methods", nargs="+", default=["angular", "projected", "silhouette", "depth"])
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--step", type=int, default=8, help="clip subsampling (120 fps / step)")
    ap.add_argument("--start", type=int, default=60, help="first clip frame used")
    ap.add_argument("--points", type=int, default=100, help="at most this many depth points")
    ap.add_argument("--joint-sigma", type=float, default=0.03, help="Σ_l = joint_sigma² I (m)")
    ap.add_argument("--lik-sigma", type=float, default=0.1, help="σ of the point-cloud likelihood (m)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch's default)")
    ap.add_argument(
        "--ik-iters",
        type=int,
        default=None,
        help="IK iterations of the projection (default: the prior's, 3)",
    )
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    skel = Skeleton.from_urdf(path("human.urdf"))
    fps = 120.0 / args.step
    t0 = time.perf_counter()
    truth, cams, obs = _sequence(skel, args.frames, args.step, args.start, args.points)
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    print(
        f"sequence: {CLIP.name} frames {args.start}..+{args.step * args.frames} every {args.step} "
        f"({fps:.0f} fps), {args.frames} tracked frames; human.urdf, {len(skel.dof_names)} DOFs "
        f"({int((~ik.frozen_mask(skel, FROZEN)).sum())} frozen); 2 silhouette cameras 80x60, "
        f"depth points <= {args.points}; synthesis {time.perf_counter() - t0:.1f} s"
    )
    results = {}
    for n in args.particles:
        for method in args.methods:
            runs = [
                _run(
                    skel,
                    method,
                    n,
                    truth,
                    cams,
                    obs,
                    fps,
                    args.joint_sigma,
                    args.lik_sigma,
                    1000 * r + n,
                    args.ik_iters,
                )
                for r in range(args.runs)
            ]
            results[method, n] = runs
            e = [r[0] for r in runs]
            print(f"  done {method:>10} N={n:<4} error {100 * statistics.mean(e):.1f} cm", flush=True)

    def ms(values, scale=1.0, fmt="{:.1f}"):
        m = statistics.mean(values) * scale
        s = statistics.stdev(values) * scale if len(values) > 1 else 0.0
        return (fmt + " ± " + fmt).format(m, s)

    print()
    print(
        f"{'method':>10} {'N':>4} {'error cm':>12} {'ESS':>14} {'ESS/N':>6} {'x angular':>9} "
        f"{'ms/frame':>14} {'x angular':>9} {'rej/joint':>9}"
    )
    for n in args.particles:
        base = results.get(("angular", n))
        for method in args.methods:
            runs = results[method, n]
            err, ess, tpf, rej = ([r[i] for r in runs] for i in range(4))
            ess_ratio = statistics.mean(ess) / statistics.mean([r[1] for r in base]) if base else float("nan")
            t_ratio = statistics.mean(tpf) / statistics.mean([r[2] for r in base]) if base else float("nan")
            print(
                f"{method:>10} {n:>4} {ms(err, 100):>12} {ms(ess):>14} {statistics.mean(ess) / n:>6.2f} "
                f"{ess_ratio:>9.2f} {ms(tpf, 1000, '{:.0f}'):>14} {t_ratio:>9.2f}"
                f" {statistics.mean(rej):>9.2f}"
            )


if __name__ == "__main__":
    main()
