"""Where a computation runs. The particles' device decides (DESIGN.md); code that must run on the CPU
(OpenCV calls, the visual hull, the body fit's rasterisation) works on CPU copies of the modules it is handed
and leaves the caller's modules where they are.

* :func:`on_cpu` -- a module itself when it is on the CPU, else a CPU copy of it.
"""

from __future__ import annotations

import copy
import itertools
from typing import TypeVar

from torch import nn

M = TypeVar("M", bound=nn.Module)


def on_cpu(module: M) -> M:
    """``module`` when all its parameters and buffers are on the CPU, else a deep copy moved there (same
    dtype). The copy keeps a tracker's skeleton and cameras on its GPU while its CPU-side helpers (e.g.
    :class:`torchpf.detect.PersonDetector`) read theirs."""
    tensors = itertools.chain(module.parameters(), module.buffers())
    if all(t.device.type == "cpu" for t in tensors):
        return module
    return copy.deepcopy(module).cpu()
