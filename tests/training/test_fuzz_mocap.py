"""Seeded mutation fuzzing of BVH and mocap CSV files (``load_bvh``, ``load_csv``).

Property: a clear error naming the file, or a correct result (``tests/fuzzing.py``: the mutations and the
checks). ``TORCHPF_FUZZ_EXAMPLES=500`` raises the number of examples.
"""

from ..fuzzing import fuzz_test

test_bvh_mutations = fuzz_test("bvh")
test_csv_mutations = fuzz_test("csv")
