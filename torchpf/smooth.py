"""Fixed-interval smoothing of a finished track on a differentiable cue: the MAP trajectory under a
second-order (acceleration) prior, found by gradient descent from the filter's estimates.

A filter's estimate at frame ``t`` sees the observations up to ``t``; on masks with per-frame defects (a
random erosion, ragged edges, a limb missing from one camera) each frame's cue has its optimum somewhere
else around the truth, and the estimate follows it. :class:`TrajectorySmoother` minimises, over the whole
trajectory ``x_{1:T}`` at once::

    E(x_{1:T}) = sum_t -log p_cue(z_t | x_t) + 1/2 sum_{t=2}^{T-1} sum_d (a_{t,d} / sigma_d)^2
    a_t = w(x_{t+1} - x_t) - w(x_t - x_{t-1})

where ``p_cue`` is the refinement's differentiable cue (default the two-sided distance-transform silhouette
cue of :mod:`torchpf.refine`), ``w`` wraps revolute differences to ``(-pi, pi]`` and ``sigma`` is a
per-DOF acceleration std (per frame squared). The prior is the negative log density of a constant-velocity
motion model with white acceleration noise (Rius et al. eq. 3 with ``alpha = 1``, read as a smoothness
prior over the whole sequence rather than as a one-step prediction): it penalises jerky motion, not fast
motion, so a run's swing is kept where the masks show it, while a frame whose masks a defect pulls one way
is held by its neighbours. With a per-frame cue whose errors are independent across frames, this averages
them out; a one-sided window (a filter) cannot.

**Where the descent starts.** The energy has its optimum near the truth but the descent is local: on the
noisy foreign renders, smoothing from the *true* trajectory ended 39-54 mm from the truth (four clips), and
still 41-50 mm from the truth with 0.15 rad of independent noise added to every angle of every frame, while
from the filter's track it ended 56-152 mm away. A filter's track has frames a mask defect threw off (a
limb 10-30 cm away for one or two frames), and the prior bends their neighbours towards them, out of the
cue's reach. So each finite piece of the track is first replaced by its running median over ``median``
frames per DOF (along the unwrapped angles; the window cut short at the ends), which drops such frames and
keeps a monotone swing as it is; the track as given stays a candidate and is kept where its energy is lower.
On the same filter tracks (11 CMU clips, two draws of noisy masks, one run each) the smoothed tracks went
from 69.5 / 71.3 to 65.8 / 64.9 mm, none worse by more than 0.3 mm (35_24: 152 -> 96 mm); 9 frames gave
65.5 / 64.9.

**A mask a defect spoiled.** A segmentation's defect spoils one camera's mask in one frame, not all of them
at once: a 1-px erosion wipes a 2-3 px arm out of that camera, a limb drops out, a closing merges the legs.
The squared cue of that camera then pulls the whole body towards the defect, with the pull of a good mask.
So each frame's camera term ``E_{t,l}`` is made robust (``robust``; iteratively reweighted least squares):
every ``reweight`` steps it is weighted by ``w_{t,l} = min(1, (1 + 1/k) / (1 + E_{t,l} / (k u_{t,l})))``,
``k`` = :data:`ROBUST`, where the usual cost ``u_{t,l} = m_l median_{l'}(E_{t,l'} / m_{l'})`` is camera
``l``'s level ``m_l`` (the median of its terms over the window's frames that see someone) times how costly
frame ``t`` is in all its cameras. A mask up to its usual cost weighs 1 (on clean masks next to nothing
changes); beyond, the weight falls as the derivative of a Cauchy-type cost ``log(1 + E / (k u))``: a mask
that costs far more than the frame's other masks is heard much less, and the other cameras and the
neighbouring frames decide. A pose that is off costs in every camera (the first frame after a gap, a
re-acquired track) and keeps its weights: measured against the camera's level alone, such a frame was
weighed down and the prior pulled it back towards the lost frames (a re-acquired pose 0.3 m off instead of
0.05).

Descent is the refiner's projected, damped Adam (:func:`torchpf.refine.damped_adam_step`) on all frames at
once, keep-best per trajectory (the total ``E`` never increases), joint limits enforced. Long sequences go
in overlapping windows of ``window`` frames (memory is one window's masks): each window after the first
holds its first two frames at the previous window's result (the prior's anchors) and re-optimises the
previous window's last ``overlap`` frames with their future.

Measured (BENCHMARKS.md, "Smoothing the track"; foreign renders of the 11 CMU clips, ``track``'s
defaults, 500 evaluations per frame, 2 runs): the smoothed tracks are 38 -> 31 mm from the truth on clean
masks and 97 -> 84 mm on noisy ones (three draws of the defects: 89 / 103 / 100 -> 75 / 90 / 88), every
clip gaining, for ~15 ms per frame on one CPU core (80 steps over a 64-frame window; with the 512
foreground samples of :data:`SAMPLES`, 1.2-1.6 mm closer on noisy masks, ~8 ms more). The acceleration std
``sigma`` that ``Tracker`` gave it was 16 times the random walk's per-frame step std (8 and 32 were 1-2 mm
worse on one kind of mask or the other); with the :data:`AREA_POINTS` and 120 steps, 12 times: together
1.1-2.2 mm closer again on each of ten sets of saved noisy filter tracks. Without the prior (the same
descent, each frame on its own) the clean tracks gain as much but the noisy ones nothing (107 against 105
mm on 5 clips): on clean masks the gain is the filter's estimates converged further, on noisy ones it is
the neighbours holding a frame.

Example::

    from torchpf.smooth import TrajectorySmoother
    smoother = TrajectorySmoother(skel, cameras, sigma=0.1)
    x = smoother(track.angles, [frame.silhouettes for frame in frames]).x      # (T, D) -> (T, D)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchpf.observations import Silhouettes
from torchpf.refine import damped_adam_step, damping_factor, descent_setup

__all__ = ["AREA_POINTS", "ROBUST", "SAMPLES", "SmoothResult", "TrajectorySmoother"]

#: Foreground samples per camera of the default cue. The smoother sees each frame once per step (one pose,
#: not the filter's hundreds), so it can afford 4x the refiner's 128. On eight sets of saved filter tracks
#: (noisy foreign renders of 11 CMU clips, six draws of the defects) the smoothed tracks came out 1.2-1.6 mm
#: closer to the truth, every set (e.g. 65.8 -> 64.6 and 64.9 -> 63.4 mm; 256 samples 64.9 / 63.5, 1,024 no
#: better than 512), no clip worse by more than 0.3 mm, for ~8 ms per frame (BENCHMARKS.md, "Round 9").
SAMPLES = 512

#: Model area points per capsule body and per end cap of the default cue (the refiner's 8 and 2), for the
#: same reason. Together with 120 descent steps (80 before) and ``Tracker``'s acceleration std at 12 step
#: stds (16 before), the smoothed tracks came out 1.1-2.2 mm closer to the truth on every one of ten sets of
#: saved filter tracks (noisy foreign renders, ten draws of the defects: mean 70.1 -> 68.3 mm), for ~11 ms per
#: frame (BENCHMARKS.md, "Round 10").
AREA_POINTS = (16, 4)

#: The default scale ``k`` of the cameras' robust weights (``TrajectorySmoother(robust=...)``; module
#: docstring, "A mask a defect spoiled"). On the saved filter tracks of two noisy draws (11 clips each) the
#: smoothed tracks came out 2.1 / 1.5 mm closer to the truth (all joints), every one of the 22 closer; on
#: clean ones +0.1 mm; 0.25 and 1 within 0.4 mm of 0.5; ~2 ms per frame (BENCHMARKS.md, "Round 11").
ROBUST = 0.5


@dataclass
class SmoothResult:
    """What :meth:`TrajectorySmoother.forward` returns: ``x (T, ..., D)`` the smoothed trajectory,
    ``loss_before``, ``loss`` ``(...)`` the objective ``E`` per trajectory before and after (summed over
    windows), ``windows`` optimised."""

    x: Tensor
    loss_before: Tensor
    loss: Tensor
    windows: int


def _wrapped_steps(x: Tensor, revolute: Tensor) -> Tensor:
    """``x[t + 1] - x[t]`` along the first axis, revolute DOFs wrapped to ``(-pi, pi]``."""
    d = x[1:] - x[:-1]
    return torch.where(revolute, torch.atan2(torch.sin(d), torch.cos(d)), d)


class TrajectorySmoother(nn.Module):
    """MAP trajectory under the cue and an acceleration prior (module docstring), batched over sequences.

    Args:
        skeleton: the body model (limits, revolute mask).
        cameras: a :class:`~torchpf.camera.CameraRig` or list of cameras; used to build a named cue.
        sigma: per-frame acceleration std: a float (radians and metres per frame squared alike) or ``(D,)``;
            a DOF with ``sigma = 0`` is held where the track put it.
        cue: a likelihood module ``(x (..., K, D), obs) -> (..., K)`` or a name of
            :data:`~torchpf.likelihoods.LIKELIHOODS` (default ``"silhouette_distance"``, the refiner's).
        cue_options: keywords of a named cue. The default cue takes :data:`SAMPLES` foreground samples
            per camera and :data:`AREA_POINTS` model points per capsule unless ``n_samples``, ``n_body``
            or ``n_cap`` is given (the refiner's 128 samples are few for a frame's mask: its ~1,500
            foreground pixels at 160x120).
        steps: descent steps per window.
        lr_rotation, lr_translation, damping: the refiner's Adam steps (radians, metres) and damping
            (:class:`~torchpf.refine.Refiner`).
        window: frames per window (memory: one window's masks and ``window`` poses per sequence).
        overlap: frames a window re-optimises of the one before (>= 2: its two anchors are among them).
        median: the descent starts from the track's running median over this many frames (odd; 1: from the
            track itself); the track as given is kept where its energy is lower (module docstring).
        robust: the scale ``k`` of the cameras' robust weights (module docstring, "A mask a defect
            spoiled"): each frame's camera term is weighted by ``min(1, (1 + 1/k) / (1 + e / (k u)))``,
            ``e`` its energy at the current trajectory and ``u`` its usual cost (that camera's median level
            times the frame's median over its cameras), recomputed every ``reweight`` steps. ``None``:
            every mask weighs 1. Needs a cue with per-camera terms
            (:meth:`~torchpf.likelihoods.images.ImageLikelihood.camera_log_likelihoods`); another cue is
            used unweighted.
        reweight: descent steps between two computations of the robust weights.
    """

    def __init__(
        self,
        skeleton,
        cameras=None,
        *,
        sigma: float | Tensor = 0.1,
        cue="silhouette_distance",
        cue_options=None,
        steps: int = 120,
        lr_rotation: float = 0.03,
        lr_translation: float = 0.01,
        damping: float = 0.1,
        window: int = 64,
        overlap: int = 8,
        median: int = 5,
        robust: float | None = ROBUST,
        reweight: int = 30,
    ):
        super().__init__()
        if cue == "silhouette_distance":
            n_body, n_cap = AREA_POINTS
            cue_options = {"n_samples": SAMPLES, "n_body": n_body, "n_cap": n_cap, **dict(cue_options or {})}
        self.cue, lr = descent_setup(
            skeleton, cameras, cue, cue_options, steps, lr_rotation, lr_translation, damping
        )
        if not (overlap >= 2 and window > overlap):
            raise ValueError(f"need window > overlap >= 2, got window={window}, overlap={overlap}")
        if not (int(median) == median and median >= 1 and median % 2 == 1):
            raise ValueError(f"median must be an odd number of frames >= 1, got {median}")
        D = len(skeleton.lower)
        sigma = torch.as_tensor(sigma, dtype=torch.float64).to(skeleton.lower.device)
        if sigma.dim() == 0:
            sigma = sigma.expand(D)
        if sigma.shape != (D,) or not bool(torch.isfinite(sigma).all()) or bool((sigma < 0).any()):
            raise ValueError(f"sigma must be a float or a ({D},) tensor of finite values >= 0")
        self.skeleton = skeleton
        self.steps, self.window, self.overlap = int(steps), int(window), int(overlap)
        self.median = int(median)
        if robust is not None and not robust > 0:
            raise ValueError(f"robust must be > 0 or None, got {robust}")
        if not (int(reweight) == reweight and reweight >= 1):
            raise ValueError(f"reweight must be a number of steps >= 1, got {reweight}")
        self.robust = None if robust is None else float(robust)
        self.reweight = int(reweight)
        self.damping = float(damping)
        self.register_buffer("lr", torch.where(sigma == 0, 0.0, lr.to(sigma.device)))
        # 1 / sigma^2 of the prior; a held DOF has no step, so its weight only needs to be finite
        self.register_buffer("precision", torch.where(sigma > 0, sigma.clamp_min(1e-12) ** -2, 0.0))

    def prior_energy(self, x: Tensor, anchors: Tensor | None = None) -> Tensor:
        """``1/2 sum_t sum_d (a_{t,d} / sigma_d)^2`` per trajectory ``(...)`` of ``x (T, ..., D)``, the
        accelerations taken over ``anchors (A, ..., D)`` (frames before ``x``, held) followed by ``x``."""
        full = x if anchors is None else torch.cat([anchors.to(x), x])
        if len(full) < 3:
            return x.new_zeros(x.shape[1:-1])
        step = _wrapped_steps(full, self.skeleton.dof_revolute.to(x.device))
        a = step[1:] - step[:-1]
        return 0.5 * (a.square() * self.precision.to(x)).sum((0, -1))

    def _window(
        self, x: Tensor, obs: Silhouettes, anchors: Tensor | None, start: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Descend on ``x (T, B, D)`` (obs batched ``(T B, V, H, W)``) from ``start`` (default ``x``);
        ``(best x, E before, E after)``, ``E before`` at ``x``, the best of ``x`` and the iterates kept."""
        T, B, D = x.shape
        lr = self.lr.to(x)
        damp = damping_factor(self.damping, lr)

        own = hasattr(self.cue, "log_likelihood_and_grad")
        robust = (
            self.robust is not None
            and isinstance(obs, Silhouettes)
            and hasattr(self.cue, "camera_log_likelihoods")
        )
        seen = obs  # the window's masks with their current robust weights (read when a step runs)

        def energy_and_grad(z):
            with torch.enable_grad():
                zr = z.detach().requires_grad_(True)
                energy = self.prior_energy(zr, anchors)
                if not own:  # the cue through autograd
                    energy = energy - self.cue(zr.reshape(T * B, 1, D), seen).reshape(T, B).sum(0)
                # (fewer than 3 frames in all: no acceleration, no prior, no graph)
                g = torch.autograd.grad(energy.sum(), zr)[0] if energy.requires_grad else torch.zeros_like(z)
            energy = energy.detach()
            if own:  # the cue's own gradient: no backward pass through forward kinematics
                loglik, grad = self.cue.log_likelihood_and_grad(z.reshape(T * B, 1, D), seen)
                energy = energy - loglik.reshape(T, B).sum(0).to(z)
                g = g - grad.reshape(T, B, D).to(z)
            return energy, g

        track = self.skeleton.clamp(x.detach())
        cur = track if start is None else self.skeleton.clamp(start.detach())
        best, best_e = track, torch.full((B,), math.inf, dtype=x.dtype, device=x.device)
        first = None
        m, v = torch.zeros_like(cur), torch.zeros_like(cur)
        for step in range(self.steps + 1):
            if step == 0 or (robust and step % self.reweight == 0):
                if robust:  # new weights, a new objective: the candidates are compared under it from here on
                    seen = self._robust_weights(cur, obs)
                    best_e = torch.full_like(best_e, math.inf)
                if start is not None:  # the track as given is a candidate too: its first energy is E before
                    e0, _ = energy_and_grad(track)
                    first = e0 if first is None else first
                    best, best_e = track, torch.where(torch.isnan(e0), best_e, e0)
            e, grad = energy_and_grad(cur)
            first = e if first is None else first
            better = e < best_e  # NaN compares False
            best = torch.where(better.view(1, B, 1), cur, best)
            best_e = torch.where(better, e, best_e)
            if step == self.steps:
                break
            grad = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)
            cur = damped_adam_step(cur, grad, m, v, lr, damp, step, self.steps)
            cur = self.skeleton.clamp(cur)
        # a trajectory whose energy was never finite keeps the track
        stuck = ~torch.isfinite(best_e)
        return torch.where(stuck.view(1, B, 1), x, best), first, torch.where(stuck, first, best_e)

    @torch.no_grad()
    def _robust_weights(self, z: Tensor, obs: Silhouettes) -> Silhouettes:
        """``obs`` (``(T B, V, H, W)``) with each mask's robust weight at the trajectory ``z (T, B, D)``
        (``robust`` in the class docstring), times the weight the mask came with."""
        T, B, D = z.shape
        e = -self.cue.camera_log_likelihoods(self.cue.body(z.reshape(T * B, 1, D)), obs)
        # a missing or empty mask (a camera that sees nobody) has no term: it must not set the usual level
        seen = (obs.valid & (obs.area() > 0)).reshape(T * B, -1).to(e.device)
        e = torch.where(seen, e.reshape(T * B, -1), torch.nan).reshape(T, B, -1)
        level = e.nanmedian(0, keepdim=True).values  # (1, B, V): each camera's level in this window
        # a mask is spoiled where it costs more than the frame's other masks, each on its camera's level: a
        # pose that is off (after a gap, a recovery) costs in every camera and keeps its weights
        typical = level * (e / level.clamp_min(1e-12)).nanmedian(-1, keepdim=True).values
        # (a usual cost of next to 0 nats, a mask the body fits exactly, must not make every other a defect)
        typical = typical.clamp_min(1e-3)
        k = self.robust
        # 1 up to the usual cost: an ordinary mask keeps the cue's full weight against the prior
        w = ((1.0 + 1.0 / k) / (1.0 + e.clamp_min(0) / (k * typical))).clamp(max=1.0)
        w = torch.nan_to_num(w, nan=1.0).reshape(T * B, -1).to(obs.masks.dtype)
        return obs.with_weight(w if obs.weight is None else w * obs.weight)

    def forward(self, x: Tensor, observations: Sequence[Silhouettes]) -> SmoothResult:
        """Smooth ``x (T, ..., D)`` (a track's estimates: frames first, then any batch of sequences, on the
        smoother's device) given the per-frame observations the cue reads (``T`` of them, each batched as
        the poses' ``...``:
        :class:`~torchpf.observations.Silhouettes` ``(..., V, H, W)`` or the
        :class:`~torchpf.observations.Frame` holding them, or a tensor ``(..., E)`` for a cue that reads
        ``(T B, E)``; read one window at a time, so a lazy sequence works). A frame whose silhouettes are
        ``None`` has only the prior. Non-finite frames are left as they are and cut the trajectory into
        pieces smoothed on their own."""
        x = torch.as_tensor(x)
        if x.dim() < 2:
            raise ValueError(f"x must be (T, ..., D), got shape {tuple(x.shape)}")
        if len(observations) != len(x):
            raise ValueError(f"{len(observations)} observations for {len(x)} frames")
        if x.device != self.lr.device:  # the cue's buffers and the prior live on the module's device
            raise ValueError(
                f"x is on {x.device} but the smoother is on {self.lr.device}: move one (smoother.to(...))"
            )
        T, D = len(x), x.shape[-1]
        lead = x.shape[1:-1]
        flat = x.reshape(T, -1, D)
        out = flat.clone()
        before = flat.new_zeros(flat.shape[1])
        after = flat.new_zeros(flat.shape[1])
        windows = 0
        finite = torch.isfinite(flat).all(-1).all(-1)  # (T,) a frame all sequences have
        t = 0
        while t < T:
            if not finite[t]:
                t += 1
                continue
            end = t
            while end < T and finite[end]:
                end += 1
            # the descent starts from the piece's running median: a frame that a mask defect threw off (a
            # limb 10-30 cm away for a frame or two) otherwise holds its neighbours in its basin
            median = None
            if self.median > 1 and end - t > 2:
                median = _running_median(flat[t:end], self.median, self.skeleton.dof_revolute.to(x.device))
                median = torch.where(self.lr > 0, median, flat[t:end])  # a held DOF stays where it is
            start, done = t, t  # a finite piece [t, end): windows over it; frames before `done` smoothed
            while True:
                stop = min(end, start + self.window)
                held = 2 if start > t else 0
                anchors = out[start : start + held] if held else None
                free = slice(start + held, stop)
                if free.stop - free.start > 0:
                    obs = _stack([observations[k] for k in range(free.start, free.stop)], flat.shape[1])
                    if obs is not None:  # a window without observations keeps the track
                        begin = None
                        if median is not None:  # the window's smoothed frames start where they are
                            begin = torch.cat(
                                [out[free.start : done], median[max(done, free.start) - t : stop - t]]
                            )
                        x_w, e0, e1 = self._window(out[free], obs, anchors, begin)
                        out[free] = x_w
                        before, after = before + e0, after + e1
                        windows += 1
                done = stop
                if stop == end:
                    break
                start = stop - self.overlap
            t = end
        return SmoothResult(
            x=out.reshape(x.shape),
            loss_before=before.reshape(lead),
            loss=after.reshape(lead),
            windows=windows,
        )


def _running_median(x: Tensor, k: int, revolute: Tensor) -> Tensor:
    """The running median of ``x (T, B, D)`` over ``k`` frames (odd) per DOF, the window cut short at the
    ends (the lower median of an even count); revolute DOFs taken along their unwrapped path and returned
    on each frame's own branch."""
    steps = _wrapped_steps(x, revolute)
    path = torch.cat([x[:1], x[:1] + steps.cumsum(0)])  # revolute DOFs without their 2 pi jumps
    pad = path.new_full((k // 2, *path.shape[1:]), math.nan)
    med = torch.cat([pad, path, pad]).unfold(0, k, 1).nanmedian(-1).values  # (T, B, D)
    d = med - path
    return x + torch.where(revolute, torch.atan2(torch.sin(d), torch.cos(d)), d)


def _stack(observations: list, batch: int) -> Silhouettes | Tensor | None:
    """``(T B, V, H, W)`` silhouettes of a window's frames (a :class:`~torchpf.observations.Frame` gives its
    ``silhouettes``; a missing frame has every camera invalid, so only the prior sees it; the frames' outline
    offsets and mask weights kept, 0 px and 1 where a frame has none), or tensors
    ``(..., E)`` per frame stacked to ``(T B, E)`` for a cue that reads tensors; None when no frame of the
    window has one."""
    obs = [getattr(o, "silhouettes", o) for o in observations]
    ref = next((o for o in obs if o is not None), None)
    if ref is None:
        return None
    if not isinstance(ref, Silhouettes):  # a tensor per frame, (..., E): one row per sequence
        if any(o is None for o in obs):
            raise ValueError("a frame without an observation is only understood with silhouettes")
        return torch.cat([torch.as_tensor(o).reshape(batch, -1) for o in obs])
    V, H, W = ref.masks.shape[-3:]
    masks, valid = [], []
    for o in obs:
        if o is None:
            masks.append(ref.masks.new_zeros(batch, V, H, W))
            valid.append(torch.zeros(batch, V, dtype=torch.bool, device=ref.masks.device))
        else:
            masks.append(o.masks.reshape(-1, V, H, W).expand(batch, -1, -1, -1))
            valid.append(o.valid.reshape(-1, V).expand(batch, -1))

    def per_mask(name: str, fill: float) -> Tensor | None:
        """A per-mask field (``offset``, ``weight``) where a frame has one, ``fill`` for the others; None
        where no frame has it."""
        given = [None if o is None else getattr(o, name) for o in obs]
        if all(g is None for g in given):
            return None
        default = torch.full((batch, V), fill, device=ref.masks.device)
        return torch.cat([default if g is None else g.reshape(-1, V).expand(batch, -1) for g in given])

    return Silhouettes(
        torch.cat(masks),
        valid=torch.cat(valid),
        offset=per_mask("offset", 0.0),  # the masks' outline offsets, 0 px where a frame has none
        weight=per_mask("weight", 1.0),
    )
