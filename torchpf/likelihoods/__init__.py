"""Observation likelihoods of the four papers, batched over particles: ``lik(theta, obs) -> (..., N)``.

Every likelihood is an ``nn.Module`` built from a skeleton (normally :class:`torchpf.Skeleton`) and, for
image cues, the cameras. It maps poses ``theta`` (..., N, D) and one frame's observation to
**log**-likelihoods (..., N) (up to a constant), so terms add, annealing exponents multiply, and the filter
normalises with ``logsumexp``. Underneath, each cue scores a :class:`Body` (joint positions and capsules
from one forward kinematics): ``lik(theta, obs)`` is ``lik.log_likelihood_body(Body.of(skel, theta), obs)``,
and :class:`ProductLikelihood` computes the body once for all its terms.

Modules, by observation: :mod:`~torchpf.likelihoods.base` (``Body``, ``Likelihood``, the ``LIKELIHOODS``
registry), :mod:`~torchpf.likelihoods.images` (silhouette, dual silhouette, overlap, skin blobs, Chamfer),
:mod:`~torchpf.likelihoods.points` (point cloud), :mod:`~torchpf.likelihoods.keypoints` (2-D points),
:mod:`~torchpf.likelihoods.product` (``ProductLikelihood``, ``make_likelihood`` by registered name).

* :class:`PointCloudLikelihood` (Hauberg et al. eq. 15): ``-sum_k min(D^2(theta, z_k), tau) / 2 sigma^2``,
  D the distance from point z_k to the (half-)capsule skin. obs: ``PointCloud``.
* :class:`SilhouetteLikelihood` (Fontmarty et al. eq. 2): ``-sum_l D_l^2 / 2 sigma^2``, D_l the share of the
  projected model's area outside camera l's mask. obs: ``Silhouettes``.
* :class:`DualSilhouetteLikelihood` (Fontmarty §3.2.2): same form, D_l the share of N_s foreground points
  not covered by the projected model. obs: ``Silhouettes``.
* :class:`SilhouetteDistanceLikelihood` (Gall et al. 2010 §4): ``-sum_l E_l / 2 sigma^2``, E_l the mean
  cost ``rho(d) = min(d, tau)^2 + 2 a min(d, tau)`` of the model's area points' distance to the mask plus
  that of the mask's points' distance to the model; informative away from the boundary (the cue of
  :mod:`torchpf.refine`). obs: ``Silhouettes``.
* :class:`OverlapLikelihood` (Rius et al. eq. 7): ``beta sum_l log(|model & mask| / |model | mask|)``.
  obs: ``Silhouettes``.
* :class:`Keypoints2DLikelihood` (Brubaker et al. eq. 3-4): ``sum_{l,i} log p(m_li - P_l(X_i))``, Gaussian or
  Student-t, missing points skipped. obs: ``Keypoints2D``.
* :class:`SkinBlobLikelihood` (Fontmarty §3.2.3): ``-sum_l D_l^2 / 2 sigma^2``, D_l the mean skin-distance
  image value at the projected head and hands. obs: ``DistanceMaps`` (field ``skin`` of a ``Frame``).
* :class:`ChamferLikelihood` (Brubaker eq. 9): ``-sum_l mean_i min(d_l(b_i)^2, tau^2) / 2 sigma^2`` over
  model outline points b_i. obs: ``DistanceMaps`` of edges (field ``edges``).
* :class:`ProductLikelihood` (Fontmarty §3.2.4, Brubaker eq. 10): ``sum_k w_k log p_k``. obs: ``Frame``.

``obs`` is the container named above (:mod:`torchpf.observations`) or a
:class:`~torchpf.observations.Frame` holding it; a missing container (None) or camera contributes 0.
Image terms hold their cameras as a :class:`~torchpf.camera.CameraRig` (buffers that move with ``.to()``) and
work in the observation's pixel grid: masks may be smaller than the camera images (the rig is resized to
them), which is how 640x480 cameras are scored on 160x120 masks.

A batch of S independent sequences: ``(S, N, D)`` poses with one frame per sequence, ``(S, V, H, W)`` masks
or distance images, ``(S, V, J, 2)`` keypoints, ``(S, K, 3)`` clouds (:meth:`Body.rows` aligns them; the
images are looked up per sequence, never copied per particle).

Learning: scale parameters (``sigma``, the overlap's ``beta``, a product's exponents) are buffers, or
``nn.Parameter`` s with ``learnable=True``; image cues hold a given :class:`~torchpf.camera.CameraRig` by
reference, so a rig built with ``learnable=["K"]`` is fitted through them (``ParticleFilter.run(...,
grad=True)`` differentiates the log-evidence).

Sampling: the model points of the silhouette cues come from a **fixed quasi-random pattern**
(:func:`torchpf.geometry.sample_pattern`) mapped into every projected capsule, and the dual cue uses
fixed stratified foreground points (:meth:`Silhouettes.foreground_samples`). Likelihoods are therefore
deterministic, smooth functions of the pose - the same particle always gets the same weight - unless a
``generator`` is passed, which draws fresh i.i.d. model points on each call.

Gradients: the point-cloud, silhouette (bilinear mask look-ups ramp across boundary pixels), overlap, 2D
point, skin and Chamfer terms are differentiable in ``theta``; the dual cue is too with ``softness > 0``.

Example::

    from torchpf.likelihoods import PointCloudLikelihood, SilhouetteLikelihood, ProductLikelihood
    lik = ProductLikelihood({"sil": SilhouetteLikelihood(skel, cams), "pc": PointCloudLikelihood(skel)},
                            weights={"sil": 1.0, "pc": 0.5})
    logw = lik(particles, Frame(silhouettes=Silhouettes(masks), points=PointCloud(cloud)))   # (N,)
"""

from torchpf.likelihoods.base import LIKELIHOODS, Body, Likelihood
from torchpf.likelihoods.collision import SelfCollisionPrior
from torchpf.likelihoods.images import (
    ChamferLikelihood,
    DualSilhouetteLikelihood,
    ImageLikelihood,
    OverlapLikelihood,
    SilhouetteDistanceLikelihood,
    SilhouetteLikelihood,
    SkinBlobLikelihood,
)
from torchpf.likelihoods.keypoints import Keypoints2DLikelihood
from torchpf.likelihoods.points import PointCloudLikelihood
from torchpf.likelihoods.product import (
    ProductLikelihood,
    TemperedLikelihood,
    calibrate_temperature,
    make_likelihood,
)

__all__ = [
    "LIKELIHOODS",
    "Body",
    "ChamferLikelihood",
    "DualSilhouetteLikelihood",
    "ImageLikelihood",
    "Keypoints2DLikelihood",
    "Likelihood",
    "OverlapLikelihood",
    "PointCloudLikelihood",
    "ProductLikelihood",
    "SelfCollisionPrior",
    "SilhouetteDistanceLikelihood",
    "SilhouetteLikelihood",
    "SkinBlobLikelihood",
    "TemperedLikelihood",
    "calibrate_temperature",
    "make_likelihood",
]
