"""Motion priors by name: Table 5 stds, entry points, factories."""

import math

import pytest
import torch

from priors.factories import TABLE5, table5_sigma
from torchpf import Skeleton
from torchpf.assets import path
from torchpf.distributions import DYNAMICS, make_dynamics


@pytest.fixture(scope="module")
def f22():
    return Skeleton.from_urdf(path("fontmarty22.urdf"))


def test_table5_on_the_22_dof_model(f22):
    sigma = dict(zip(f22.dof_names, table5_sigma(f22).tolist(), strict=True))
    assert sigma["pelvis_tx"] == TABLE5["base_translation"] == 0.07
    assert sigma["pelvis_rz"] == TABLE5["base_rotation"] == 0.05
    assert sigma["l_shoulder_ry"] == sigma["r_hip_rz"] == 0.1
    assert sigma["l_elbow_rx"] == 0.3 and sigma["r_knee_rx"] == 0.1
    # a random walk's std scales with sqrt(dt): 20 Hz frames are half as noisy as 5 Hz frames
    torch.testing.assert_close(table5_sigma(f22, fps=20.0), table5_sigma(f22) / 2)
    with pytest.raises(ValueError, match="fps"):
        table5_sigma(f22, fps=0)


def test_table5_on_the_cmu_joint_tree():
    human = Skeleton.from_urdf(path("human.urdf"))
    sigma = dict(zip(human.dof_names, table5_sigma(human, scale=2.0).tolist(), strict=True))
    assert sigma["Hips_Xposition"] == pytest.approx(0.14) and sigma["Hips_Yrotation"] == pytest.approx(0.1)
    assert sigma["LeftForeArm_Zrotation"] == pytest.approx(0.6) and sigma[
        "RightUpLeg_Xrotation"
    ] == pytest.approx(0.2)
    assert sigma["LeftArm_Yrotation"] == pytest.approx(0.2) and sigma["RightLeg_Xrotation"] == pytest.approx(
        0.2
    )
    # unobservable and, in CMU data, constant joints are held still
    for dof in (
        "LeftShoulder_Zrotation",
        "LHipJoint_Xrotation",
        "RThumb_Yrotation",
        "LeftFingerBase_Xrotation",
    ):
        assert sigma[dof] == 0.0
    assert math.isclose(sigma["Spine1_Xrotation"], 0.1)


def test_entry_points_build_working_dynamics(f22):
    assert {"random_walk", "constant_velocity", "damped", "action"} <= set(DYNAMICS.names())
    gen = torch.Generator().manual_seed(0)
    for name in ("constant_velocity", "damped"):
        dyn = make_dynamics(name, f22, fps=5.0)
        x = torch.zeros(4000, 22, dtype=torch.float64)
        extras = dyn.init_extras(x)
        step = dyn.sample(x, gen, extras=extras) - x
        torch.testing.assert_close(step.std(0), table5_sigma(f22), rtol=0.08, atol=0)
    walk = make_dynamics("random_walk", f22, fps=5.0)
    x = walk.sample(torch.zeros(4000, 22, dtype=torch.float64), gen)
    assert torch.all(f22.within_limits(x))  # knees and elbows cannot bend backwards from 0
    torch.testing.assert_close(walk.sigma, table5_sigma(f22))
    with pytest.raises(ValueError, match="unknown dynamics"):
        make_dynamics("teleport", f22)
