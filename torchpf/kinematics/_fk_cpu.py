"""Fused CPU kernel of the skeleton's forward kinematics (:meth:`torchpf.Skeleton._world`; numba, optional).

The tensor version composes the tree in ~130 tensor operations (one product per motion group, pointer jumping
or one composition per depth level, the DOF axes rotated per group). For the few poses a gradient
refinement moves (4 poses, 38 nodes), each operation's dispatch, not its arithmetic, is the cost: ~0.4 ms
per call, 20 calls per frame. This kernel does the same arithmetic node by node in one pass: each node's
monomials of ``(cos q, sin q, 1)`` / ``(q, 1)`` per DOF (:meth:`torchpf.Skeleton._compile`), its local 3x4
transform (and DOF axes and pivots in its parent frame) as the fused coefficients times those monomials, then
the parent's world transform composed with it, parents before children. Every loop nest has the batch
innermost (batch-last layout, as the tensor version), so it vectorises over poses.

Same inputs and results as the tensor version to rounding (the order of the compositions differs: node by
node here, pointer jumping there; the tests compare both, and both with pytorch-kinematics). CPU only, no
autograd: :meth:`torchpf.Skeleton._world` calls it when :func:`applies`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchpf.devices import fused_cpu

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; a platform without it keeps the tensor path
    numba = None

AVAILABLE = numba is not None


def applies(theta: Tensor) -> bool:
    """Whether FK of poses ``theta (B, D)`` may run the fused kernel: numba installed and
    :func:`torchpf.devices.fused_cpu` (no autograd, a CPU float tensor, one thread or a small batch,
    ``TORCHPF_FUSED`` not ``0``)."""
    return AVAILABLE and fused_cpu(theta, theta.shape[0])


class Structure:
    """The tree and its fused coefficients as the kernel's arrays, in one dtype (built once per dtype).

    Per node (level order, parents first): ``parent (M,)`` (-1 for a root), ``dofs (M, k)`` the DOFs of its
    run (-1 padding) and ``kinds (M, k)`` (0 revolute, 1 prismatic), ``coef (M, 12 + 6k, P)`` its local
    transform's 12 entries, then its DOFs' axes (3 rows each) and pivots (3 rows each, where ``pivots``)
    as coefficients of its ``P`` monomials; ``pivots (M,)`` whether its pivots are computed (else its own
    origin is every pivot of its run).
    """

    def __init__(self, parent, dofs, kinds, coef, pivots, n_dofs: int, dtype: torch.dtype):
        np_dtype = np.float32 if dtype == torch.float32 else np.float64
        self.parent = np.ascontiguousarray(parent, np.int64)
        self.dofs = np.ascontiguousarray(dofs, np.int64)
        self.kinds = np.ascontiguousarray(kinds, np.int64)
        self.coef = np.ascontiguousarray(coef, np_dtype)
        self.pivots = np.ascontiguousarray(pivots, np.bool_)
        in_run = np.zeros(n_dofs, np.bool_)
        in_run[self.dofs[self.dofs >= 0]] = True
        self.orphans = np.flatnonzero(~in_run).astype(np.int64)
        self.n_dofs = n_dofs
        self.np_dtype = np_dtype


def _kernel(q, parent, dofs, kinds, coef, pivots, orphans, with_axes, world, axes, piv):
    """FK of poses ``q (D, B)``: writes ``world (M, 3, 4, B)`` and, ``with_axes``, every DOF's world axis
    ``axes (D, 3, B)`` and pivot ``piv (D, 3, B)``; ``orphans``: the DOFs in no node's run (below every body
    joint), which get a zero axis about node 0's origin, as in the tensor version."""
    M, kmax = dofs.shape
    P = coef.shape[2]
    B = q.shape[1]
    dt = q.dtype
    feat = np.empty((kmax, 3, B), dt)
    mono = np.empty((P, B), dt)
    grown = np.empty((P, B), dt)
    loc = np.empty((coef.shape[1], B), dt)
    for r in range(M):
        m = 0
        while m < kmax and dofs[r, m] >= 0:
            m += 1
        # the monomials: products of one feature per DOF, the first DOF's index the most significant
        n = 1
        for b in range(B):
            mono[0, b] = 1.0
        for k in range(m):
            d = dofs[r, k]
            nf = 3 if kinds[r, k] == 0 else 2
            if nf == 3:
                for b in range(B):
                    feat[k, 0, b] = math.cos(q[d, b])
                    feat[k, 1, b] = math.sin(q[d, b])
                    feat[k, 2, b] = 1.0
            else:
                for b in range(B):
                    feat[k, 0, b] = q[d, b]
                    feat[k, 1, b] = 1.0
            for i in range(n):
                for j in range(nf):
                    for b in range(B):
                        grown[i * nf + j, b] = mono[i, b] * feat[k, j, b]
            n *= nf
            for i in range(n):
                for b in range(B):
                    mono[i, b] = grown[i, b]
        rows = 12
        if with_axes and m > 0:
            rows = 12 + (6 * m if pivots[r] else 3 * m)
        for row in range(rows):
            for b in range(B):
                loc[row, b] = 0.0
            for f in range(n):
                c = coef[r, row, f]
                if c != 0.0:  # the coefficients are sparse: half the time of a dense product
                    for b in range(B):
                        loc[row, b] += c * mono[f, b]
        # A non-finite angle makes the whole local transform NaN, as the tensor version's dense product does
        # (0 x NaN is NaN there, and the zeros skipped above would leave some entries finite).
        for k in range(m):
            d = dofs[r, k]
            for b in range(B):
                if not math.isfinite(q[d, b]):
                    for row in range(rows):
                        loc[row, b] = math.nan
        p = parent[r]
        if p < 0:
            for i in range(3):
                for j in range(4):
                    for b in range(B):
                        world[r, i, j, b] = loc[4 * i + j, b]
        else:
            for i in range(3):
                for j in range(4):
                    for b in range(B):
                        s = world[p, i, 0, b] * loc[j, b]
                        s += world[p, i, 1, b] * loc[4 + j, b]
                        s += world[p, i, 2, b] * loc[8 + j, b]
                        if j == 3:
                            s += world[p, i, 3, b]
                        world[r, i, j, b] = s
        if not with_axes:
            continue
        for k in range(m):
            d = dofs[r, k]
            for i in range(3):
                for b in range(B):
                    a0 = loc[12 + 3 * k, b]
                    a1 = loc[13 + 3 * k, b]
                    a2 = loc[14 + 3 * k, b]
                    if p < 0:
                        axes[d, i, b] = a0 if i == 0 else (a1 if i == 1 else a2)
                    else:
                        axes[d, i, b] = (
                            world[p, i, 0, b] * a0 + world[p, i, 1, b] * a1 + world[p, i, 2, b] * a2
                        )
                    if pivots[r]:
                        o = 12 + 3 * m + 3 * k
                        c0, c1, c2 = loc[o, b], loc[o + 1, b], loc[o + 2, b]
                        if p < 0:
                            piv[d, i, b] = c0 if i == 0 else (c1 if i == 1 else c2)
                        else:
                            piv[d, i, b] = (
                                world[p, i, 0, b] * c0
                                + world[p, i, 1, b] * c1
                                + world[p, i, 2, b] * c2
                                + world[p, i, 3, b]
                            )
                    else:
                        piv[d, i, b] = world[r, i, 3, b]
    if with_axes:
        for d in orphans:
            for i in range(3):
                for b in range(B):
                    axes[d, i, b] = 0.0
                    piv[d, i, b] = world[0, i, 3, b]


_compiled = numba.njit(cache=True, nogil=True)(_kernel) if AVAILABLE else None


def world(structure: Structure, theta: Tensor, with_axes: bool):
    """:meth:`torchpf.Skeleton._world` of CPU poses ``theta (B, D)`` by the fused kernel: ``world (M, 3, 4,
    B)`` and, ``with_axes``, ``axes, pivots (D, 3, B)``, tensors of ``theta``'s dtype."""
    q = np.ascontiguousarray(theta.detach().t().numpy().astype(structure.np_dtype, copy=False))
    M = structure.parent.shape[0]
    B = q.shape[1]
    out = np.empty((M, 3, 4, B), structure.np_dtype)
    shape = (structure.n_dofs, 3, B) if with_axes else (1, 3, 1)
    axes = np.empty(shape, structure.np_dtype)
    piv = np.empty(shape, structure.np_dtype)
    _compiled(
        q,
        structure.parent,
        structure.dofs,
        structure.kinds,
        structure.coef,
        structure.pivots,
        structure.orphans,
        with_axes,
        out,
        axes,
        piv,
    )
    if not with_axes:
        return torch.from_numpy(out)
    return torch.from_numpy(out), torch.from_numpy(axes), torch.from_numpy(piv)
