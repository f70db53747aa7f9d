"""Fused CPU kernel for the articulated-body solve of :mod:`torchpf.kinematics.aba` (numba; optional).

The eager tensor version (:func:`torchpf.kinematics.aba.aba_solve`) runs each small contraction of each tree
level as its own tensor operation: on a CPU that is ~1,000 operations per solve, bound by their dispatch for
small batches and by the memory traffic of their intermediates for large ones. This kernel runs the same
recursion (Featherstone's ABA, world-frame spatial vectors) body by body, each step one loop over the batch
with the small dimensions unrolled into registers, so that it vectorises over poses and keeps its
intermediates in cache. Same inputs and result as the eager version (checked by the tests); CPU only, no
autograd: :func:`torchpf.kinematics.aba.aba_solve` calls it when those hold and numba is installed.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torchpf.devices import kernel_array

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; a platform without it keeps the eager path
    numba = None

AVAILABLE = numba is not None


def _kernel(tw, rel, w, r, tau, arm, on, point_body, bdofs, bk, bparent, out):
    """ABA over bodies ``0..nb-1`` (parents before children), batch last.

    tw (D, 6, B) twists; rel (J, 3, B) joint positions about the twists' centre, w (J, B) weights, r (J, 3, B)
    residuals, point_body (J,) the body that carries each joint's point mass (-1: none); tau, arm, on
    (D, B) (``on``: 1 for a free DOF, 0 for a held one); bdofs (nb, kmax) DOFs of each body's run (-1
    padding), bk (nb,) run lengths, bparent (nb,) parent body (-1 for a root). Writes ``out (D, B)``.
    Every loop nest has the batch innermost, so that it vectorises over poses.
    """
    nb, kmax = bdofs.shape
    B = tw.shape[2]
    dt = tw.dtype
    # Body inertias and bias forces of the point masses: w [[|y|² I - y yᵀ, [y]x], [-[y]x, I]] and
    # -(y x w r, w r); the articulated ones accumulate their children's as those are eliminated.
    IA = np.zeros((nb, 6, 6, B), dt)
    PA = np.zeros((nb, 6, B), dt)
    for pt in range(rel.shape[0]):
        i = point_body[pt]
        if i < 0:
            continue
        for b in range(B):
            m = w[pt, b]
            x, y, z = rel[pt, 0, b], rel[pt, 1, b], rel[pt, 2, b]
            mx, my, mz = m * x, m * y, m * z
            IA[i, 0, 0, b] += my * y + mz * z
            IA[i, 1, 1, b] += mx * x + mz * z
            IA[i, 2, 2, b] += mx * x + my * y
            IA[i, 0, 1, b] -= mx * y
            IA[i, 0, 2, b] -= mx * z
            IA[i, 1, 2, b] -= my * z
            IA[i, 0, 4, b] -= mz
            IA[i, 0, 5, b] += my
            IA[i, 1, 3, b] += mz
            IA[i, 1, 5, b] -= mx
            IA[i, 2, 3, b] -= my
            IA[i, 2, 4, b] += mx
            IA[i, 3, 3, b] += m
            fx, fy, fz = m * r[pt, 0, b], m * r[pt, 1, b], m * r[pt, 2, b]
            PA[i, 0, b] -= y * fz - z * fy
            PA[i, 1, b] -= z * fx - x * fz
            PA[i, 2, b] -= x * fy - y * fx
            PA[i, 3, b] -= fx
            PA[i, 4, b] -= fy
            PA[i, 5, b] -= fz
    for i in range(nb):  # the symmetric entries, the translational mass m I
        for b in range(B):
            IA[i, 1, 0, b] = IA[i, 0, 1, b]
            IA[i, 2, 0, b] = IA[i, 0, 2, b]
            IA[i, 2, 1, b] = IA[i, 1, 2, b]
            IA[i, 4, 4, b] = IA[i, 3, 3, b]
            IA[i, 5, 5, b] = IA[i, 3, 3, b]
            for a in range(3):
                for c in range(3):
                    IA[i, 3 + c, a, b] = IA[i, a, 3 + c, b]
    D = tw.shape[0]
    S = np.empty((D, 6, B), dt)  # per DOF: motion subspace row (zero for a held DOF)
    R = np.empty((D, 7, B), dt)  # per DOF: [D⁻¹ u | D⁻¹ Uᵀ]
    U = np.empty((kmax, 6, B), dt)
    L = np.empty((kmax, kmax, B), dt)  # Cholesky factor of D = Sᵀ I S + diag(arm)
    for i in range(nb - 1, -1, -1):
        k = bk[i]
        for j in range(k):
            dj = bdofs[i, j]
            for c in range(6):
                for b in range(B):
                    S[dj, c, b] = tw[dj, c, b] * on[dj, b]
        # U = I S (row j: (I S_j)ᵀ), right-hand sides [u | Uᵀ] with u = tau - Sᵀ p
        for j in range(k):
            dj = bdofs[i, j]
            for a in range(6):
                for b in range(B):
                    U[j, a, b] = IA[i, a, 0, b] * S[dj, 0, b]
                for c in range(1, 6):
                    for b in range(B):
                        U[j, a, b] += IA[i, a, c, b] * S[dj, c, b]
                for b in range(B):
                    R[dj, 1 + a, b] = U[j, a, b]
            for b in range(B):
                R[dj, 0, b] = tau[dj, b] * on[dj, b]
            for c in range(6):
                for b in range(B):
                    R[dj, 0, b] -= S[dj, c, b] * PA[i, c, b]
        # D = Sᵀ U + diag(arm) (1 for a held DOF, so that it solves to 0); Cholesky D = L Lᵀ
        for j in range(k):
            dj = bdofs[i, j]
            for m in range(j + 1):
                for b in range(B):
                    L[j, m, b] = S[dj, 0, b] * U[m, 0, b]
                for c in range(1, 6):
                    for b in range(B):
                        L[j, m, b] += S[dj, c, b] * U[m, c, b]
                if m == j:
                    for b in range(B):
                        L[j, j, b] += arm[dj, b] if on[dj, b] > 0 else 1
                for p in range(m):
                    for b in range(B):
                        L[j, m, b] -= L[j, p, b] * L[m, p, b]
                if m == j:
                    for b in range(B):
                        L[j, j, b] = np.sqrt(L[j, j, b])
                else:
                    for b in range(B):
                        L[j, m, b] /= L[m, m, b]
        # [D⁻¹ u | D⁻¹ Uᵀ]: forward then backward substitution, in place
        for j in range(k):
            dj = bdofs[i, j]
            for e in range(7):
                for p in range(j):
                    dp = bdofs[i, p]
                    for b in range(B):
                        R[dj, e, b] -= L[j, p, b] * R[dp, e, b]
                for b in range(B):
                    R[dj, e, b] /= L[j, j, b]
        for j in range(k - 1, -1, -1):
            dj = bdofs[i, j]
            for e in range(7):
                for p in range(j + 1, k):
                    dp = bdofs[i, p]
                    for b in range(B):
                        R[dj, e, b] -= L[p, j, b] * R[dp, e, b]
                for b in range(B):
                    R[dj, e, b] /= L[j, j, b]
        par = bparent[i]
        if par >= 0:
            # the parent sees I - U D⁻¹ Uᵀ and p + U D⁻¹ u
            for a in range(6):
                for c in range(6):
                    for b in range(B):
                        IA[par, a, c, b] += IA[i, a, c, b]
                    for j in range(k):
                        dj = bdofs[i, j]
                        for b in range(B):
                            IA[par, a, c, b] -= U[j, a, b] * R[dj, 1 + c, b]
                for b in range(B):
                    PA[par, a, b] += PA[i, a, b]
                for j in range(k):
                    dj = bdofs[i, j]
                    for b in range(B):
                        PA[par, a, b] += U[j, a, b] * R[dj, 0, b]
    # forward: joint accelerations, then the body's spatial acceleration, from the roots down
    acc = np.zeros((nb, 6, B), dt)
    qdd = np.empty((kmax, B), dt)
    for i in range(nb):
        k = bk[i]
        par = bparent[i]
        for j in range(k):
            dj = bdofs[i, j]
            for b in range(B):
                qdd[j, b] = R[dj, 0, b]
            if par >= 0:
                for c in range(6):
                    for b in range(B):
                        qdd[j, b] -= R[dj, 1 + c, b] * acc[par, c, b]
        for a in range(6):
            if par >= 0:
                for b in range(B):
                    acc[i, a, b] = acc[par, a, b]
            for j in range(k):
                dj = bdofs[i, j]
                for b in range(B):
                    acc[i, a, b] += S[dj, a, b] * qdd[j, b]
        for j in range(k):
            dj = bdofs[i, j]
            for b in range(B):
                out[dj, b] = qdd[j, b] * on[dj, b]


_compiled = numba.njit(cache=True, fastmath=True, nogil=True)(_kernel) if AVAILABLE else None


class Structure:
    """The tree as the kernel takes it: body runs, run lengths and parents (``numpy`` int64)."""

    def __init__(self, runs: list[list[int]], parents: list[int]):
        kmax = max((len(r) for r in runs), default=1)
        self.bdofs = np.full((len(runs), kmax), -1, dtype=np.int64)
        for i, r in enumerate(runs):
            self.bdofs[i, : len(r)] = r
        self.bk = np.array([len(r) for r in runs], dtype=np.int64)
        self.bparent = np.array(parents, dtype=np.int64)


def aba_solve(
    structure: Structure,
    tw: Tensor,
    rel: Tensor,
    w: Tensor,
    r: Tensor,
    tau: Tensor,
    arm: Tensor,
    on: Tensor,
    point_body: np.ndarray,
) -> Tensor:
    """``δ (D, B)``: see :func:`torchpf.kinematics.aba.aba_solve` (same system, CPU tensors, no autograd)."""
    D, _, B = tw.shape
    out = torch.zeros(D, B, dtype=tw.dtype)

    def arr(t: Tensor) -> np.ndarray:
        return kernel_array(t, tw.dtype)

    _compiled(
        arr(tw),
        arr(rel),
        arr(w),
        arr(r),
        arr(tau),
        arr(arm),
        arr(on),
        point_body,
        structure.bdofs,
        structure.bk,
        structure.bparent,
        out.numpy(),
    )
    return out
