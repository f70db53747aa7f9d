"""Point-cloud cue (Hauberg et al. eq. 15): a depth sensor's points scored against the capsule skin.

Example::

    from torchpf.likelihoods import PointCloudLikelihood
    lik = PointCloudLikelihood(skel, sigma=0.02, view_point=depth_camera)
    logw = lik(particles, PointCloud(cloud))                   # (..., N, D), (K, 3) -> (..., N)
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchpf.geometry import capsule_truncated_cost
from torchpf.likelihoods.base import LIKELIHOODS, Likelihood
from torchpf.observations import PointCloud

__all__ = ["PointCloudLikelihood"]


@LIKELIHOODS.register("pointcloud")
class PointCloudLikelihood(Likelihood):
    """Hauberg et al. eq. 15: ``log p(Z | theta) = -sum_k min(D^2(theta, z_k), tau) / (2 sigma^2)``.

    Args:
        skeleton: the body model (:class:`~torchpf.likelihoods.Body` says what it needs).
        sigma: standard deviation (m) of the point-to-skin distance.
        tau: truncation of ``D^2`` (m^2) that makes outliers cost a constant; default ``(3 sigma)^2``.
        view_point: (3,) sensor position (m) or a :class:`~torchpf.camera.Camera` (its centre): score
            against the half-capsules facing the sensor (Hauberg §5); None scores full capsules.
        bones: optional subset of capsule indices (e.g. drop fingers and toes for speed).
        chunk_size: poses per chunk of the distance kernel (memory bound; see ``capsule_distance``).
        compile: fuse the distance kernel with ``torch.compile`` (about 2x faster on CPU after a one-off
            compilation of 10-20 s; see ``capsule_truncated_cost``).
        learnable: ``True`` (or ``["sigma"]``) makes ``sigma`` an ``nn.Parameter`` (``tau`` stays fixed).

    obs: :class:`~torchpf.observations.PointCloud` with ``points`` (K, 3), or a (K, 3) tensor.
    Cost: O(N K C) in chunks of ~2^20 pose-capsule-point triples; memory O(N) beyond the chunk.
    """

    obs_type = PointCloud
    obs_field = "points"
    scales = ("sigma",)

    def __init__(
        self,
        skeleton,
        *,
        sigma: float = 0.02,
        tau: float | None = None,
        view_point=None,
        bones: Sequence[int] | None = None,
        chunk_size: int | None = None,
        compile: bool = False,
        learnable: bool | Sequence[str] = False,
    ):
        super().__init__(skeleton, bones)
        self.compile = bool(compile)
        self.scale_parameter("sigma", sigma, learnable)
        self.tau = float(tau) if tau is not None else (3 * float(sigma)) ** 2
        if view_point is not None and hasattr(view_point, "center"):
            view_point = view_point.center
        if view_point is not None:
            self.register_buffer("view_point", torch.as_tensor(view_point, dtype=torch.float64).reshape(3))
        else:
            self.view_point = None
        self.chunk_size = chunk_size

    def _log_lik(self, body, obs: PointCloud):
        a, b, r = body.capsules(self.bones)
        pts = obs.points.to(a)
        if pts.shape[-2] == 0:
            return a.new_zeros(a.shape[0])
        if pts.ndim > 2:
            # (..., K, 3) clouds go with theta's leading dims (one cloud per sequence, shared by its N).
            pts = pts.unsqueeze(-3).expand(*body.batch, *pts.shape[-2:]).reshape(-1, *pts.shape[-2:])
        tau = self.tau
        view = None if self.view_point is None else self.view_point.to(a)
        ssq = capsule_truncated_cost(
            pts, a, b, r, tau=tau, view_point=view, chunk_size=self.chunk_size, compile=self.compile
        )
        return -ssq / (2 * self.sigma**2)
