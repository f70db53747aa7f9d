"""Skeletons and pose helpers shared by the kinematics tests (URDFs in ``tests/data``)."""

import math
from pathlib import Path

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import path

DATA = Path(__file__).resolve().parents[2] / "data"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``tests/data``: the URDFs of the test robots."""
    return DATA


@pytest.fixture(scope="session")
def f22():
    """The shipped 22-DOF Fontmarty model."""
    return Skeleton.from_urdf(path("fontmarty22.urdf"))


@pytest.fixture(scope="session")
def odd():
    """``tests/data/odd.urdf``: prismatic root, fixed joints mid-chain, odd axes, a branching frame."""
    return Skeleton.from_urdf(DATA / "odd.urdf")


@pytest.fixture(scope="session")
def telescope():
    """``tests/data/telescope.urdf``: a run mixing revolute and prismatic DOFs, a fixed end site."""
    return Skeleton.from_urdf(DATA / "telescope.urdf", joint_names=["slide", "torso", "hand", "tip"])


def _random_poses(skel, shape, dtype, seed=0):
    """Uniform poses within the limits (revolute ranges cut to +-pi)."""
    gen = torch.Generator().manual_seed(seed)
    lo = skel.lower.clamp(min=-math.pi)
    hi = skel.upper.clamp(max=math.pi)
    u = torch.rand(*shape, len(skel.dof_names), generator=gen, dtype=torch.float64)
    return (lo + u * (hi - lo)).to(dtype)


def _interior_poses(skel, n, seed, dtype=torch.float64, spread=0.8):
    """Random poses in the central ``spread`` of every DOF's range (root translation within 1 m)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = skel.lower.clamp(-1.0, 1.0), skel.upper.clamp(-1.0, 1.0)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    u = 2 * torch.rand(n, len(skel.dof_names), generator=g, dtype=torch.float64) - 1
    return (mid + spread * half * u).to(dtype)


@pytest.fixture(scope="session")
def random_poses():
    """``random_poses(skel, shape, dtype, seed=0)``: uniform in-limit poses ``(*shape, D)``."""
    return _random_poses


@pytest.fixture(scope="session")
def interior_poses():
    """``interior_poses(skel, n, seed, dtype=float64, spread=0.8)``: poses away from the limits ``(n, D)``."""
    return _interior_poses
