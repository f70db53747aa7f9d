"""Time alignment of performances: resampling, period estimation, DTW and DTW Barycenter Averaging (DBA).

The synchronisation of Rius §2 (with Mozerov et al.'s dense matching), used by :mod:`training.fit` to build
the mean performance ĝ of an action model; all in float64 numpy (performances are small). Shapes: ``T``
frames, ``D`` dimensions (aSpace coordinates), ``K`` mean postures.

* :func:`resample` -- linear interpolation of a clip onto another frame rate (time normalisation).
* :func:`estimate_period` -- YIN-style period of a trajectory (:data:`PERIODIC_THRESHOLD` decides "periodic").
* :func:`dtw_align` -- slope-constrained DTW of a performance to a (cyclic or acyclic) mean performance.
* :func:`initial_mean` / :func:`dba_update` -- DBA: the mean before the first alignment, and the re-estimate
  of each mean posture from the frames aligned to it.

Example::

    mean = initial_mean(coords, [estimate_period(z) for z in coords], K, cyclic=True)
    for _ in range(30):
        paths = [dtw_align(z, mean, cyclic=True)[0] for z in coords]
        mean = dba_update(coords, paths, mean, cyclic=True)
"""

from __future__ import annotations

import math

import numpy as np

#: Normalised-difference threshold under which a performance counts as periodic (YIN uses 0.1-0.2 on
#: audio; mocap cycles repeat less exactly).
PERIODIC_THRESHOLD = 0.35


def resample(values: np.ndarray, fps: float, new_fps: float) -> np.ndarray:
    """Linear interpolation of ``values (T, D)`` sampled at ``fps`` onto the grid ``0, 1/new_fps, ...``
    within the clip (unwrap angles first)."""
    T = values.shape[0]
    if math.isclose(fps, new_fps, rel_tol=1e-9) or T < 2:
        return values.copy()
    n = int(math.floor((T - 1) * new_fps / fps + 1e-9)) + 1
    pos = np.arange(n) * (fps / new_fps)  # fractional source frame of each new frame
    i0 = np.minimum(np.floor(pos).astype(int), T - 2)
    w = (pos - i0)[:, None]
    return (1.0 - w) * values[i0] + w * values[i0 + 1]


def estimate_period(coords: np.ndarray, min_overlap: float = 0.2) -> tuple[int | None, float]:
    """Period (frames) of a trajectory ``coords (T, D)`` and its normalised difference score.

    ``d(τ) = mean_i ||z_{i+τ} - z_i||²`` is normalised YIN-style by its running mean,
    ``d'(τ) = d(τ) / ((1/τ) Σ_{u<=τ} d(u))``; the period is the first local minimum of ``d'`` below
    :data:`PERIODIC_THRESHOLD` (else the global minimum), searched over lags that leave at least
    ``min_overlap · T`` (and 4) overlapping frames. Returns ``(None, inf)`` when the clip is too short.
    """
    T = coords.shape[0]
    max_lag = T - max(4, int(math.ceil(min_overlap * T)))
    if max_lag < 3:
        return None, math.inf
    d = np.array([np.mean(np.sum((coords[tau:] - coords[:-tau]) ** 2, 1)) for tau in range(1, max_lag + 1)])
    cmnd = d * np.arange(1, max_lag + 1) / np.maximum(np.cumsum(d), 1e-300)
    interior = np.flatnonzero((cmnd[1:-1] <= cmnd[:-2]) & (cmnd[1:-1] <= cmnd[2:])) + 1
    below = [i for i in interior if cmnd[i] < PERIODIC_THRESHOLD]
    i = below[0] if below else (int(interior[np.argmin(cmnd[interior])]) if len(interior) else None)
    if i is None:
        return None, math.inf
    return i + 1, float(cmnd[i])


