"""Data-driven proposals (Hauberg eq. 4, 12-14) on a synthetic capsule body seen by two cameras and a depth
sensor: constraint checks against an independent projection (OpenCV), degenerate masks, nearest neighbours
against brute force, and the paper's weighting inside a particle filter."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from priors.motion import AngularRandomWalk, ProjectedGaussian
from priors.proposals import AngularRejection, DepthGuided, SilhouetteGuided, joint_radii, nearest_distance
from torchpf import Skeleton
from torchpf.assets import path
from torchpf.camera import look_at
from torchpf.filters import ParticleFilter, Proposal
from torchpf.observations import Frame, Silhouettes
from torchpf.synth import synthesize


@pytest.fixture(scope="module")
def scene():
    skel = Skeleton.from_urdf(path("fontmarty22.urdf"))
    D = len(skel.dof_names)
    truth = torch.zeros(1, D, dtype=torch.float64)
    truth[0, 2] = 1.0  # pelvis 1 m above the ground
    truth[0, skel.dof_names.index("l_shoulder_ry")] = -1.0  # arms away from the body
    truth[0, skel.dof_names.index("r_shoulder_ry")] = 1.0
    truth[0, skel.dof_names.index("l_elbow_rx")] = 0.8
    truth = skel.clamp(truth)
    cams = [
        look_at((0.0, -4.0, 1.2), (0.0, 0.0, 1.0), width=160, height=120, fov_deg=50, name="front"),
        look_at((4.0, 0.0, 1.2), (0.0, 0.0, 1.0), width=160, height=120, fov_deg=50, name="side"),
    ]
    seq = synthesize(skel, truth, cams, depth_camera=cams[0], mask_size=(80, 60), seed=0)
    frame = seq.frame(0)
    g = torch.Generator().manual_seed(0)
    parents = skel.clamp(truth.float() + 0.03 * torch.randn(60, D, generator=g))
    return skel, cams, truth.float(), frame, parents


def _inside_opencv(cams, masks, X):
    """(M, 3) world points -> (M,) bool inside every mask, by cv2.projectPoints (independent of torchpf)."""
    ok = np.ones(len(X), dtype=bool)
    for cam, mask in zip(cams, masks, strict=True):
        rvec, _ = cv2.Rodrigues(cam.R.numpy())
        uv, _ = cv2.projectPoints(X.astype(np.float64), rvec, cam.t.numpy(), cam.K.numpy(), None)
        H, W = mask.shape
        uv = (uv[:, 0] + 0.5) * np.array([W / cam.width, H / cam.height]) - 0.5
        u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        valid = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        hit = np.zeros(len(X), dtype=bool)
        hit[valid] = mask[v[valid], u[valid]] > 0.5
        ok &= hit
    return ok


def test_proposals_follow_the_protocol(scene):
    skel, cams, *_ = scene
    for q in (SilhouetteGuided(skel, cams), DepthGuided(skel, cams), AngularRejection(skel, cams)):
        assert isinstance(q, Proposal)


def test_silhouette_guided_joints_project_inside_every_mask(scene):
    skel, cams, _, frame, parents = scene
    q = SilhouetteGuided(skel, cams, joint_sigma=0.03, max_tries=40)
    d = q.draw(parents, frame, torch.Generator().manual_seed(1))
    N, J = parents.shape[0], len(skel.joint_names)
    assert d.x.shape == parents.shape and d.log_q.shape == (N,) and d.rejections.shape == (N, J)
    assert skel.within_limits(d.x).all()
    masks = frame.silhouettes.masks.numpy()
    inside = _inside_opencv(cams, masks, d.joints.reshape(-1, 3).double().numpy()).reshape(N, J)
    acc = d.accepted.numpy()
    assert acc.mean() > 0.9
    assert inside[acc].all()  # every accepted joint really is inside both silhouettes
    assert (d.rejections >= 0).all() and d.rejections.sum() > 0
    torch.testing.assert_close(d.log_q, q.prior.log_prob(d.x, parents))


def test_full_masks_reduce_to_the_projected_prior_and_empty_masks_exhaust(scene):
    skel, cams, _, frame, parents = scene
    full = Frame(silhouettes=Silhouettes(torch.ones_like(frame.silhouettes.masks)))
    q = SilhouetteGuided(skel, cams, joint_sigma=0.03, max_tries=5)
    d = q.draw(parents, full, torch.Generator().manual_seed(2))
    assert torch.all(d.rejections == 0) and d.accepted.all()
    same = ProjectedGaussian(skel, 0.03).sample(parents, torch.Generator().manual_seed(2))
    torch.testing.assert_close(d.x, same)
    empty = Frame(silhouettes=Silhouettes(torch.zeros_like(frame.silhouettes.masks)))
    d = q.draw(parents, empty, torch.Generator().manual_seed(3))
    assert not d.accepted.any() and torch.all(d.rejections == 5)
    # a missing camera frame does not constrain
    half = Frame(
        silhouettes=Silhouettes(torch.zeros_like(frame.silhouettes.masks), valid=torch.tensor([False, False]))
    )
    assert q.draw(parents, half, torch.Generator().manual_seed(4)).accepted.all()


def test_guided_proposals_project_with_the_priors_ik_options(scene):
    # a prior that freezes the arms: the proposals inherit its IK options unless given their own, so their
    # samples keep the frozen DOFs at the parents' values, as the filter's dynamics does
    skel, cams, _, frame, parents = scene
    frozen = torch.tensor(["shoulder" in n or "elbow" in n for n in skel.dof_names])
    prior = ProjectedGaussian(skel, 0.03, ik_options={"free": ~frozen, "iters": 4})
    for q in (SilhouetteGuided(skel, cams, prior=prior), DepthGuided(skel, cams, prior=prior)):
        assert q.spatial.ik_options == prior.ik_options
        d = q.draw(parents, frame, torch.Generator().manual_seed(6))
        torch.testing.assert_close(d.x[:, frozen], skel.clamp(parents)[:, frozen])
        assert (d.x[:, ~frozen] != parents[:, ~frozen]).any()
    own = SilhouetteGuided(skel, cams, prior=prior, ik_options={"iters": 2})
    assert own.spatial.ik_options["iters"] == 2 and "free" not in own.spatial.ik_options


def test_batched_redraws_keep_the_law_of_one_at_a_time(scene):
    # k candidates per round and the first acceptable kept = k sequential rejection rounds: same accepted
    # positions and rejection counts in law (means over 2,400 joint draws, stated tolerances)
    skel, cams, _, frame, parents = scene
    many = parents.repeat(10, 1)
    draws = {}
    for k in (1, 8):
        q = SilhouetteGuided(skel, cams, joint_sigma=0.05, max_tries=40, batch_tries=k)
        draws[k] = q.draw(many, frame, torch.Generator().manual_seed(11 + k))
    one, batched = draws[1], draws[8]
    assert one.accepted.float().mean() > 0.95 and batched.accepted.float().mean() > 0.95
    r1, r8 = one.rejections.double().mean(), batched.rejections.double().mean()
    assert r1 > 0.3 and abs(r8 - r1) < 0.15 * r1
    # per joint over the 600 particles: std 5 cm -> standard error ~2 mm per coordinate, 4.5 SE allowed
    gap = (one.joints.mean(0) - batched.joints.mean(0)).abs()
    assert gap.max() < 0.009


def test_nearest_distance_matches_brute_force():
    g = torch.Generator().manual_seed(5)
    pts, qs = torch.rand(500, 3, generator=g), torch.rand(7, 11, 3, generator=g)
    ref = torch.from_numpy(np.sqrt(((qs.numpy()[..., None, :] - pts.numpy()) ** 2).sum(-1)).min(-1)).float()
    for backend in ("cdist", "kdtree"):
        torch.testing.assert_close(
            nearest_distance(pts, qs, backend=backend, chunk=13), ref, atol=1e-6, rtol=0
        )
    assert torch.isinf(nearest_distance(pts[:0], qs)).all()


def test_joint_radii_are_small_for_hands_and_large_for_the_spine():
    human = Skeleton.from_urdf(path("human.urdf"))
    r = dict(zip(human.joint_names, joint_radii(human).tolist(), strict=True))
    assert r["LeftHand"] < r["LeftArm"] < r["Spine1"]


@pytest.mark.parametrize("backend", ["cdist", "kdtree"])
def test_depth_guided_joints_lie_near_observed_points(scene, backend):
    skel, cams, _, frame, parents = scene
    q = DepthGuided(skel, cams, joint_sigma=0.03, max_tries=40, backend=backend)
    d = q.draw(parents, frame, torch.Generator().manual_seed(6))
    pts = frame.points.points.double().numpy()
    X = d.joints.double().numpy()
    dist = np.sqrt(((X[..., None, :] - pts) ** 2).sum(-1)).min(-1)  # brute force (N, J)
    acc = d.accepted.numpy()
    assert acc.mean() > 0.5
    assert (dist[acc] < q.radii.numpy()[np.nonzero(acc)[1]]).all()
    masks = frame.silhouettes.masks.numpy()
    assert _inside_opencv(cams, masks, X[acc]).all()
    assert skel.within_limits(d.x).all()


def test_depth_backends_draw_the_same_particles(scene):
    skel, cams, _, frame, parents = scene
    a = DepthGuided(skel, cams, backend="cdist").draw(parents, frame, torch.Generator().manual_seed(7))
    b = DepthGuided(skel, cams, backend="kdtree").draw(parents, frame, torch.Generator().manual_seed(7))
    assert torch.equal(a.accepted, b.accepted) and torch.equal(a.rejections, b.rejections)
    torch.testing.assert_close(a.x, b.x)


def test_paper_weighting_leaves_the_likelihood_as_weight(scene):
    # q reports log_q = prior.log_prob, so with that prior as the dynamics the correction of eq. 2 cancels and
    # after one step from uniform weights the log-weights are the normalised log-likelihood.
    skel, cams, truth, frame, parents = scene
    prior = ProjectedGaussian(skel, 0.03)
    q = SilhouetteGuided(skel, cams, joint_sigma=0.03, prior=prior)

    def likelihood(x, obs):
        return -((skel.fk(x) - skel.fk(truth)) ** 2).sum((-1, -2)) / (2 * 0.05**2)

    pf = ParticleFilter(prior, likelihood, proposal=q, n_particles=parents.shape[0], ess_threshold=0.0)
    state = pf.step(pf.init(parents), frame, generator=torch.Generator().manual_seed(8))
    ll = likelihood(state.particles, frame)
    torch.testing.assert_close(state.log_weights, ll - torch.logsumexp(ll, 0), atol=1e-4, rtol=0)


def test_angular_rejection_counts_and_caps(scene):
    skel, cams, _, frame, parents = scene
    walk = AngularRandomWalk.from_skeleton(skel, fps=25.0)
    full = Frame(silhouettes=Silhouettes(torch.ones_like(frame.silhouettes.masks)))
    q = AngularRejection(skel, cams, walk, max_rejections=7, batch=64)
    d = q.draw(parents, full, torch.Generator().manual_seed(9))
    assert torch.all(d.rejections == 0)
    torch.testing.assert_close(d.x, walk.sample(parents, torch.Generator().manual_seed(9)))
    empty = Frame(silhouettes=Silhouettes(torch.zeros_like(frame.silhouettes.masks)))
    d = q.draw(parents, empty, torch.Generator().manual_seed(10))
    assert torch.all(d.rejections == 7) and not d.accepted.any()
    q = AngularRejection(skel, cams, walk, max_rejections=200, batch=2048)
    d = q.draw(parents, frame, torch.Generator().manual_seed(11))
    masks = frame.silhouettes.masks.numpy()
    J = len(skel.joint_names)
    inside = _inside_opencv(cams, masks, d.joints.reshape(-1, 3).double().numpy()).reshape(-1, J).all(-1)
    acc = d.accepted.numpy()
    assert acc.any() and inside[acc].all()
    assert (d.rejections[~d.accepted] == 200).all()
    torch.testing.assert_close(d.log_q, walk.log_prob(d.x, parents))


@pytest.mark.parametrize("backend", ["cdist", "kdtree"])
def test_guided_proposals_follow_the_particles_device(scene, device, dtype, backend):
    skel, cams, _, frame, parents = scene
    moved = Skeleton.from_urdf(path("fontmarty22.urdf")).to(device)  # own copy: the fixture stays on the CPU
    x = parents.to(device, dtype)
    g = torch.Generator(device=device).manual_seed(1)
    for q in (
        SilhouetteGuided(moved, cams, joint_sigma=0.03, max_tries=10).to(device),
        DepthGuided(moved, cams, joint_sigma=0.03, max_tries=10, backend=backend).to(device),
    ):
        d = q.draw(x, frame, g)  # the frame stays on the CPU: the proposals move what they read
        for t in (d.x, d.log_q, d.joints):
            assert t.device.type == device.type and t.dtype == dtype, type(q).__name__
        assert d.accepted.device.type == device.type and d.accepted.float().mean() > 0.5
        assert moved.within_limits(d.x).all()
