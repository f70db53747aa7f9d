"""benchmarks/body_fit.py: defect sets and fit keywords parse with clear errors; the clean masks fitted
twice give the same body, and eroded or dilated masks give a different one."""

from pathlib import Path

import pytest
import torch

from benchmarks import body_fit
from benchmarks.foreign import PRESETS, Defects

CMU = Path(__file__).resolve().parents[2].parent / "shared" / "mocap" / "cmu"


def test_parse_defects_and_fit():
    assert body_fit.parse_defects("noisy") == PRESETS["noisy"]
    assert body_fit.parse_defects("morph_px=1, merge=0.3") == Defects(morph_px=1, merge=0.3)
    with pytest.raises(ValueError, match="'blur=2' is not a preset"):
        body_fit.parse_defects("blur=2")
    assert body_fit.parse_fit("view_offset_sigma=1.0, iterations=40") == {
        "view_offset_sigma": 1.0,
        "iterations": 40,
    }
    with pytest.raises(ValueError, match="'iterations' is not key=value"):
        body_fit.parse_fit("iterations")


def test_clean_refit_is_the_reference_and_morphology_moves_the_body():
    if not (CMU / "07_01.bvh").is_file():
        pytest.skip("CMU clips not present")
    rows = body_fit.clip_bodies(
        CMU / "07_01.bvh", [Defects(), Defects(morph_px=1)], frames=3, seed=0, fit={"iterations": 60}
    )
    assert len(rows) == 3
    assert torch.equal(rows[0]["radii"], rows[1]["radii"])  # deterministic: the clean row is the reference
    assert rows[0]["iou"] == rows[1]["iou"] and 0.5 < rows[0]["iou"] <= 1.0
    moved = (rows[2]["radii"].log() - rows[0]["radii"].log()).abs().max()
    assert moved > 0.05  # a 1-px erosion or dilation per mask is a third of a limb at 160x120
