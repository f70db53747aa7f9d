"""benchmarks/step_speed.py's options: what runs off the CPU, and a clear error where it cannot."""

import pytest
import torch

from benchmarks import step_speed


def test_only_the_tracking_rows_run_off_the_cpu(capsys):
    with pytest.raises(SystemExit) as exc:
        step_speed.main(["--device", "cuda", "--paths", "hybrid,refine"])
    assert exc.value.code == 2
    assert "--device cuda times the apf, hybrid and bank rows only" in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error where no CUDA device is present")
def test_no_cuda_device_is_a_clear_error(capsys):
    with pytest.raises(SystemExit) as exc:
        step_speed.main(["--device", "cuda", "--paths", "hybrid"])
    assert exc.value.code == 2 and "no CUDA device is available" in capsys.readouterr().err
