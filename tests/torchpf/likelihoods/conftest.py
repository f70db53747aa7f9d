"""Fixtures of the likelihood tests: the shipped body, a pose, three cameras, a depth camera and one
synthetic frame with every kind of observation."""

import cv2
import numpy as np
import pytest
import torch

from torchpf.likelihoods import SkinBlobLikelihood
from torchpf.observations import DistanceMaps
from torchpf.synth import synthesize

from .cases import H, W


@pytest.fixture(scope="module")
def skel(human):
    return human


@pytest.fixture(scope="module")
def truth(skel):
    names = skel.dof_names
    th = torch.zeros(len(names), dtype=torch.float64)
    for k, v in {
        "Hips_Yposition": 1.0,
        "LeftArm_Yrotation": 0.6,
        "RightArm_Yrotation": -0.5,
        "LeftForeArm_Zrotation": 0.5,
        "RightUpLeg_Xrotation": -0.3,
    }.items():
        th[names.index(k)] = v
    return th


@pytest.fixture(scope="module")
def frame(skel, truth, rig, depth_cam):
    seq = synthesize(skel, truth[None], rig, depth_camera=depth_cam, seed=0)
    fr = seq.frame(0)
    # Skin blobs: discs at the projected head and hands; edges: Canny on the rendered silhouettes.
    markers = SkinBlobLikelihood(skel, rig).markers(truth)
    blobs = []
    for cam in rig.values():
        m = np.zeros((H, W), np.uint8)
        for u, v in cam.project(markers).numpy():
            cv2.circle(m, (round(u), round(v)), 3, 255, -1)
        blobs.append(m)
    fr.skin = DistanceMaps.from_features(blobs)
    fr.edges = DistanceMaps.from_features([cv2.Canny(m, 50, 150) for m in seq.masks[0]])
    return fr
