"""An independent silhouette renderer for the calibration tests (no torchpf.synth, no torchpf.geometry):
each capsule is the convex hull of its two end spheres, so its image is the convex hull of the projected
points of both spheres, projected with ``cv2.projectPoints`` and filled with ``cv2.fillConvexPoly``."""

import cv2
import numpy as np


def _sphere_points(n: int = 96) -> np.ndarray:
    """(n, 3) unit vectors spread over the sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (3 - np.sqrt(5)) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def render_masks(joints, bones, radii, cameras, supersample: int = 8) -> np.ndarray:
    """(V, H, W) uint8 0/255 silhouettes of capsules between ``joints[bones[:, 0]]`` and
    ``joints[bones[:, 1]]`` (joints (J, 3) m, radii (C,) m) in each camera of ``cameras`` (Camera objects
    with K, R, t, width, height). Drawn at ``supersample`` x the resolution, area-averaged and thresholded
    at half coverage: polygon filling adds about half a pixel all round, which at the mask resolution
    would be 10-20 % of a limb's width."""
    joints = np.asarray(joints, dtype=np.float64)
    bones = np.asarray(bones)
    unit = _sphere_points()
    out = []
    for cam in cameras:
        k = supersample
        mask = np.zeros((cam.height * k, cam.width * k), np.uint8)
        K = cam.K.numpy().astype(np.float64).copy()
        K[:2] *= k
        K[:2, 2] += (k - 1) / 2  # pixel centres: u_k + 0.5 = k (u + 0.5)
        rvec = cv2.Rodrigues(cam.R.numpy().astype(np.float64))[0]
        for (p, c), r in zip(bones, np.asarray(radii, dtype=np.float64), strict=True):
            pts = np.concatenate([joints[p] + r * unit, joints[c] + r * unit])
            uv, _ = cv2.projectPoints(pts, rvec, cam.t.numpy().astype(np.float64), K, None)
            hull = cv2.convexHull(np.round(uv.reshape(-1, 2) * 16).astype(np.int32))
            cv2.fillConvexPoly(mask, hull, 255, lineType=cv2.LINE_8, shift=4)
        small = cv2.resize(mask, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        out.append(np.where(small >= 128, 255, 0).astype(np.uint8))
    return np.stack(out)
