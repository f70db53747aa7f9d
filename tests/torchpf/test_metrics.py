"""Metrics against literal loop implementations of the paper equations and closed-form cases."""

import math

import numpy as np
import pytest
import torch

from torchpf import metrics


def loops(truth, est, threshold):
    """Fontmarty eq. 3-6 written as the sums in the paper, in numpy float64."""
    R, K, J, _ = est.shape
    rmse = bias = disp = 0.0
    fails = 0
    for j in range(J):
        rmse += math.sqrt(
            sum(np.sum((truth[k, j] - est[r, k, j]) ** 2) for k in range(K) for r in range(R)) / (K * R)
        )
        mean_r = est[:, :, j].mean(0)  # (K, 3)
        bias += np.linalg.norm(sum(truth[k, j] - mean_r[k] for k in range(K)) / K)
        disp += math.sqrt(
            sum(np.sum((est[r, k, j] - mean_r[k]) ** 2) for k in range(K) for r in range(R)) / (K * R)
        )
        fails += sum(
            np.sum((truth[k, j] - est[r, k, j]) ** 2) > threshold**2 for k in range(K) for r in range(R)
        )
    return rmse / J, bias / J, disp / J, fails / (R * J * K)


def test_fontmarty_criteria_match_the_equations():
    gen = torch.Generator().manual_seed(0)
    truth = torch.randn(7, 5, 3, generator=gen, dtype=torch.float64)
    est = truth + 0.2 * torch.randn(4, 7, 5, 3, generator=gen, dtype=torch.float64) + 0.05
    ref = loops(truth.numpy(), est.numpy(), 0.3)
    got = (
        metrics.rmse(truth, est),
        metrics.bias(truth, est),
        metrics.dispersion(est),
        metrics.failure_rate(truth, est, 0.3),
    )
    for g, r in zip(got, ref, strict=True):
        assert float(g) == pytest.approx(r, rel=1e-12)
    assert 0 < ref[3] < 1  # the threshold splits the data


def test_closed_form_cases():
    truth = torch.zeros(10, 4, 3, dtype=torch.float64)
    shifted = truth + torch.tensor([0.03, 0.04, 0.0], dtype=torch.float64)  # 5 cm everywhere
    assert float(metrics.rmse(truth, shifted)) == pytest.approx(0.05)
    assert float(metrics.bias(truth, shifted)) == pytest.approx(0.05)
    assert float(metrics.mpjpe(truth, shifted)) == pytest.approx(0.05)
    two_runs = torch.stack([truth + 0.1, truth - 0.1])  # symmetric: no bias, all dispersion
    assert float(metrics.bias(truth, two_runs)) == pytest.approx(0.0, abs=1e-15)
    assert float(metrics.dispersion(two_runs)) == pytest.approx(0.1 * math.sqrt(3))
    assert float(metrics.failure_rate(truth, two_runs, threshold=0.2)) == 0.0
    assert float(metrics.failure_rate(truth, two_runs, threshold=0.1)) == 1.0
    assert metrics.frame_failures(truth, shifted, 0.04).all()
    torch.testing.assert_close(
        metrics.per_joint_error(truth, shifted), torch.full((4,), 0.05, dtype=torch.float64)
    )
    table = metrics.evaluate(truth, two_runs)
    assert set(table) == {"rmse", "bias", "dispersion", "failure_rate", "mpjpe"}


def test_shape_errors():
    with pytest.raises(ValueError, match="truth"):
        metrics.rmse(torch.zeros(3, 4), torch.zeros(3, 4))
    with pytest.raises(ValueError, match="estimates"):
        metrics.rmse(torch.zeros(3, 4, 3), torch.zeros(2, 3, 5, 3))


def test_effective_sample_size():
    n = 50
    assert float(metrics.effective_sample_size(torch.zeros(n))) == pytest.approx(n)
    one_hot = torch.full((n,), -math.inf)
    one_hot[3] = 0.0
    assert float(metrics.effective_sample_size(one_hot)) == pytest.approx(1.0)
    w = torch.rand(3, n, dtype=torch.float64) + 0.1
    ref = w.sum(-1) ** 2 / (w**2).sum(-1)  # the squared-weights form, unnormalised
    torch.testing.assert_close(metrics.effective_sample_size(w.log() + 7.0), ref)
    dead = torch.stack([torch.full((n,), -math.inf), torch.full((n,), math.nan)])
    assert torch.equal(metrics.effective_sample_size(dead), torch.zeros(2))
    assert float(metrics.mean_ess(torch.tensor([[1.0, 3.0], [2.0, 2.0]]))[0]) == 2.0


def test_marker_to_skin_and_angle_mse():
    # one capsule along x from 0 to 1 m, radius 0.1 m; markers on the surface, 2 cm outside, 3 cm inside
    ends = torch.tensor([[[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]]], dtype=torch.float64)  # (T=1, C=1, 2, 3)
    radii = torch.tensor([0.1], dtype=torch.float64)
    markers = torch.tensor([[[0.5, 0.1, 0.0], [0.5, 0.0, 0.12], [0.3, -0.07, 0.0]]], dtype=torch.float64)
    assert float(metrics.marker_to_skin(markers, ends, radii)) == pytest.approx((0.0 + 0.02 + 0.03) / 3)
    truth = torch.tensor([[3.1, 0.5, 1.0]])
    est = torch.tensor([[-3.1, 0.6, 5.0]])  # 3.1 and -3.1 rad are 0.083 rad apart on the circle
    wrapped = (2 * math.pi - 6.2) ** 2
    assert float(metrics.angle_mse(truth, est, torch.tensor([True, True, False]))) == pytest.approx(
        (wrapped + 0.01) / 2, rel=1e-5
    )


def test_metrics_follow_the_device(device, dtype):
    gen = torch.Generator().manual_seed(0)
    truth = torch.randn(7, 5, 3, generator=gen, dtype=torch.float64)
    est = truth + 0.2 * torch.randn(4, 7, 5, 3, generator=gen, dtype=torch.float64)
    ref = metrics.evaluate(truth, est)
    got = metrics.evaluate(truth.to(device, dtype), est.to(device, dtype))
    for key, value in got.items():
        value = torch.as_tensor(value)
        assert value.device.type in (device.type, "cpu")
        assert float(value) == pytest.approx(float(ref[key]), rel=1e-5), key
