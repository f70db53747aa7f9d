"""Seeded mutation fuzzing of action-model files (``ActionModel.load``).

Property: a clear error naming the file, or a correct result (``tests/fuzzing.py``: the mutations and the
checks). ``TORCHPF_FUZZ_EXAMPLES=500`` raises the number of examples.
"""

from ..fuzzing import fuzz_test

test_action_mutations = fuzz_test("action")
