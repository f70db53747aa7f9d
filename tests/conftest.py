"""Suite-wide settings and fixtures.

The suite runs as ``pytest -n 2`` on a 2-core machine: one torch thread per worker avoids oversubscribing the
cores (two workers x two intra-op threads made small-tensor tests several times slower).

Devices: a test marked ``@pytest.mark.cuda`` is skipped where no CUDA device is present (the one place that
decides it); the ``device`` fixture runs a test on the CPU and, where present, on CUDA; ``dtype`` runs it in
float32 and float64; ``generator`` is a seeded generator on ``device``.
"""

import pytest
import torch

torch.set_num_threads(1)

HAS_CUDA = torch.cuda.is_available()


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Back to one torch thread after every test: a command line run in-process (``main([...])``) sets
    its own (all cores outside CI), and the worker's later tests then fought the other worker for the cores
    (``test_auto_init_finds_the_pose`` took 114 s in the suite, 15 s alone)."""
    yield
    torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    if HAS_CUDA:
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def device(request) -> torch.device:
    """The device a test runs on: the CPU always, CUDA where present."""
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    """The floating dtype a test runs in."""
    return request.param


@pytest.fixture
def generator(device) -> torch.Generator:
    """A generator on ``device`` seeded with 0."""
    return torch.Generator(device=device).manual_seed(0)


@pytest.fixture(scope="session")
def human():
    """The shipped full-body model (``torchpf/assets/human.urdf``), parsed once for the whole suite."""
    from torchpf import Skeleton
    from torchpf.assets import path

    return Skeleton.from_urdf(path("human.urdf"))
