"""Time alignment (training.align): resampling, period estimation, DTW and the DBA mean update."""

import numpy as np
import pytest

from training.align import dba_update, dtw_align, estimate_period, initial_mean, resample


def test_resample_is_linear_interpolation():
    t = np.arange(13) / 120.0
    values = np.stack([3 * t + 1, -t], 1)
    out = resample(values, 120.0, 30.0)
    np.testing.assert_allclose(out, np.stack([3 * t[::4] + 1, -t[::4]], 1), atol=1e-12)
    np.testing.assert_allclose(resample(values, 120.0, 240.0)[1], (values[0] + values[1]) / 2)


def test_estimate_period_of_a_noisy_cycle():
    rng = np.random.default_rng(0)
    t = np.arange(150)
    z = np.stack([np.sin(2 * np.pi * t / 37), np.cos(4 * np.pi * t / 37)], 1) + 0.05 * rng.normal(
        size=(150, 2)
    )
    period, score = estimate_period(z)
    assert period == 37 and score < 0.2
    assert estimate_period(np.cumsum(rng.normal(size=(150, 2)), 0))[1] > 0.35  # a random walk is not periodic


def test_dtw_recovers_an_exact_subsequence_of_a_cycle():
    K = 20
    mean = np.stack([np.cos(2 * np.pi * np.arange(K) / K), np.sin(2 * np.pi * np.arange(K) / K)], 1)
    truth = (7 + np.array([0, 1, 1, 2, 4, 5, 6, 8, 9, 10, 10, 11, 13, 15, 16, 17, 18, 19, 20, 22])) % K
    path, cost = dtw_align(mean[truth], mean, cyclic=True)
    np.testing.assert_array_equal(path, truth)
    assert cost == pytest.approx(0.0, abs=1e-12)
    path, _ = dtw_align(mean[:K], mean, cyclic=False)
    np.testing.assert_array_equal(path, np.arange(K))
    with pytest.raises(ValueError, match="no alignment"):
        dtw_align(mean[:5], mean, cyclic=False)  # 5 frames cannot cover 20 postures with steps <= 2


def test_dba_recovers_a_cycle_from_time_warped_copies():
    K = 16
    phase = 2 * np.pi * np.arange(K) / K
    cycle = np.stack([np.cos(phase), np.sin(2 * phase)], 1)
    rng = np.random.default_rng(1)
    coords = []
    for speed in (0.8, 1.0, 1.25):  # three performances of the cycle at different speeds
        t = np.arange(int(3 * K / speed)) * speed
        coords.append(np.stack([np.cos(2 * np.pi * t / K), np.sin(4 * np.pi * t / K)], 1))
        coords[-1] += 0.01 * rng.normal(size=coords[-1].shape)
    periods = [estimate_period(z) for z in coords]
    mean = initial_mean(coords, periods, K, cyclic=True)
    for _ in range(10):
        paths = [dtw_align(z, mean, cyclic=True)[0] for z in coords]
        mean = dba_update(coords, paths, mean, cyclic=True)
    # the same cycle up to a phase shift
    err = min(np.abs(np.roll(mean, s, 0) - cycle).max() for s in range(K))
    assert err < 0.15
