"""High-level tracker: skeleton + likelihood(s) + motion prior + particle filter in one ``nn.Module``.

``Tracker`` assembles the pieces from keyword arguments (or a small YAML/dict config) and runs them on a
sequence: a sequence directory of DESIGN.md, a :class:`~torchpf.sequence.SequenceData` in memory, or a list of
:class:`~torchpf.observations.Frame` s. The result is an estimated motion (mocap-CSV-able), per-frame ESS,
the log-evidence and per-frame failure flags.

Pieces by name:

* likelihoods (:data:`LIKELIHOODS`): ``silhouette`` (Fontmarty eq. 2), ``dual_silhouette``, ``overlap``
  (Rius eq. 7), ``pointcloud`` (Hauberg eq. 15), ``keypoints`` (Brubaker eq. 3-4), ``chamfer``, ``skin``;
  several combine with per-term weights (:class:`~torchpf.likelihoods.ProductLikelihood`).
* filters (:data:`FILTERS`): ``sir`` (= ``condensation``), ``qrs``, ``partitioned``, ``partitioned_qrs``,
  ``apf``, ``mcmc`` (Fontmarty Tables 1-4, Brubaker Alg. 1-4). ``n_particles`` is the number of likelihood
  evaluations per frame for every filter (Fontmarty's equal-budget protocol): the APF runs
  ``n_particles / L`` particles per layer, the partitioned filter ``n_particles / M`` per stage (torso, then
  one stage per limb, each weighted by the full likelihood unless ``partial_likelihoods``), the MCMC
  filter ``n_particles / (1 + R (L + 1))`` particles for R HMC moves of L leapfrog steps (gradients counted
  as evaluations).
* motion priors: any object following :mod:`torchpf.filters.protocols`, or a name registered under the
  ``torchpf.dynamics`` entry-point group (the ``priors`` package registers ``random_walk``,
  ``constant_velocity``, ``damped``, ``action``...). torchpf itself never imports ``priors``.

Initialisation (the papers initialise "by hand"): ``track(seq, init=...)`` takes ``"truth"`` (the first frame
of the ground truth, the default when the sequence has one), a (D,) pose or a mocap CSV, or ``"auto"``: the
person found from the silhouettes alone (:mod:`torchpf.detect`: visual hull, heading and stride search,
pose refined by :func:`torchpf.calibrate.fit_body`; a stick-figure body is replaced by the fitted one).
Particles are that pose plus Gaussian noise of ``init_spread`` (rad for angles, m for translations), clamped
to the joint limits. With ``recovery`` (default), a lost track (silhouettes gone, the estimate's likelihood
collapsed or its root off the visual hull) is re-acquired from the same detector
(:class:`torchpf.detect.Recovery`); ``result.failed`` / ``result.recovered`` flag those frames.

Example::

    tracker = Tracker(skel, cameras, likelihood="silhouette", dynamics="random_walk", filter="apf",
                      n_particles=600)
    result = tracker.track("data/seq01")              # a sequence directory
    result.save_csv("track.csv"); result.ess          # (T,) effective sample size per frame
"""

from __future__ import annotations

import dataclasses
import inspect
import os
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from torchpf.distributions import DYNAMICS, as_generator, make_dynamics
from torchpf.filters.base import frame_summary
from torchpf.filters.registry import FILTERS
from torchpf.io import MocapCsvWriter, write_mocap_csv
from torchpf.kinematics import body_partition
from torchpf.kinematics.anatomy import arm_bones, torso_limits
from torchpf.likelihoods import LIKELIHOODS, TemperedLikelihood, calibrate_temperature, make_likelihood
from torchpf.observations import Frame, Keypoints2D, PointCloud, Silhouettes


def _diffusion_std(dynamics) -> Any:
    """The step std of a motion prior (``std`` or ``sigma``, looking inside wrapping dynamics), else None."""
    while dynamics is not None:
        for name in ("std", "sigma"):
            value = getattr(dynamics, name, None)
            if value is not None:
                return value
        dynamics = getattr(dynamics, "dynamics", None)
    return None


def _spec_names(spec) -> list[str]:
    return [spec] if isinstance(spec, str) else list(spec)


@dataclass
class TrackResult:
    """What :meth:`Tracker.track` returns.

    Attributes:
        dof_names: (D) names of the columns of ``angles``.
        fps: frame rate (Hz) of the sequence.
        angles: (T, D) float64 MMSE estimates (rad / m), CPU.
        map_angles: (T, D) highest-weight particle of each frame.
        ess: (T,) effective sample size after weighting (Brubaker eq. 18).
        log_evidence: log p(z_{1:T}) estimate (see the filter's docstring for what the APF reports).
        failed: (T,) bool, frames where every weight was -inf/NaN (predicted particles kept), or where the
            track was judged lost (:class:`torchpf.detect.Recovery`) although the frame had evidence.
        no_evidence: (T,) bool, frames whose observations cannot tell poses apart (no camera with a usable
            mask, no points, no keypoints: :meth:`~torchpf.observations.Frame.has_evidence`); their
            estimate is the motion prior's prediction.
        stats: filter-specific per-frame statistics (HMC acceptance, APF betas, ...).
        seconds: wall-clock time of the filtering loop (and of the smoothing after it).
        likelihood_evaluations: per frame.
        recovered: (T,) bool, frames where a lost track was re-acquired (all False without recovery).
        skeleton: the skeleton the angles belong to: the tracker's, or the body fitted by ``init="auto"``.
        init: how the track started (``"truth"``, ``"pose"``, ``"auto"``).
        filtered_angles: (T, D) the filter's estimates where ``angles`` are the smoothed track
            (``Tracker(smooth=...)``), else None: each frame's from the frames up to it (what an online
            user gets).
    """

    dof_names: list[str]
    fps: float
    angles: torch.Tensor
    map_angles: torch.Tensor
    ess: torch.Tensor
    log_evidence: float
    failed: torch.Tensor
    stats: dict = field(default_factory=dict)
    seconds: float = 0.0
    likelihood_evaluations: int = 0
    no_evidence: torch.Tensor | None = None
    recovered: torch.Tensor | None = None
    skeleton: Any = None
    init: str = "truth"
    filtered_angles: torch.Tensor | None = None

    def save_csv(self, path: str | os.PathLike) -> None:
        """Write the estimates as mocap CSV (DESIGN.md: ``time`` column then one column per DOF)."""
        times = torch.arange(self.angles.shape[0], dtype=torch.float64) / self.fps
        write_mocap_csv(path, self.dof_names, self.angles.numpy(), times=times.numpy())


def _to_device(obs, device, dtype):
    """Move a Frame (and its containers' tensors) to ``device``; other objects pass through."""
    if isinstance(obs, torch.Tensor):
        return obs.to(device=device, dtype=dtype if obs.is_floating_point() else obs.dtype)
    if dataclasses.is_dataclass(obs) and not isinstance(obs, type):
        changes = {}
        for f in dataclasses.fields(obs):
            if f.name.startswith("_"):
                continue
            v = getattr(obs, f.name)
            if isinstance(v, torch.Tensor) or (dataclasses.is_dataclass(v) and not isinstance(v, type)):
                changes[f.name] = _to_device(v, device, dtype)
        return dataclasses.replace(obs, **changes) if changes else obs
    return obs


