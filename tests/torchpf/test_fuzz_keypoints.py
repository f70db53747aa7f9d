"""Seeded mutation fuzzing of a sequence directory's ``keypoints.npz`` (``read_sequence``).

Property: a clear error naming the file, or a correct result (``tests/fuzzing.py``: the mutations and the
checks). ``TORCHPF_FUZZ_EXAMPLES=500`` raises the number of examples.
"""

import tempfile

from hypothesis import HealthCheck, given, settings

from ..fuzzing import FUZZ_EXAMPLES, check, plans


@settings(
    derandomize=True, max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck)
)
@given(plan=plans())
def test_keypoints_mutations(plan):
    with tempfile.TemporaryDirectory() as folder:
        assert check("keypoints", plan, folder) in ("ok", "error")
