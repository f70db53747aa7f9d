"""Seeded mutation fuzzing of a sequence directory's ``keypoints.npz`` (``read_sequence``).

Property: a clear error naming the file, or a correct result (``tests/fuzzing.py``: the mutations and the
checks). ``TORCHPF_FUZZ_EXAMPLES=500`` raises the number of examples.
"""

from ..fuzzing import fuzz_test

test_keypoints_mutations = fuzz_test("keypoints")
