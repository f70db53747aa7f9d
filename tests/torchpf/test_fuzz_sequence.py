"""Fuzz the sequence-side loaders (issue 16): sequence directories, cameras.yaml, OpenCV FileStorage files,
keypoints.npz. Each example is a seeded mutation of a valid input (tests/torchpf/_fuzz.py says which ones
and checks the property: a ValueError/OSError naming the file, or a correct, finite result within memory
bounded by the input).

The suite runs a few dozen examples per loader (derandomized: the same ones every run);
``TORCHPF_FUZZ_EXAMPLES=500`` runs 500. ``python tests/torchpf/_fuzz.py --n 500`` counts failures instead of
stopping at the first."""

import os

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.torchpf._fuzz import LOADERS, run_example

EXAMPLES = int(os.environ.get("TORCHPF_FUZZ_EXAMPLES", "30"))


@pytest.mark.parametrize("loader", LOADERS)
def test_loader_keeps_the_property(loader, tmp_path_factory):
    work = str(tmp_path_factory.mktemp(f"fuzz-{loader}") / "x")

    @settings(
        derandomize=True,
        max_examples=EXAMPLES,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow],
    )
    @given(seed=st.integers(0, 2**31 - 1))
    def check(seed):
        problem = run_example(loader, seed, work)
        assert problem is None, f"{loader} seed {seed}: {problem}"

    check()
