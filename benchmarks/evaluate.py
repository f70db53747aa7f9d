"""Evaluation harness: the Fontmarty et al. protocol for particle-filter human motion trackers.

What it does
------------
Fontmarty, Danès & Lerasle ("Evaluations of particle filter based human motion visual trackers", §3.3-5)
compare CONDENSATION (SIR), QRS, PARTITIONED, PARTITIONED QRS and the APF on multi-camera silhouette
sequences, at **equal numbers of likelihood evaluations** per frame ``N in {100, 250, 500, 1000, 1500}`` and
over ``R`` runs of each stochastic filter, with four criteria and a ranking per criterion (their Tables 6-7).
This script runs that protocol with :class:`torchpf.Tracker`:

* sequences synthesised from real CMU mocap clips (``../shared/mocap/cmu``: a walk and a run, each rendered on
  the clip's own converted skeleton, i.e. the model fits the subject as in the paper's synthetic study) and
  from the embedded generator (``wave`` - the paper's "arm waving" - and ``walk`` on ``human.urdf``). Three
  cameras in a triangle around the subject (:func:`torchpf.camera.camera_ring`), low-resolution silhouettes
  with segmentation noise (random erosion/dilation and speckle). Frames are subsampled to ``--fps`` and the
  mean horizontal drift of the root is removed ("treadmill") so the body stays in view of the fixed cameras;
* the Fontmarty composite likelihood (silhouette ``sigma_s1 = 0.1`` + dual silhouette ``sigma_s2 = 0.07``, and
  optionally the skin-blob cue on the head and hands, ``sigma_skin = 5`` px) and a Gaussian random walk with
  the per-joint-group standard deviations of Fontmarty Table 5 (given at 5 Hz; a random walk's variance grows
  linearly in time, so they become ``std sqrt(5 / fps)`` per frame): by default the registered
  ``random_walk`` prior of the ``priors`` package (truncated to the joint limits, clavicles/fingers frozen),
  else (``--dynamics table5``) a plain Gaussian walk with :func:`priors.table5.table5_sigma`;
* every filter is initialised from the first ground-truth frame and gets the same budget ``N``: SIR/QRS run
  ``N`` particles, the APF 3 layers of ``N/3``, the partitioned filters ``M`` stages of ``N/M`` (``M = 5``:
  torso then each limb, :func:`torchpf.kinematics.body_partition`), the MCMC filter
  ``N / (1 + moves (L + 1))`` particles, each HMC move costing ``L + 1`` likelihood gradients (counted as
  evaluations; a gradient costs more wall time, which the time column shows).

Criteria (Fontmarty eq. 3-6, :mod:`torchpf.metrics`), over ``J`` evaluated joints, ``K`` frames and ``R``
runs, ``m_j^{t_k}`` the true and ``m_j^{k,r}`` the estimated (MMSE) position of joint ``j``::

    RMSE       (eq. 3)  1/J sum_j sqrt( 1/(K R) sum_k sum_r |m_j^{t_k} - m_j^{k,r}|^2 )
    bias       (eq. 4)  1/J sum_j | 1/K sum_k ( m_j^{t_k} - 1/R sum_r m_j^{k,r} ) |
    dispersion (eq. 5)  1/J sum_j sqrt( 1/(K R) sum_k sum_r |m_j^{k,r} - 1/R sum_r' m_j^{k,r'}|^2 )
    failure    (eq. 6)  1/(R J K) sum_{r,j,k} [ |m_j^{t_k} - m_j^{k,r}|^2 > T_failure^2 ],  T_failure = 0.25 m

The ``J`` joints are those of Fontmarty's model (pelvis, hips, knees, ankles, neck, head, shoulders, elbows,
wrists; ``--joints all`` takes every skeleton joint). All ``K`` tracked frames count, frame 0 included.

Ranks (Tables 6-7): in every (sequence, N) cell the filters are ranked per criterion (1 = lowest value; ties
share the mean rank); a filter's rank for a criterion is the rank of its mean cell rank, and the table is
sorted by the mean of its four criterion ranks. Values shown next to the ranks are means over the cells.

How to run
----------
::

    python -m benchmarks.evaluate           # default: 4 sequences, 5 filters, N 100 500, R 2 (minutes)
    python -m benchmarks.evaluate --quick   # smoke run (seconds)
    python -m benchmarks.evaluate --particles 100 500 1500 --runs 3 --frames 15
    python -m benchmarks.evaluate --full    # the paper's grid: N 100..1500, R 10, all 6 filters (hours)
    python -m benchmarks.evaluate --sequences cmu:16_46,generator:wave --filters apf,partitioned_qrs

Foreign renders (issue 11)
--------------------------
``--renderer foreign`` runs another protocol: every CMU clip rendered by :mod:`benchmarks.foreign` (a body
the tracker's model has never seen; clean and noisy masks, 30 fps, 3 cameras, 160x120), written as a
sequence directory and tracked by each named setup of :data:`FOREIGN_SETUPS` (``before``: the ``track``
defaults before issue 11, pinned; ``defaults``: the ``track`` defaults now; 500 evaluations per frame),
printing MPJPE, RMSE, failure rates, ESS and time per clip and averaged, one row per setup
("before/after")::

    python -m benchmarks.evaluate --renderer foreign                     # all 11 clips (a few minutes)
    python -m benchmarks.evaluate --renderer foreign --clips 07_01 --presets clean --frames 20
    python -m benchmarks.evaluate --renderer foreign --in-place --runs 3 --setups before,defaults
    python -m benchmarks.evaluate --renderer foreign --setups defaults,calibrated,auto   # issue 13: no truth

Outputs in ``--out`` (default ``out/evaluate``): ``table.md`` (printed too), ``results.csv`` (one row per
sequence x filter x N x run, then one ``aggregate`` row per sequence x filter x N), ``frames.csv`` (mean
joint error per frame and run), ``config.json``, and plots ``fig8_<seq>.png`` / ``fig8_all.png`` (criteria
vs N, like Fontmarty Fig. 8) and ``fig15_<seq>.png`` (error vs frame for each N per filter, failure rate vs
N in log scale, like Fig. 15).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from priors.table5 import table5_sigma
from torchpf import Skeleton, metrics
from torchpf.assets import path as asset_path
from torchpf.camera import camera_ring
from torchpf.distributions import DYNAMICS, make_dynamics
from torchpf.observations import DistanceMaps
from torchpf.proposals import GaussianRandomWalk
from torchpf.synth import SynthOptions, synthesize
from torchpf.tracker import Tracker

REPO = Path(__file__).resolve().parents[1]

FILTER_LABELS = {
    "sir": "CONDENSATION",
    "qrs": "QRS",
    "partitioned": "PARTITIONED",
    "partitioned_qrs": "PARTITIONED QRS",
    "apf": "APF",
    "mcmc": "MCMC",
}
FONTMARTY_FILTERS = ("sir", "qrs", "partitioned", "partitioned_qrs", "apf")
CMU_DIR = (REPO / ".." / "shared" / "mocap" / "cmu").resolve()
CMU_SCALE = 0.056444  # metres per CMU BVH unit
DEFAULT_ITEMS = {"cmu": ("07_01", "35_24"), "generator": ("wave", "walk")}  # a walk and a run; wave, walk

# The joints of Fontmarty's body model, on which the criteria are computed by default.
EVAL_JOINTS = (
    "Hips",
    "LeftUpLeg",
    "LeftLeg",
    "LeftFoot",
    "RightUpLeg",
    "RightLeg",
    "RightFoot",
    "Neck",
    "Head",
    "LeftArm",
    "LeftForeArm",
    "LeftHand",
    "RightArm",
    "RightForeArm",
    "RightHand",
)
# Criteria of Tables 6-7, in their column order: (result key, column title). All are "lower is better".
CRITERIA = (
    ("rmse", "Accuracy"),
    ("dispersion", "Dispersion"),
    ("failure_rate", "Failure rate"),
    ("bias", "Bias"),
)


# ================================================================================================ config
@dataclass
class EvalConfig:
    """Everything one evaluation depends on (written to ``config.json``)."""

    sequences: tuple[str, ...] = ("cmu", "generator")  # sources, or "source:item" (cmu:07_01, generator:wave)
    filters: tuple[str, ...] = FONTMARTY_FILTERS
    particles: tuple[int, ...] = (100, 500)  # likelihood evaluations per frame, N
    runs: int = 2  # R
    frames: int = 12  # K (a short clip gives fewer)
    fps: float = 15.0  # tracking frame rate; mocap is subsampled to it
    mask_size: tuple[int, int] = (80, 60)  # (width, height) of the silhouettes
    morph_px: int = 1  # segmentation noise: random erosion/dilation radius (px)
    speckle: float = 0.01  # segmentation noise: share of flipped pixels
    cues: tuple[str, ...] = ("silhouette", "dual_silhouette")  # + "skin"
    threshold: float = 0.25  # T_failure (m)
    # "random_walk" (the registered prior), "table5" (built here) or "auto" (the former when registered)
    dynamics: str = "auto"
    dynamics_scale: float = 1.0  # multiplies the Table 5 stds (after their 5 Hz -> fps rescaling)
    joints: str = "body"  # "body" (EVAL_JOINTS) or "all"
    mcmc_moves: int = 1
    mcmc_leapfrog: int = 3
    camera_radius: float = 4.0
    cmu_dir: str = str(CMU_DIR)
    seed: int = 0

    def __post_init__(self):
        self.sequences = tuple(self.sequences)
        self.filters = tuple(self.filters)
        self.particles = tuple(int(n) for n in self.particles)
        self.cues = tuple(self.cues)
        self.mask_size = tuple(int(v) for v in self.mask_size)
        unknown = [f for f in self.filters if f not in FILTER_LABELS]
        if unknown:
            raise ValueError(f"unknown filter(s) {unknown}; choose from {list(FILTER_LABELS)}")
        if not self.filters or not self.particles or self.runs < 1 or self.frames < 2:
            raise ValueError("need at least one filter, one N, runs >= 1 and frames >= 2")
        if min(self.particles) < 1:
            raise ValueError(f"particle budgets must be positive, got {self.particles}")
        bad_cues = [c for c in self.cues if c not in ("silhouette", "dual_silhouette", "skin")]
        if bad_cues or not self.cues:
            raise ValueError(f"unknown cue(s) {bad_cues}; choose from silhouette, dual_silhouette, skin")
        if self.dynamics not in ("auto", "table5", "random_walk"):
            raise ValueError(f"dynamics must be auto, table5 or random_walk, got {self.dynamics!r}")
        if self.joints not in ("body", "all"):
            raise ValueError(f"joints must be 'body' or 'all', got {self.joints!r}")


QUICK = {"particles": (60, 180), "runs": 2, "frames": 6, "mask_size": (64, 48)}
QUICK_SEQUENCES = ("cmu:07_01", "generator:wave")
FULL = {
    "particles": (100, 250, 500, 1000, 1500),
    "runs": 10,
    "frames": 30,
    "filters": tuple(FILTER_LABELS),
}


# ================================================================================================ sequences
@dataclass(eq=False)
class EvalSequence:
    """A synthetic multi-camera sequence with its ground truth.

    Fields: ``angles`` (K, D) true poses in ``skeleton.dof_names`` order; ``frames`` K observations;
    ``joints`` indices of the evaluated joints; ``truth`` (K, J, 3) their true positions (m).
    """

    name: str
    source: str
    action: str
    skeleton: Skeleton
    cameras: object
    frames: list
    angles: torch.Tensor
    fps: float
    joints: list[int]
    truth: torch.Tensor = field(init=False)

    def __post_init__(self):
        with torch.no_grad():
            self.truth = self.skeleton.fk(self.angles.to(torch.float64))[:, self.joints]


def _cmu_rows(cmu_dir: Path) -> dict[str, dict[str, str]]:
    """Clip stem -> its ``INDEX.tsv`` row (``subject``, ``description``, ...; empty if absent)."""
    index = cmu_dir / "INDEX.tsv"
    if not index.is_file():
        return {}
    with open(index, encoding="utf-8") as f:
        return {Path(r["file"]).stem: r for r in csv.DictReader(f, delimiter="\t")}


def _cmu_index(cmu_dir: Path) -> dict[str, str]:
    """Clip stem -> description ("walk", "run/jog") from ``INDEX.tsv`` (empty if absent)."""
    return {stem: r["description"] for stem, r in _cmu_rows(cmu_dir).items()}


def treadmill(skeleton: Skeleton, angles: torch.Tensor) -> torch.Tensor:
    """Remove the least-squares straight-line drift of the root's horizontal translation DOFs.

    The fixed cameras of Fontmarty's set-up look at a small volume; a walk or run of 2 m per second would
    leave it (and the random-walk prior could not keep up with 0.1 m per frame of steady drift). What remains
    is the in-place part of the motion (sway, bob), centred on the origin. ``angles`` (K, D) -> (K, D).
    """
    out = angles.clone()
    rest = skeleton.fk(torch.zeros(angles.shape[-1], dtype=torch.float64))
    root = skeleton.parents.index(-1)
    t = torch.arange(len(angles), dtype=angles.dtype)
    t = t - t.mean()
    for d in range(len(skeleton.dof_names)):
        if skeleton.dof_revolute[d] or skeleton.dof_joints[d] != root:
            continue
        unit = torch.zeros(angles.shape[-1], dtype=torch.float64)
        unit[d] = 1.0
        axis = skeleton.fk(unit)[root] - rest[root]
        if abs(float(axis[2])) > 1e-6:  # the vertical translation (bob) is kept
            continue
        x = out[:, d]
        slope = (t * (x - x.mean())).sum() / t.square().sum().clamp_min(1e-12)
        out[:, d] = x - x.mean() - slope * t
    return out


def _joint_indices(skeleton: Skeleton, which: str) -> list[int]:
    names = list(skeleton.joint_names)
    if which == "all":
        return list(range(len(names)))
    missing = [j for j in EVAL_JOINTS if j not in names]
    if missing:
        raise ValueError(f"the skeleton lacks the evaluated joints {missing}; use --joints all")
    return [names.index(j) for j in EVAL_JOINTS]


def skin_maps(skeleton, angles, cameras, mask_size, rng: np.random.Generator, noise_px: float = 0.5):
    """Synthetic skin-blob distance images (Fontmarty §3.2.3): disks at the projected head centre and hands.

    Returns K :class:`~torchpf.observations.DistanceMaps` (V, H, W); blob centres get ``noise_px`` of
    Gaussian noise, blob radius ~4% of the image width (a hand at 4 m).
    """
    W, H = mask_size
    names = list(skeleton.joint_names)
    centres = [
        (names.index("Head"), names.index("Head_end")),
        (names.index("LeftHand"),),
        (names.index("RightHand"),),
    ]
    radius = max(1.0, 0.04 * W)
    vv, uu = np.mgrid[0:H, 0:W]
    maps = []
    with torch.no_grad():
        joints = skeleton.fk(angles.to(torch.float64))
    for k in range(len(angles)):
        marks = torch.stack([joints[k, list(c)].mean(0) for c in centres])
        feats = []
        for cam in cameras.cameras:
            uv = cam.resized(W, H).project(marks).numpy() + rng.normal(0.0, noise_px, (len(centres), 2))
            f = np.zeros((H, W), dtype=bool)
            for u, v in uv:
                f |= (uu - u) ** 2 + (vv - v) ** 2 <= radius**2
            feats.append(f)
        maps.append(DistanceMaps.from_features(feats))
    return maps


def make_sequence(source: str, item: str, cfg: EvalConfig) -> EvalSequence:
    """One synthetic sequence: ``source`` "cmu" (``item`` a clip stem) or "generator" (``item`` an action)."""
    if source == "cmu":
        from training.mocap import load_bvh

        clip = Path(cfg.cmu_dir) / f"{item}.bvh"
        if not clip.is_file():
            raise FileNotFoundError(f"no CMU clip {clip}; pass --cmu-dir or --sequences generator")
        # The clip's own skeleton: CMU angle tracks on human.urdf would cross the legs (CMU thigh bones slant
        # outwards, human.urdf's hang straight down), so render and track on the converted skeleton.
        skel, motion = load_bvh(clip, scale=CMU_SCALE)
        step = max(1, round(motion.fps / cfg.fps))
        angles = motion.angles[1::step][: cfg.frames]  # frame 0 of a CMU clip is a rest pose
        fps = motion.fps / step
        action = _cmu_index(Path(cfg.cmu_dir)).get(item, "mocap").replace("/", "-")
    elif source == "generator":
        from training.synthetic import generate, sample_style

        skel = Skeleton.from_urdf(asset_path("human.urdf"))
        # bone_scale 1: the performer is exactly the tracked template, as in the paper's synthetic study.
        style = dataclasses.replace(
            sample_style(item, torch.Generator().manual_seed(cfg.seed)), bone_scale=1.0
        )
        angles = generate(item, cfg.frames, cfg.fps, style=style, seed=cfg.seed).angles
        fps, action = cfg.fps, item
    else:
        raise ValueError(f"unknown sequence source {source!r}; choose cmu or generator")
    angles = treadmill(skel, angles.to(torch.float64))
    with torch.no_grad():
        hip_height = float(skel.fk(angles)[:, skel.parents.index(-1), 2].mean())
    cams = camera_ring(
        3,
        radius=cfg.camera_radius,
        height=1.5,
        target=(0.0, 0.0, hip_height),
        width=cfg.mask_size[0],
        height_px=cfg.mask_size[1],
    )
    opts = SynthOptions(morph_px=cfg.morph_px, speckle=cfg.speckle)
    seq = synthesize(skel, angles, cams, mask_size=cfg.mask_size, options=opts, fps=fps, seed=cfg.seed)
    frames = [seq.frame(k) for k in range(len(seq))]
    if "skin" in cfg.cues:
        maps = skin_maps(skel, angles, cams, cfg.mask_size, np.random.default_rng(cfg.seed + 1))
        frames = [dataclasses.replace(f, skin=m) for f, m in zip(frames, maps, strict=True)]
    name = f"{source}-{item}" if source == "generator" else f"cmu-{item}-{action}"
    return EvalSequence(
        name=name,
        source=source,
        action=action,
        skeleton=skel,
        cameras=cams,
        frames=frames,
        angles=angles,
        fps=float(fps),
        joints=_joint_indices(skel, cfg.joints),
    )


def sequence_specs(cfg: EvalConfig) -> list[tuple[str, str]]:
    """``cfg.sequences`` expanded to (source, item) pairs: a bare source takes its default items."""
    specs = []
    for entry in cfg.sequences:
        source, _, item = entry.partition(":")
        if source not in DEFAULT_ITEMS:
            raise ValueError(f"unknown sequence source {source!r} in {entry!r}; choose cmu or generator")
        specs += [(source, item)] if item else [(source, i) for i in DEFAULT_ITEMS[source]]
    return specs


# ================================================================================================ filters
def resolve_dynamics(cfg: EvalConfig) -> str:
    """ "table5" or "random_walk": which motion prior the run uses (``auto`` prefers the registered one)."""
    if cfg.dynamics == "auto":
        return "random_walk" if "random_walk" in DYNAMICS else "table5"
    return cfg.dynamics


def make_prior(seq: EvalSequence, cfg: EvalConfig, dynamics: str):
    """The Table 5 random walk for ``seq``: the registered ``random_walk`` prior (Table 5 stds rescaled from
    5 Hz to the sequence's rate, restricted to the joint limits) or the harness's own
    :func:`priors.table5.table5_sigma` Gaussian random walk; both have a ``(D,)`` ``std`` buffer."""
    if dynamics == "random_walk":
        return make_dynamics("random_walk", seq.skeleton, fps=seq.fps, scale=cfg.dynamics_scale)
    return GaussianRandomWalk(table5_sigma(seq.skeleton, seq.fps, cfg.dynamics_scale).float())


def make_tracker(seq: EvalSequence, name: str, budget: int, cfg: EvalConfig, dynamics: str) -> Tracker:
    """The tracker of ``name`` at budget ``N`` with the harness's likelihood and prior."""
    likelihood = {c: 1.0 for c in cfg.cues}
    prior = make_prior(seq, cfg, dynamics)
    options = {}
    if name == "mcmc":
        # the Tracker takes the HMC moves' gradients out of the same budget (FilterKind.for_budget)
        options = {
            "n_moves": cfg.mcmc_moves,
            "n_leapfrog": cfg.mcmc_leapfrog,
            "burn_in": min(5, len(seq.frames)),
            "step_size": 0.3,
            # Brubaker's diagonal Delta: steps proportional to the prior's spread; frozen DOFs do not move.
            "step_scale": prior.std.float(),
        }
    return Tracker(
        seq.skeleton,
        seq.cameras,
        likelihood=likelihood if len(likelihood) > 1 else cfg.cues[0],
        dynamics=prior,
        filter=name,
        n_particles=budget,
        filter_options=options,
        progress=False,
        smooth=False,  # Fontmarty's protocol compares the filters' own estimates, not a smoothed track
    )


# ================================================================================================ running
@dataclass
class BenchmarkResult:
    """What :func:`run_benchmark` returns.

    ``rows``: one dict per sequence x filter x N x run (``kind == "run"``) then per sequence x filter x N
    (``kind == "aggregate"``, criteria over the R runs). ``frame_rows``: per sequence x filter x N x run x
    frame mean joint error. ``sequences``: name -> (source, action, frames, fps).
    """

    config: EvalConfig
    dynamics: str
    rows: list[dict] = field(default_factory=list)
    frame_rows: list[dict] = field(default_factory=list)
    sequences: dict[str, dict] = field(default_factory=dict)
    seconds: float = 0.0

    def aggregates(self) -> list[dict]:
        return [r for r in self.rows if r["kind"] == "aggregate"]


def evaluate_runs(truth: torch.Tensor, estimates: torch.Tensor, threshold: float) -> dict[str, float]:
    """Criteria of R runs ``estimates (R, K, J, 3)`` vs ``truth (K, J, 3)`` (m; failure as a fraction)."""
    out = metrics.evaluate(truth, estimates, threshold)
    if estimates.shape[0] < 2:
        out["dispersion"] = float("nan")  # eq. 5 is a spread across runs: undefined for one run
    return out


def run_benchmark(cfg: EvalConfig, progress: bool = False, log=None) -> BenchmarkResult:
    """Run the protocol of ``cfg`` and return the raw and aggregated figures (module docstring)."""
    t_start = time.perf_counter()
    dynamics = resolve_dynamics(cfg)
    result = BenchmarkResult(config=cfg, dynamics=dynamics)
    specs = sequence_specs(cfg)
    bar = None
    if progress:
        from tqdm import tqdm

        total = len(specs) * len(cfg.filters) * len(cfg.particles) * cfg.runs
        bar = tqdm(total=total, desc="tracking runs", unit="run", file=sys.stderr)
    for source, item in specs:
        seq = make_sequence(source, item, cfg)
        K = len(seq.frames)
        if K < cfg.frames and log is not None:
            log(f"note: {seq.name} has only {K} frames at {seq.fps:g} Hz (asked for {cfg.frames})")
        result.sequences[seq.name] = {"source": source, "action": seq.action, "frames": K, "fps": seq.fps}
        for name in cfg.filters:
            for budget in cfg.particles:
                tracker = make_tracker(seq, name, budget, cfg, dynamics)
                n_particles, evaluations = tracker.filter.n_particles, tracker.likelihood_evaluations
                estimates, seconds, ess, degenerate = [], [], [], []
                for r in range(cfg.runs):
                    track = tracker.track(seq.frames, init=seq.angles[0], seed=cfg.seed + r, fps=seq.fps)
                    with torch.no_grad():
                        est = seq.skeleton.fk(track.angles)[:, seq.joints]  # (K, J, 3)
                    estimates.append(est)
                    seconds.append(track.seconds / K)
                    ess.append(float(track.ess.float().mean()))
                    degenerate.append(int(track.failed.sum()))  # frames where every weight vanished
                    crit = evaluate_runs(seq.truth, est[None], cfg.threshold)
                    common = {
                        "sequence": seq.name,
                        "source": source,
                        "filter": name,
                        "label": FILTER_LABELS[name],
                        "N": budget,
                        "particles": n_particles,
                        "evaluations": evaluations,
                        "frames": K,
                    }
                    result.rows.append(
                        {
                            **common,
                            "kind": "run",
                            "run": r,
                            **crit,
                            "seconds_per_frame": seconds[-1],
                            "mean_ess": ess[-1],
                            "degenerate_frames": degenerate[-1],
                        }
                    )
                    err = (est - seq.truth).norm(dim=-1)  # (K, J)
                    fail = metrics.frame_failures(seq.truth, est, cfg.threshold)[0]
                    for k in range(K):
                        result.frame_rows.append(
                            {
                                "sequence": seq.name,
                                "filter": name,
                                "N": budget,
                                "run": r,
                                "frame": k,
                                "mean_joint_error": float(err[k].mean()),
                                "max_joint_error": float(err[k].max()),
                                "failed": bool(fail[k]),
                            }
                        )
                    if bar is not None:
                        bar.update()
                crit = evaluate_runs(seq.truth, torch.stack(estimates), cfg.threshold)
                result.rows.append(
                    {
                        **common,
                        "kind": "aggregate",
                        "run": "all",
                        **crit,
                        "seconds_per_frame": float(np.mean(seconds)),
                        "mean_ess": float(np.mean(ess)),
                        "degenerate_frames": sum(degenerate),
                    }
                )
    if bar is not None:
        bar.close()
    result.seconds = time.perf_counter() - t_start
    return result


# ================================================================================================ ranks
def rank_values(values: Mapping[str, float]) -> dict[str, float]:
    """Ranks 1..n of ``values`` (lower value = better = rank 1); ties share their mean rank; NaN ties last."""
    vals = {k: math.inf if math.isnan(float(v)) else float(v) for k, v in values.items()}
    ordered = sorted(vals.values())
    # a value first seen at 0-based position i and held by c entries spans ranks i+1 .. i+c
    return {k: ordered.index(v) + (ordered.count(v) + 1) / 2 for k, v in vals.items()}


def rank_filters(aggregates: Iterable[Mapping], criteria=CRITERIA) -> dict[str, dict]:
    """Fontmarty Tables 6-7 from aggregate rows (one per sequence x filter x N).

    Returns ``{filter: {"<key>": mean value over cells, "<key>_cell_rank": mean cell rank,
    "<key>_rank": rank of that mean, "seconds_per_frame": mean, "mean_rank": mean of the criterion ranks,
    "overall": rank of mean_rank, "cells": number of cells}}``. Filters missing from a cell are left out of
    that cell's ranking.
    """
    cells: dict[tuple, dict[str, Mapping]] = {}
    for row in aggregates:
        cells.setdefault((row["sequence"], row["N"]), {})[row["filter"]] = row
    filters = sorted({f for c in cells.values() for f in c}, key=lambda f: list(FILTER_LABELS).index(f))
    table = {f: {"cells": 0, "seconds_per_frame": []} for f in filters}
    for key, _ in criteria:
        for f in filters:
            table[f][key] = []
            table[f][f"{key}_cell_rank"] = []
    for cell in cells.values():
        for f, row in cell.items():
            table[f]["cells"] += 1
            table[f]["seconds_per_frame"].append(row["seconds_per_frame"])
        for key, _ in criteria:
            ranks = rank_values({f: row[key] for f, row in cell.items()})
            for f, row in cell.items():
                table[f][key].append(row[key])
                table[f][f"{key}_cell_rank"].append(ranks[f])
    for f in filters:
        for k, v in list(table[f].items()):
            if isinstance(v, list):
                finite = [x for x in v if not math.isnan(x)]
                table[f][k] = float(np.mean(finite)) if finite else float("nan")
    for key, _ in criteria:
        ranks = rank_values({f: table[f][f"{key}_cell_rank"] for f in filters})
        for f in filters:
            table[f][f"{key}_rank"] = ranks[f]
    for f in filters:
        table[f]["mean_rank"] = float(np.mean([table[f][f"{key}_rank"] for key, _ in criteria]))
    overall = rank_values({f: table[f]["mean_rank"] for f in filters})
    for f in filters:
        table[f]["overall"] = overall[f]
    return table


# ================================================================================================ report
def _fmt_rank(r: float) -> str:
    return f"{r:.0f}" if float(r).is_integer() else f"{r:.1f}"


def _fmt(x: float, scale: float = 1.0, digits: int = 1) -> str:
    return "-" if x is None or math.isnan(x) else f"{x * scale:.{digits}f}"


def ranking_markdown(table: Mapping[str, Mapping], title: str) -> str:
    """A Tables 6-7 style markdown table (values in cm / %, ranks per criterion, mean rank), best first."""
    head = (
        "| Filter | RMSE (cm) | Bias (cm) | Dispersion (cm) | Failure (%) | Time/frame (s) "
        "| Accuracy | Dispersion | Failure rate | Bias | Mean rank |"
    )
    lines = [f"### {title}", "", head, "|" + "---|" * 11]
    for f in sorted(table, key=lambda f: (table[f]["mean_rank"], list(FILTER_LABELS).index(f))):
        t = table[f]
        lines.append(
            f"| {FILTER_LABELS[f]} | {_fmt(t['rmse'], 100)} | {_fmt(t['bias'], 100)} "
            f"| {_fmt(t['dispersion'], 100)} | {_fmt(t['failure_rate'], 100)} "
            f"| {_fmt(t['seconds_per_frame'], 1, 3)} | "
            + " | ".join(_fmt_rank(t[f"{k}_rank"]) for k, _ in CRITERIA)
            + f" | {t['mean_rank']:.2f} |"
        )
    return "\n".join(lines)


def rmse_by_n_markdown(result: BenchmarkResult) -> str:
    """RMSE (cm) per sequence x filter (rows) and N (columns): the numbers behind Fig. 8 (a)."""
    budgets = list(result.config.particles)
    lines = [
        "### RMSE (cm) by budget N (likelihood evaluations per frame)",
        "",
        "| Sequence | Filter | " + " | ".join(f"N={n}" for n in budgets) + " |",
        "|---|---|" + "---|" * len(budgets),
    ]
    agg = {(r["sequence"], r["filter"], r["N"]): r for r in result.aggregates()}
    for seq in result.sequences:
        for f in result.config.filters:
            vals = [_fmt(agg[(seq, f, n)]["rmse"], 100) if (seq, f, n) in agg else "-" for n in budgets]
            lines.append(f"| {seq} | {FILTER_LABELS[f]} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def format_markdown(result: BenchmarkResult) -> str:
    """The whole report: rankings over all sequences, per source (generator ~ Table 6, CMU ~ Table 7)."""
    cfg = result.config
    agg = result.aggregates()
    seqs = ", ".join(f"{n} ({s['frames']} frames @ {s['fps']:.3g} Hz)" for n, s in result.sequences.items())
    parts = [
        "## Filter evaluation (Fontmarty et al. protocol)",
        "",
        f"Sequences: {seqs}. Budgets N = {', '.join(map(str, cfg.particles))} likelihood evaluations per "
        f"frame; R = {cfg.runs} runs; cues {'+'.join(cfg.cues)}; masks {cfg.mask_size[0]}x{cfg.mask_size[1]} "
        f"(morph {cfg.morph_px} px, speckle {cfg.speckle}); dynamics {result.dynamics}; "
        f"T_failure = {cfg.threshold} m; {'all' if cfg.joints == 'all' else len(EVAL_JOINTS)} joints. "
        "Values are means over the (sequence, N) cells; ranks: 1 = best.",
        "",
        ranking_markdown(rank_filters(agg), "All sequences"),
    ]
    sources = sorted({r["source"] for r in agg})
    if len(sources) > 1:
        titles = {"generator": "Generator sequences (model fits, cf. Table 6)", "cmu": "CMU mocap sequences"}
        for s in sources:
            parts += ["", ranking_markdown(rank_filters(r for r in agg if r["source"] == s), titles[s])]
    parts += ["", rmse_by_n_markdown(result), "", f"Total time {result.seconds:.0f} s."]
    return "\n".join(parts) + "\n"


def _write_csv(path: Path, rows: Sequence[Mapping]) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def plot_figures(result: BenchmarkResult, out: Path) -> list[Path]:
    """Fig. 8-like plots (criteria vs N, per sequence and averaged) and Fig. 15-like ones (error vs frame)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg, paths = result.config, []
    agg = result.aggregates()
    panels = [
        ("rmse", "(a) RMSE (cm)", 100),
        ("dispersion", "(b) dispersion (cm)", 100),
        ("failure_rate", "(c) failure rate (%)", 100),
        ("bias", "(d) bias (cm)", 100),
    ]
    groups = {name: [r for r in agg if r["sequence"] == name] for name in result.sequences}
    if len(groups) > 1:
        groups["all"] = agg
    for name, rows in groups.items():
        fig, axes = plt.subplots(2, 2, figsize=(9, 6.5), constrained_layout=True)
        for ax, (key, title, scale) in zip(axes.flat, panels, strict=True):
            for f in cfg.filters:
                xs = sorted({r["N"] for r in rows if r["filter"] == f})
                ys = [
                    np.nanmean([r[key] for r in rows if r["filter"] == f and r["N"] == n]) * scale for n in xs
                ]
                ax.plot(xs, ys, marker="o", label=FILTER_LABELS[f])
            ax.set_title(title)
            ax.set_xlabel("N (likelihood evaluations / frame)")
            ax.set_xticks(list(cfg.particles))
            ax.grid(alpha=0.3)
        axes[0, 0].legend(fontsize=8)
        fig.suptitle(f"{name}: criteria vs N (R = {cfg.runs})" if name != "all" else "mean over sequences")
        paths.append(out / f"fig8_{name}.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)
    for name in result.sequences:
        frames = [r for r in result.frame_rows if r["sequence"] == name]
        n_panels = len(cfg.filters) + 1
        cols = min(3, n_panels)
        rows_ = math.ceil(n_panels / cols)
        fig, axes = plt.subplots(
            rows_, cols, figsize=(4 * cols, 3 * rows_), squeeze=False, constrained_layout=True
        )
        top = 0.0
        for ax, f in zip(axes.flat, cfg.filters, strict=False):
            for n in cfg.particles:
                sel = [r for r in frames if r["filter"] == f and r["N"] == n]
                K = max(r["frame"] for r in sel) + 1
                err = [
                    np.mean([r["mean_joint_error"] for r in sel if r["frame"] == k]) * 100 for k in range(K)
                ]
                ax.plot(range(K), err, label=f"N={n}")
            ax.set_title(FILTER_LABELS[f])
            top = max(top, ax.get_ylim()[1])
            ax.set_xlabel("frame")
            ax.set_ylabel("mean joint error (cm)")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        for ax in list(axes.flat)[: len(cfg.filters)]:
            ax.set_ylim(0.0, top)  # one error scale for all filters, as in Fig. 15 (a)-(e)
        ax = axes.flat[len(cfg.filters)]
        for f in cfg.filters:
            sel = sorted((r for r in agg if r["sequence"] == name and r["filter"] == f), key=lambda r: r["N"])
            ax.plot(
                [r["N"] for r in sel],
                [r["failure_rate"] * 100 for r in sel],
                marker="o",
                label=FILTER_LABELS[f],
            )
        ax.set_xscale("log")
        ax.set_xticks(list(cfg.particles), [str(n) for n in cfg.particles])
        ax.minorticks_off()
        ax.set_title("failure rate vs N")
        ax.set_xlabel("N")
        ax.set_ylabel("failures (%)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        for ax in list(axes.flat)[n_panels:]:
            ax.axis("off")
        fig.suptitle(f"{name}: error per frame (mean over {cfg.runs} runs)")
        paths.append(out / f"fig15_{name}.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)
    return paths


def write_outputs(result: BenchmarkResult, out: str | os.PathLike, plots: bool = True) -> dict[str, Path]:
    """Write table.md, results.csv, frames.csv, config.json (and the PNG plots) under ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "table": out / "table.md",
        "results": out / "results.csv",
        "frames": out / "frames.csv",
        "config": out / "config.json",
    }
    paths["table"].write_text(format_markdown(result), encoding="utf-8")
    _write_csv(paths["results"], result.rows)
    _write_csv(paths["frames"], result.frame_rows)
    meta = {
        **dataclasses.asdict(result.config),
        "dynamics_used": result.dynamics,
        "sequences_used": result.sequences,
        "seconds": result.seconds,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
    }
    paths["config"].write_text(json.dumps(meta, indent=2, default=str), encoding="utf-8")
    if plots:
        for p in plot_figures(result, out):
            paths[p.stem] = p
    return paths


# ============================================================================================ foreign renders
# Issue 11: every CMU clip rendered by benchmarks/foreign.py (a body the tracker's model has never seen),
# written as a sequence directory and tracked as a user would, by each named "setup".


def _sequence_fps(seq_dir: Path) -> float | None:
    from torchpf.sequence import load_truth_csv

    _, _, times = load_truth_csv(Path(seq_dir) / "truth.csv")
    return None if times is None or len(times) < 2 else 1.0 / float(times[1] - times[0])


def _tracker(seq_dir: Path, skeleton: Skeleton, cameras, n_particles: int, **options: Any) -> Tracker:
    """``Tracker(skeleton, cameras, n_particles=N, fps=<the sequence's>, **options)``: what ``python -m
    torchpf track SEQ --particles N`` builds with those options (the CLI passes the sequence's rate)."""
    return Tracker(
        skeleton, cameras, n_particles=n_particles, fps=_sequence_fps(seq_dir), progress=False, **options
    )


_AS_GIVEN = {"calibrate": False}  # track the converted skeleton's body as it is


def tracker_setup(
    track_options: Mapping[str, Any] | None = None,
    *,
    attributes: Mapping[str, Any] | None = None,
    **options: Any,
) -> Callable[..., Tracker]:
    """A setup that builds ``Tracker(skel, cameras, n_particles=N, fps=..., **options)`` (the CLI with
    those options), sets the tracker's ``attributes`` (``Tracker.hold_thin_arms``, ...: Python API only),
    and is tracked with ``tracker.track(seq_dir, seed=..., **track_options)``."""

    def setup(seq_dir: Path, skeleton: Skeleton, *, n_particles: int = 500, **_) -> Tracker:
        from torchpf.sequence import read_sequence

        tracker = _tracker(seq_dir, skeleton, read_sequence(seq_dir).cameras, n_particles, **options)
        for name, value in (attributes or {}).items():
            if not hasattr(tracker, name):
                raise AttributeError(f"Tracker has no attribute {name!r}")
            setattr(tracker, name, value)
        return tracker

    setup.__doc__ = f"Tracker options {options}, track options {dict(track_options or {})}"
    setup.track_options = dict(track_options or {})
    return setup


def setup_before(seq_dir: Path, skeleton: Skeleton, *, n_particles: int = 500, **_) -> Tracker:
    """The ``track`` defaults before issue 11, pinned: silhouette cue alone, APF (3 layers), the random walk
    with Fontmarty's Table 5 stds mapped by joint names (:func:`priors.table5.table5_sigma`, exactly), the
    converted skeleton's own capsules and no joint limits; initial pose from ``truth.csv`` frame 0."""
    stds = table5_sigma(skeleton, _sequence_fps(seq_dir))
    return tracker_setup(
        likelihood="silhouette",
        filter="apf",
        dynamics="random_walk",
        dynamics_options={"stds": stds},
        torso_limit=None,
        attributes={"hold_thin_arms": None},
    )(seq_dir, skeleton, n_particles=n_particles)


#: The ``track`` defaults as they are now: ``Tracker(skel, cameras, n_particles=N)`` and nothing else.
setup_defaults = tracker_setup()
setup_before.track_options = _AS_GIVEN  # the old defaults tracked the body as given


_BIDIR = {"likelihood": {"silhouette": 1.0, "dual_silhouette": 1.0}}


_FITTED: dict[tuple[str, int], Skeleton] = {}


def calibrated_setup(frames_used: int = 8, **options: Any) -> Callable[..., Tracker]:
    """A setup that first fits the body to the sequence's first ``frames_used`` frames
    (:func:`torchpf.calibrate.fit_body`, poses from ``truth.csv`` as ``python -m torchpf calibrate`` takes
    them), then builds ``Tracker(fitted, cameras, n_particles=N, **options)``; the fit's time counts in the
    setup's total time, not in the tracker's frame rate. The fit is made once per sequence and shared by
    every calibrated setup of the run (it is deterministic)."""

    def setup(seq_dir: Path, skeleton: Skeleton, *, n_particles: int = 500, **_) -> Tracker:
        from torchpf.calibrate import fit_body
        from torchpf.sequence import read_sequence

        seq = read_sequence(seq_dir)
        k = min(frames_used, len(seq.truth))
        key = (str(Path(seq_dir).resolve()), k)  # one fit per sequence, shared by the calibrated setups
        if key not in _FITTED:
            _FITTED[key] = fit_body(
                skeleton, seq.cameras, seq.masks[:k], seq.truth[:k].double(), frames_used=k
            )[0]
        return _tracker(seq_dir, _FITTED[key], seq.cameras, n_particles, **options)

    setup.__doc__ = f"fit_body on {frames_used} frames, then Tracker options {options}"
    return setup


def auto_setup(**options: Any) -> Callable[..., Any]:
    """A setup that tracks without the ground truth: ``Tracker(skel, cameras, n_particles=N, **options)
    .track(seq_dir, init="auto")`` (:mod:`torchpf.detect`: the person found from the masks, the body fitted
    to frame 0 when it looks uncalibrated); returns the TrackResult, whose ``skeleton`` is the estimate's."""

    def setup(seq_dir: Path, skeleton: Skeleton, *, n_particles: int = 500, seed: int = 0, **_):
        import warnings

        from torchpf.sequence import read_sequence

        tracker = _tracker(seq_dir, skeleton, read_sequence(seq_dir).cameras, n_particles, **options)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the uncalibrated-body warning, expected here
            return tracker.track(seq_dir, init="auto", seed=seed)

    setup.__doc__ = f"init='auto', then Tracker options {options}"
    return setup


_LIMITS: dict[tuple[tuple[str, ...], str, float], tuple[torch.Tensor, torch.Tensor]] = {}
_ACTIONS: dict[tuple[tuple[str, ...], str, float, bool], list] = {}


def _other_performers(seq_dir: Path, same_action: bool = False) -> dict[str, dict[str, str]]:
    """The ``INDEX.tsv`` rows (by clip stem) of every clip of ``CMU_DIR`` by *another*
    performer (with ``same_action`` only those of this clip's action): the user's mocap in a leave one
    performer out evaluation."""
    clip = Path(json.loads((Path(seq_dir) / "render.json").read_text())["clip"]).stem
    index = _cmu_rows(Path(CMU_DIR))
    if clip not in index:
        raise ValueError(f"{clip} is not in {CMU_DIR}/INDEX.tsv: its performer is unknown")
    me = index[clip]
    others = {
        c: r
        for c, r in index.items()
        if r["subject"] != me["subject"] and (not same_action or r["description"] == me["description"])
    }
    if not others:
        raise ValueError(f"no clip of another performer than {me['subject']} in {CMU_DIR}/INDEX.tsv")
    return others


def _mocap(clips, skeleton: Skeleton) -> list:
    """Each CMU clip converted in ``skeleton``'s DOF order, its first frame (the CMU rest pose) dropped."""
    from training.mocap import bvh_motion

    return [bvh_motion(Path(CMU_DIR) / f"{c}.bvh", dof_names=skeleton.dof_names)[1:] for c in clips]


def _learned_limits(others: Mapping[str, Any], skeleton: Skeleton, margin: float) -> Skeleton:
    """``skeleton`` with the joint limits :func:`training.limits.fit_limits` learns from the clips ``others``
    (stems, e.g. :func:`_other_performers`' rows: what ``python -m training fit-limits`` writes); learned once
    per set of clips and margin."""
    from training.limits import fit_limits

    key = (tuple(others), skeleton.source, float(margin))
    if key not in _LIMITS:
        _LIMITS[key] = fit_limits(_mocap(others, skeleton), skeleton, margin=margin)[:2]
    return skeleton.with_limits(*_LIMITS[key])


def learned_limits_setup(
    margin: float = 0.15, same_action: bool = False, **options: Any
) -> Callable[..., Tracker]:
    """A setup that first gives the converted skeleton joint limits learned from the *other performers'*
    clips (leave one performer out: every BVH of ``CMU_DIR`` whose subject in ``INDEX.tsv`` is not this
    clip's, with ``same_action`` only those of this clip's action; each converted on this skeleton, its first
    frame, the CMU rest pose, dropped; :func:`training.limits.fit_limits` with ``margin``), what ``python -m
    training fit-limits`` does from a user's mocap of the actions they track, then builds
    ``Tracker(limited, cameras, n_particles=N, **options)``. The limits are learned once per performer (and
    action) and run; their time is not the tracker's."""

    def setup(seq_dir: Path, skeleton: Skeleton, *, n_particles: int = 500, **_) -> Tracker:
        from torchpf.sequence import read_sequence

        limited = _learned_limits(_other_performers(seq_dir, same_action), skeleton, margin)
        return _tracker(seq_dir, limited, read_sequence(seq_dir).cameras, n_particles, **options)

    which = " of the same action" if same_action else ""
    setup.__doc__ = f"joint limits from the other performers' clips{which} (margin {margin} rad), {options}"
    return setup


def action_bank_setup(
    limits: float | None = None,
    components: int | str = "auto",
    single_clip: bool = True,
    track_options: Mapping[str, Any] | None = None,
    **options: Any,
) -> Callable[..., Tracker]:
    """A setup that tracks with a bank of action models (:class:`priors.bank.ActionBank`, the ``bank``
    prior) learned from the *other performers'* clips, one model per action of ``INDEX.tsv`` (``python -m
    training fit --action A`` on each action's clips: ``components`` by validation where an action has two
    clips or more, else 6, or with ``single_clip=False`` no model of that action, as ``training fit``'s
    validation refuses one clip; ``n_sigma`` 4), on the structural random walk; with ``limits`` (a margin
    in rad) also the joint limits of :func:`learned_limits_setup`. Then ``Tracker(..., dynamics=bank,
    **options)``: ``track --action walk.npz --action run.npz`` with a user's models of the actions. Learned
    once per performer and rate; their time is not the tracker's. ``track_options``: as
    :func:`tracker_setup`'s (``{"init": "auto"}``: without the ground truth)."""

    def setup(seq_dir: Path, skeleton: Skeleton, *, n_particles: int = 500, **_) -> Tracker:
        from priors.factories import bank
        from torchpf.sequence import read_sequence
        from training.fit import ActionModelFitter

        fps = _sequence_fps(seq_dir)
        others = _other_performers(seq_dir)
        key = (tuple(others), skeleton.source, fps, single_clip)
        if key not in _ACTIONS:
            by_action: dict[str, list[str]] = {}
            for c, r in others.items():
                by_action.setdefault(r["description"], []).append(c)
            _ACTIONS[key] = [
                ActionModelFitter(
                    n_components=components if len(clips) > 1 else 6,
                    n_sigma=4.0,
                    action=action.split("/")[0],
                    fps=fps,
                )
                .fit(_mocap(clips, skeleton))
                .model_
                for action, clips in sorted(by_action.items(), key=lambda kv: -len(kv[1]))
                if single_clip or len(clips) > 1
            ]
        if limits is not None:
            skeleton = _learned_limits(others, skeleton, limits)
        dynamics = bank(skeleton, models=_ACTIONS[key], fps=fps)
        cameras = read_sequence(seq_dir).cameras
        return _tracker(seq_dir, skeleton, cameras, n_particles, dynamics=dynamics, **options)

    setup.__doc__ = f"a bank of action models from the other performers' clips (limits {limits}), {options}"
    setup.track_options = dict(track_options or {})
    return setup


#: Tracker configurations compared on the foreign renders, printed side by side ("before/after"). A setup
#: is ``setup(seq_dir, skeleton, *, n_particles, seed) -> Tracker | TrackResult``: a Tracker is run on
#: ``seq_dir`` (``tracker.track(seq_dir, seed=seed)``), a TrackResult is taken as the run (a setup that
#: calibrates the body first, then tracks, returns one). Its wall time counts in ``total_seconds``.
FOREIGN_SETUPS: dict[str, Callable[..., Any]] = {
    "before": setup_before,
    "defaults": setup_defaults,
    # candidates for the new defaults: the bidirectional silhouette cue with each filter, fixed or
    # first-frame-calibrated likelihood temperature
    "bidir_apf": tracker_setup(_AS_GIVEN, **_BIDIR),
    "bidir_apf_adaptive": tracker_setup(_AS_GIVEN, **_BIDIR, filter_options={"betas": "adaptive"}),
    "bidir_partitioned": tracker_setup(_AS_GIVEN, **_BIDIR, filter="partitioned"),
    "bidir_partitioned_auto": tracker_setup(_AS_GIVEN, **_BIDIR, filter="partitioned", temperature="auto"),
    "bidir_sir": tracker_setup(_AS_GIVEN, **_BIDIR, filter="sir"),
    "bidir_partitioned_table5": tracker_setup(
        _AS_GIVEN, **_BIDIR, filter="partitioned", dynamics_options={"stds": "table5"}
    ),
    "calibrated": calibrated_setup(filter="apf"),  # fit_body, then the defaults of issue 11 (APF)
    "auto": auto_setup(),  # issue 13: no ground truth; detector + fit_body on frame 0, then the defaults
    # the defaults on the skeleton with joint limits learned from the other performers' clips (fit-limits)
    "learned_limits": learned_limits_setup(),
    "learned_limits_action": learned_limits_setup(same_action=True),  # ... of the clip's action only
    # the defaults with a bank of walk and run models learned from the other performers' clips (issue 12)
    "action_bank": action_bank_setup(),
    "action_bank_limits": action_bank_setup(limits=0.15),
    "action_bank_limits_auto": action_bank_setup(limits=0.15, track_options={"init": "auto"}),  # no truth
    # ... with no model of an action that only one clip of the other performers shows (35's runs)
    "action_bank_limits_validated": action_bank_setup(limits=0.15, single_clip=False),
    "calibrated_bidir_partitioned": calibrated_setup(**_BIDIR, filter="partitioned"),
    "calibrated_bidir_sir": calibrated_setup(**_BIDIR, filter="sir"),
    "calibrated_bidir_apf": calibrated_setup(**_BIDIR, filter="apf"),
    "calibrated_bidir_sir_table5": calibrated_setup(
        **_BIDIR, filter="sir", dynamics_options={"stds": "table5"}
    ),
    "bidir_partitioned_cv": tracker_setup(
        _AS_GIVEN, **_BIDIR, filter="partitioned", dynamics="constant_velocity"
    ),
    "bidir_partitioned_damped": tracker_setup(_AS_GIVEN, **_BIDIR, filter="partitioned", dynamics="damped"),
    # issue 12: each filter with the default cue and prior on the converted body as given (no fit of the
    # body at frame 0, which track does by default to an uncalibrated-looking body), at 100 / 500 / 2,000
    "apf": tracker_setup(_AS_GIVEN, filter="apf"),
    "partitioned": tracker_setup(_AS_GIVEN, filter="partitioned"),
    # issue 12: the hybrid filter (APF layers + gradient refinement, torchpf.filters.hybrid), same budget
    "hybrid": tracker_setup(_AS_GIVEN, filter="hybrid"),
    "hybrid_particles": tracker_setup(
        _AS_GIVEN, filter="hybrid", filter_options={"refine_mode": "particles", "refine_prior": True}
    ),
    "hybrid_particles_free": tracker_setup(
        _AS_GIVEN, filter="hybrid", filter_options={"refine_mode": "particles", "refine_prior": False}
    ),
    "hybrid_estimate": tracker_setup(_AS_GIVEN, filter="hybrid", filter_options={"refine_mode": "estimate"}),
    "calibrated_hybrid_estimate": calibrated_setup(
        filter="hybrid", filter_options={"refine_mode": "estimate"}
    ),
    "calibrated_hybrid": calibrated_setup(filter="hybrid"),
    # the refinement cue's truncation (default 6 px) at 10 and 20 px, as compared in BENCHMARKS.md
    "hybrid_tau10": tracker_setup(
        _AS_GIVEN, filter="hybrid", filter_options={"refine_options": {"cue_options": {"tau": 10.0}}}
    ),
    "hybrid_tau20": tracker_setup(
        _AS_GIVEN, filter="hybrid", filter_options={"refine_options": {"cue_options": {"tau": 20.0}}}
    ),
    "calibrated_hybrid_particles": calibrated_setup(
        filter="hybrid", filter_options={"refine_mode": "particles", "refine_prior": True}
    ),
    # `track`'s defaults without the smoothing of the finished track (torchpf.smooth): the filter alone
    "no_smooth": tracker_setup(smooth=False),
    # `track --torso-limit 0.5`: the converted skeleton's spine, neck and head held within 0.5 rad
    "torso_limit": tracker_setup(torso_limit=0.5),
    # `track --hold-thin-arms none`: the arms' widths fitted like every capsule (the defaults to session 26)
    "arms_fitted": tracker_setup(attributes={"hold_thin_arms": None}),
    # the arms put back at the skeleton's radii where they project < 2 px, whatever the masks' noise
    "hold_thin_arms_always": tracker_setup(attributes={"hold_arms_outline": 0.0}),
    # ---- AFTER (issue 11): add the new configurations here, one entry each, e.g.
    # "calibrated": fit the body (torchpf.calibrate.fit_body on the first frames, pose from truth.csv
    #               frame 0), then track with the fitted skeleton;
    # "new defaults": Tracker(skel, cameras, n_particles=n_particles) once the defaults have changed.
}


@dataclass
class ForeignConfig:
    """One run of the foreign-render evaluation (written to ``config.json``)."""

    clips: tuple[str, ...] = ()  # CMU clip stems; empty: every clip in INDEX.tsv
    presets: tuple[str, ...] = ("clean", "noisy")  # benchmarks.foreign.PRESETS
    setups: tuple[str, ...] = ("before", "defaults")  # FOREIGN_SETUPS
    frames: int = 60  # K per clip (the runs are shorter: ~34 frames at 30 fps)
    fps: float = 30.0
    particles: tuple[int, ...] = (500,)  # likelihood evaluations per frame, one or several budgets
    runs: int = 1  # seeds seed..seed+runs-1 per (clip, preset, setup)
    mask_size: tuple[int, int] = (160, 120)
    joints: str = "body"  # "body": BodyPlan.eval_joints (15, found structurally) or "all"
    threshold: float = 0.25  # T_failure (m)
    cmu_dir: str = str(CMU_DIR)
    work_dir: str = ""  # where the sequence directories go (default: <out>/sequences)
    in_place: bool = False  # remove the root's horizontal drift (treadmill), for diagnosis
    seed: int = 0

    def __post_init__(self):
        from benchmarks.foreign import PRESETS

        self.clips, self.presets, self.setups = tuple(self.clips), tuple(self.presets), tuple(self.setups)
        if isinstance(self.particles, int):
            self.particles = (self.particles,)
        self.particles = tuple(int(n) for n in self.particles)
        self.mask_size = tuple(int(v) for v in self.mask_size)
        for what, names, known in (
            ("preset", self.presets, PRESETS),
            ("setup", self.setups, FOREIGN_SETUPS),
        ):
            bad = [n for n in names if n not in known]
            if bad or not names:
                raise ValueError(f"unknown {what}(s) {bad}; choose from {list(known)}")
        if self.frames < 2 or self.runs < 1 or not self.particles or min(self.particles) < 1:
            raise ValueError("need frames >= 2, runs >= 1 and particles >= 1")
        if self.joints not in ("body", "all"):
            raise ValueError(f"joints must be 'body' or 'all', got {self.joints!r}")


def mpjpe_standard_error(sds: Sequence[float], runs: int) -> float:
    """Standard error (m) of a mean over ``n`` clips of per-clip MPJPEs, each the mean of ``runs`` runs
    whose spread (sample std) is ``sds[c]``: ``sqrt(sum_c sds[c]^2 / runs) / n``. It is what the tracker's
    randomness alone moves the mean by, for the same masks: two setups run on the same masks whose means
    differ by less than about twice ``sqrt(se_a^2 + se_b^2)`` are not told apart. NaN with one run."""
    sds = np.asarray(list(sds), dtype=np.float64)
    if runs < 2 or len(sds) == 0 or not np.isfinite(sds).all():
        return math.nan
    return float(np.sqrt(np.sum(sds**2) / runs) / len(sds))


@dataclass
class ForeignResult:
    """What :func:`run_foreign` returns: ``rows`` one dict per clip x preset x setup (criteria over the runs),
    ``config``, ``seconds`` (whole run, rendering included)."""

    config: ForeignConfig
    rows: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    def cells(self) -> list[tuple[str, int]]:
        """(setup, budget) pairs in table order: each setup at each budget."""
        return [(setup, n) for setup in self.config.setups for n in self.config.particles]

    def label(self, setup: str, budget: int) -> str:
        """A table row's name: the setup, with its budget when the run has several."""
        return f"{setup} @{budget}" if len(self.config.particles) > 1 else setup

    def means(self) -> list[dict]:
        """Per preset x setup x budget: the criteria averaged over the clips (``clip == "mean"``)."""
        keys = ("mpjpe", "rmse", "failure_rate", "frame_failure", "mean_ess", "seconds_per_frame")
        out = []
        for preset in self.config.presets:
            for setup, budget in self.cells():
                sel = [
                    r
                    for r in self.rows
                    if r["preset"] == preset and r["setup"] == setup and r["particles"] == budget
                ]
                if sel:
                    mean = {k: float(np.mean([r[k] for r in sel])) for k in keys}
                    mean["mpjpe_se"] = mpjpe_standard_error(
                        [r.get("mpjpe_sd", math.nan) for r in sel], self.config.runs
                    )
                    frames = sum(r["frames"] for r in sel)
                    seconds = sum(r["seconds_per_frame"] * r["frames"] for r in sel)
                    out.append(
                        {
                            "clip": "mean",
                            "action": "",
                            "preset": preset,
                            "setup": setup,
                            "particles": budget,
                            **mean,
                            "fps": frames / max(seconds, 1e-12),
                            "frames": frames,
                        }
                    )
        return out


def foreign_clips(cfg: ForeignConfig) -> list[str]:
    """The clip stems of ``cfg`` (all of INDEX.tsv, else every ``*.bvh``, when none are named)."""
    cmu = Path(cfg.cmu_dir)
    clips = list(cfg.clips) or list(_cmu_index(cmu)) or sorted(p.stem for p in cmu.glob("*.bvh"))
    missing = [c for c in clips if not (cmu / f"{c}.bvh").is_file()]
    if missing or not clips:
        raise FileNotFoundError(f"no CMU clip(s) {missing or '*.bvh'} in {cmu}; pass --cmu-dir")
    return clips


def run_foreign(cfg: ForeignConfig, out: str | os.PathLike = "out/foreign", progress=False, log=None):
    """Render every clip x preset with the foreign renderer, track it with every setup, and score it.

    Criteria per clip (over ``runs``, :mod:`torchpf.metrics`, on the evaluated joints): ``mpjpe`` (m),
    ``rmse`` (Fontmarty eq. 3), ``failure_rate`` (Fontmarty eq. 6: share of joint-frames further than
    ``threshold`` from the truth), ``frame_failure`` (share of frames where any joint is: the issue's
    "failure rate"), ``mean_ess``, ``seconds_per_frame`` (the filter loop, ``TrackResult.seconds / K``),
    ``fps`` and ``total_seconds`` (setup + tracking wall time, reading the sequence included).
    """
    from benchmarks.foreign import body_plan, build_sequence
    from torchpf.sequence import load_truth_csv
    from torchpf.tracker import TrackResult

    t_start = time.perf_counter()
    result = ForeignResult(config=cfg)
    work = Path(cfg.work_dir or Path(out) / "sequences")
    clips = foreign_clips(cfg)
    index = _cmu_index(Path(cfg.cmu_dir))
    bar = None
    if progress:
        from tqdm import tqdm

        total = len(clips) * len(cfg.presets) * len(cfg.setups) * len(cfg.particles) * cfg.runs
        bar = tqdm(total=total, desc="foreign tracking runs", unit="run", file=sys.stderr)
    for clip in clips:
        for preset in cfg.presets:
            seq = build_sequence(
                Path(cfg.cmu_dir) / f"{clip}.bvh",
                work / f"{clip}-{preset}",
                defects=preset,
                fps=cfg.fps,
                frames=cfg.frames,
                size=cfg.mask_size,
                seed=cfg.seed,
                in_place=cfg.in_place,
            )
            skel = Skeleton.from_urdf(str(seq.skeleton_path))  # what a user loads, not the builder's object
            truth_angles, _, _ = load_truth_csv(seq.path / "truth.csv")
            joints = body_plan(skel).eval_joints() if cfg.joints == "body" else list(range(len(skel.parents)))
            with torch.no_grad():
                truth = skel.fk(truth_angles)[:, joints]
            K = len(truth)
            for name, budget in result.cells():
                estimates, seconds, totals, ess = [], [], [], []
                for r in range(cfg.runs):
                    t0 = time.perf_counter()
                    made = FOREIGN_SETUPS[name](seq.path, skel, n_particles=budget, seed=cfg.seed + r)
                    extra = getattr(FOREIGN_SETUPS[name], "track_options", {})
                    track = (
                        made
                        if isinstance(made, TrackResult)
                        else made.track(seq.path, seed=cfg.seed + r, **extra)
                    )
                    totals.append(time.perf_counter() - t0)
                    # a setup that fitted the body tracks with its own skeleton: its joints are the estimate
                    body = track.skeleton if track.skeleton is not None else skel
                    with torch.no_grad():
                        estimates.append(body.fk(track.angles)[:, joints])
                    seconds.append(track.seconds / K)
                    ess.append(float(track.ess.float().mean()))
                    if bar is not None:
                        bar.update()
                est = torch.stack(estimates)  # (R, K, J, 3)
                crit = metrics.evaluate(truth, est, cfg.threshold)
                per_run = [float(metrics.mpjpe(truth, e)) for e in est]
                result.rows.append(
                    {
                        "clip": clip,
                        "action": index.get(clip, "mocap"),
                        "preset": preset,
                        "setup": name,
                        "particles": budget,
                        "frames": K,
                        "joints": len(joints),
                        "camera_radius": seq.info["camera_radius"],
                        "mpjpe": crit["mpjpe"],
                        # the runs' spread (m): what the tracker's randomness alone moves one clip's MPJPE by
                        "mpjpe_sd": float(np.std(per_run, ddof=1)) if len(per_run) > 1 else math.nan,
                        "rmse": crit["rmse"],
                        "failure_rate": crit["failure_rate"],
                        "frame_failure": float(
                            metrics.frame_failures(truth, est, cfg.threshold).float().mean()
                        ),
                        "mean_ess": float(np.mean(ess)),
                        "seconds_per_frame": float(np.mean(seconds)),
                        "fps": 1.0 / max(float(np.mean(seconds)), 1e-12),
                        "total_seconds": float(np.mean(totals)),
                    }
                )
                if log is not None:
                    row = result.rows[-1]
                    log(
                        f"{clip} {preset} {result.label(name, budget)}: MPJPE {row['mpjpe'] * 1000:.0f} mm, "
                        f"frames failed {row['frame_failure'] * 100:.0f} %"
                    )
    if bar is not None:
        bar.close()
    result.seconds = time.perf_counter() - t_start
    return result


def foreign_markdown(result: ForeignResult) -> str:
    """Per-clip tables (one per preset) and the before/after summary over the clips."""
    cfg = result.config
    head = (
        "| Clip | Action | Setup | MPJPE (mm) | RMSE (mm) | Failure (%) | Frames failed (%) | ESS "
        "| Time/frame (s) | fps |"
    )

    def line(r, bold=False):
        b = "**" if bold else ""
        return (
            f"| {b}{r['clip']}{b} | {r['action']} | {result.label(r['setup'], r['particles'])} "
            f"| {b}{r['mpjpe'] * 1000:.0f}{b} "
            f"| {r['rmse'] * 1000:.0f} | {r['failure_rate'] * 100:.1f} "
            f"| {b}{r['frame_failure'] * 100:.0f}{b} "
            f"| {r['mean_ess']:.1f} | {r['seconds_per_frame']:.3f} | {r['fps']:.1f} |"
        )

    frames = sorted({r["frames"] for r in result.rows})
    parts = [
        "## Foreign renders (issue 11)",
        "",
        f"{len({r['clip'] for r in result.rows})} CMU clips, up to {cfg.frames} frames at {cfg.fps:g} fps "
        f"(clips give {frames[0]}-{frames[-1]}), 3 cameras, {cfg.mask_size[0]}x{cfg.mask_size[1]} masks "
        f"rendered by benchmarks/foreign.py; {', '.join(map(str, cfg.particles))} likelihood evaluations "
        "per frame; "
        f"{cfg.runs} run(s); {'15 structural body' if cfg.joints == 'body' else 'all'} joints; "
        f"T_failure = {cfg.threshold} m. Failure: Fontmarty eq. 6 (joint-frames beyond T); frames failed: "
        "frames with any joint beyond T. "
        + ("Root drift removed (--in-place)." if cfg.in_place else "Performers walk through the volume."),
        "",
        "### Summary (mean over the clips)",
        "",
        "MPJPE ± its standard error from the runs' spread (the tracker's randomness on the same masks; "
        "with 2 runs or more).",
        "",
        "| Setup | "
        + " | ".join(f"{p} MPJPE (mm) | {p} frames failed (%)" for p in cfg.presets)
        + " | fps |",
        "|---|" + "---|---|" * len(cfg.presets) + "---|",
    ]
    means = result.means()
    for setup, budget in result.cells():
        cells, fps = [], []
        for preset in cfg.presets:
            m = next(
                r for r in means if r["preset"] == preset and r["setup"] == setup and r["particles"] == budget
            )
            se = "" if math.isnan(m["mpjpe_se"]) else f" ± {m['mpjpe_se'] * 1000:.1f}"
            cells.append(f"{m['mpjpe'] * 1000:.0f}{se} | {m['frame_failure'] * 100:.0f}")
            fps.append(m["fps"])
        parts.append(f"| {result.label(setup, budget)} | " + " | ".join(cells) + f" | {np.mean(fps):.1f} |")
    for preset in cfg.presets:
        parts += ["", f"### {preset} masks", "", head, "|" + "---|" * 10]
        parts += [line(r) for r in result.rows if r["preset"] == preset]
        parts += [line(r, bold=True) for r in means if r["preset"] == preset]
    parts += ["", f"Total time {result.seconds:.0f} s (rendering included)."]
    return "\n".join(parts) + "\n"


def write_foreign_outputs(result: ForeignResult, out: str | os.PathLike) -> dict[str, Path]:
    """Write ``table.md``, ``results.csv`` (rows per clip, then the means) and ``config.json`` in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"table": out / "table.md", "results": out / "results.csv", "config": out / "config.json"}
    paths["table"].write_text(foreign_markdown(result), encoding="utf-8")
    _write_csv(paths["results"], result.rows + result.means())
    meta = {
        **dataclasses.asdict(result.config),
        "seconds": result.seconds,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
    }
    paths["config"].write_text(json.dumps(meta, indent=2, default=str), encoding="utf-8")
    return paths


# ================================================================================================ CLI
class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows argparse defaults, except the None of the options whose help names their own default."""

    def _get_help_string(self, action):
        return action.help if action.default is None else super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.evaluate",
        description="Fontmarty et al. evaluation of the particle filters: RMSE, bias, dispersion, failure "
        "rate and ranks at equal numbers of likelihood evaluations (see the module docstring).",
        formatter_class=_HelpFormatter,
    )
    d = EvalConfig()
    # Options that --quick/--full preset default to None here so that an explicit value always wins.
    p.add_argument(
        "--sequences",
        help="comma list of sources (cmu, generator) or source:item (cmu:16_46, generator:walk); "
        f"a source alone takes its default items {DEFAULT_ITEMS} (default: {','.join(d.sequences)})",
    )
    p.add_argument(
        "--filters", help=f"comma list of {list(FILTER_LABELS)} or 'all' (default: {','.join(d.filters)})"
    )
    p.add_argument("--particles", type=int, nargs="+", help=f"budgets N (default: {list(d.particles)})")
    p.add_argument(
        "--runs", type=int, help=f"runs R per filter and N, seeds seed..seed+R-1 (default: {d.runs})"
    )
    p.add_argument("--frames", type=int, help=f"frames K per sequence (default: {d.frames})")
    p.add_argument("--mask-size", type=int, nargs=2, metavar=("W", "H"), help=f"(default: {d.mask_size})")
    p.add_argument(
        "--fps", type=float, help=f"tracking frame rate (mocap is subsampled) (default: {d.fps}; foreign: 30)"
    )
    p.add_argument("--morph-px", type=int, default=d.morph_px, help="segmentation noise: erosion/dilation px")
    p.add_argument("--speckle", type=float, default=d.speckle, help="segmentation noise: flipped pixel share")
    p.add_argument("--cues", default=",".join(d.cues), help="comma list of silhouette, dual_silhouette, skin")
    p.add_argument("--threshold", type=float, default=d.threshold, help="T_failure (m)")
    p.add_argument(
        "--dynamics",
        choices=["auto", "table5", "random_walk"],
        default=d.dynamics,
        help="motion prior: Table 5 random walk built here, the registered 'random_walk', or auto",
    )
    p.add_argument(
        "--dynamics-scale", type=float, default=d.dynamics_scale, help="multiplies the Table 5 stds"
    )
    p.add_argument("--joints", choices=["body", "all"], default=d.joints, help="joints the criteria use")
    p.add_argument("--cmu-dir", default=d.cmu_dir, help="folder of the CMU BVH clips")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--out", help="output folder (default: out/evaluate; foreign: out/foreign)")
    p.add_argument(
        "--renderer",
        choices=["synthetic", "foreign"],
        default="synthetic",
        help="synthetic: the Fontmarty protocol on torchpf.synth renders (the tracker's own body); foreign: "
        "every CMU clip rendered by benchmarks/foreign.py, tracked by each --setups entry (issue 11)",
    )
    f = ForeignConfig()
    p.add_argument("--clips", help="foreign: comma list of CMU clip stems (default: all in INDEX.tsv)")
    p.add_argument(
        "--in-place",
        action="store_true",
        help="foreign: remove the root's straight horizontal drift (the performer walks on a treadmill)",
    )
    p.add_argument("--presets", help=f"foreign: comma list of mask presets (default: {','.join(f.presets)})")
    p.add_argument(
        "--setups", help=f"foreign: comma list of {list(FOREIGN_SETUPS)} (default: {','.join(f.setups)})"
    )
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help=f"smoke run: {QUICK_SEQUENCES}, {QUICK}")
    mode.add_argument("--full", action="store_true", help=f"the paper's grid: {FULL}")
    return p


