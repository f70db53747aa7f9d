"""torchpf.registry.Registry: the one name -> object mechanism (resamplers, filters, likelihoods, priors)."""

import pytest

from torchpf.registry import Registry


def test_register_lookup_aliases_and_errors():
    reg = Registry("shape", aliases={"circle": "disc"})

    @reg.register("Disc")
    def disc():
        return "disc"

    assert reg.get("disc") is disc and reg["DISC"] is disc and reg.get("circle") is disc
    assert "circle" in reg and "square" not in reg and 3 not in reg
    assert reg.names() == ["disc"] and reg.names(aliases=True) == ["circle", "disc"] and len(reg) == 1
    assert reg.resolve(len) is len and reg.resolve("disc") is disc
    assert reg.canonical("Circle") == "disc" and reg.canonical("DISC") == "disc"
    with pytest.raises(ValueError, match="unknown shape"):
        reg.canonical("square")
    with pytest.raises(ValueError, match=r"unknown shape 'square'; choose from \['disc'\]"):
        reg.get("square")
    with pytest.raises(ValueError, match="already registered"):
        reg.register("disc", len)
    reg.register("disc", len, replace=True)
    assert reg.unregister("disc") is len and "disc" not in reg


def test_entry_points_are_loaded_lazily():
    """The priors package offers its motion priors through the ``torchpf.dynamics`` entry-point group."""
    reg = Registry("dynamics", entry_point_group="torchpf.dynamics")
    assert {"random_walk", "constant_velocity", "damped", "action"} <= set(reg.names())
    assert not reg._entries  # nothing imported yet
    from priors.factories import random_walk

    assert reg.get("random_walk") is random_walk
