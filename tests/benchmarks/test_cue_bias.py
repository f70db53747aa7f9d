"""benchmarks/cue_bias.py: settings parse with clear errors; on clean foreign masks the distance cue's
optimum lies near the true pose, and a cue with a wrong idea of the masks moves it further."""

from pathlib import Path

import pytest

from benchmarks import cue_bias, foreign

CMU = Path(__file__).resolve().parents[2].parent / "shared" / "mocap" / "cmu"


def test_parse_setting():
    assert cue_bias.parse_setting("") == {}
    assert cue_bias.parse_setting("tau=4, despeckle=3") == {"tau": 4.0, "despeckle": 3}
    with pytest.raises(ValueError, match="'tau' is not key=value"):
        cue_bias.parse_setting("tau")


def test_drift_is_small_on_clean_masks_and_grows_with_a_wrong_cue(tmp_path):
    if not (CMU / "07_01.bvh").is_file():
        pytest.skip("CMU clips not present")
    seq = foreign.build_sequence(CMU / "07_01.bvh", tmp_path / "seq", frames=9)
    # a 9x9 median erases the arms and thins the legs at 160x120: its optimum is far from the truth
    floor, drift = cue_bias.drift(seq.path, ["", "despeckle=9"], steps=20, every=4)
    assert floor < 15.0
    assert drift[""] < 30.0  # 14 mm here
    assert drift["despeckle=9"] > drift[""] + 30.0  # 101 mm here