def _with_outline_offset(obs, cue, pose):
    """``obs`` (a :class:`Frame` or :class:`Silhouettes`) with its masks' outline offset measured by ``cue``
    (:meth:`~torchpf.likelihoods.images.ImageLikelihood.boundary_offset`) at ``pose``, the last estimate."""
    sil = obs.silhouettes if isinstance(obs, Frame) else obs
    if not isinstance(sil, Silhouettes) or sil.offset is not None or not bool(torch.isfinite(pose).all()):
        return obs  # nothing to measure, an offset the caller gave, or no estimate to measure it at
    sil = sil.with_offset(cue.boundary_offset(pose, sil))
    return dataclasses.replace(obs, silhouettes=sil) if isinstance(obs, Frame) else sil


def _evidence(obs, fields) -> bool:
    """Whether one frame's observations can tell poses apart for a likelihood reading ``fields`` of a
    :class:`Frame` (None: unknown, any field counts). Objects other than the containers: assumed."""
    if isinstance(obs, Frame):
        return obs.has_evidence(fields)
    for name, kind in (("silhouettes", Silhouettes), ("points", PointCloud), ("keypoints", Keypoints2D)):
        if isinstance(obs, kind):
            return Frame(**{name: obs}).has_evidence()
    return True


def _observed_fields(likelihood) -> set[str] | None:
    """The :class:`Frame` fields the likelihood's terms read (their ``obs_field``), None if one is unknown.
    A prior term (``obs_field`` None, e.g. :class:`~torchpf.likelihoods.SelfCollisionPrior`) reads none."""
    fields = set()
    for module in likelihood.modules():
        if hasattr(module, "obs_field") and module.obs_field is not None:
            if not module.obs_field:
                return None
            fields.add(module.obs_field)
    return fields or None


class _FrameBuffer:
    """Per-frame tensors of a run, moved to the CPU and stacked every ``chunk`` frames: a long run keeps a few
    (T, ...) arrays instead of T small tensors (each with its own allocation and object overhead)."""

    def __init__(self, chunk: int = 256):
        self.chunk, self.chunks, self.pending = chunk, {}, {}

    def add(self, values: Mapping[str, torch.Tensor]) -> None:
        for key, value in values.items():
            self.pending.setdefault(key, []).append(torch.as_tensor(value).detach().cpu())
        if len(next(iter(self.pending.values()), ())) >= self.chunk:
            self._flush()

    def _flush(self) -> None:
        for key, values in self.pending.items():
            self.chunks.setdefault(key, []).append(torch.stack(values))
        self.pending = {}

    def result(self) -> dict[str, torch.Tensor]:
        self._flush()
        return {key: torch.cat(chunks) for key, chunks in self.chunks.items()}


class _Frames:
    """``n`` items made on demand by ``make(t)``: indexable, re-iterable, with a length (progress bar)."""

    def __init__(self, n: int, make):
        self.n, self.make = n, make

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, t: int):
        return self.make(t)

    def __iter__(self):
        return (self.make(t) for t in range(self.n))


def _warn_outside_limits(skeleton, pose: torch.Tensor, how: str) -> None:
    """Warn when the initial ``pose`` (D,) lies outside ``skeleton``'s joint limits (by more than 1e-6, the
    limits' rounding in a URDF): the filter starts from it clamped, not from the pose given (e.g. limits
    learned from other performers' mocap, ``python -m training fit-limits``)."""
    beyond = (pose - skeleton.clamp(pose)).abs()
    bad = torch.nonzero(beyond > 1e-6).flatten().tolist()
    if bad:
        worst = sorted(bad, key=lambda d: -float(beyond[d]))
        shown = ", ".join(f"{skeleton.dof_names[d]} by {float(beyond[d]):.3g}" for d in worst[:3])
        more = f" and {len(bad) - 3} more" if len(bad) > 3 else ""
        warnings.warn(
            f"Tracker: the initial pose ({how}) lies outside the skeleton's joint limits on {len(bad)} DOFs "
            f"({shown}{more} rad or m); the track starts from it clamped",
            stacklevel=3,
        )


def _limit_the_torso(skeleton, limit: float):
    """``skeleton`` with its unlimited torso rotations held within ``limit`` rad
    (:func:`~torchpf.kinematics.anatomy.torso_limits`), warned when it guesses."""
    limited, names = torso_limits(skeleton, limit)
    if names:
        warnings.warn(
            f"Tracker: {len(names)} rotations of the skeleton's torso chain (spine, neck, head, found from "
            f"the tree: {names[0]}, ...) have no joint limits; holding each within {limit:g} rad of the "
            "rest pose, a guess from the structure (limits of the skeleton's own, e.g. from 'python -m "
            "training fit-limits', are kept where it has them)",
            stacklevel=3,
        )
    return limited


