"""The limb-torso non-penetration prior: segment distances against a dense sampling of both segments, the
pair set from the tree and the rest pose (no names), and the penalty against closed-form geometry."""

import pytest
import torch

from torchpf import Skeleton
from torchpf.assets import path
from torchpf.kinematics.tree import body_partition
from torchpf.likelihoods import ProductLikelihood, SelfCollisionPrior, make_likelihood
from torchpf.likelihoods.collision import limb_torso_pairs, segment_distance


def _sampled_distance(p1, q1, p2, q2, n=801):
    """Segment-to-segment distance by brute force: the closest of n x n points along the two segments."""
    s = torch.linspace(0, 1, n, dtype=torch.float64)
    a = p1 + s[:, None] * (q1 - p1)
    b = p2 + s[:, None] * (q2 - p2)
    return torch.cdist(a, b).min()


def test_segment_distance_matches_a_dense_sampling():
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(200, 4, 3, generator=g, dtype=torch.float64)
    # degenerate cases: parallel, crossing, a point against a segment, two points, end-to-end
    pts[0, 2:] = pts[0, :2] + torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64)
    pts[1, 3] = 2 * pts[1, 0] - pts[1, 2]  # segment 2 through segment 1's start point
    pts[2, 1] = pts[2, 0]
    pts[3, 1], pts[3, 3] = pts[3, 0], pts[3, 2]
    pts[4, 2] = pts[4, 1]
    d = segment_distance(pts[:, 0], pts[:, 1], pts[:, 2], pts[:, 3])
    ref = torch.stack([_sampled_distance(*p) for p in pts])
    # the sampled distance is an upper bound within half a sample step of the exact one
    step = torch.stack([(p[1] - p[0]).norm() + (p[3] - p[2]).norm() for p in pts]) / 800
    assert torch.all(d <= ref + 1e-8)
    assert torch.all(ref - d <= step + 1e-8)
    assert float(d[4]) == pytest.approx(0.0, abs=1e-9) and float(d[1]) < 1e-6


@pytest.fixture(scope="module")
def human():
    return Skeleton.from_urdf(path("human.urdf")).double()


def test_pairs_come_from_the_tree_and_clear_each_other_in_the_rest_pose(human):
    parts = body_partition(human, per_limb=True, joints=True)
    torso, limbs = set(parts[0]), {j for p in parts[1:] for j in p}
    pairs = limb_torso_pairs(human)
    assert pairs
    rest = human.fk(torch.zeros(len(human.dof_names), dtype=torch.float64))
    bones = [tuple(b) for b in human.bones]
    for a, b in pairs:
        assert bones[a][1] in limbs and bones[b][1] in torso
        d = segment_distance(rest[bones[a][0]], rest[bones[a][1]], rest[bones[b][0]], rest[bones[b][1]])
        assert float(d) > float(human.radii[a] + human.radii[b])
    # every limb with geometry has a pair: the arms' and legs' capsules against the torso's
    assert {bones[a][1] for a, _ in pairs} & set(parts[1]) and {bones[a][1] for a, _ in pairs} & set(
        parts[-1]
    )
    # renaming the joints changes nothing
    renamed = Skeleton.from_urdf(path("human.urdf")).double()
    renamed.joint_names = [f"j{i}" for i in range(len(renamed.joint_names))]
    assert limb_torso_pairs(renamed) == pairs


def test_the_penalty_is_the_squared_depth_of_each_penetrating_pair(human, device):
    prior = SelfCollisionPrior(human, sigma=0.02).to(device)
    x = torch.zeros(1, len(human.dof_names), dtype=torch.float64, device=device)
    assert float(prior(x, {"any": None})) == 0.0  # the rest pose clears every pair
    # the same poses scored against geometry computed here: penetration depth per pair, summed
    g = torch.Generator().manual_seed(1)
    poses = human.clamp(1.2 * torch.randn(64, len(human.dof_names), generator=g, dtype=torch.float64))
    poses[:, :6] = 0
    ends, radii = human.capsules(poses)
    expected = torch.zeros(64, dtype=torch.float64)
    for a, b in limb_torso_pairs(human):
        d = torch.stack([_sampled_distance(*e[a], *e[b], n=401) for e in ends])
        expected -= 0.5 * (torch.relu(radii[a] + radii[b] - d) / 0.02) ** 2
    got = prior(poses.to(device), {"any": None}).cpu()
    assert (expected < 0).sum() >= 8  # random poses put limbs through the torso
    torch.testing.assert_close(got, expected, atol=0.05 * float(expected.abs().max()), rtol=0.02)
    assert float(prior(poses.to(device), None).abs().sum()) == 0.0  # no frame: no term, as every cue


def test_a_prior_term_leaves_the_tracker_reading_silhouettes(human):
    from torchpf.tracker import _observed_fields

    lik = make_likelihood(human, None, ("pointcloud", "self_collision"))
    assert isinstance(lik, ProductLikelihood) and isinstance(lik.terms["self_collision"], SelfCollisionPrior)
    assert _observed_fields(lik) == {"points"}
    with pytest.raises(ValueError, match="sigma"):
        SelfCollisionPrior(human, sigma=0.0)
