"""torchpf.distributions: Gaussian density, angle wrap, generators, batch flattening, Dynamics base."""

import copy
import math

import pytest
import torch

from torchpf.distributions import (
    Dynamics,
    as_dynamics,
    as_generator,
    diag_normal_log_prob,
    flatten_batch,
    unflatten_batch,
    wrap_angle,
)
from torchpf.filters import ParticleFilter
from torchpf.proposals import GaussianRandomWalk


def test_diag_normal_matches_torch_and_treats_zero_std_as_a_dirac():
    g = torch.Generator().manual_seed(0)
    x, mu = torch.randn(4, 5, 3, generator=g, dtype=torch.float64), torch.randn(3, dtype=torch.float64)
    std = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)
    ref = torch.distributions.Normal(mu, std).log_prob(x).sum(-1)
    torch.testing.assert_close(diag_normal_log_prob(x, mu, std), ref)
    # a frozen DOF (std 0) drops out of the density of the DOFs that move
    frozen = torch.tensor([0.5, 0.0, 2.0], dtype=torch.float64)
    x0 = x.clone()
    x0[..., 1] = mu[1]
    keep = [0, 2]
    ref0 = torch.distributions.Normal(mu[keep], std[keep]).log_prob(x0[..., keep]).sum(-1)
    torch.testing.assert_close(diag_normal_log_prob(x0, mu, frozen), ref0)


def test_wrap_angle_range_and_identity_modulo_two_pi():
    a = torch.linspace(-20, 20, 1001, dtype=torch.float64)
    w = wrap_angle(a)
    assert (w >= -math.pi).all() and (w < math.pi).all()
    torch.testing.assert_close(torch.sin(w), torch.sin(a)) and torch.testing.assert_close(
        torch.cos(w), torch.cos(a)
    )


def test_as_generator_is_reproducible_and_lives_on_the_device():
    assert as_generator(None) is None
    a, b = as_generator(3, "cpu"), as_generator(3, "cpu")
    assert torch.equal(torch.randn(5, generator=a), torch.randn(5, generator=b))
    g = torch.Generator().manual_seed(1)
    assert as_generator(g, "cpu") is g
    with pytest.raises(TypeError, match="seed"):
        as_generator(1.5)


def test_flatten_batch_round_trip():
    x = torch.arange(2 * 3 * 4 * 5.0).reshape(2, 3, 4, 5)
    flat, batch = flatten_batch(x, 2)
    assert flat.shape == (6, 4, 5) and batch == (2, 3)
    assert torch.equal(unflatten_batch(flat, batch), x)
    flat, batch = flatten_batch(torch.zeros(4, 5), 2)
    assert flat.shape == (1, 4, 5) and batch == ()


class _DuckWalk:
    """A duck-typed random walk (no Dynamics base): what a user may hand a filter."""

    def __init__(self, std):
        self.std = std

    def sample(self, x, generator):
        return x + self.std * torch.randn(x.shape, generator=generator, dtype=x.dtype)

    def log_prob(self, x_new, x_old):
        return diag_normal_log_prob(x_new, x_old, self.std)


class _DuckVelocity(_DuckWalk):
    """A duck-typed stateful model: defines update_extras, so it is called with extras=."""

    def sample(self, x, generator, extras):
        return x + extras["v"] + self.std * torch.randn(x.shape, generator=generator, dtype=x.dtype)

    def log_prob(self, x_new, x_old, extras):
        return diag_normal_log_prob(x_new, x_old + extras["v"], self.std)

    def init_extras(self, x0):
        return {"v": torch.ones_like(x0)}

    def update_extras(self, x_new, x_old, extras):
        return {"v": x_new - x_old}


def test_duck_typed_dynamics_are_adapted_once_and_match_the_base_class():
    x = torch.zeros(2, 50, 3)
    duck, base = as_dynamics(_DuckWalk(0.1)), GaussianRandomWalk(0.1)
    assert isinstance(duck, Dynamics) and as_dynamics(base) is base and duck.std == 0.1
    assert duck.init_extras(x) == {} and not duck.has_noise_map() and base.has_noise_map()
    assert copy.deepcopy(duck).std == 0.1 and not hasattr(duck, "no_such_attribute")
    a = duck.sample(x, torch.Generator().manual_seed(0), extras={"ignored": x})
    b = base.sample(x, torch.Generator().manual_seed(0))
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(duck.log_prob(a, x), base.log_prob(a, x))
    lik = lambda x, z: -((x - z) ** 2).sum(-1)  # noqa: E731
    obs = torch.linspace(0, 1, 5)[:, None, None, None].expand(5, 2, 1, 3)
    runs = [
        ParticleFilter(d, lik, n_particles=50, progress=False).run(obs, x, torch.Generator().manual_seed(4))
        for d in (_DuckWalk(0.1), base)
    ]
    torch.testing.assert_close(runs[0].estimates, runs[1].estimates)


def test_stateful_duck_dynamics_get_their_extras():
    dyn = as_dynamics(_DuckVelocity(1e-6))
    x = torch.zeros(10, 2)
    extras = dyn.init_extras(x)
    x1 = dyn.sample(x, None, extras=extras)
    torch.testing.assert_close(x1, torch.ones_like(x), atol=1e-4, rtol=0)
    assert torch.equal(dyn.update_extras(x1, x, extras)["v"], x1 - x)
    with pytest.raises(TypeError, match="sample"):
        as_dynamics(object())
