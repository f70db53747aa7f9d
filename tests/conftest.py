"""Suite-wide settings.

The suite runs as ``pytest -n 2`` on a 2-core machine: one torch thread per worker avoids oversubscribing the
cores (two workers x two intra-op threads made small-tensor tests several times slower).
"""

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def human():
    """The shipped full-body model (``torchpf/assets/human.urdf``), parsed once for the whole suite."""
    from torchpf import Skeleton
    from torchpf.assets import path

    return Skeleton.from_urdf(path("human.urdf"))
