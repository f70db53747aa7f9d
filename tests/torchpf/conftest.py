"""Fixtures of the synthetic scenes shared by the synthesis, sequence and likelihood tests: three cameras on a
ring and a depth camera around a subject standing at the origin, 160x120 pixels."""

import pytest

from torchpf.camera import camera_ring, look_at


@pytest.fixture(scope="module")
def rig():
    """Three 160x120 cameras on a 4 m ring, 1.5 m high, looking at (0, 0, 0.8)."""
    return camera_ring(3, radius=4.0, height=1.5, target=(0, 0, 0.8), width=160, height_px=120)


@pytest.fixture(scope="module")
def depth_cam():
    """A 160x120 depth camera in front of the subject, named ``depth``."""
    return look_at((0.6, -3.0, 1.4), (0, 0, 0.8), width=160, height=120, name="depth")
