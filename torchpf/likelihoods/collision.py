"""A limb-torso non-penetration prior, as a term of the tracker's likelihood product.

On foreign renders with mask defects the tracker loses an arm by folding it into the torso: where a limb
drops out of one camera or a morphological closing merges it with the body, a forearm inside the torso's
silhouette costs the silhouette cues nothing. On the lost-wrist frames of ten noisy draws the forearm and
hand capsules penetrated the torso's by more than 20 mm on 46 % of frames and never at the true poses
(BENCHMARKS.md, "Round 10"). :class:`SelfCollisionPrior` refuses that fold in the filter's weights::

    log p(theta) = -1/2 sum_{(a, b) in P} relu(r_a + r_b - d_ab(theta))^2 / sigma^2

``d_ab`` the distance between the axes of capsules ``a`` and ``b`` (segment to segment), ``r`` their radii.
The pair set ``P`` comes from structure alone (:func:`limb_torso_pairs`): each capsule of a limb
(:func:`~torchpf.kinematics.tree.body_partition`) against each torso capsule that it clears in the rest pose,
so the pairs a body makes at its joints (a shoulder, a hip) are never penalised.

Example::

    tracker = Tracker(skel, cams, likelihood=("silhouette", "dual_silhouette", "self_collision"))
"""

from __future__ import annotations

import torch

from torchpf.likelihoods.base import LIKELIHOODS, Body, Likelihood

__all__ = ["SelfCollisionPrior", "limb_torso_pairs", "segment_distance"]


def segment_distance(p1: torch.Tensor, q1: torch.Tensor, p2: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Distance (...,) between segments ``p1 q1`` and ``p2 q2`` (each (..., 3)), the closest points found
    in closed form (Ericson, Real-Time Collision Detection §5.1.9) with the parameters clamped to [0, 1];
    zero-length segments are points. Differentiable almost everywhere."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = (d1 * d1).sum(-1)
    e = (d2 * d2).sum(-1)
    b = (d1 * d2).sum(-1)
    c = (d1 * r).sum(-1)
    f = (d2 * r).sum(-1)
    tiny = 1e-12
    a_, e_ = a.clamp_min(tiny), e.clamp_min(tiny)
    denom = a * e - b * b
    # parallel (or degenerate) segments: any s will do, take 0
    s = torch.where(denom > tiny * a_ * e_, ((b * f - c * e) / denom.clamp_min(tiny)).clamp(0, 1), 0.0 * a)
    t = (b * s + f) / e_
    # t outside [0, 1]: clamp it and recompute s for that end of the second segment
    s = torch.where(t < 0, (-c / a_).clamp(0, 1), torch.where(t > 1, ((b - c) / a_).clamp(0, 1), s))
    t = t.clamp(0, 1)
    s = torch.where(a > tiny, s, 0.0 * s)
    t = torch.where(e > tiny, t, 0.0 * t)
    gap = (p1 + s[..., None] * d1) - (p2 + t[..., None] * d2)
    return gap.square().sum(-1).clamp_min(1e-18).sqrt()


def limb_torso_pairs(skeleton, clearance: float = 0.0) -> list[tuple[int, int]]:
    """Capsule pairs ``(limb, torso)`` of ``skeleton`` whose capsules are apart by more than ``clearance``
    metres in the rest pose (all DOFs 0): a bone belongs to its child joint's part of
    :func:`~torchpf.kinematics.tree.body_partition` (the torso, or a limb). Zero-radius capsules (no
    geometry) are left out. Names are never read."""
    from torchpf.kinematics.tree import body_partition

    parts = body_partition(skeleton, per_limb=True, joints=True)
    torso = set(parts[0])
    limbs = {j for p in parts[1:] for j in p}
    bones = [tuple(b) for b in skeleton.bones]
    radii = skeleton.radii.detach().cpu().to(torch.float64)
    rest = skeleton.rest_joints().cpu()
    torso_caps = [c for c, (_, child) in enumerate(bones) if child in torso and radii[c] > 0]
    limb_caps = [c for c, (_, child) in enumerate(bones) if child in limbs and radii[c] > 0]
    pairs = []
    for a in limb_caps:
        for b in torso_caps:
            if set(bones[a]) & set(bones[b]):  # bones that share a joint touch there
                continue
            d = segment_distance(rest[bones[a][0]], rest[bones[a][1]], rest[bones[b][0]], rest[bones[b][1]])
            if float(d) > float(radii[a] + radii[b]) + clearance:
                pairs.append((a, b))
    return pairs


@LIKELIHOODS.register("self_collision")
class SelfCollisionPrior(Likelihood):
    """Limb-torso non-penetration (module docstring): ``-1/2 sum relu(r_a + r_b - d_ab)^2 / sigma^2`` nats
    over the pairs of :func:`limb_torso_pairs`. A prior on the pose, not a cue: it scores every frame that
    has any observation (a frame without one contributes 0, like every term).

    Args:
        skeleton: a :class:`~torchpf.skeleton.Skeleton` (its tree, rest pose and capsule radii).
        sigma: penetration depth (m) that costs 1/2 nat.
        pairs: ``(C_a, C_b)`` capsule index pairs; default :func:`limb_torso_pairs` of ``skeleton``.
        clearance: rest-pose clearance (m) a pair needs to be in the default set.
    """

    obs_field = None  # a prior: it reads no observation

    def __init__(self, skeleton, sigma: float = 0.02, pairs=None, clearance: float = 0.0):
        super().__init__(skeleton)
        if not sigma > 0:
            raise ValueError(f"sigma must be > 0 (m), got {sigma}")
        self.sigma = float(sigma)
        pairs = limb_torso_pairs(skeleton, clearance) if pairs is None else [tuple(p) for p in pairs]
        index = torch.as_tensor(pairs, dtype=torch.long).reshape(-1, 2)
        self.register_buffer("pairs", index, persistent=False)

    def select(self, obs):
        return obs

    def _log_lik(self, body: Body, obs) -> torch.Tensor:
        if self.pairs.numel() == 0:
            return body.theta.new_zeros(body.theta.shape[0])
        ends, radii = body.ends, body.radii
        a, b = self.pairs[:, 0], self.pairs[:, 1]
        ea, eb = ends[:, a], ends[:, b]  # (B, P, 2, 3)
        d = segment_distance(ea[..., 0, :], ea[..., 1, :], eb[..., 0, :], eb[..., 1, :])
        depth = torch.relu(radii[a] + radii[b] - d)
        return -0.5 * (depth / self.sigma).square().sum(-1)
