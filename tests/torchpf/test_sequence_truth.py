"""truth.csv may list the DOF columns in any order: SequenceData.truth_in puts them in a skeleton's."""

import pytest
import torch

from torchpf.camera import CameraRig
from torchpf.sequence import SequenceData


def test_truth_in_reorders_and_refuses_other_dofs():
    truth = torch.arange(6, dtype=torch.float64).reshape(2, 3)
    seq = SequenceData(cameras=CameraRig([]), truth=truth, dof_names=["b", "c", "a"])
    torch.testing.assert_close(seq.truth_in(["a", "b", "c"]), truth[:, [2, 0, 1]])
    assert seq.truth_in(["b", "c", "a"]) is truth
    with pytest.raises(ValueError, match=r"unknown \['c'\], missing \['d'\]"):
        seq.truth_in(["a", "b", "d"])
