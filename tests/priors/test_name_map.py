"""Action models on a skeleton that names the DOFs differently: a name map file (issue 14)."""

from __future__ import annotations

import pytest
import torch

from priors.action import ActionModel, read_name_map
from priors.factories import action
from torchpf import Skeleton
from torchpf.__main__ import main
from torchpf.assets import path
from torchpf.camera import camera_ring
from torchpf.sequence import write_sequence
from torchpf.synth import synthesize
from training.fit import ActionModelFitter
from training.synthetic import generate

HUMAN = str(path("human.urdf"))


@pytest.fixture(scope="module")
def foreign_model(tmp_path_factory):
    """A walk model whose DOFs carry another mocap system's names (``mocap.<name>``), saved, and a
    sequence of the human skeleton to track with it."""
    skel = Skeleton.from_urdf(HUMAN)
    walks = [generate("walk", 60, 15.0, seed=k) for k in range(2)]
    model = ActionModelFitter(n_components=3, action="walk", fps=15.0).fit(walks, skeleton=skel).model_
    root = tmp_path_factory.mktemp("name_map")
    foreign = model.renamed({n: f"mocap.{n}" for n in model.dof_names})
    foreign.save(root / "walk.npz")
    cams = camera_ring(2, radius=4.0, width=64, height_px=48, target=(0.0, 0.0, 1.0))
    write_sequence(root / "seq", synthesize(skel, generate("walk", 4, 15.0, seed=5).angles, cams, fps=15.0))
    return skel, model, root


def write_map(file, mapping):
    file.write_text("".join(f"{k}: {v}\n" for k, v in mapping.items()))
    return file


def test_renamed_keeps_the_model_and_refuses_unknown_or_clashing_names(foreign_model):
    skel, model, root = foreign_model
    foreign = ActionModel.load(root / "walk.npz")
    assert foreign.dof_names[0].startswith("mocap.") and foreign.posture_dofs[0].startswith("mocap.")
    back = foreign.renamed({f"mocap.{n}": n for n in skel.dof_names})
    assert back.dof_names == model.dof_names and back.posture_dofs == model.posture_dofs
    theta = generate("walk", 10, 15.0, seed=3).angles.to(torch.float64)
    torch.testing.assert_close(back.accept_probability(theta), model.accept_probability(theta))
    with pytest.raises(ValueError, match=r"does not have: \['nope'\]"):
        foreign.renamed({"nope": "x"})
    a, b = foreign.dof_names[:2]
    with pytest.raises(ValueError, match=r"the same name: \['same'\]"):
        foreign.renamed({a: "same", b: "same"})


def test_the_action_factory_maps_names_and_lists_unmatched_dofs(foreign_model, tmp_path):
    skel, _, root = foreign_model
    with pytest.raises(ValueError, match=r"walk\.npz: .*other DOFs.*name map.*96 DOFs that the model lacks"):
        action(skel, model=root / "walk.npz", fps=15.0)
    full = {f"mocap.{n}": n for n in skel.dof_names}
    dyn = action(skel, model=str(root / "walk.npz"), fps=15.0, name_map=write_map(tmp_path / "m.yaml", full))
    assert dyn.model.dof_names == skel.dof_names
    partial = dict(list(full.items())[:-1])
    left = skel.dof_names[-1]
    with pytest.raises(ValueError, match=rf"1 DOFs that the model lacks \['{left}'\].*\['mocap\.{left}'\]"):
        action(skel, model=root / "walk.npz", name_map=partial)


def test_read_name_map_refuses_what_is_not_a_map_of_names(tmp_path):
    assert read_name_map(write_map(tmp_path / "ok.yaml", {"a": "b", "c": "d"})) == {"a": "b", "c": "d"}
    (tmp_path / "list.yaml").write_text("- a\n- b\n")
    with pytest.raises(ValueError, match=r"list\.yaml: a name map is a non-empty mapping"):
        read_name_map(tmp_path / "list.yaml")
    (tmp_path / "num.yaml").write_text("a: 1\n")
    with pytest.raises(ValueError, match=r"num\.yaml: name map entries must map a name to a name"):
        read_name_map(tmp_path / "num.yaml")


def test_track_cli_takes_a_name_map(foreign_model, tmp_path, capsys):
    skel, _, root = foreign_model
    track = [
        "track", str(root / "seq"), "--skeleton", HUMAN, "--action", str(root / "walk.npz"),
        "--filter", "sir", "--particles", "40", "--no-progress",
    ]  # fmt: skip
    assert main([*track, "--out", str(tmp_path / "a.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "DOFs that the model lacks" in err and "--name-map" in err
    mapping = write_map(tmp_path / "map.yaml", {f"mocap.{n}": n for n in skel.dof_names})
    assert main([*track, "--name-map", str(mapping), "--out", str(tmp_path / "b.csv")]) == 0
    assert "tracked 4 frames" in capsys.readouterr().out and (tmp_path / "b.csv").exists()
    no_action = [t for t in track if t not in ("--action", str(root / "walk.npz"))]
    assert main([*no_action, "--name-map", str(mapping), "--out", str(tmp_path / "c.csv")]) == 2
    assert "it needs --action" in capsys.readouterr().err
