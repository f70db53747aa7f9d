"""Suite-wide settings.

The suite runs as ``pytest -n 2`` on a 2-core machine: one torch thread per worker avoids oversubscribing the
cores (two workers x two intra-op threads made small-tensor tests several times slower).
"""

import torch

torch.set_num_threads(1)
