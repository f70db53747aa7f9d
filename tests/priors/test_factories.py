"""Motion priors by name: entry points, factories."""

import pytest
import torch

from priors.diffusion import structural_sigma
from priors.table5 import table5_sigma
from torchpf import Skeleton
from torchpf.assets import path
from torchpf.distributions import DYNAMICS, make_dynamics


@pytest.fixture(scope="module")
def f22():
    return Skeleton.from_urdf(path("fontmarty22.urdf"))


def test_entry_points_build_working_dynamics(f22):
    assert {"random_walk", "constant_velocity", "damped", "action"} <= set(DYNAMICS.names())
    gen = torch.Generator().manual_seed(0)
    for name in ("constant_velocity", "damped"):
        dyn = make_dynamics(name, f22, fps=5.0)
        x = torch.zeros(4000, 22, dtype=torch.float64)
        extras = dyn.init_extras(x)
        step = dyn.sample(x, gen, extras=extras) - x
        torch.testing.assert_close(step.std(0), structural_sigma(f22, 5.0), rtol=0.08, atol=0)
    walk = make_dynamics("random_walk", f22, fps=5.0)
    x = walk.sample(torch.zeros(4000, 22, dtype=torch.float64), gen)
    assert torch.all(f22.within_limits(x))  # knees and elbows cannot bend backwards from 0
    torch.testing.assert_close(walk.sigma, structural_sigma(f22, 5.0))
    # Table 5 on request: the 22-DOF model is the paper's, every group is recognised, nothing is replaced
    torch.testing.assert_close(
        make_dynamics("random_walk", f22, fps=5.0, stds="table5").sigma, table5_sigma(f22)
    )
    with pytest.raises(ValueError, match="unknown dynamics"):
        make_dynamics("teleport", f22)


def test_a_prior_given_the_wrong_options_names_itself_and_what_it_takes(f22):
    """``dynamics="action", dynamics_options={"path": ...}`` (the key is ``model``): a ``TypeError`` that
    names the prior, the options given and the ones it takes, not the factory's bare signature error."""
    with pytest.raises(
        TypeError, match=r"dynamics 'action': missing .*'model'.*given \['path'\].*takes model"
    ):
        make_dynamics("action", f22, path="walk.npz")
    with pytest.raises(TypeError, match=r"dynamics 'bank': missing .*'models'.*given \['model'\]"):
        make_dynamics("bank", f22, model=["walk.npz"])


def test_quasi_random_filters_refuse_a_prior_without_a_noise_map_and_say_what_to_use(f22):
    """QRS sampling maps low-discrepancy noise through the prior; an action bank has no such map (its action
    switch is discrete), and the error names the prior and the filters that work with it."""
    from priors.bank import ActionBank
    from torchpf.filters import ParticleFilter

    bank = ActionBank.__new__(ActionBank)  # only its type matters: the check comes before any use
    torch.nn.Module.__init__(bank)
    with pytest.raises(ValueError, match=r"ActionBank has none: use the Monte Carlo filters \('sir'"):
        ParticleFilter(bank, lambda x, obs: x.sum(-1), n_particles=8, sampling="qrs")
