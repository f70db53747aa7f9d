"""Per-mask weights (``Silhouettes.weight``) in the silhouette cues' sums over the cameras: the weighted cue
equals the weighted sum of the same cue built on each camera alone (an independent computation)."""

import pytest
import torch

from torchpf.camera import CameraRig
from torchpf.likelihoods import (
    DualSilhouetteLikelihood,
    OverlapLikelihood,
    SilhouetteDistanceLikelihood,
    SilhouetteLikelihood,
)
from torchpf.observations import Silhouettes

CUES = [SilhouetteLikelihood, DualSilhouetteLikelihood, SilhouetteDistanceLikelihood, OverlapLikelihood]


@pytest.mark.parametrize("cls", CUES, ids=lambda c: c.__name__)
def test_weighted_cue_is_the_weighted_sum_of_one_camera_cues(skel, truth, rig, frame, cls):
    sil = frame.silhouettes
    V = sil.masks.shape[-3]
    g = torch.Generator().manual_seed(0)
    poses = truth + 0.05 * torch.randn(6, truth.shape[-1], generator=g, dtype=truth.dtype)
    weight = torch.tensor([0.25, 0.0, 1.5])[:V]
    whole = cls(skel, rig)(poses, sil.with_weight(weight))
    per_camera = torch.stack(
        [
            cls(skel, CameraRig([rig[v]]))(
                poses, Silhouettes(sil.masks[v : v + 1], valid=sil.valid[v : v + 1])
            )
            for v in range(V)
        ],
        -1,
    )
    torch.testing.assert_close(whole, (per_camera * weight.to(per_camera)).sum(-1), rtol=1e-5, atol=1e-6)
    # no weight is weight 1; the terms themselves, unweighted, per camera
    cue = cls(skel, rig)
    torch.testing.assert_close(cue(poses, sil), per_camera.sum(-1), rtol=1e-5, atol=1e-6)
    terms = cue.camera_log_likelihoods(cue.body(poses), sil).reshape(6, V)
    torch.testing.assert_close(terms, per_camera, rtol=1e-5, atol=1e-6)


def test_weights_are_checked_and_share_the_masks_derived_images(frame):
    sil = frame.silhouettes
    V = sil.masks.shape[-3]
    with pytest.raises(ValueError, match="one value per mask"):
        Silhouettes(sil.masks, weight=torch.ones(V + 1))
    with pytest.raises(ValueError, match=">= 0"):
        Silhouettes(sil.masks, weight=-torch.ones(V))
    sil.outside_distance()
    weighted = sil.with_weight(torch.ones(V))
    assert weighted._cache is sil._cache and weighted.offset is sil.offset
