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


def test_a_checkout_that_was_never_installed_reads_its_pyproject(monkeypatch, tmp_path):
    """Run from the sources without package metadata (PYTHONPATH=., as on a bare GPU machine), the motion
    priors come from the checkout's pyproject.toml: the same names and objects as the installed metadata."""
    from importlib.metadata import entry_points

    import torchpf.registry as registry

    installed = {ep.name: ep.value for ep in entry_points(group="torchpf.dynamics")}
    declared = registry.checkout_entry_points("torchpf.dynamics")
    assert {name: ep.value for name, ep in declared.items()} == installed
    monkeypatch.setattr(registry, "entry_points", lambda group: [])
    reg = Registry("dynamics", entry_point_group="torchpf.dynamics")
    from priors.factories import random_walk

    assert reg.get("random_walk") is random_walk and set(reg.names()) == set(installed)
    # another project's pyproject, or none: nothing registered, and the error says how to get them
    other = tmp_path / "pyproject.toml"
    other.write_text('[project]\nname = "other"\n[project.entry-points."torchpf.dynamics"]\nx = "a:b"\n')
    assert registry.checkout_entry_points("torchpf.dynamics", other) == {}
    assert registry.checkout_entry_points("torchpf.dynamics", tmp_path / "missing.toml") == {}
    monkeypatch.setattr(registry, "checkout_entry_points", lambda group: {})
    with pytest.raises(ValueError, match=r"none is registered.*pip install -e \."):
        Registry("dynamics", entry_point_group="torchpf.dynamics").get("random_walk")
