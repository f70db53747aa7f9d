"""Resampling schemes: unbiased offspring counts, low variance, batching, registry, edge cases."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchpf.resampling import RESAMPLERS, offspring_counts, resample

SCHEMES = ["multinomial", "systematic", "stratified", "residual"]
LOW_VARIANCE = ["systematic", "stratified", "residual"]
REPLICATES = 4000  # independent resamplings per weight vector, run as one batched call

weight_vectors = st.lists(st.one_of(st.just(0.0), st.floats(1e-3, 1.0)), min_size=2, max_size=40).filter(
    lambda w: sum(w) > 0
)


def _counts(weights: list[float], scheme: str, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    w = torch.tensor(weights, dtype=torch.float64)
    w = w / w.sum()
    log_w = torch.log(w).expand(REPLICATES, -1)  # zeros become -inf
    anc = resample(log_w, scheme, torch.Generator().manual_seed(seed))
    return offspring_counts(anc).to(torch.float64), w


@pytest.mark.parametrize("scheme", SCHEMES)
@settings(max_examples=25, deadline=None, derandomize=True)
@given(weights=weight_vectors)
def test_counts_are_unbiased(scheme, weights):
    counts, w = _counts(weights, scheme, seed=1)
    n = w.numel()
    expected = n * w
    # 5 standard errors of the mean count, using the multinomial variance, an upper bound for every scheme.
    tol = 5 * torch.sqrt(n * w * (1 - w) / REPLICATES) + 1e-9
    assert torch.all((counts.mean(0) - expected).abs() <= tol)
    assert torch.all(counts[:, w == 0] == 0), "a zero-weight particle was selected"
    assert torch.all(counts.sum(-1) == n)


@pytest.mark.parametrize("scheme", LOW_VARIANCE)
@settings(max_examples=25, deadline=None, derandomize=True)
@given(weights=weight_vectors)
def test_low_variance_schemes_beat_multinomial(scheme, weights):
    counts, w = _counts(weights, scheme, seed=2)
    multi, _ = _counts(weights, "multinomial", seed=3)
    n = w.numel()
    multinomial_theory = n * (1 - (w * w).sum())  # sum_i N w_i (1 - w_i)
    # Sampling error of each estimated total variance: sum_i sqrt((m4_i - var_i^2) / R) bounds its std
    # (rare offspring make the variance estimate noisy, so a fixed relative tolerance would not do).
    total_var, se = _total_variance(counts)
    multi_var, multi_se = _total_variance(multi)
    assert total_var <= multinomial_theory + 5 * se + 1e-9
    assert total_var <= multi_var + 5 * (se + multi_se) + 1e-9


def _total_variance(counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    centred = counts - counts.mean(0)
    var = (centred**2).mean(0)
    m4 = (centred**4).mean(0)
    return var.sum(), torch.sqrt((m4 - var**2).clamp(min=0) / counts.shape[0]).sum()


def test_low_variance_is_strict_on_a_typical_vector():
    weights = torch.linspace(0.1, 1.0, 20).tolist()
    multi = _counts(weights, "multinomial", seed=4)[0].var(0).sum()
    for scheme in LOW_VARIANCE:
        assert _counts(weights, scheme, seed=5)[0].var(0).sum() < 0.6 * multi


def test_systematic_counts_are_floor_or_ceil():
    w = torch.tensor([0.05, 0.3, 0.15, 0.5], dtype=torch.float64)
    log_w = torch.log(w).expand(1000, -1)
    counts = offspring_counts(resample(log_w, "systematic", torch.Generator().manual_seed(0)))
    n_w = 4 * w
    assert torch.all((counts >= torch.floor(n_w)) & (counts <= torch.ceil(n_w)))


def test_residual_is_deterministic_for_multiples_of_one_over_n():
    w = torch.tensor([0.25, 0.0, 0.5, 0.25])
    counts = offspring_counts(
        resample(torch.log(w).expand(50, -1), "residual", torch.Generator().manual_seed(0))
    )
    assert torch.equal(counts, torch.tensor([1, 0, 2, 1]).expand(50, -1))


@pytest.mark.parametrize("scheme", SCHEMES)
def test_batched_shapes_dtypes_and_unnormalised_input(scheme):
    g = torch.Generator().manual_seed(0)
    log_w = torch.randn(2, 3, 17, generator=g) * 3 + 100.0  # far from normalised: must not matter
    anc = resample(log_w, scheme, g)
    assert anc.shape == (2, 3, 17) and anc.dtype == torch.long
    assert anc.min() >= 0 and anc.max() < 17
    # one sharp weight in one row only: that row collapses onto it, the others do not
    log_w = torch.zeros(2, 3, 17, dtype=torch.float64)
    log_w[1, 2, 5] = 50.0
    anc = resample(log_w, scheme, g)
    assert torch.all(anc[1, 2] == 5)
    assert offspring_counts(anc[0, 0]).max() < 17


@pytest.mark.parametrize("scheme", SCHEMES)
def test_rows_without_valid_weights_get_identity(scheme):
    log_w = torch.zeros(3, 8)
    log_w[0] = -math.inf
    log_w[1] = math.nan
    anc = resample(log_w, scheme, torch.Generator().manual_seed(0))
    assert torch.equal(anc[0], torch.arange(8)) and torch.equal(anc[1], torch.arange(8))
    assert anc[2].min() >= 0 and anc[2].max() < 8


@pytest.mark.parametrize("scheme", SCHEMES)
def test_same_generator_state_same_ancestors(scheme):
    log_w = torch.randn(4, 100, generator=torch.Generator().manual_seed(1))
    a = resample(log_w, scheme, torch.Generator().manual_seed(7))
    b = resample(log_w, scheme, torch.Generator().manual_seed(7))
    c = resample(log_w, scheme, torch.Generator().manual_seed(8))
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_registry():
    assert set(SCHEMES) <= set(RESAMPLERS)
    assert RESAMPLERS.resolve("Systematic") is RESAMPLERS["systematic"]
    with pytest.raises(ValueError, match="unknown resampler"):
        RESAMPLERS.resolve("nope")
    with pytest.raises(ValueError, match="already registered"):
        RESAMPLERS.register("multinomial")(lambda lw, g: lw)

    def keep_all(log_weights, generator=None):
        return torch.arange(log_weights.shape[-1]).expand(log_weights.shape)

    assert RESAMPLERS.resolve(keep_all) is keep_all
    RESAMPLERS.register("test_keep_all")(keep_all)
    try:
        assert torch.equal(resample(torch.zeros(5), "test_keep_all"), torch.arange(5))
    finally:
        RESAMPLERS.unregister("test_keep_all")


@pytest.mark.parametrize("scheme", SCHEMES)
def test_device_and_dtype(scheme, device, dtype, generator):
    log_w = torch.randn(3, 1000, device=device, dtype=dtype, generator=generator)
    anc = resample(log_w, scheme, generator)
    assert anc.device.type == device.type and anc.shape == (3, 1000) and anc.dtype == torch.long
    assert ((anc >= 0) & (anc < 1000)).all()
