"""Fixtures shared by the motion-prior tests."""

from __future__ import annotations

import pytest

from torchpf import Skeleton
from torchpf.assets import path
from torchpf.camera import camera_ring
from torchpf.sequence import write_sequence
from torchpf.synth import synthesize
from training.fit import ActionModelFitter
from training.synthetic import generate


@pytest.fixture(scope="module")
def saved_models(tmp_path_factory):
    """``(skeleton, root)``: ``human.urdf``, and in ``root`` a walk and a wave model fitted on the generator's
    motion (``walk.npz``, ``wave.npz``, 3 components) and a 6-frame walk sequence to track (``seq``, two
    64x48 cameras)."""
    skel = Skeleton.from_urdf(str(path("human.urdf")))
    root = tmp_path_factory.mktemp("models")
    for action in ("walk", "wave"):
        clips = [generate(action, 60, 15.0, seed=k) for k in range(2)]
        fitter = ActionModelFitter(n_components=3, action=action, fps=15.0)
        fitter.fit(clips, skeleton=skel).model_.save(root / f"{action}.npz")
    cams = camera_ring(2, radius=4.0, width=64, height_px=48, target=(0.0, 0.0, 1.0))
    write_sequence(root / "seq", synthesize(skel, generate("walk", 6, 15.0, seed=7).angles, cams, fps=15.0))
    return skel, root
