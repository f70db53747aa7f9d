"""Fitting action models from mocap: aSpace PCA, DTW/DBA synchronisation, σ_k, Δ, σ_φ and α (Rius eq. 1-3).

One *action* (walk, bend, ...) is learned from several *performances*: mocap clips of different lengths,
speeds and performers, each a :class:`~training.mocap.Motion` (``angles (T, D_full)``). The result is an
:class:`priors.action.ActionModel` ``Γ = (Ω, ĝ, σ)`` plus σ_φ, α and Δ (see :mod:`priors.action`), saved as
``.npz`` and used by :class:`priors.action.ActionConstrained` in a particle filter.

Recommended use::

    from training import fit_action_model
    model = fit_action_model([load_csv(p) for p in paths], action="walk")   # D by validation
    model.save("walk.npz")

or ``python -m training fit --action walk --skeleton S.urdf --out walk.npz DATA/*.csv``; the sklearn-style
:class:`ActionModelFitter` keeps the intermediate results (``coords_``, ``paths_``, ``pca_``, ...).

**Steps** (all in float64 numpy; the performances are small; resampling, period estimation, DTW and DBA live
in :mod:`training.align`):

1. *Frame rate.* Every performance is resampled (linear interpolation of its unwrapped angles) to the model's
   ``fps`` (default: the performances' common rate). σ_φ and α are per-frame quantities at this rate, so fit
   at the rate you will track at.
2. *Postures.* The posture is the DOF vector without the root (``exclude_root``: translation *and*
   orientation; in CMU's ``Zrotation Yrotation Xrotation`` root order the heading is the middle Euler angle
   and cannot be separated from the tilt channel by channel) and without the channels matching ``exclude``
   (default: hands, fingers and thumbs, whose CMU tracks glitch and flip).
3. *Angles for PCA.* Raw angles in radians (the paper's choice; sin/cos would double the dimension and
   curve the PCA's straight lines). Each angular posture DOF is brought to the branch nearest its circular
   mean over the training set, ``x = center + wrap(θ - center)``: a function of the pose alone, so particles
   are projected exactly like training frames, and equal to the unwrapped angle for every DOF that stays
   within ±π of its mean. (σ_φ and α, which are about time, use ``np.unwrap`` along each performance.)
4. *aSpace* Ω: ``sklearn.decomposition.PCA`` over the postures of all frames of all performances; ``D``
   components chosen by leave-one-performer-out validation (``n_components="auto"``, the default:
   :func:`select_n_components`), by count (``n_components=13``, the paper) or by explained variance
   (``n_components=0.95``).
5. *Synchronisation* (Rius §2 with Mozerov et al.'s dense matching, here DTW Barycenter Averaging): a mean
   performance ĝ of ``K`` postures is initialised from one performance, then every performance is aligned
   to ĝ with dynamic time warping in aSpace and each ĝ_k is re-estimated as the mean of the frames matched
   to it, until the alignments stop changing (``max_iter`` at most). The DTW maps each frame ``i`` to one
   mean posture ``k(i)``; from one frame to the next ``k`` stays (at most ``max_stay`` times in a row) or
   advances by 1 .. ``max_step`` — a slope constraint that bounds the local speed ratio to
   ``[1 / max_step, max_stay + 1]`` frames per mean posture; the path cost is ``Σ_i ||φ̃_i - ĝ_{k(i)}||²``.
   *Cyclic* actions (walking, waving) get a cyclic mean (one cycle, ``K`` = median period; ``k`` advances
   modulo ``K`` and the path may start and end at any phase, because clips start and stop anywhere in the
   cycle); acyclic ones (a single bend) a mean of the median length with paths from first to last posture.
   ``cyclic=None`` decides per data set from the performances' periodicity (YIN-style normalised difference
   of the aSpace trajectory).
6. *Spreads.* With residuals ``r_i = φ̃_i - ĝ_{k(i)}``: σ_k is the RMS of the residuals of the frames matched
   to posture k, pooled over neighbouring postures with a Gaussian window of ``sigma_smoothing`` postures
   (a few frames per posture per performance are too few for a standard deviation); Δ the RMS of all
   residuals per dimension.
7. *Constant-velocity statistics* (Rius eq. 3; :func:`training.dynamics.cv_statistics`, shared with
   ``fit-dynamics``): with ``V_t = α V_{t-1} + (1 - α)(φ_t - φ_{t-1})`` and the prediction
   ``φ̂_{t+1} = φ_t + V_t``, each DOF's α minimises its squared prediction error over all performances
   (per DOF, Rius §3.1; stored per DOF in the model file since its version 3), and σ_φ is the per-DOF robust
   standard deviation (``1.4826 · median |e|``, insensitive to Euler flips) of the prediction errors ``e`` at
   those α.

Shapes: ``T`` frames, ``D_full`` DOFs of the pose vector, ``P`` posture DOFs, ``D`` aSpace dimensions,
``K`` mean postures, ``R`` performances.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from sklearn.base import BaseEstimator
from sklearn.decomposition import PCA
from sklearn.exceptions import NotFittedError
from tqdm.auto import tqdm

from priors.action import ActionModel, guess_revolute
from training.align import PERIODIC_THRESHOLD, dba_update, dtw_align, estimate_period, initial_mean, resample
from training.dynamics import cv_statistics
from training.mocap import Motion

#: Default ``exclude`` patterns (case-insensitive regular expressions searched in DOF names): the hand,
#: finger and thumb channels, which glitch and flip in the CMU data.
HAND_PATTERNS = ("hand", "finger", "thumb")


# ================================================================================================ helpers
def root_dofs(dof_names: Sequence[str]) -> list[str]:
    """The root's DOFs: those named ``<joint>_*`` with ``<joint>`` the joint of the first DOF (``Hips``).

    URDF skeletons of this project list the root (3 prismatic + 3 revolute DOFs) first and name DOFs
    ``<Joint>_<channel>`` (:mod:`training.mocap`).
    """
    if not dof_names:
        return []
    prefix = dof_names[0].rsplit("_", 1)[0] + "_"
    return [n for n in dof_names if n.startswith(prefix)]


def select_posture_dofs(
    dof_names: Sequence[str], *, exclude_root: bool = True, exclude: Sequence[str] = HAND_PATTERNS
) -> list[str]:
    """Posture DOFs: ``dof_names`` without the root (if ``exclude_root``) and without names matching any of
    the ``exclude`` regular expressions (case-insensitive), in ``dof_names`` order."""
    drop = set(root_dofs(dof_names)) if exclude_root else set()
    patterns = [re.compile(p, re.IGNORECASE) for p in exclude]
    return [n for n in dof_names if n not in drop and not any(p.search(n) for p in patterns)]


def circular_mean(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """Mean direction ``atan2(mean sin, mean cos)`` of angles (radians) along ``axis``."""
    return np.arctan2(np.sin(x).mean(axis), np.cos(x).mean(axis))


def wrap_about(x: np.ndarray, center: np.ndarray, angular: np.ndarray) -> np.ndarray:
    """``center + wrap(x - center)`` (wrap into ``[-π, π)``) on the ``angular`` columns of ``x (..., P)``."""
    wrapped = center + np.mod(x - center + math.pi, 2.0 * math.pi) - math.pi
    return np.where(angular, wrapped, x)


def _smooth_over_postures(values: np.ndarray, width: float, cyclic: bool) -> np.ndarray:
    """Gaussian smoothing of ``values (K, ...)`` along postures (std ``width``; cyclic or truncated)."""
    if width <= 0:
        return values
    K = values.shape[0]
    r = int(math.ceil(3 * width))
    offsets = np.arange(-r, r + 1)
    w = np.exp(-0.5 * (offsets / width) ** 2)
    out = np.zeros_like(values)
    for o, wo in zip(offsets, w, strict=True):
        if cyclic:
            out += wo * np.roll(values, o, axis=0)
        else:  # truncated window: postures past the ends contribute nothing
            shifted = np.zeros_like(values)
            if o >= 0:
                shifted[o:] = values[: K - o]
            else:
                shifted[:o] = values[-o:]
            out += wo * shifted
    return out


# ================================================================================================ fitter
class ActionModelFitter(BaseEstimator):
    """Learn an :class:`~priors.action.ActionModel` from performances of one action (sklearn style).

    Configuration is keyword-only and only stored by ``__init__`` (checked by :meth:`fit`); :meth:`fit`
    learns. A scikit-learn estimator: ``get_params(deep=True)``, ``set_params(**params)`` and
    ``sklearn.base.clone`` work as for any sklearn estimator (``sklearn.base.BaseEstimator``). It is not a
    transformer or predictor of numeric ``X``: :meth:`fit` takes performances (Motions), so the
    ``check_estimator`` checks that fit numeric arrays do not apply. See the module docstring for the method.

    Args:
        n_components: ``"auto"`` (default): chosen by leave-one-performer-out validation
            (:func:`select_n_components`, the curve in ``validation_curve_`` and in the model file);
            or the aSpace dimension ``D`` (int, Rius: 13), or the fraction of variance to keep (float in
            (0, 1)); capped at the number of posture DOFs and frames.
        action: the action's name, stored in the model.
        fps: model frame rate (Hz); performances are resampled to it. ``None``: their common rate (the median
            if they differ).
        cyclic: ``True``/``False``, or ``None`` to decide from the data.
        n_postures: ``K``; ``None``: the median period (cyclic) or median length (acyclic), in frames.
        exclude_root: leave the root's DOFs (translation and orientation) out of the posture.
        exclude: regular expressions (case-insensitive) of further DOFs to leave out of the posture.
        max_step, max_stay: DTW slope constraint (see :func:`dtw_align`).
        max_iter: most synchronisation (DBA) iterations.
        sigma_smoothing: std (in postures) of the window that pools residuals for σ_k; 0: none.
        n_sigma: acceptance half-width in σ (Rius eq. 6: 2).
        alpha: fix α (one value for every DOF) instead of fitting it per DOF.
        validate: also fit ``R`` leave-one-performance-out models and measure how often each accepts the
            performance left out (``validation_acceptance_``): the check that ``D`` generalises. With few
            performers the trailing components only fit the training performers and this rate collapses
            (Rius §4: "too high values lead to overfitting"); lower ``n_components`` then.
        progress: show a progress bar over the synchronisation iterations.
        negatives: performances of other actions that the model should reject (``"auto"`` scores them).
        candidates, min_heldout: the ``D`` values ``"auto"`` tries and its held-out acceptance target.

    Learned attributes: ``model_`` (the ActionModel), ``dof_names_``, ``posture_dofs_``, ``fps_``,
    ``center_ (P,)``, ``pca_`` (the sklearn PCA), ``coords_`` (R arrays ``(T_r, D)``: aSpace trajectories),
    ``periods_`` (per performance, frames or None), ``cyclic_``, ``n_postures_``,
    ``mean_performance_ (K, D)``, ``paths_`` (R arrays ``(T_r,)``: matched mean posture per frame),
    ``costs_`` (mean DTW cost per iteration), ``n_iter_``, ``converged_``, ``std_ (K, D)``, ``delta_ (D,)``,
    ``alpha_ (D_full,)``, ``sigma_phi_ (D_full,)``, ``train_acceptance_`` (mean eq. 6 acceptance probability
    of the training frames), ``validation_acceptance_`` (``(R,)`` the same for each left-out performance under
    the model fitted without it, with ``validate=True``; else None), ``validation_curve_`` (a
    :class:`ValidationCurve` with ``n_components="auto"``, else None).

    Example::

        fitter = ActionModelFitter(n_components=13, action="walk", fps=30).fit(motions)
        fitter.model_.save("walk.npz"); fitter.paths_[0]      # phase of each frame of the first performance
    """

    def __init__(
        self,
        *,
        n_components: int | float | str = "auto",
        action: str = "action",
        fps: float | None = None,
        cyclic: bool | None = None,
        n_postures: int | None = None,
        exclude_root: bool = True,
        exclude: Sequence[str] = HAND_PATTERNS,
        max_step: int = 2,
        max_stay: int = 1,
        max_iter: int = 30,
        sigma_smoothing: float = 1.0,
        n_sigma: float = 2.0,
        alpha: float | None = None,
        validate: bool = False,
        progress: bool = False,
        negatives: Sequence[Motion] | None = None,
        candidates: Sequence[int] = tuple(range(1, 21)),
        min_heldout: float = 0.5,
    ):
        # sklearn's contract: store every parameter as given (clone and set_params rely on it)
        self.negatives = negatives
        self.candidates = candidates
        self.min_heldout = min_heldout
        self.n_components = n_components
        self.action = action
        self.fps = fps
        self.cyclic = cyclic
        self.n_postures = n_postures
        self.exclude_root = exclude_root
        self.exclude = exclude
        self.max_step = max_step
        self.max_stay = max_stay
        self.max_iter = max_iter
        self.sigma_smoothing = sigma_smoothing
        self.n_sigma = n_sigma
        self.alpha = alpha
        self.validate = validate
        self.progress = progress

    # ------------------------------------------------------------------------------------------ checks
    def _check_config(self) -> None:
        n = self.n_components
        if isinstance(n, str) and n == "auto":
            return self._check_rest()
        if isinstance(n, bool) or not isinstance(n, int | float | np.integer | np.floating):
            raise ValueError(f"n_components must be 'auto', an int >= 1 or a float in (0, 1), got {n!r}")
        if isinstance(n, int | np.integer) and n < 1:
            raise ValueError(f"n_components must be >= 1, got {n}")
        if isinstance(n, float | np.floating) and not 0.0 < n < 1.0:
            raise ValueError(f"n_components as a variance fraction must be in (0, 1), got {n}")
        self._check_rest()

    def _check_rest(self) -> None:
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be > 0, got {self.fps}")
        if self.n_postures is not None and int(self.n_postures) < 2:
            raise ValueError(f"n_postures must be >= 2, got {self.n_postures}")
        if int(self.max_step) < 1 or int(self.max_stay) < 0 or int(self.max_iter) < 1:
            raise ValueError("need max_step >= 1, max_stay >= 0, max_iter >= 1")
        if self.sigma_smoothing < 0 or not self.n_sigma > 0:
            raise ValueError("need sigma_smoothing >= 0 and n_sigma > 0")
        if self.alpha is not None and not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must be in [0, 1], got {self.alpha}")
        if isinstance(self.exclude, str):
            raise ValueError(f"exclude must be a sequence of patterns, got the string {self.exclude!r}")
        if not len(self.candidates) or min(int(c) for c in self.candidates) < 1:
            raise ValueError(f"candidates must be integers >= 1, got {self.candidates}")
        if not 0.0 <= float(self.min_heldout) <= 1.0:
            raise ValueError(f"min_heldout must be in [0, 1], got {self.min_heldout}")

    def _check_performances(self, performances: Sequence[Motion]) -> list[Motion]:
        motions = list(performances)
        if not motions:
            raise ValueError("fit needs at least one performance")
        for i, m in enumerate(motions):
            if not isinstance(m, Motion):
                raise TypeError(f"performance {i} is a {type(m).__name__}, expected training.mocap.Motion")
        names = motions[0].dof_names
        out = []
        for i, m in enumerate(motions):
            label = m.name or f"performance {i}"
            if set(m.dof_names) != set(names) or len(m.dof_names) != len(names):
                missing = sorted(set(names) - set(m.dof_names))[:5]
                extra = sorted(set(m.dof_names) - set(names))[:5]
                raise ValueError(
                    f"{label}: DOFs differ from those of {motions[0].name or 'performance 0'} "
                    f"(missing {missing}, extra {extra})"
                )
            if m.n_frames < 4:
                raise ValueError(f"{label}: {m.n_frames} frames; a performance needs at least 4")
            if not torch.isfinite(m.angles).all():
                raise ValueError(f"{label}: angles must be finite")
            out.append(m if m.dof_names == names else m.select(names))
        return out

    # ------------------------------------------------------------------------------------------ fit
    def fit(self, performances: Sequence[Motion], y=None, *, skeleton=None) -> ActionModelFitter:
        """Learn the model from ``performances`` (``R`` Motions with the same DOFs); returns ``self``.

        ``y`` is ignored (sklearn's ``fit(X, y=None)`` signature, so the fitter fits in a ``Pipeline``).

        ``skeleton`` (the performances' :class:`torchpf.Skeleton`) says which DOFs are angles
        (``skeleton.dof_revolute``, stored in the model); without one, DOF names decide
        (:func:`priors.action.guess_revolute`).
        """
        self._check_config()
        motions = self._check_performances(performances)
        if isinstance(self.n_components, str):  # "auto": leave-one-performer-out selection, then the fit
            curve = select_n_components(
                motions, skeleton=skeleton, negatives=self.negatives, **self._selection_params()
            )
            params = {
                **self.get_params(deep=False),
                "n_components": curve.chosen,
                "n_sigma": curve.chosen_n_sigma,
                "negatives": None,
            }
            fitted = ActionModelFitter(**params).fit(motions, skeleton=skeleton)
            self.__dict__.update({k: v for k, v in vars(fitted).items() if k.endswith("_")})
            self.validation_curve_ = curve
            self.model_.training_data["info"]["validation"] = curve.as_dict()
            self.model_.training_data["info"]["config"]["n_components"] = "auto"
            return self
        self.validation_curve_ = None
        names = list(motions[0].dof_names)
        angular_full = self._revolute(names, skeleton)
        fps = float(self.fps) if self.fps is not None else float(np.median([m.fps for m in motions]))

        # 1. unwrap along time, then resample (interpolating wrapped angles across ±π would be wrong)
        full = []
        for m in motions:
            a = m.angles.detach().to("cpu", torch.float64).numpy().copy()
            a[:, angular_full] = np.unwrap(a[:, angular_full], axis=0)
            full.append(resample(a, m.fps, fps))
        if any(len(a) < 4 for a in full):
            raise ValueError(f"a performance has fewer than 4 frames at {fps:g} fps")

        # 2-3. postures on the action's angle branch
        posture = select_posture_dofs(names, exclude_root=self.exclude_root, exclude=tuple(self.exclude))
        if not posture:
            raise ValueError("no posture DOFs left after exclude_root / exclude")
        pidx = np.array([names.index(n) for n in posture])
        angular = angular_full[pidx]
        stacked = np.concatenate([a[:, pidx] for a in full])
        center = np.where(angular, circular_mean(stacked), stacked.mean(0))
        postures = [wrap_about(a[:, pidx], center, angular) for a in full]

        # 4. aSpace
        X = np.concatenate(postures)
        n = self.n_components
        if isinstance(n, int | np.integer):
            n = int(min(n, X.shape[0], X.shape[1]))
        pca = PCA(n_components=n, svd_solver="full").fit(X)
        coords = [pca.transform(p) for p in postures]

        # 5. synchronisation
        periods = [estimate_period(z) for z in coords]
        cyclic = self.cyclic
        found = [p for p, score in periods if p is not None and score < PERIODIC_THRESHOLD]
        if cyclic is None:
            cyclic = len(found) * 2 >= len(coords) and len(found) > 0
        if self.n_postures is not None:
            K = int(self.n_postures)
        elif cyclic:
            if not found:
                raise ValueError("cyclic=True but no performance shows a period; pass n_postures")
            K = int(round(float(np.median(found))))
        else:
            K = int(round(float(np.median([len(z) for z in coords]))))
        K = max(K, 2)
        mean = initial_mean(coords, periods, K, bool(cyclic))
        paths, costs, converged, prev = [], [], False, None
        bar = tqdm(range(int(self.max_iter)), desc=f"synchronising {self.action}", disable=not self.progress)
        for _ in bar:
            aligned = [
                self._align(z, mean, bool(cyclic), m.name or f"performance {r}")
                for r, (z, m) in enumerate(zip(coords, motions, strict=True))
            ]
            paths = [p for p, _ in aligned]
            costs.append(float(np.mean([c for _, c in aligned])))
            bar.set_postfix(cost=f"{costs[-1]:.4g}")
            if prev is not None and all(np.array_equal(p, q) for p, q in zip(paths, prev, strict=True)):
                converged = True  # same alignment, hence same mean: a fixed point of DBA
                break
            mean = dba_update(coords, paths, mean, bool(cyclic))
            prev = paths
        bar.close()

        # 6. spreads
        resid = np.concatenate([z - mean[p] for z, p in zip(coords, paths, strict=True)])
        phase = np.concatenate(paths)
        delta = np.sqrt(np.mean(resid**2, 0))
        delta = np.maximum(delta, 1e-12 + 1e-9 * float(delta.max()))
        sq = np.zeros((K, mean.shape[1]))
        np.add.at(sq, phase, resid**2)
        counts = np.bincount(phase, minlength=K).astype(float)
        sq_s = _smooth_over_postures(sq, float(self.sigma_smoothing), bool(cyclic))
        n_s = _smooth_over_postures(counts[:, None], float(self.sigma_smoothing), bool(cyclic))
        std = np.where(n_s > 1e-9, np.sqrt(sq_s / np.maximum(n_s, 1e-300)), delta)
        std = np.maximum(std, 1e-3 * delta)  # a posture matched by identical frames would accept nothing

        # 7. constant-velocity statistics
        deltas = [np.diff(a, axis=0) for a in full]
        # α and σ_φ per DOF (Rius §3.1): training.dynamics' rule, shared with fit-dynamics
        alpha, sigma_phi = cv_statistics(deltas, self.alpha, per_dof=True)
        alpha = np.full(len(names), float(alpha)) if np.ndim(alpha) == 0 else np.asarray(alpha)

        self.dof_names_ = names
        self.posture_dofs_ = posture
        self.fps_ = fps
        self.center_ = center
        self.pca_ = pca
        self.coords_ = coords
        self.periods_ = [p for p, _ in periods]
        self.cyclic_ = bool(cyclic)
        self.n_postures_ = K
        self.mean_performance_ = mean
        self.paths_ = paths
        self.costs_ = costs
        self.n_iter_ = len(costs)
        self.converged_ = converged
        self.std_ = std
        self.delta_ = delta
        self.alpha_ = alpha
        self.sigma_phi_ = sigma_phi
        self.model_ = ActionModel(
            dof_names=names,
            posture_dofs=posture,
            center=center,
            pca_mean=pca.mean_,
            components=pca.components_,
            mean_performance=mean,
            std=std,
            delta=delta,
            sigma_phi=sigma_phi,
            alpha=alpha,
            fps=fps,
            action=self.action,
            cyclic=bool(cyclic),
            n_sigma=self.n_sigma,
            revolute=angular_full,
            explained_variance=pca.explained_variance_,
            explained_variance_ratio=pca.explained_variance_ratio_,
            training={
                "coords": np.concatenate(coords),
                "lengths": np.array([len(z) for z in coords]),
                "phase": phase,
                "info": {
                    "performances": [m.name or f"performance {i}" for i, m in enumerate(motions)],
                    "config": self._config(),
                },
            },
        )
        self.train_acceptance_ = float(
            self.model_.accept_probability_aspace(torch.from_numpy(np.concatenate(coords))).mean()
        )
        self.validation_acceptance_ = None
        if self.validate and len(motions) >= 2:
            params = {**self.get_params(deep=False), "fps": fps, "cyclic": bool(cyclic), "validate": False}
            rates = []
            for r in tqdm(range(len(motions)), desc="validating", disable=not self.progress):
                sub = (
                    ActionModelFitter(**params).fit(motions[:r] + motions[r + 1 :], skeleton=skeleton).model_
                )
                frames = torch.from_numpy(full[r])  # unwrapped and resampled: the model wraps it itself
                rates.append(float(sub.accept_probability(frames).mean()))
            self.validation_acceptance_ = np.array(rates)
        return self

    @staticmethod
    def _revolute(names: Sequence[str], skeleton) -> np.ndarray:
        """``(D_full,)`` bool: which of the performances' DOFs ``names`` are angles."""
        if skeleton is None:
            return np.array(guess_revolute(names))
        missing = sorted(set(names) - set(skeleton.dof_names))
        if missing:
            raise ValueError(f"the performances have DOFs the skeleton lacks: {missing[:5]}")
        revolute = skeleton.dof_revolute.tolist()
        index = {n: i for i, n in enumerate(skeleton.dof_names)}
        return np.array([revolute[index[n]] for n in names])

    def _align(self, z: np.ndarray, mean: np.ndarray, cyclic: bool, label: str) -> tuple[np.ndarray, float]:
        try:
            return dtw_align(z, mean, cyclic=cyclic, max_step=self.max_step, max_stay=self.max_stay)
        except ValueError as e:
            raise ValueError(f"{label}: {e}") from None

    # ------------------------------------------------------------------------------------------ after fit
    def align(self, performance: Motion) -> np.ndarray:
        """Matched mean posture of every frame of a new performance: ``(T',)`` int at the model's fps."""
        if not hasattr(self, "model_"):
            raise NotFittedError("ActionModelFitter: call fit() first")
        m = performance if performance.dof_names == self.dof_names_ else performance.select(self.dof_names_)
        a = m.angles.detach().to("cpu", torch.float64).numpy().copy()
        ang = self.model_.revolute.numpy()
        a[:, ang] = np.unwrap(a[:, ang], axis=0)
        a = resample(a, m.fps, self.fps_)
        z = self.model_.project(torch.from_numpy(a)).numpy()
        return dtw_align(
            z, self.mean_performance_, cyclic=self.cyclic_, max_step=self.max_step, max_stay=self.max_stay
        )[0]

    def _selection_params(self) -> dict[str, Any]:
        return {
            **{k: v for k, v in self._config().items() if k not in ("n_components", "validate")},
            "candidates": tuple(int(c) for c in self.candidates),
            "min_heldout": float(self.min_heldout),
            "progress": self.progress,
        }

    def _config(self) -> dict[str, Any]:
        """The configuration as JSON (stored in the model file): the parameters but ``negatives`` and
        ``progress``."""
        return {
            "n_components": self.n_components,
            "action": self.action,
            "fps": self.fps,
            "cyclic": self.cyclic,
            "n_postures": self.n_postures,
            "exclude_root": self.exclude_root,
            "exclude": list(self.exclude),
            "max_step": self.max_step,
            "max_stay": self.max_stay,
            "max_iter": self.max_iter,
            "sigma_smoothing": self.sigma_smoothing,
            "n_sigma": self.n_sigma,
            "alpha": self.alpha,
            "validate": self.validate,
            "candidates": [int(c) for c in self.candidates],
            "min_heldout": float(self.min_heldout),
        }


# ================================================================================================ selection
def performer_of(name: str | None) -> str:
    """The performer of a performance named ``<subject>_<trial>`` (CMU: ``07_01`` -> ``07``); a name
    without ``_`` is its own performer."""
    name = str(name or "")
    return name.split("_", 1)[0] if "_" in name else name


def random_postures(model: ActionModel, n: int, *, skeleton=None, seed: int = 0) -> torch.Tensor:
    """``(n, D_full)`` poses whose posture DOFs are uniform within the joint limits (``skeleton.lower`` /
    ``upper``; angles within one turn, ``[-π, π)`` where the limits are wider or unknown; lengths within
    the training range without a skeleton): the "random in-limit poses" an action model must reject."""
    g = torch.Generator().manual_seed(seed)
    idx = model.posture_index
    ang = model.angular
    if skeleton is not None:
        order = [skeleton.dof_names.index(n) for n in model.dof_names]
        lo = skeleton.lower.to(torch.float64)[order][idx]
        hi = skeleton.upper.to(torch.float64)[order][idx]
        lo = torch.where(ang, lo.clamp_min(-math.pi), lo)
        hi = torch.where(ang, hi.clamp_max(math.pi), hi)
    else:
        span = model.reconstruct(model.mean_performance)  # (K, P) training range of the lengths
        lo = torch.where(ang, torch.full_like(model.center, -math.pi), span.min(0).values)
        hi = torch.where(ang, torch.full_like(model.center, math.pi), span.max(0).values)
    u = torch.rand(n, len(idx), generator=g, dtype=torch.float64)
    poses = torch.zeros(n, len(model.dof_names), dtype=torch.float64)
    poses[:, idx] = lo + (hi - lo) * u
    return poses


@dataclass
class ValidationCurve:
    """Leave-one-performer-out validation of the aSpace dimension ``D`` and the acceptance half-width
    ``n_sigma`` (:func:`select_n_components`).

    Attributes:
        candidates: ``(C,)`` the ``D`` values tried; ``n_sigmas``: ``(S,)`` the half-widths tried.
        performers: ``(P,)`` performer names (one fold each).
        heldout: ``(S, P, C)`` mean eq. 6 acceptance probability of each left-out performer's frames under
            the model fitted without that performer.
        random: ``(S, C)`` the same for random in-limit poses (:func:`random_postures`), mean over folds.
        negative: ``(S, C)`` the same for the frames of other actions (``negatives``), or NaN without them.
        chosen, chosen_n_sigma: the selection; ``rule``: how (one line).
    """

    candidates: list[int]
    n_sigmas: list[float]
    performers: list[str]
    heldout: np.ndarray
    random: np.ndarray
    negative: np.ndarray
    chosen: int
    chosen_n_sigma: float
    rule: str

    def as_dict(self) -> dict[str, Any]:
        """JSON-able (stored in the model file's training info, printed by ``python -m training inspect``)."""
        neg = np.asarray(self.negative, dtype=float)
        return {
            "candidates": list(self.candidates),
            "n_sigmas": list(self.n_sigmas),
            "performers": list(self.performers),
            "heldout": np.asarray(self.heldout).tolist(),
            "random": np.asarray(self.random).tolist(),
            "negative": np.where(np.isfinite(neg), neg, -1.0).tolist(),
            "chosen": int(self.chosen),
            "chosen_n_sigma": float(self.chosen_n_sigma),
            "rule": self.rule,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ValidationCurve:
        """Inverse of :meth:`as_dict`."""
        neg = np.array(d["negative"], dtype=float)
        return cls(
            list(d["candidates"]), list(d["n_sigmas"]), list(d["performers"]),
            np.array(d["heldout"], dtype=float), np.array(d["random"], dtype=float),
            np.where(neg < 0, np.nan, neg), int(d["chosen"]), float(d["chosen_n_sigma"]), str(d["rule"]),
        )  # fmt: skip

    def table(self) -> str:
        """The curve as a text table, one row per ``(n_sigma, D)`` (``*`` marks the chosen one)."""
        has_neg = bool(np.isfinite(self.negative).any())
        head = f"{'n_sigma':>7} {'D':>3} | " + " ".join(f"{p:>6}" for p in self.performers)
        head += f" | {'mean':>5} {'random':>7}" + (f" {'other':>6}" if has_neg else "")
        rows = [
            "leave-one-performer-out acceptance (eq. 6, % of frames): held-out performer | random in-limit "
            "poses" + (" | other actions" if has_neg else ""),
            head,
            "-" * len(head),
        ]
        for k, ns in enumerate(self.n_sigmas):
            for c, d in enumerate(self.candidates):
                line = f"{ns:>7g} {d:>3} | " + " ".join(f"{100 * v:>6.1f}" for v in self.heldout[k, :, c])
                line += f" | {100 * self.heldout[k, :, c].mean():>5.1f} {100 * self.random[k, c]:>7.2f}"
                line += f" {100 * self.negative[k, c]:>6.1f}" if has_neg else ""
                mark = d == self.chosen and ns == self.chosen_n_sigma
                rows.append(line + ("  *" if mark else ""))
        return "\n".join(rows + [f"chosen D={self.chosen}, n_sigma={self.chosen_n_sigma:g}: {self.rule}"])


def select_n_components(
    motions: Sequence[Motion],
    *,
    skeleton=None,
    negatives: Sequence[Motion] | None = None,
    candidates: Sequence[int] = tuple(range(1, 21)),
    n_sigmas: Sequence[float] = (2.0, 3.0, 4.0),
    min_heldout: float = 0.5,
    max_random: float = 0.01,
    max_negative: float = 0.05,
    n_random: int = 5000,
    progress: bool = False,
    **options,
) -> ValidationCurve:
    """Choose the aSpace dimension ``D`` and the acceptance half-width ``n_sigma`` by leave-one-performer-out
    validation (Rius §4: too large a ``D`` overfits the training performers, too small a one accepts
    anything; Rius fix ``n_sigma = 2``, which with a few training performers rejects most postures of a
    new one).

    For each performer (:func:`performer_of` of the performances' names; where that finds only one, each
    performance counts as a performer of its own), a model is fitted
    on the other performers' performances with ``max(candidates)`` components, and every candidate
    ``(n_sigma, D)`` is scored on its leading ``D`` dimensions (:meth:`ActionModel.truncated`; PCA
    coordinates are nested, so only the synchronisation is shared): the mean eq. 6 acceptance probability
    of the left-out performer's frames, of ``n_random`` random in-limit poses (:func:`random_postures`) and
    of the ``negatives`` (other actions' performances). The choice is the largest ``D`` (the most
    discriminative model), then the smallest ``n_sigma``, whose mean held-out acceptance is at least
    ``min_heldout`` with random poses accepted below ``max_random`` and other actions at most
    ``max_negative``; if none qualifies, the pair maximising held-out acceptance minus the worse of the two
    false-acceptance rates. On the CMU walks of subjects 07, 08 and 16 at 30 fps this picks D = 13 and
    n_sigma = 4 (mean held-out acceptance 55 %); the model fitted on all three then accepts 85 % of the
    subject-35 walk frames, 0 % of the run frames (35_24, 35_26, 16_46) and 0 % of random in-limit poses.

    Args:
        motions: performances of the action (named ``<performer>_<trial>``).
        skeleton: their skeleton (joint types; joint limits for the random poses).
        negatives: performances of other actions (same DOFs), optional.
        candidates: ``D`` values to try (capped at what the data supports); ``n_sigmas``: half-widths.
        **options: other :class:`ActionModelFitter` options (``fps``, ...).

    Returns:
        :class:`ValidationCurve`.
    """
    motions = list(motions)
    groups = [performer_of(m.name) for m in motions]
    if len(set(groups)) < 2:  # names do not tell performers apart: leave one performance out instead
        groups = [m.name or f"performance {i}" for i, m in enumerate(motions)]
    performers = sorted(set(groups))
    if len(performers) < 2:
        raise ValueError(
            "n_components='auto' needs at least two performances (of two performers, named like 07_01 and "
            "08_09, for leave-one-performer-out validation); pass an integer n_components"
        )
    drop = ("n_components", "validate", "negatives", "candidates", "min_heldout", "n_sigma", "progress")
    options = {k: v for k, v in options.items() if k not in drop}
    top = int(max(candidates))
    cands, sigmas = [int(c) for c in candidates], [float(n) for n in n_sigmas]
    S, P, C = len(sigmas), len(performers), len(cands)
    heldout, random, negative = np.zeros((S, P, C)), np.zeros((S, P, C)), np.full((S, P, C), np.nan)
    for i, p in enumerate(tqdm(performers, desc="leave-one-performer-out", disable=not progress)):
        train = [m for m, g in zip(motions, groups, strict=True) if g != p]
        test = [m for m, g in zip(motions, groups, strict=True) if g == p]
        model = ActionModelFitter(n_components=top, **options).fit(train, skeleton=skeleton).model_
        frames = torch.cat([m.select(model.dof_names).angles.to(torch.float64) for m in test])
        rand = random_postures(model, n_random, skeleton=skeleton, seed=i)
        neg = [m.select(model.dof_names).angles.to(torch.float64) for m in negatives or []]
        for k, ns in enumerate(sigmas):
            for c, d in enumerate(cands):
                sub = model.truncated(min(d, model.n_components), ns)
                heldout[k, i, c] = float(sub.accept_probability(frames).mean())
                random[k, i, c] = float(sub.accept_probability(rand).mean())
                if neg:
                    negative[k, i, c] = float(sub.accept_probability(torch.cat(neg)).mean())
    random, negative = random.mean(1), negative.mean(1)
    mean = heldout.mean(1)  # (S, C)
    false_neg = np.nan_to_num(negative, nan=0.0)
    ok = (mean >= min_heldout) & (random < max_random) & (false_neg <= max_negative)
    if ok.any():
        c = max(np.nonzero(ok.any(0))[0])
        k = min(np.nonzero(ok[:, c])[0])
        rule = (
            f"the largest D, then the smallest n_sigma, with held-out acceptance >= {100 * min_heldout:g}%, "
            f"random poses < {100 * max_random:g}%"
            + (f", other actions <= {100 * max_negative:g}%" if negatives else "")
        )
    else:
        k, c = np.unravel_index(int(np.argmax(mean - np.maximum(random, false_neg))), mean.shape)
        rule = "no pair meets the targets; the best held-out acceptance minus false acceptance"
    return ValidationCurve(
        cands, sigmas, performers, heldout, random, negative, cands[int(c)], sigmas[int(k)], rule
    )


def fit_action_model(
    motions: Sequence[Motion], n_components: int | float | str = "auto", *, skeleton=None, **options
) -> ActionModel:
    """Fit an action model to performances of one action: ``ActionModelFitter(...).fit(motions).model_``.

    Args:
        motions: ``R`` performances (Motions with the same DOF names; any lengths and frame rates).
        n_components: ``"auto"`` (default: leave-one-performer-out validation, :func:`select_n_components`),
            the aSpace dimension ``D`` (Rius: 13) or the fraction of variance to keep.
        skeleton: the performances' skeleton: its ``dof_revolute`` says which DOFs are angles (default:
            their names, :func:`priors.action.guess_revolute`).
        **options: any other :class:`ActionModelFitter` option (``action``, ``fps``, ``cyclic``, ...).

    Returns:
        the :class:`~priors.action.ActionModel` (save it with ``.save(path)``).
    """
    return ActionModelFitter(n_components=n_components, **options).fit(motions, skeleton=skeleton).model_