def dtw_align(
    coords: np.ndarray,
    mean: np.ndarray,
    *,
    cyclic: bool,
    max_step: int = 2,
    max_stay: int = 1,
) -> tuple[np.ndarray, float]:
    """Slope-constrained DTW of a performance to a mean performance.

    Args:
        coords: ``(T, D)`` the performance in aSpace.
        mean: ``(K, D)`` the mean performance ĝ.
        cyclic: ĝ is one cycle (``k`` advances modulo ``K``; free start and end phase) or a whole
            performance (path from ``k = 0`` at the first frame to ``k = K-1`` at the last).
        max_step: largest advance of ``k`` from one frame to the next.
        max_stay: most consecutive frames that keep the same ``k`` after the first.

    Returns:
        ``(path (T,) int, cost)``: the matched mean posture of each frame and the mean squared distance
        ``(1/T) Σ_i ||coords_i - mean_{path_i}||²`` of the optimal path.

    Raises:
        ValueError: no path satisfies the constraints (acyclic, lengths differ by more than the slope allows).
    """
    T, K = coords.shape[0], mean.shape[0]
    S = max_stay + 1
    cost = (np.sum(coords**2, 1)[:, None] + np.sum(mean**2, 1)[None, :] - 2.0 * coords @ mean.T).clip(
        min=0.0
    )  # (T, K)
    acc = np.full((K, S), np.inf)  # acc[k, s]: best cost of frame i at posture k after s stays
    if cyclic:
        acc[:, 0] = cost[0]
    else:
        acc[0, 0] = cost[0, 0]
    from_step = np.zeros((T, K), dtype=np.int16)  # advance a of the best entry into (i, k, s=0)
    from_stay = np.zeros((T, K), dtype=np.int16)  # stay count s' of its predecessor (i-1, k-a, s')
    steps = np.arange(1, max_step + 1)
    ks = np.arange(K)
    for i in range(1, T):
        best_s = acc.argmin(1)
        best = acc[ks, best_s]  # (K,)
        src = ks[None, :] - steps[:, None]  # (A, K) predecessor postures
        if cyclic:
            src = src % K
            cand = best[src]
        else:
            cand = np.where(src >= 0, best[src.clip(min=0)], np.inf)
        a = cand.argmin(0)
        new = np.empty_like(acc)
        new[:, 0] = cand[a, ks] + cost[i]
        new[:, 1:] = acc[:, :-1] + cost[i][:, None]
        from_step[i] = steps[a]
        from_stay[i] = best_s[src[a, ks]]
        acc = new
    if cyclic:
        k, s = np.unravel_index(int(np.argmin(acc)), acc.shape)
    else:
        k, s = K - 1, int(np.argmin(acc[K - 1]))
    total = acc[k, s]
    if not np.isfinite(total):
        raise ValueError(
            f"no alignment of a {T}-frame performance to a {K}-posture mean within the slope constraints "
            f"(max_step={max_step}, max_stay={max_stay}); trim the performances or relax the constraints"
        )
    path = np.empty(T, dtype=np.int64)
    path[T - 1] = k
    for i in range(T - 1, 0, -1):
        if s > 0:
            s -= 1
        else:
            k, s = (k - int(from_step[i, k])) % K, int(from_stay[i, k])
        path[i - 1] = k
    return path, float(total) / T


def _fill_missing(values: np.ndarray, counts: np.ndarray, cyclic: bool) -> np.ndarray:
    """Interpolate rows of ``values (K, D)`` whose ``counts`` are 0 from the rows that have data."""
    have = np.flatnonzero(counts > 0)
    if len(have) == len(counts):
        return values
    K = len(counts)
    out = values.copy()
    missing = np.flatnonzero(counts == 0)
    for d in range(values.shape[1]):
        out[missing, d] = np.interp(missing, have, values[have, d], period=K if cyclic else None)
    return out


def initial_mean(coords: list[np.ndarray], periods, K: int, cyclic: bool) -> np.ndarray:
    """ĝ before DBA: a cycle folded from the most typical periodic performance, or the most typical
    performance resampled to ``K`` frames (acyclic)."""
    if cyclic:
        cands = [(abs(p - K), i) for i, (p, _) in enumerate(periods) if p is not None]
        r = min(cands)[1] if cands else int(np.argmax([len(z) for z in coords]))
        z = coords[r]
        period = periods[r][0] or len(z)
        bins = np.floor((np.arange(len(z)) / period % 1.0) * K).astype(int) % K
        sums = np.zeros((K, z.shape[1]))
        np.add.at(sums, bins, z)
        counts = np.bincount(bins, minlength=K)
        return _fill_missing(sums / np.maximum(counts, 1)[:, None], counts, True)
    r = int(np.argmin([abs(len(z) - K) for z in coords]))
    return resample(coords[r], 1.0, (K - 1) / max(len(coords[r]) - 1, 1))[:K]


def dba_update(coords, paths, mean: np.ndarray, cyclic: bool) -> np.ndarray:
    """DBA update: each ĝ_k is the mean of the frames matched to it.

    A posture that a path skips (an advance of 2 or more between frames ``i-1`` and ``i``) gets the
    linear interpolation of those two frames at its place, as classic DTW would match it to one of
    them: without it, postures that faster performances skip are averaged over fewer performances and
    the mean gets kinks there. Postures nobody matched are interpolated along ĝ.
    """
    K = mean.shape[0]
    sums = np.zeros_like(mean)
    counts = np.zeros(K)
    for z, p in zip(coords, paths, strict=True):
        np.add.at(sums, p, z)
        counts += np.bincount(p, minlength=K)
        step = np.diff(p) % K if cyclic else np.diff(p)
        for gap in range(2, int(step.max(initial=0)) + 1):
            i = np.flatnonzero(step == gap) + 1  # frames reached by a jump of `gap` postures
            for s in range(1, gap):
                k = (p[i - 1] + s) % K
                w = s / gap
                np.add.at(sums, k, (1.0 - w) * z[i - 1] + w * z[i])
                counts += np.bincount(k, minlength=K)
    return _fill_missing(sums / np.maximum(counts, 1)[:, None], counts, cyclic)
