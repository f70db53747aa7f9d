"""Where a computation runs. The particles' device decides (DESIGN.md); code that must run on the CPU
(OpenCV calls, the visual hull, the body fit's rasterisation) works on CPU copies of the modules it is handed
and leaves the caller's modules where they are.

* :func:`on_cpu` -- a module itself when it is on the CPU, else a CPU copy of it.
* :func:`fused_cpu` -- whether a fused CPU kernel (numba) may stand in for a computation's tensor operations
  (the one place that reads ``TORCHPF_FUSED``).
"""

from __future__ import annotations

import copy
import itertools
import os
from typing import TypeVar

import numpy as np
import torch
from torch import Tensor, nn

M = TypeVar("M", bound=nn.Module)


def on_cpu(module: M) -> M:
    """``module`` when all its parameters and buffers are on the CPU, else a deep copy moved there (same
    dtype). The copy keeps a tracker's skeleton and cameras on its GPU while its CPU-side helpers (e.g.
    :class:`torchpf.detect.PersonDetector`) read theirs."""
    tensors = itertools.chain(module.parameters(), module.buffers())
    if all(t.device.type == "cpu" for t in tensors):
        return module
    return copy.deepcopy(module).cpu()


#: With more than one torch thread, batches of more poses than this stay on the tensor operations, which
#: spread over the threads while a fused kernel runs on one: on a 16-core host, 4 or 16 threads, the tensor
#: FK and projection were as fast as the kernels at 2,000 poses and faster at 10,000 (BENCHMARKS.md,
#: "Round 8"); at 500 the kernels were 1.1-2x faster, with one thread 2-8x at every size.
FUSED_MAX_POSES_THREADED = 1024


def kernel_array(t: Tensor, dtype: torch.dtype | None = None) -> np.ndarray:
    """A CPU tensor ``t`` as the C-contiguous numpy array a fused kernel takes, in ``dtype`` (default its
    own); no copy where it already is one."""
    return np.ascontiguousarray(t.detach().to(dtype or t.dtype).numpy())


def fused_cpu(t: Tensor, poses: int | None = None) -> bool:
    """Whether a fused CPU kernel may replace the tensor operations on ``t``: a plain CPU float32/float64
    tensor that autograd (or a ``torch.func`` transform: vmap, jacrev) does not track, ``TORCHPF_FUSED`` not
    ``0`` in the environment (the one switch of every fused kernel: FK, projection, chamfer, articulated-body
    solve), and, where ``poses`` is given (a kernel the threaded tensor version overtakes on large batches),
    one torch thread or at most :data:`FUSED_MAX_POSES_THREADED` poses. Whether numba is installed is the
    kernel's to add."""
    if t.device.type != "cpu" or t.dtype not in (torch.float32, torch.float64):
        return False
    if t.requires_grad and torch.is_grad_enabled():
        return False
    if type(t) is not Tensor or torch._C._functorch.is_functorch_wrapped_tensor(t):
        return False  # a subclass or a transform's wrapper: no storage of its own to hand to numba
    if poses is not None and poses > FUSED_MAX_POSES_THREADED and torch.get_num_threads() > 1:
        return False
    return os.environ.get("TORCHPF_FUSED", "1") != "0"