def config_from_args(args: argparse.Namespace) -> EvalConfig:
    """EvalConfig from the CLI; --quick/--full set the sizes that were not given explicitly."""
    d = EvalConfig()
    preset = {**QUICK, "sequences": QUICK_SEQUENCES} if args.quick else FULL if args.full else {}
    kwargs = {}
    for key in ("sequences", "filters", "particles", "runs", "frames", "mask_size"):
        value = getattr(args, key)
        if isinstance(value, str):
            value = tuple(FILTER_LABELS) if value == "all" else tuple(s for s in value.split(",") if s)
        if value is not None:
            kwargs[key] = tuple(value) if isinstance(value, list) else value
        elif key in preset:
            kwargs[key] = preset[key]
    kwargs.update(
        fps=d.fps if args.fps is None else args.fps,
        morph_px=args.morph_px,
        speckle=args.speckle,
        cues=tuple(s for s in args.cues.split(",") if s),
        threshold=args.threshold,
        dynamics=args.dynamics,
        dynamics_scale=args.dynamics_scale,
        joints=args.joints,
        cmu_dir=args.cmu_dir,
        seed=args.seed,
    )
    return EvalConfig(**kwargs)


def foreign_config_from_args(args: argparse.Namespace) -> ForeignConfig:
    """ForeignConfig from the CLI (``--renderer foreign``); options left out keep ForeignConfig's defaults."""
    d = ForeignConfig()

    def names(text, default):
        return default if text is None else tuple(s for s in text.split(",") if s)

    return ForeignConfig(
        clips=names(args.clips, d.clips),
        presets=names(args.presets, d.presets),
        setups=names(args.setups, d.setups),
        frames=d.frames if args.frames is None else args.frames,
        fps=d.fps if args.fps is None else args.fps,
        particles=d.particles if args.particles is None else tuple(args.particles),
        runs=d.runs if args.runs is None else args.runs,
        mask_size=d.mask_size if args.mask_size is None else tuple(args.mask_size),
        joints=args.joints,
        threshold=args.threshold,
        cmu_dir=args.cmu_dir,
        in_place=args.in_place,
        seed=args.seed,
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    if args.renderer == "foreign":
        out = args.out or "out/foreign"
        try:
            fcfg = foreign_config_from_args(args)
            log = None if args.no_progress else (lambda m: print(m, file=sys.stderr))
            result = run_foreign(fcfg, out, progress=not args.no_progress, log=log)
        except (ValueError, FileNotFoundError) as e:
            parser.exit(2, f"error: {e}\n")
        paths = write_foreign_outputs(result, out)
        print(paths["table"].read_text(encoding="utf-8"))
        print(f"wrote {', '.join(str(p) for p in paths.values())}", file=sys.stderr)
        return 0
    try:
        cfg = config_from_args(args)
        result = run_benchmark(cfg, progress=not args.no_progress, log=lambda m: print(m, file=sys.stderr))
    except (ValueError, FileNotFoundError) as e:
        parser.exit(2, f"error: {e}\n")
    paths = write_outputs(result, args.out or "out/evaluate", plots=not args.no_plots)
    print(paths["table"].read_text(encoding="utf-8"))
    print(f"wrote {', '.join(str(p) for p in paths.values())}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
