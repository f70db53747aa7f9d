"""2-D body-point cue (Brubaker et al. eq. 3-4): detected joints against the projected skeleton.

Example::

    from torchpf.likelihoods import Keypoints2DLikelihood
    lik = Keypoints2DLikelihood(skel, cameras, joints=["Head", "LeftHand"], sigma=4.0, noise="student")
    logw = lik(particles, Keypoints2D(uv))                     # (..., N, D), (V, J, 2) -> (..., N)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from torchpf.likelihoods.base import LIKELIHOODS, resolve_joints
from torchpf.likelihoods.images import ImageLikelihood
from torchpf.observations import Keypoints2D

__all__ = ["Keypoints2DLikelihood"]


@LIKELIHOODS.register("keypoints")
class Keypoints2DLikelihood(ImageLikelihood):
    """Brubaker et al. eq. 3-4: ``log p = sum_{l, i visible} log p_i(m_{l,i} - P_l(X_i(theta)))``.

    Noise ``p_i``: ``"gaussian"`` (eq. 4, isotropic, ``sigma`` pixels) or ``"student"`` (bivariate
    Student-t with ``dof`` degrees of freedom and scale ``sigma``: heavy tails for unreliable detections).
    Both are normalised densities, so the value compares across frames with different visible counts.

    Args:
        joints: joint names (or indices) the detections refer to, in the obs ``J`` order; default all
            ``skeleton.joint_names``.
        sigma: pixels, in the observation's pixel frame (``image_size``).
        image_size: (width, height) of the detections' pixel frame per camera if not the cameras' own;
            default: the observation's ``image_size`` (a sequence directory's mask grid), else the cameras'.
        learnable: ``True`` (or ``["sigma"]``) makes ``sigma`` an ``nn.Parameter`` (see
            :class:`~torchpf.likelihoods.Likelihood`); the density is normalised, so the log-evidence has
            its maximum at the detections' noise level.

    obs: :class:`~torchpf.observations.Keypoints2D` (V, J, 2), NaN or ``visible=False`` for missing ones.
    """

    obs_type = Keypoints2D
    obs_field = "keypoints"
    scales = ("sigma",)

    def __init__(
        self,
        skeleton,
        cameras,
        *,
        joints: Sequence[str | int] | None = None,
        sigma: float = 4.0,
        noise: str = "gaussian",
        dof: float = 3.0,
        image_size: tuple[int, int] | None = None,
        learnable: bool | Sequence[str] = False,
    ):
        super().__init__(skeleton, cameras)
        if noise not in ("gaussian", "student"):
            raise ValueError(f"noise must be 'gaussian' or 'student', got {noise!r}")
        self.joint_index = resolve_joints(skeleton, joints)
        self.scale_parameter("sigma", sigma, learnable)
        self.noise, self.dof = noise, float(dof)
        self.image_size = image_size

    def _log_lik(self, body, obs: Keypoints2D):
        self._check_cameras(obs.uv, body)
        if obs.uv.shape[-2] != len(self.joint_index):
            raise ValueError(
                f"obs has {obs.uv.shape[-2]} points per camera, expected {len(self.joint_index)}"
            )
        X = body.joints[:, self.joint_index]  # (B, J, 3)
        size = self.image_size or obs.image_size
        rig = self.cameras if size is None else self.cameras.resized(*size)
        uv = rig.project(X)  # (B, J, V, 2)
        observed = body.rows(obs.uv.to(uv), 3).transpose(-3, -2)  # (J, V, 2) or (B, J, V, 2)
        visible = body.rows(obs.visible.to(uv.device), 2).transpose(-2, -1)
        d2 = (uv - observed).square().sum(-1)  # (B, J, V)
        s2 = self.sigma.to(d2).square()
        if self.noise == "gaussian":
            lp = -d2 / (2 * s2) - torch.log(2 * math.pi * s2)
        else:
            nu = self.dof
            lp = (
                math.lgamma((nu + 2) / 2)
                - math.lgamma(nu / 2)
                - torch.log(nu * math.pi * s2)
                - (nu + 2) / 2 * torch.log1p(d2 / (nu * s2))
            )
        return (lp * visible).sum((-1, -2))
