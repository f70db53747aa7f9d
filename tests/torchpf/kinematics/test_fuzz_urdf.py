"""Seeded mutation fuzzing of URDF files (``Skeleton.from_urdf``).

Property: a clear error naming the file, or a correct result (``tests/fuzzing.py``: the mutations and the
checks). ``TORCHPF_FUZZ_EXAMPLES=500`` raises the number of examples.
"""

from ...fuzzing import fuzz_test

test_urdf_mutations = fuzz_test("urdf")