class Tracker(nn.Module):
    """Articulated tracker assembled from a skeleton, cameras, a likelihood, a motion prior and a filter.

    Args:
        skeleton: :class:`~torchpf.Skeleton` (or a URDF path).
        cameras: a :class:`~torchpf.camera.CameraRig` / list of cameras (image likelihoods need them).
        likelihood: a module, a name, a list of names or ``{name: weight}`` (see :func:`make_likelihood`).
            Default: the bidirectional silhouette cue, Fontmarty's silhouette (model inside the mask) times
            the dual silhouette (mask covered by the model), which penalises a model thinner than the
            silhouette or a limb folded into the torso; measured best on foreign renders (BENCHMARKS.md).
        likelihood_options: ``{name: {keyword: value}}`` for the named likelihoods.
        temperature: exponent ``beta`` on the log-likelihood
            (:class:`~torchpf.likelihoods.TemperedLikelihood`), or ``"auto"``: set per sequence on the first
            frame so that one prediction step of the initial particles keeps ``ESS / N = 0.2``
            (:func:`~torchpf.likelihoods.calibrate_temperature`), whatever the masks' resolution and noise
            make the cue's sharpness. ``result.stats["temperature"]`` reports it. Not the default: on
            noisy foreign renders it tracked two draws at 87.0 / 74.5 mm against 67.4 / 66.4 with the
            fixed exponent 1 (BENCHMARKS.md, "Round 12"); the hybrid's last annealing layer is meant to be
            sharp (ESS ~2 of 167), its estimate is the refined one.
        dynamics: a motion prior object or a registered name (see :func:`make_dynamics`). With the
            ``priors`` package: ``"random_walk"`` (default), ``"constant_velocity"``, ``"damped"``,
            ``"learned"``, ``"action"`` (one action model) and ``"bank"`` (several,
            ``dynamics_options={"models": [walk.npz, run.npz]}``); the bank of actions learned from other
            performers' mocap, on a skeleton with their joint limits, is the most accurate set-up measured on
            noisy masks (BENCHMARKS.md, "A learned prior").
        dynamics_options: keywords of the named prior's factory (e.g. ``{"scale": 0.5}``).
        proposal: optional importance distribution (``sample(state, obs, generator) -> (x, log_q)``).
        filter: one of :data:`FILTERS`, or ``"auto"`` (default): ``"hybrid"`` (APF layers, then gradient
            refinement on the silhouettes, :mod:`torchpf.filters.hybrid`) when the likelihood reads
            silhouettes and cameras are given, else ``"apf"``. On foreign renders of 11 CMU clips at 500
            evaluations per frame the hybrid's error was 2.5x lower on clean masks (BENCHMARKS.md, "Hybrid
            search"); the refinement needs the silhouettes its cue reads. The hybrid also tries the mirror
            limbs of the skeleton exchanged (``swaps``, :func:`torchpf.kinematics.symmetry.limb_swaps`, from
            the tree and the rest pose): on the same renders, clean masks, 47 -> 43 mm and 8 -> 1 % of frames
            failed, the runs' lost arms put back (BENCHMARKS.md, "Swapped limbs").
        n_particles: likelihood evaluations per frame (the equal-budget N of Fontmarty's protocol).
        filter_options: extra keywords of the filter (e.g. ``{"betas": "adaptive"}`` for the APF;
            ``{"swaps": ()}`` turns the hybrid's limb swaps off).
        init_spread: std of the initial particles around the initial pose: a float (rad and m alike) or a
            (D,) tensor.
        fps: frame rate (Hz) of the sequences to track; passed to a named prior's factory that takes ``fps``
            (the default random walk's structural stds are a distance per frame, ``speed / fps``;
            :mod:`priors.diffusion`). ``None``: each sequence's own rate where it has times (:meth:`track`
            builds the named prior for it), else the factory's default, with its warning. Tracking a 30 fps
            foreign render of CMU 16_21 with the prior built for Table 5's 5 Hz gave 98 mm instead of 41.
        recovery: detect a lost track and re-acquire it from the silhouettes
            (:class:`torchpf.detect.Recovery`, Brubaker §6).
        boundary_offset: before each frame, measure how far each mask's outline lies outside the body's at
            the last estimate (:meth:`~torchpf.likelihoods.images.ImageLikelihood.boundary_offset`: a
            segmentation that fattens or thins the person per camera and frame) and let the silhouette cues
            widen or thin the projected capsules by it (:attr:`~torchpf.observations.Silhouettes.offset`).
            Off by default: on foreign renders whose only defect is a random 1-px erosion or dilation per
            camera and frame it took two clips from 97 / 110 to 61 / 59 mm; on the full noisy preset (11
            clips, three draws of the defects, 2 runs) with today's filter 85 mm against 84 (96 / 82 / 78
            per draw), clean masks 32-34 mm against 31 (BENCHMARKS.md, "The rig's unanimated channels, and
            the masks' outline offset, as defaults"); four draws with session 21's defaults: 69.1 mm
            against 64.0, "Round 12"). The smoothing reads the masks without it (with it: 81 / 80 mm
            against 75 / 78 on two draws; farther on every saved track re-smoothed in session 22).
        smooth: after the last frame, smooth the whole track on the refinement's cue under an acceleration
            prior (:class:`~torchpf.smooth.TrajectorySmoother`, a fixed-interval smoother: each frame's
            estimate then also sees the frames after it); ``result.filtered_angles`` keeps the filter's
            own. ``None`` (default): where the likelihood reads silhouettes through cameras (the cue needs
            them). On foreign renders of the 11 CMU clips (500 evaluations per frame) it took clean masks
            from 38 to 31 mm and noisy ones from 97 to 84 mm, for ~15 ms per frame on one CPU core
            (BENCHMARKS.md, "Smoothing the track"); started from the track's running median over 5
            frames (not from the track itself), noisy ones 71.4 -> 69.1 mm over five draws
            (BENCHMARKS.md, "The smoother's start"); its cue reading 512 foreground samples per camera
            (the refiner's 128), 1.2-1.6 mm closer still (BENCHMARKS.md, "Round 9"); with twice the model
            points per capsule, 120 steps and ``scale`` 12, 1.1-2.2 mm closer again (BENCHMARKS.md,
            "Round 10"); with each camera's mask down-weighted where it costs far more than usual
            (``robust``, :data:`~torchpf.smooth.ROBUST`), 2.1 / 1.5 mm closer again on two draws' saved
            filter tracks, every track closer, clean ones as they were (BENCHMARKS.md, "Round 11"); end to
            end, ten noisy draws 67.5 mm against 70.5 (paired -2.9, standard error 1.0; "Round 12").
            ``False`` for the filter alone (an online use).
        smooth_options: keywords of :class:`~torchpf.smooth.TrajectorySmoother`; besides its own, ``scale``
            (default 12): its acceleration std ``sigma`` is ``scale`` times the motion prior's per-frame
            step std (0.03 rad or m where the prior has none), unless ``sigma`` is given. The body refit's
            first pass (:meth:`_refit`) smooths with ``median=1`` and ``robust=None`` unless given here.
        torso_limit: where the skeleton leaves the torso's rotations unlimited (a converted BVH: the spine,
            neck and head joints, found from the tree, :func:`~torchpf.kinematics.anatomy.torso_limits`),
            hold each within this many rad of the rest pose (e.g.
            :data:`~torchpf.kinematics.anatomy.TORSO_LIMIT`, 0.5), with a warning that says so; limits the
            skeleton has are kept. ``None`` (default): the skeleton as given. Not the default: on noisy
            foreign renders of the 11 CMU clips, 0.5 rad tracked ten draws of the defects at 66.6 mm
            against 67.5 (paired -0.9, standard error 1.4: no gain resolved) with more frames failed
            (21.5 % against 19.7), though the torso's limits learned from mocap gained ~7 mm on two draws
            (BENCHMARKS.md, "Which joint limits carry the gain").
        device, dtype: where and in which precision to run (observations are moved per frame).
        progress: tqdm progress bar.
    """

    def __init__(
        self,
        skeleton,
        cameras=None,
        *,
        likelihood: Any = ("silhouette", "dual_silhouette"),
        likelihood_options: Mapping[str, Mapping] | None = None,
        temperature: float | str = 1.0,
        dynamics: Any = "random_walk",
        dynamics_options: Mapping[str, Any] | None = None,
        proposal: Any = None,
        filter: str = "auto",
        n_particles: int = 500,
        filter_options: Mapping[str, Any] | None = None,
        init_spread: float | torch.Tensor = 0.02,
        fps: float | None = None,
        recovery: bool = True,
        boundary_offset: bool = False,
        smooth: bool | None = None,
        smooth_options: Mapping[str, Any] | None = None,
        torso_limit: float | None = None,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float32,
        progress: bool = True,
    ):
        super().__init__()
        # the keywords, to rebuild the same tracker on a fitted body (``track(init="auto")``)
        self._options = {
            k: v for k, v in locals().items() if k not in ("self", "skeleton", "cameras", "__class__")
        }
        if not isinstance(skeleton, nn.Module):
            from torchpf.skeleton import Skeleton

            skeleton = Skeleton.from_urdf(skeleton)
        if torso_limit is not None:
            skeleton = _limit_the_torso(skeleton, torso_limit)
        filter_name = None if filter == "auto" else FILTERS.canonical(filter)  # unknown names raise here
        if n_particles < 1:
            raise ValueError(f"n_particles must be >= 1, got {n_particles}")
        self.skeleton = skeleton
        self.cameras = cameras
        self._likelihood_spec = likelihood
        self._likelihood_options = dict(likelihood_options or {})
        self.likelihood = make_likelihood(skeleton, cameras, likelihood, likelihood_options)
        if isinstance(temperature, str) and temperature != "auto":
            raise ValueError(f"temperature must be a number or 'auto', got {temperature!r}")
        if temperature == "auto" or float(temperature) != 1.0:  # "auto" starts at 1, set per sequence
            self.likelihood = TemperedLikelihood(
                self.likelihood, 1.0 if temperature == "auto" else temperature
            )
        self.temperature = temperature
        # a named prior that takes a rate but got none: track() builds it for the sequence's (or warns),
        # and remembers the rate it built it for
        self._rate_unknown, self._rate_built = False, None
        if isinstance(dynamics, str):
            options = dict(dynamics_options or {})
            factory = DYNAMICS.get(dynamics) if dynamics in DYNAMICS else None
            takes_fps = factory is not None and "fps" in inspect.signature(factory).parameters
            if "fps" not in options and takes_fps:
                if fps is not None:
                    options["fps"] = fps  # a random walk's per-frame std depends on the frame rate
                else:
                    self._rate_unknown = True
            with warnings.catch_warnings():
                if self._rate_unknown:  # said in track(), where the sequence may still give the rate
                    warnings.filterwarnings("ignore", message=".*no fps given")
                dynamics = make_dynamics(dynamics, skeleton, **options)
        self.dynamics = dynamics
        self.proposal = proposal
        if filter_name is None:  # "auto": refine where the silhouettes give the refinement its cue
            filter_name = "hybrid" if self._reads_silhouettes() else "apf"
        self.filter_name = filter_name
        self.n_particles = int(n_particles)
        self.filter_options = dict(filter_options or {})
        self.init_spread = init_spread
        self.fps = fps
        self.recovery = recovery
        self.boundary_offset = bool(boundary_offset)
        self.smooth = smooth
        self.smooth_options = dict(smooth_options or {})
        if smooth and not self._reads_silhouettes() and "cue" not in self.smooth_options:
            raise ValueError(
                "smooth=True smooths on the silhouettes and needs cameras and a silhouette likelihood; "
                "otherwise pass smooth_options={'cue': a differentiable cue}"
            )
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.dtype = dtype
        self.progress = progress
        self.filter = self._build_filter()
        spent = self.filter.likelihood_evaluations
        if spent is not None and spent > n_particles:  # the filter's smallest set costs more than that
            warnings.warn(
                f"Tracker: filter {self.filter_name!r} spends {spent} likelihood evaluations per frame with "
                f"{self.filter.n_particles} particle(s), more than n_particles={n_particles}: raise "
                "n_particles, or lower what one particle costs (HMC moves, refinement steps)",
                stacklevel=2,
            )
        self.to(self.device)  # the modules follow the particles' device

    def to(self, *args, **kwargs) -> Tracker:
        """Move the computation: ``tracker.to("cuda")``, ``.to(torch.float64)``, ``.to(device, dtype)``.

        The device moves every submodule (skeleton, likelihoods, cameras, dynamics) and sets
        :attr:`device`, where the particles and the run's generator then live; a dtype sets :attr:`dtype`,
        the particles' precision. Buffers keep their own (float64) precision and are cast per call to the
        particles' dtype, so ``.to(torch.float32)`` loses nothing (learnable parameters included: they stay
        in their precision and the cast is part of the graph).
        """
        device, dtype, non_blocking, _ = torch._C._nn._parse_to(*args, **kwargs)
        if dtype is not None:
            if not dtype.is_floating_point:
                raise TypeError(f"Tracker.to only accepts floating dtypes, got {dtype}")
            self.dtype = dtype
        if device is not None:
            self.device = torch.device(device)
            if self.device.type == "cuda" and self.device.index is None:
                self.device = torch.device("cuda", torch.cuda.current_device())
            super().to(device=self.device, non_blocking=non_blocking)
        return self

    def cuda(self, device: int | torch.device | None = None) -> Tracker:
        return self.to(torch.device("cuda", device) if isinstance(device, int) else device or "cuda")

    def cpu(self) -> Tracker:
        return self.to("cpu")

    def double(self) -> Tracker:
        return self.to(torch.float64)

    def float(self) -> Tracker:
        return self.to(torch.float32)

    @classmethod
    def from_config(
        cls, config: Mapping[str, Any] | str | os.PathLike, skeleton=None, cameras=None, **overrides
    ):
        """Build from a dict or a YAML file with the constructor's keywords (``skeleton`` may be a path).

        Example YAML::

            skeleton: skeleton.urdf
            likelihood: {silhouette: 1.0, dual_silhouette: 0.5}
            dynamics: random_walk
            filter: apf
            n_particles: 600
            filter_options: {betas: adaptive}
        """
        if not isinstance(config, Mapping):
            import yaml

            from torchpf.io import load_yaml

            path = os.fspath(config)
            try:
                with open(path, encoding="utf-8") as f:
                    loaded = load_yaml(f.read()) or {}  # plain numbers only (no "1_000")
            except yaml.YAMLError as e:
                raise ValueError(f"{path}: invalid YAML ({e})") from None
            if not isinstance(loaded, Mapping):
                raise ValueError(f"{path}: a tracker config must be a mapping of keywords")
            config = loaded
        kwargs = {**config, **overrides}
        skeleton = kwargs.pop("skeleton", None) if skeleton is None else skeleton
        if skeleton is None:
            raise ValueError("the config names no skeleton and none was given")
        kwargs.pop("cameras", None)
        if "dtype" in kwargs and isinstance(kwargs["dtype"], str):
            kwargs["dtype"] = getattr(torch, kwargs["dtype"])
        return cls(skeleton, cameras, **kwargs)

    # ------------------------------------------------------------------ assembly
    def _build_filter(self):
        opts = dict(self.filter_options)
        opts.setdefault("progress", self.progress)
        kind = FILTERS.get(self.filter_name)
        if kind.partitioned:
            per_limb = opts.pop("per_limb", True)
            partial = opts.pop("partial_likelihoods", False)
            groups = opts.pop("groups", None) or body_partition(self.skeleton, per_limb=per_limb)
            stages = self._stage_likelihoods(groups) if partial else [self.likelihood] * len(groups)
            n = kind.for_budget(self.n_particles, groups=groups, **opts)
            return kind.build(self.dynamics, stages, groups, n_particles=n, **opts)
        if getattr(kind.cls, "needs_refiner", False) and "refiner" not in opts:
            from torchpf.refine import Refiner

            refine_options = dict(opts.pop("refine_options", {}))
            if self.cameras is None and "cue" not in refine_options:
                raise ValueError(
                    f"filter={self.filter_name!r} refines poses on the silhouettes and needs cameras; "
                    "without them pass filter_options={'refine_options': {'cue': a differentiable cue}}"
                )
            if "steps" not in refine_options and "n_refine" not in opts:  # a small budget refines less
                k, refine_options["steps"] = kind.cls.plan_refinement(self.n_particles)
                opts["n_refine"] = k
            opts["refiner"] = Refiner(self.skeleton, self.cameras, **refine_options)
            if "swaps" not in opts and hasattr(self.skeleton, "tree"):
                from torchpf.kinematics.symmetry import limb_swaps

                opts["swaps"] = limb_swaps(self.skeleton)  # mirror limbs, from the tree and the rest pose
        if self.filter_name in ("apf", "hybrid") and "diffusion_std" not in opts:
            if getattr(self.dynamics, "std", None) is None:
                opts["diffusion_std"] = _diffusion_std(self.dynamics)
        n = kind.for_budget(self.n_particles, **opts)
        return kind.build(self.dynamics, self.likelihood, self.proposal, n_particles=n, **opts)

    def _stage_likelihoods(self, groups: list[list[int]]) -> list:
        """Partial likelihoods l_m of Fontmarty Table 2 (``filter_options={"partial_likelihoods": True}``):
        stage m scores only the bones moved by partitions 1..m (terms built by name that take ``bones``); the
        last stage is the full likelihood. A likelihood given as a module is used whole at every stage.

        Not the default: in the evaluation harness (CMU walk + generated walk, N=500, R=3) they raised the
        RMSE from about 13 cm to 18 cm, because the partitioned filter multiplies the stage weights and the
        partial silhouette terms of the early stages pull the torso toward poses the limbs cannot explain.
        """
        if isinstance(self._likelihood_spec, nn.Module):
            return [self.likelihood] * len(groups)
        owner = self.skeleton.dof_joints
        stages, moved = [], set()
        for group in groups[:-1]:
            moved |= {owner[d] for d in group}
            bones = [c for c, (_, child) in enumerate(self.skeleton.bones) if child in moved]
            options = {}
            for term in _spec_names(self._likelihood_spec):
                options[term] = dict(self._likelihood_options.get(term, {}))
                if "bones" in inspect.signature(LIKELIHOODS[term]).parameters:
                    options[term]["bones"] = bones
            stages.append(make_likelihood(self.skeleton, self.cameras, self._likelihood_spec, options))
        return [*stages, self.likelihood]

    @property
    def likelihood_evaluations(self) -> int:
        """Likelihood evaluations per frame of the assembled filter (at most ``n_particles``)."""
        return self.filter.likelihood_evaluations

    def _calibrate_temperature(self, x0: torch.Tensor, obs, generator) -> None:
        """Set the likelihood exponent from frame 0: the particles one prediction step after ``x0``."""
        dynamics = self.filter.dynamics
        with torch.no_grad():
            predicted = dynamics.sample(x0, generator, extras=dynamics.init_extras(x0))
            beta = calibrate_temperature(self.likelihood.likelihood, predicted, obs)
        self.likelihood.beta = beta.to(self.likelihood.beta)

    # ------------------------------------------------------------------ running
    def initial_particles(self, pose: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """(N, D) initial particles: ``pose`` (D,) plus N(0, init_spread^2) noise, clamped to the limits.

        N is the filter's particle count (per layer / stage for the APF / partitioned filter).
        """
        pose = torch.as_tensor(pose, dtype=self.dtype).to(self.device)
        n = self.filter.n_particles
        spread = torch.as_tensor(self.init_spread, dtype=self.dtype, device=self.device)
        generator = as_generator(generator, self.device)
        noise = torch.randn(n, pose.shape[-1], generator=generator, dtype=self.dtype, device=self.device)
        x0 = pose + noise * spread
        x0[0] = pose  # the given pose itself is one of the hypotheses
        return self.skeleton.clamp(x0)

    #: ``init="auto"`` on an uncalibrated body: frames tracked to fit the body again at the tracked poses
    #: (:meth:`_refit`; 0 or 1: keep the body fitted at the detected pose). 16 against 8 on the 11
    #: foreign clips: 53 against 56 mm with clean masks, 110 against 123 with noisy ones, for ~10 s more
    #: start-up per sequence on a 2-core VM (BENCHMARKS.md).
    auto_refit_frames: int = 16

    #: A given initial pose on an uncalibrated body: frames tracked on the body fitted to frame 0, then the
    #: body fitted again to those frames at the tracked poses and the whole sequence tracked on it
    #: (:meth:`_refit`; 0 or 1: track on the frame-0 body). One frame's mask defects (a 1-px erosion or
    #: dilation is a third of a limb at 160x120) make a one-frame fit's radii off by a factor of 2-3 on noisy
    #: masks; 30 frames average the defects out (BENCHMARKS.md, "The body refitted over the first 30 tracked
    #: frames").
    refit_frames: int = 30

    #: The refit's outline offsets (:func:`torchpf.calibrate.fit_body` ``view_offset_sigma``, px; None: fit
    #: every mask as it is). With 1.0 each mask's own erosion or dilation is fitted beside the shared radii:
    #: on noisy foreign renders the body fitted at the true poses matched the clean masks better (IoU
    #: 0.74-0.85 -> 0.82-0.87), but the tracks did not gain (five noisy draws: 71.6 mm against 71.4, frames
    #: failed 22.7 against 21.1 %; BENCHMARKS.md, "Outline offsets in the body fit"), so it is an option.
    refit_view_offset: float | None = None

    #: The spread of the body's widths in ``track``'s body fits (frame 0 and the refit; the
    #: ``radius_sigma`` of :func:`torchpf.calibrate.fit_body`; None: each bone group's radius fitted
    #: freely). At 0.25 the bodies fitted to noisy foreign renders stay sane (a 35-70 mm torso where a free
    #: fit gives 1-8 mm and 100 mm hands), but the tracks were no closer: four noisy draws paired 0.0 mm,
    #: and with the limb-torso prior (``"self_collision"``) +4.7 mm over four (BENCHMARKS.md, "Round 10"
    #: and "Round 11"). An option for bodies a user knows to be ordinary.
    fit_radius_sigma: float | None = None

    #: ``track``'s bodies (fitted to frame 0, then refitted) keep the arms' capsule radii as the skeleton has
    #: them (:func:`~torchpf.kinematics.anatomy.arm_bones`) when the masks cannot measure them: the arms'
    #: thickest capsule projects to a radius under this many pixels of frame 0's masks at the initial pose
    #: (:func:`~torchpf.calibrate.projected_radii`, mean over the cameras) *and* frame 0's masks are noisy,
    #: their outlines straying from the body fitted to them by more than :attr:`hold_arms_outline` px
    #: (:func:`~torchpf.calibrate.outline_disagreement`, mean over the cameras); warned. Each fit fits every
    #: capsule; the arms' radii are put back after it. None fits the arms like every other capsule (``track
    #: --hold-thin-arms PX|none``). Masks whose outlines move by a pixel do not measure an arm a pixel or two
    #: across: on noisy foreign renders (160x120, the converted CMU skeleton's upper arms 1.1-1.6 px) the fit
    #: made the arms 1.3-2.4 times as thick as the clean masks' fit does. Put back at the converter's ``0.15
    #: x`` bone length after each fit, ten noisy draws tracked at 62.4 against 67.5 mm (paired -5.1,
    #: standard error 1.3); held *during* the fits instead, 65.3 (paired -2.3, standard error 1.7). Clean
    #: masks do measure the arms (held there too, 29.7 against 26.9 mm), hence the outline test, which holds
    #: nothing on them (BENCHMARKS.md, "The arms put back after each fit").
    hold_thin_arms: float | None = 2.0

    #: The outline disagreement (px) of frame 0's masks with the body fitted to them, mean over the cameras,
    #: above which :attr:`hold_thin_arms` holds thin arms. Frame 0 of the foreign renders of 11 CMU clips
    #: (two draws of the defects, body fitted at the true pose): 0.15-0.26 px on clean masks, 0.59-0.85 with
    #: the noisy preset's defects, 0.17-0.48 with any one of them alone (ragged edges and speckle the most).
    hold_arms_outline: float = 0.5

    def with_skeleton(self, skeleton) -> Tracker:
        """The same tracker (all keywords alike) on another skeleton, e.g. a body fitted to the masks. It runs
        where this one runs now (:meth:`to` included), at the frame rate its prior was built for."""
        fps = self.fps if self.fps is not None else self._rate_built
        options = {**self._options, "device": self.device, "dtype": self.dtype, "fps": fps}
        return type(self)(skeleton, self.cameras, **options)

    def _prior_for_rate(self, fps: float) -> None:
        """Build the named motion prior, and the filter around it, for frame rate ``fps``: a tracker made
        without ``fps`` learns the rate from the sequence (the likelihood and its parameters stay)."""
        if self._rate_built == fps:
            return
        options = {**dict(self._options["dynamics_options"] or {}), "fps": fps}
        self.dynamics = make_dynamics(self._options["dynamics"], self.skeleton, **options)
        self.filter = self._build_filter()
        self.to(self.device)
        self._rate_built = fps

    def track(
        self,
        sequence,
        *,
        init: torch.Tensor | str | os.PathLike | None = None,
        generator: torch.Generator | None = None,
        seed: int | None = 0,
        fps: float | None = None,
        out: str | os.PathLike | None = None,
        calibrate: bool | None = None,
    ) -> TrackResult:
        """Track a sequence, one frame at a time.

        Args:
            sequence: a sequence directory (path), a :class:`~torchpf.sequence.SequenceData`, or a list of
                per-frame observations (:class:`~torchpf.observations.Frame` or whatever the likelihood
                takes). A directory is read lazily (:func:`~torchpf.sequence.read_sequence`): each frame is
                read, moved to the device, tracked and dropped, so memory does not grow with the length.
            init: ``"truth"`` (the sequence's first ground-truth frame; the default when it has one), a (D,)
                pose, a mocap CSV path (its first row), or ``"auto"``: found from the silhouettes alone
                (:meth:`torchpf.detect.PersonDetector.fit`: visual hull, heading and stride search, pose
                refined by :func:`torchpf.calibrate.fit_body` on frame 0). When the body looks uncalibrated
                (:func:`torchpf.detect.looks_uncalibrated`, warned) the track runs on the fitted body,
                returned as ``result.skeleton``: fitted at the detected pose, then again at the poses
                tracked over the first :attr:`auto_refit_frames` frames where that explains them better
                (:meth:`_refit`).
            generator: random generator; default one seeded with ``seed`` (0). A generator on another device
                than the tracker's seeds a new one there (:func:`torchpf.distributions.as_generator`).
            fps: frame rate of the result (default: from the sequence's times, else 30).
            out: optional mocap CSV written as the frames are tracked (:class:`~torchpf.io.MocapCsvWriter`):
                ``<out>.partial`` holds every finished frame if the run stops, ``out`` appears complete at
                the end.
            calibrate: fit the body's widths and scale to frame 0's silhouettes at the initial pose first
                (:func:`torchpf.detect.fit_body_to_frame`), then again to the first :attr:`refit_frames`
                frames at the poses tracked on that body (:meth:`_refit`), and track on the refitted body
                (``result.skeleton``), starting from the initial pose (not a fit's refined one, which one
                frame's mask defects move). Arms too thin for noisy masks to measure get the skeleton's
                widths back after both fits (:attr:`hold_thin_arms`). ``None`` (default): only when the
                body looks uncalibrated (:func:`torchpf.detect.looks_uncalibrated`: a converted skeleton's
                stick-figure capsules), with a warning; on foreign renders of 3 CMU clips it took the hybrid
                tracker from 60 to 47 mm on clean masks and 157 to 120 mm on noisy ones (BENCHMARKS.md).
                Needs cameras and a silhouette likelihood.

        Returns:
            :class:`TrackResult`; ``no_evidence`` flags the frames without usable observations.

        Raises:
            ValueError: no frames, no observations at all (no masks, points or keypoints), or no frame with
                evidence (every mask empty or missing); no initial pose; a malformed frame (the error names
                its file).
        """
        from torchpf.sequence import SequenceData, read_sequence

        where = "the sequence"
        if isinstance(sequence, str | os.PathLike):
            where = os.fspath(sequence)
            sequence = read_sequence(sequence)
        if isinstance(init, str | os.PathLike) and os.fspath(init) not in ("auto", "truth"):
            from torchpf.io import read_mocap_csv

            _, _, rows = read_mocap_csv(init, expected_dof_names=self.skeleton.dof_names)
            if len(rows) == 0:
                raise ValueError(f"{os.fspath(init)}: the initial pose CSV has no rows")
            init = torch.as_tensor(rows[0], dtype=torch.float64)
        truth = None
        if isinstance(sequence, SequenceData):
            observed = _observed_fields(self.likelihood)
            if len(sequence) and not sequence.has_observations(observed):
                what = "masks, points or keypoints" if observed is None else " or ".join(sorted(observed))
                raise ValueError(f"{where}: no observations to track (no {what})")
            frames = _Frames(len(sequence), sequence.frame)
            if sequence.truth is not None and (init is None or isinstance(init, str) and init == "truth"):
                truth = sequence.truth_in(self.skeleton.dof_names)[0]
            if fps is None and sequence.times is not None and len(sequence.times) > 1:
                fps = 1.0 / float(sequence.times[1] - sequence.times[0])
        else:
            frames = list(sequence)
        if self._rate_unknown:
            if fps is not None:
                self._prior_for_rate(float(fps))
            else:
                warnings.warn(
                    f"Tracker: no fps given and {where} has no times; the {self._options['dynamics']!r} "
                    "prior's per-frame stds assume its default rate (pass fps=)",
                    stacklevel=2,
                )
        if not len(frames):
            raise ValueError("the sequence has no frames")
        how = "pose"
        if init is None or isinstance(init, str) and init == "truth":
            if truth is None:
                raise ValueError(
                    'no initial pose: the sequence has no ground truth; pass init="auto" or a pose'
                )
            init, how = truth, "truth"
        elif isinstance(init, str) and init == "auto":
            pose, fitted = self._auto_init(frames, calibrate)
            if fitted is not None:
                fitted, pose, _ = self._refit(
                    fitted,
                    pose,
                    frames,
                    seed,
                    fps,
                    self.auto_refit_frames,
                    gate=True,
                    held=self._held_arms(frames[0], pose, fitted, pose),
                )
                tracker = self.with_skeleton(fitted)
                result = tracker.track(
                    sequence, init=pose, generator=generator, seed=seed, fps=fps, out=out, calibrate=False
                )
                result.init = "auto"
                return result
            init, how = pose, "auto"
        init = torch.as_tensor(init, dtype=torch.float64)
        if init.shape != (len(self.skeleton.dof_names),):
            raise ValueError(
                f"init must be a ({len(self.skeleton.dof_names)},) pose, got {tuple(init.shape)}"
            )
        if how != "auto":  # the detector's pose is inside the limits; a given one may not be
            _warn_outside_limits(self.skeleton, init, how)
        if how != "auto" and self._calibrates(calibrate, frames[0], init=how):
            from torchpf.detect import fit_body_to_frame

            fitted, report = fit_body_to_frame(
                self.skeleton, self.cameras, frames[0], init, radius_sigma=self.fit_radius_sigma
            )
            held = self._held_arms(frames[0], init, fitted, report.poses[0])
            fitted, _, _ = self._refit(
                fitted, fitted.clamp(init), frames, seed, fps, self.refit_frames, held=held
            )
            # The track starts at the pose given, not at the fit's: refined on one frame with defects, the
            # fit's pose drifts (60-65 mm on noisy foreign renders, legs crossed in 3-4 of 11 clips); the
            # track needs only the body from the fit (BENCHMARKS.md, "Where the track starts after the
            # frame-0 fit").
            result = self.with_skeleton(fitted).track(
                sequence,
                init=fitted.clamp(init),  # outside the limits it was warned about above
                generator=generator,
                seed=seed,
                fps=fps,
                out=out,
                calibrate=False,
            )
            result.init = how
            return result
        fps = float(fps or self.fps or 30.0)
        # one generator on the particles' device drives the run (from the seed, or derived from `generator`)
        generator = as_generator(generator if generator is not None else int(seed or 0), self.device)
        x0 = self.initial_particles(init, generator)
        evidence, observed = [], _observed_fields(self.likelihood)

        outline = self._outline_cue() if self.boundary_offset else None
        latest = {"pose": init.to(self.device, self.dtype)}

        def observe(t: int):  # one frame in memory at a time: read (lazily), moved, tracked, dropped
            f = frames[t]
            evidence.append(_evidence(f, observed))
            f = _to_device(f, self.device, self.dtype)
            return f if outline is None else _with_outline_offset(f, outline, latest["pose"])

        t0 = time.perf_counter()
        if self.temperature == "auto":
            self._calibrate_temperature(x0, _to_device(frames[0], self.device, self.dtype), generator)
        hook = self._recovery(fps) if self.recovery and self.cameras is not None else None
        buffer = _FrameBuffer()
        writer = MocapCsvWriter(out, self.skeleton.dof_names, fps=fps) if out is not None else None
        state = None
        try:
            for state in self.filter.iterate(_Frames(len(frames), observe), x0, generator, hook=hook):
                fields, stats = frame_summary(state)
                latest["pose"] = fields["estimates"]
                buffer.add({**fields, **{f"stats/{k}": v for k, v in stats.items()}})
                if writer is not None:
                    writer.write(fields["estimates"].detach().to("cpu", torch.float64))
            if not any(evidence):
                raise ValueError(
                    f"{where}: no frame has evidence (every mask is empty or missing, no points or keypoints)"
                )
            per_frame = buffer.result()
            filtered = None
            if self.smooth if self.smooth is not None else self._reads_silhouettes():
                filtered = per_frame["estimates"]
                moved = _Frames(len(frames), lambda t: _to_device(frames[t], self.device, self.dtype))
                # the run's rows sit on the CPU; the smoother works where the particles did
                smoothed = self._smoother()(filtered.to(self.device), moved).x
                per_frame["estimates"] = smoothed.to("cpu", filtered.dtype)
        except BaseException:  # the filter's rows so far stay in OUT.partial
            if writer is not None:
                writer.abort()
            raise
        if writer is not None and filtered is not None:  # OUT gets the smoothed track, written atomically
            writer.abort()
            times = torch.arange(len(filtered), dtype=torch.float64) / fps
            write_mocap_csv(out, self.skeleton.dof_names, per_frame["estimates"].cpu().double(), times)
            os.remove(writer.partial)
        elif writer is not None:
            writer.close()
        seconds = time.perf_counter() - t0
        stats = {k[len("stats/") :]: v for k, v in per_frame.items() if k.startswith("stats/")}
        if isinstance(self.likelihood, TemperedLikelihood):
            stats["temperature"] = self.likelihood.beta.detach().cpu().clone()
        failed = per_frame["failed"]
        recovered = torch.zeros_like(failed)
        no_evidence = ~torch.tensor(evidence, dtype=torch.bool).reshape(failed.shape)
        if hook is not None:
            # a frame nobody can see is reported as no_evidence, not as lost: "failed" means the track was
            # lost while the masks showed the person (the recovery still re-acquires after an occlusion)
            lost = torch.tensor(hook.lost, dtype=torch.bool).reshape(failed.shape)
            failed = failed | (lost & ~no_evidence)
            recovered = torch.tensor(hook.recovered, dtype=torch.bool).reshape(failed.shape)
        return TrackResult(
            dof_names=list(self.skeleton.dof_names),
            fps=fps,
            angles=per_frame["estimates"].to(torch.float64),
            map_angles=per_frame["map_estimates"].to(torch.float64),
            filtered_angles=None if filtered is None else filtered.to(torch.float64),
            ess=per_frame["ess"],
            log_evidence=float(state.log_evidence),
            failed=failed,
            stats=stats,
            seconds=seconds,
            likelihood_evaluations=self.likelihood_evaluations,
            no_evidence=no_evidence,
            recovered=recovered,
            skeleton=self.skeleton,
            init=how,
        )

    # ------------------------------------------------------------------ detection (torchpf.detect)
    def detector(self):
        """The :class:`~torchpf.detect.PersonDetector` of this skeleton and rig (built once)."""
        from torchpf.detect import PersonDetector

        if getattr(self, "_detector", None) is None:
            self._detector = PersonDetector(self.skeleton, self.cameras)
        return self._detector

    def _outline_cue(self):
        """The first silhouette cue of the likelihood (it measures :attr:`Silhouettes.offset`), or None."""
        from torchpf.likelihoods.images import ImageLikelihood

        for module in self.likelihood.modules():
            if isinstance(module, ImageLikelihood) and module.obs_type is Silhouettes:
                return module
        return None

    def _smoother(self):
        """The :class:`~torchpf.smooth.TrajectorySmoother` of ``track(smooth=...)``: the hybrid refiner's cue
        (else the default distance cue; the default one with the smoother's :data:`~torchpf.smooth.SAMPLES`
        foreground samples and :data:`~torchpf.smooth.AREA_POINTS` model points), ``sigma`` from
        ``smooth_options`` or ``scale`` times the motion prior's per-frame step std (the prior this tracker
        built for the sequence's rate)."""
        from torchpf.smooth import TrajectorySmoother

        options = dict(self.smooth_options)
        scale = float(options.pop("scale", 12.0))
        if "sigma" not in options:
            std = _diffusion_std(self.dynamics)
            std = torch.as_tensor(0.03 if std is None else std, dtype=torch.float64)
            options["sigma"] = scale * std.to(self.skeleton.lower.device)
        refiner = getattr(self.filter, "refiner", None)
        refine = dict(self.filter_options.get("refine_options") or {})
        if "cue" not in options and refiner is not None:
            if refine.get("cue", "silhouette_distance") == "silhouette_distance":
                # the refiner's cue by name, with the smoother's own samples and model points
                options["cue"] = "silhouette_distance"
                options.setdefault("cue_options", refine.get("cue_options"))
            else:
                options["cue"] = refiner.cue
        return TrajectorySmoother(self.skeleton, self.cameras, **options).to(self.device)

    def _reads_silhouettes(self) -> bool:
        """Whether the likelihood reads silhouettes through cameras (what refinement and fitting need)."""
        return self.cameras is not None and "silhouettes" in (_observed_fields(self.likelihood) or set())

    def _calibrates(self, calibrate: bool | None, frame, init: str) -> bool:
        """Whether ``track`` fits the body first: ``calibrate`` True / False, or None: when the body looks
        uncalibrated (warned) and the likelihood reads silhouettes through cameras."""
        import warnings

        from torchpf.detect import looks_uncalibrated

        if calibrate is False:
            return False
        if not self._reads_silhouettes():
            if calibrate:
                raise ValueError("calibrate=True fits the body to silhouettes: it needs cameras and masks")
            return False
        if calibrate is None:
            if not looks_uncalibrated(self.skeleton) or not _evidence(frame, {"silhouettes"}):
                return False  # a calibrated body, or nothing in frame 0 to fit it to
            where = {"truth": "true", "pose": "given", "auto": "found"}.get(init, init)
            k = self.auto_refit_frames if init == "auto" else self.refit_frames
            again = f", then again to the first {k} frames at the poses tracked on it" if k > 1 else ""
            again += " where that explains them better" if again and init == "auto" else ""
            warnings.warn(
                "the skeleton's body looks uncalibrated (its torso capsules are thinner than 4 % of its "
                f"stature); tracking with the body fitted to frame 0's masks at the {where} pose{again}; "
                "calibrate it once with 'python -m torchpf calibrate' (or pass calibrate=False) to skip "
                "this guess",
                stacklevel=3,
            )
        return True

    def _auto_init(self, frames: list, calibrate: bool | None = None) -> tuple[torch.Tensor, Any]:
        """``(pose (D,), fitted skeleton or None)`` from the silhouettes of the first frames."""
        if self.cameras is None:
            raise ValueError('init="auto" needs the cameras of the silhouettes')
        detector = self.detector()
        det = detector.detect(frames[0])
        if det is None:
            raise ValueError(
                'init="auto": no person found in frame 0 (fewer than two cameras see a silhouette)'
            )
        # the hull's velocity over the first frames gives the heading (people walk forwards)
        k = min(5, len(frames) - 1)
        later = detector.detect(frames[k]) if k > 0 else None
        fps = self.fps or 30.0
        motion = (later.centre - det.centre) * fps / k if later is not None else None
        pose, fitted, _ = detector.fit(frames[0], det=det, motion=motion)
        return pose, fitted if self._calibrates(calibrate, frames[0], init="auto") else None

    def _held_arms(self, frame, pose, body, body_pose) -> list[int]:
        """The arm bones whose radii ``track`` puts back after its body fits (:attr:`hold_thin_arms`;
        warned), or []: the arms project thin at ``pose`` on ``self.skeleton`` and frame 0's masks stray
        from ``body`` (fitted to them) at ``body_pose`` by more than :attr:`hold_arms_outline` px."""
        from torchpf.detect import silhouette_masks

        got = silhouette_masks(frame) if self.hold_thin_arms is not None else None
        bones = arm_bones(self.skeleton) if got is not None else []
        if not bones:
            return []
        from torchpf.calibrate import outline_disagreement, projected_radii

        masks, valid = got
        H, W = masks.shape[-2:]
        radius = projected_radii(self.skeleton, self.cameras, pose, (W, H))[bones]
        thickest = float(radius.nan_to_num(0.0).max())  # NaN: no camera sees it
        if not thickest < self.hold_thin_arms:
            return []
        masks = [m if ok else None for m, ok in zip(masks, valid, strict=True)]
        stray = float(outline_disagreement(body, self.cameras, masks, body_pose).nanmean())  # NaN: no mask
        if not stray > self.hold_arms_outline:
            return []
        warnings.warn(
            f"the arms' capsules project at most {thickest:.1f} px thick (radius) in frame 0's {W}x{H} "
            f"masks, whose outlines stray {stray:.2f} px from the body fitted to them (hold_thin_arms="
            f"{self.hold_thin_arms:g}, hold_arms_outline={self.hold_arms_outline:g}): the fitted bodies get "
            "the arms' radii back as the skeleton has them (the masks cannot measure them); the arms are the "
            "limbs hanging off the torso above the root, a guess from the skeleton's structure",
            stacklevel=3,
        )
        return bones

    def _with_held(self, body, held: list[int] | None):
        """``body`` with the bones ``held`` (:meth:`_held_arms`) at the radii of the skeleton as given."""
        if not held:
            return body
        radii = body.radii.detach().double().cpu().clone()
        radii[held] = self.skeleton.radii.detach().double().cpu()[held]
        return body.with_body(radii=radii)

    def _refit(
        self,
        fitted,
        pose: torch.Tensor,
        frames,
        seed: int | None,
        fps: float | None,
        k: int,
        *,
        gate=False,
        held: list[int] | None = None,
    ):
        """``(body, pose, info)``: the body fitted again at the poses tracked over the first ``k`` frames.

        A body fitted on frame 0 alone carries that frame's errors through the whole track: the detected
        pose's error with ``init="auto"`` (on foreign renders the gap to a truth-initialised track stayed
        13-16 mm on every part of 60 frames), the mask defects of one frame with a given pose (noisy foreign
        renders: group radii off by a factor of 2-3). So the first ``k`` frames are tracked on ``fitted``
        from ``pose``, and the body is fitted again to the frames with silhouettes among them at the
        tracked poses (:func:`torchpf.detect.fit_body_to_frame`, one pose per frame, each refined). The bones
        ``held`` (:meth:`_held_arms`) are fitted like the others, then put back at the radii of the skeleton
        as given (``self.skeleton``), in ``fitted`` before the first pass and in the refitted body.

        ``gate`` (``init="auto"``): the same frames are tracked on the refitted body too, and it is kept
        only where its log evidence ``log p(z_1..k)`` is the higher; ``pose`` then becomes the refit's
        refined frame-0 pose. On noisy masks an auto-initialised track's poses are off, and a refit taken
        always lost 12 mm there; with the gate 8 frames took ``--init auto`` from 58 to 54 mm (clean) and
        131 to 127 mm (noisy), and 16 frames (the default) did better still (53 / 110 against 56 / 123
        with 8; BENCHMARKS.md). Without the gate (a given pose) the refit is taken and
        ``pose`` is returned as it came. The passes use ``seed`` (not a caller's generator), so gated bodies
        are compared on the same random numbers. ``info``: ``frames``, ``refit`` (taken), and with the gate
        ``log_evidence`` (first body, refitted body)."""
        fitted = self._with_held(fitted, held)
        k = min(int(k), len(frames))
        if k < 2:
            return fitted, pose, {"frames": k, "refit": False}
        from torchpf.detect import fit_body_to_frame

        first_frames = [frames[t] for t in range(k)]
        first_pass = self.with_skeleton(fitted)
        # The body is fitted at this pass's smoothed poses as the smoother took them from its own filter's
        # track: started from the track's running median (what the final track's smoothing does), the bodies
        # tracked no better (noisy foreign renders, two draws: 71.8 against 71.4 mm; BENCHMARKS.md,
        # "The smoother's start"). The masks' robust weights are left to the final smoothing, where saved
        # tracks measured their gain: with them in both passes ten noisy draws read +0.6 mm (standard error
        # 2.1; BENCHMARKS.md, "Round 11"). A `median` or `robust` in smooth_options is used in both passes.
        first_pass.smooth_options = {"median": 1, "robust": None, **first_pass.smooth_options}
        before = first_pass.track(first_frames, init=pose, seed=seed, fps=fps, calibrate=False)
        # frames the fit can read: silhouettes in them and a finite tracked pose
        used = [
            t
            for t in range(k)
            if _evidence(first_frames[t], {"silhouettes"}) and bool(torch.isfinite(before.angles[t]).all())
        ]
        if len(used) < 2:
            return fitted, pose, {"frames": len(used), "refit": False}
        refit, report = fit_body_to_frame(
            fitted,
            self.cameras,
            [first_frames[t] for t in used],
            before.angles[used].double(),
            view_offset_sigma=self.refit_view_offset,
            radius_sigma=self.fit_radius_sigma,
        )
        refit = self._with_held(refit, held)
        if not gate:
            return refit, pose, {"frames": len(used), "refit": True}
        start = report.poses[0].to(torch.float64) if used[0] == 0 else pose
        second = self.with_skeleton(refit)
        second.smooth = False  # only the filter's log evidence is compared: a smoothed track would be dropped
        after = second.track(first_frames, init=start, seed=seed, fps=fps, calibrate=False)
        keep = after.log_evidence > before.log_evidence  # NaN (no evidence) keeps the first body
        info = {"frames": len(used), "log_evidence": (before.log_evidence, after.log_evidence), "refit": keep}
        return (refit, start, info) if keep else (fitted, pose, info)

    def _recovery(self, fps: float = 30.0):
        from torchpf.detect import Recovery

        std = _diffusion_std(self.dynamics)
        std = 0.05 if std is None else torch.as_tensor(std, dtype=torch.float64).cpu()
        return Recovery(
            self.detector(),
            self.likelihood,
            std=std,
            init_extras=self.filter.dynamics.init_extras,
            dtype=self.dtype,
            fps=fps,
        )
