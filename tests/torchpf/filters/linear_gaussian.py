"""Linear-Gaussian test models and an exact Kalman filter (float64), the reference for the particle filters.

Model (column vectors, rows of tensors are states)::

    x_0 ~ N(m0, P0),   x_t = A x_{t-1} + w_t, w_t ~ N(0, Q),   z_t = H x_t + v_t, v_t ~ N(0, R)

The Kalman filter gives the exact posterior means/covariances and log p(z_{1:T}); the particle filters are run
on the same model through :class:`torchpf.proposals.LinearGaussianDynamics` and :class:`GaussianObservation`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchpf.proposals import Gaussian, LinearGaussianDynamics, ObservationGaussian

F64 = torch.float64


class GaussianObservation(nn.Module):
    """Log-likelihood ``log N(z; H x, R)``: ``x (..., N, D)``, ``z (..., M)`` -> ``(..., N)``."""

    def __init__(self, H: Tensor, R: Tensor):
        super().__init__()
        self.register_buffer("H", H)
        self.register_buffer("chol", torch.linalg.cholesky(R))

    def forward(self, x: Tensor, z: Tensor) -> Tensor:
        H = self.H.to(x)
        chol = self.chol.to(x)
        r = z.unsqueeze(-2) - x @ H.T
        y = torch.linalg.solve_triangular(chol, r.reshape(-1, r.shape[-1]).T, upper=False).T.reshape(r.shape)
        logdet = torch.log(torch.diagonal(chol)).sum()
        return -0.5 * (y * y).sum(-1) - logdet - 0.5 * H.shape[0] * math.log(2 * math.pi)


@dataclass
class LinearGaussianModel:
    A: Tensor
    Q: Tensor
    H: Tensor
    R: Tensor
    m0: Tensor
    P0: Tensor

    @property
    def dim(self) -> int:
        return self.A.shape[0]

    def dynamics(self) -> LinearGaussianDynamics:
        return LinearGaussianDynamics(self.A, self.Q)

    def likelihood(self) -> GaussianObservation:
        return GaussianObservation(self.H, self.R)

    def simulate(self, n_seq: int, n_steps: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """Ground truth ``(B, T, D)`` and observations ``(T, B, M)`` (time first, as ``run`` iterates)."""
        d, m = self.dim, self.H.shape[0]
        cq, cr, cp = (torch.linalg.cholesky(c) for c in (self.Q, self.R, self.P0))
        x = self.m0 + torch.randn(n_seq, d, generator=generator, dtype=F64) @ cp.T
        xs, zs = [], []
        for _ in range(n_steps):
            x = x @ self.A.T + torch.randn(n_seq, d, generator=generator, dtype=F64) @ cq.T
            xs.append(x)
            zs.append(x @ self.H.T + torch.randn(n_seq, m, generator=generator, dtype=F64) @ cr.T)
        return torch.stack(xs, 1), torch.stack(zs, 0)

    def initial_particles(self, n_seq: int, n: int, generator: torch.Generator) -> Tensor:
        cp = torch.linalg.cholesky(self.P0)
        return self.m0 + torch.randn(n_seq, n, self.dim, generator=generator, dtype=F64) @ cp.T

    def kalman(self, zs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Exact filter on ``zs (T, B, M)``: means ``(B, T, D)``, covariances ``(T, D, D)``, log p(z) ``(B)``.

        Float64, Joseph-form update.
        """
        A, Q, H, R = self.A, self.Q, self.H, self.R
        n_seq = zs.shape[1]
        m = self.m0.expand(n_seq, self.dim)
        P = self.P0
        eye = torch.eye(self.dim, dtype=F64)
        means, covs = [], []
        loglik = torch.zeros(n_seq, dtype=F64)
        for z in zs:
            m = m @ A.T
            P = A @ P @ A.T + Q
            S = H @ P @ H.T + R
            K = P @ H.T @ torch.linalg.inv(S)
            r = z - m @ H.T
            loglik = loglik + torch.distributions.MultivariateNormal(torch.zeros_like(r), S).log_prob(r)
            m = m + r @ K.T
            P = (eye - K @ H) @ P @ (eye - K @ H).T + K @ R @ K.T  # Joseph form keeps P symmetric PD
            means.append(m)
            covs.append(P)
        return torch.stack(means, 1), torch.stack(covs, 0), loglik


def model_1d() -> LinearGaussianModel:
    t = lambda v: torch.tensor(v, dtype=F64)  # noqa: E731
    return LinearGaussianModel(
        A=t([[0.9]]), Q=t([[0.5]]), H=t([[1.0]]), R=t([[0.3]]), m0=t([0.0]), P0=t([[1.0]])
    )


def model_4d() -> LinearGaussianModel:
    """2-D position + damped velocity; only positions observed. Factorises over the x and y axes."""
    A = torch.tensor(
        [[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0], [0.0, 0.0, 0.8, 0.0], [0.0, 0.0, 0.0, 0.8]], dtype=F64
    )
    return LinearGaussianModel(
        A=A,
        Q=torch.diag(torch.tensor([0.05, 0.05, 0.1, 0.1], dtype=F64)),
        H=torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], dtype=F64),
        R=0.5 * torch.eye(2, dtype=F64),
        m0=torch.zeros(4, dtype=F64),
        P0=torch.diag(torch.tensor([1.0, 1.0, 0.5, 0.5], dtype=F64)),
    )


def icondensation_parts(model: LinearGaussianModel) -> tuple[ObservationGaussian, Gaussian]:
    """An observation-driven ``pi(x | z)`` (positions from ``z``, zero velocity, wide) and a wide ``p0``."""
    d, m = model.dim, model.H.shape[0]
    pinv = torch.linalg.pinv(model.H)

    def mean_fn(z: Tensor) -> Tensor:
        return z @ pinv.T.to(z)

    std = torch.full((d,), 1.0, dtype=F64)
    std[m:] = 1.5
    return ObservationGaussian(mean_fn, std), Gaussian(model.m0, std=3.0)
