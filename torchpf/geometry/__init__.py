"""Capsule geometry of the body model, in 3-D (:mod:`torchpf.geometry.capsules`: distances, ray casting;
Hauberg §5) and projected into an image (:mod:`torchpf.geometry.projected`: tapered 2-D capsules, masks,
sample points, coverage; Fontmarty et al. §3.2.1) and its truncated chamfer distance to a silhouette with
a hand-written gradient (:mod:`torchpf.geometry.chamfer`, with the image look-ups the image cues share).

Shapes: ``...`` batch (poses), ``C`` capsules, ``K`` or ``P`` points. Units: metres in 3-D, pixels in 2-D.

Example::

    from torchpf.geometry import capsule_distance
    ends, radii = skel.capsules(theta)                               # (N, C, 2, 3), (C,)
    d = capsule_distance(cloud, ends[..., 0, :], ends[..., 1, :], radii)   # cloud (K, 3) -> (N, K)
"""

from torchpf.geometry.capsules import capsule_distance, capsule_truncated_cost, raycast_capsules
from torchpf.geometry.chamfer import capsule_area_mean, capsule_chamfer, distance_lookup, sample_image
from torchpf.geometry.projected import (
    Capsules2D,
    capsule_coverage,
    capsule_masks,
    distance_to_capsules,
    outline_points,
    project_capsules,
    sample_in_capsules,
    sample_pattern,
)

__all__ = [
    "Capsules2D",
    "capsule_area_mean",
    "capsule_chamfer",
    "capsule_coverage",
    "capsule_distance",
    "capsule_masks",
    "capsule_truncated_cost",
    "distance_lookup",
    "distance_to_capsules",
    "outline_points",
    "project_capsules",
    "raycast_capsules",
    "sample_image",
    "sample_in_capsules",
    "sample_pattern",
]
