"""benchmarks/action_prior.py: each prior it compares is built for a skeleton (the run is a benchmark)."""

from __future__ import annotations

import pytest

from benchmarks.action_prior import PRIORS, build_prior
from priors.action import ActionConstrained, ActionProposal
from priors.bank import ActionBank
from torchpf.assets import path as asset_path
from torchpf.skeleton import Skeleton
from training.fit import ActionModelFitter
from training.synthetic import generate


def test_every_prior_is_built():
    skel = Skeleton.from_urdf(asset_path("human.urdf"))
    walks = [generate("walk", 60, 15.0, seed=k) for k in range(2)]
    model = ActionModelFitter(n_components=3, fps=15.0).fit(walks, skeleton=skel).model_
    built = {name: build_prior(name, skel, model, 30.0, [model]) for name in PRIORS}
    assert built["random_walk"][1] is None
    assert isinstance(built["rius"][0], ActionConstrained) and built["rius"][0].mode == "rius"
    assert built["soft"][0].mode == "soft" and built["soft"][0].model.fps == 30.0
    assert isinstance(built["proposal"][1], ActionProposal) and built["proposal"][1].advance == 0.5
    assert isinstance(built["bank"][0], ActionBank) and built["bank"][0].n_actions == 2
    with pytest.raises(ValueError, match="unknown prior"):
        build_prior("magic", skel, model, 30.0)
