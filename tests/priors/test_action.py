"""Action model (Rius eq. 6) and action-constrained dynamics: semantics against a brute-force reference,
file round trips and failures, device/dtype, and a run inside a ParticleFilter."""

from __future__ import annotations

import math
import zipfile
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from priors.action import ActionConstrained, ActionModel, ActionModelFormatError, ActionProposal
from priors.motion import ConstantVelocity
from torchpf.distributions import Dynamics
from torchpf.filters import ParticleFilter

NAMES = ["Hips_Xposition", "Hips_Zrotation", "Knee_Xrotation", "Elbow_Xrotation", "Hand_Xrotation"]


def tiny_model(**overrides) -> ActionModel:
    """D=2 aSpace over the 3 angular DOFs Knee, Elbow, Hand (root excluded), K=4 mean postures."""
    u = torch.tensor([[1.0, 1.0, 0.0], [1.0, -1.0, 0.0]], dtype=torch.float64) / math.sqrt(2.0)
    kwargs = dict(
        dof_names=NAMES,
        posture_dofs=NAMES[2:],
        center=[0.2, -0.1, 3.0],  # the Hand's branch centre sits near +pi: wrapping matters
        pca_mean=[0.2, -0.1, 3.0],
        components=u,
        mean_performance=[[0.0, 0.0], [0.5, 0.1], [1.0, 0.0], [0.5, -0.1]],
        std=[[0.1, 0.05], [0.1, 0.05], [0.2, 0.05], [0.1, 0.05]],
        delta=[0.2, 0.05],
        sigma_phi=[0.01, 0.02, 0.03, 0.03, 0.0],
        alpha=0.25,
        fps=30.0,
        action="test",
        cyclic=True,
    )
    kwargs.update(overrides)
    return ActionModel(**kwargs)


def reference_accept_probability(model: ActionModel, theta: np.ndarray) -> np.ndarray:
    """Loop over poses and postures: Σ_j p(j | φ̃) 1[|φ̃ - ĝ_j| < 2 σ_j for all d]."""
    g, s, delta = model.mean_performance.numpy(), model.std.numpy(), model.delta.numpy()
    out = []
    for pose in theta:
        x = pose[model.posture_index.numpy()]
        x = model.center.numpy() + (x - model.center.numpy() + np.pi) % (2 * np.pi) - np.pi
        phi = model.components.numpy() @ (x - model.pca_mean.numpy())
        w = np.array([np.exp(-0.5 * np.sum(((phi - g[j]) / delta) ** 2)) for j in range(len(g))])
        inside = np.array([np.all(np.abs(phi - g[j]) < model.n_sigma * s[j]) for j in range(len(g))])
        out.append(np.sum(w * inside) / np.sum(w))
    return np.array(out)


def near_mean_poses(model: ActionModel, n: int, spread: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    j = torch.randint(0, model.n_postures, (n,), generator=g)
    coords = model.mean_performance[j] + spread * torch.randn(
        n, model.n_components, generator=g, dtype=torch.float64
    )
    base = torch.randn(n, len(model.dof_names), generator=g, dtype=torch.float64)
    return model.pose(coords, base)


# ----------------------------------------------------------------------------------- eq. 6 semantics


def test_accept_probability_matches_brute_force_reference():
    model = tiny_model()
    theta = near_mean_poses(model, 200, 0.1)
    theta[:, 4] += 2 * math.pi * torch.randint(-2, 3, (200,), generator=torch.Generator().manual_seed(1))
    ref = reference_accept_probability(model, theta.numpy())
    got = model.accept_probability(theta)
    assert got.shape == (200,)
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-9, atol=1e-12)
    assert 0.05 < ref.mean() < 0.95  # the test exercises both outcomes


def test_project_is_periodic_and_reconstructs():
    model = tiny_model()
    theta = near_mean_poses(model, 50, 0.2)
    shifted = theta.clone()
    shifted[:, 2:] += 2 * math.pi  # every angular posture DOF one turn further
    torch.testing.assert_close(model.project(shifted), model.project(theta))
    coords = model.project(theta)
    back = model.pose(coords, theta)
    torch.testing.assert_close(model.project(back), coords)
    # DOFs outside the posture are left alone
    torch.testing.assert_close(back[:, :2], theta[:, :2])


def test_accepts_frequency_matches_accept_probability():
    model = tiny_model()
    theta = near_mean_poses(model, 8, 0.12, seed=3)
    p = model.accept_probability(theta)
    g = torch.Generator().manual_seed(0)
    draws = torch.stack([model.accepts(theta, g) for _ in range(4000)]).double().mean(0)
    # binomial standard error <= 0.008; 5 of them
    torch.testing.assert_close(draws, p, rtol=0, atol=0.04)
    again = torch.stack([model.accepts(theta, torch.Generator().manual_seed(0)) for _ in range(2)])
    assert torch.equal(again[0], again[1])  # same generator state, same answer


def test_far_poses_are_rejected_and_batch_dims_kept():
    model = tiny_model()
    theta = near_mean_poses(model, 12, 0.0).reshape(3, 4, len(NAMES))
    assert model.accepts(theta).shape == (3, 4)
    assert model.accept_probability(theta).min() > 0.5
    far = theta.clone()
    far[..., 2] += 1.5  # 1.5 rad off the action's knee range
    assert not model.accepts(far).any()
    assert (model.accept_probability(far) == 0).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtype_follows_input(dtype):
    model = tiny_model()
    theta = near_mean_poses(model, 5, 0.1).to(dtype)
    assert model.project(theta).dtype == dtype
    assert model.accept_probability(theta).dtype == dtype
    assert model.accepts(theta).dtype == torch.bool


def test_model_follows_the_device(device, generator, tmp_path):
    model = tiny_model().to(device)
    theta = near_mean_poses(tiny_model(), 5, 0.1).to(device)
    assert model.accepts(theta, generator).device.type == device.type
    model.save(tmp_path / "m.npz")  # arrays come back to the host to be written
    assert ActionModel.load(tmp_path / "m.npz").revolute.device.type == "cpu"


def test_bad_construction_fails_clearly():
    with pytest.raises(ValueError, match="std has shape"):
        tiny_model(std=[[0.1, 0.1]])
    with pytest.raises(ValueError, match="not in dof_names"):
        tiny_model(posture_dofs=["Nope_Xrotation", "Knee_Xrotation", "Elbow_Xrotation"])
    with pytest.raises(ValueError, match="must be > 0"):
        tiny_model(delta=[0.0, 0.1])


# ----------------------------------------------------------------------------------- files


def test_save_load_round_trip(tmp_path):
    model = tiny_model(
        training={"coords": np.zeros((5, 2)), "lengths": [2, 3], "phase": [0, 1, 0, 2, 3], "info": {"a": 1}}
    )
    path = tmp_path / "m.npz"
    model.save(path)
    back = ActionModel.load(path)
    for name, buf in model.named_buffers():
        assert torch.equal(buf, getattr(back, name)), name
    assert (back.dof_names, back.posture_dofs, back.action, back.cyclic) == (NAMES, NAMES[2:], "test", True)
    assert (back.fps, back.n_sigma) == (30.0, 2.0) and back.alpha.tolist() == [0.25] * 5
    assert back.training_data["info"] == {"a": 1}
    theta = near_mean_poses(model, 64, 0.1)
    assert torch.equal(
        model.accepts(theta, torch.Generator().manual_seed(5)),
        back.accepts(theta, torch.Generator().manual_seed(5)),
    )
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]  # no temp file left behind


def test_load_with_dof_names_reorders_or_refuses(tmp_path):
    model = tiny_model()
    path = tmp_path / "m.npz"
    model.save(path)
    perm = [NAMES[i] for i in (3, 0, 4, 2, 1)]
    reordered = ActionModel.load(path, dof_names=perm)
    theta = near_mean_poses(model, 10, 0.1)
    torch.testing.assert_close(reordered.project(theta[:, [3, 0, 4, 2, 1]]), model.project(theta))
    torch.testing.assert_close(reordered.sigma_phi, model.sigma_phi[[3, 0, 4, 2, 1]])
    with pytest.raises(ValueError, match=r"m\.npz: .*trained on other DOFs.*Wrist_Xrotation"):
        ActionModel.load(path, dof_names=NAMES[:4] + ["Wrist_Xrotation"])
    with pytest.raises(ValueError, match="expects poses"):
        model.project(torch.zeros(3, 4))


def test_corrupt_files_fail_clearly(tmp_path):
    good = tmp_path / "good.npz"
    tiny_model().save(good)
    data = good.read_bytes()

    cases = {
        "text.npz": b"hello, I am not a model\n",
        "truncated.npz": data[: len(data) // 2],
        "empty.npz": b"",
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ActionModelFormatError, match=rf"{name}: not a readable action-model"):
            ActionModel.load(tmp_path / name)

    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(ActionModelFormatError, match=r"other\.npz: not an action-model file"):
        ActionModel.load(tmp_path / "other.npz")

    def rewrite(name, **changes):
        with np.load(good) as npz:
            arrays = {k: npz[k] for k in npz.files}
        meta = __import__("json").loads(str(arrays["metadata"]))
        meta.update(changes.pop("meta", {}))
        arrays["metadata"] = np.array(__import__("json").dumps(meta))
        for k, v in changes.items():
            if v is None:
                del arrays[k]
            else:
                arrays[k] = v
        np.savez(tmp_path / name, **arrays)
        return tmp_path / name

    with pytest.raises(ActionModelFormatError, match=r"newer\.npz: format version 99 is newer"):
        ActionModel.load(rewrite("newer.npz", meta={"version": 99}))
    with pytest.raises(ActionModelFormatError, match=r"nostd\.npz: missing entries \['std'\]"):
        ActionModel.load(rewrite("nostd.npz", std=None))
    with pytest.raises(ActionModelFormatError, match=r"shape\.npz: .*std has shape"):
        ActionModel.load(rewrite("shape.npz", std=np.ones((4, 3))))
    with pytest.raises(ActionModelFormatError, match=r"nan\.npz: .*finite"):
        ActionModel.load(rewrite("nan.npz", delta=np.array([np.nan, 1.0])))
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        ActionModel.load(tmp_path / "missing.npz")
    assert zipfile.is_zipfile(good)


def test_failed_save_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "m.npz"
    tiny_model().save(path)
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(OSError, match="disk full"):
        tiny_model(alpha=0.9).save(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]


# ----------------------------------------------------------------------------------- dynamics


def test_action_constrained_follows_the_stateful_protocol_and_reports_acceptance():
    model = tiny_model()
    dyn = ActionConstrained(model, alpha=0.5)
    assert isinstance(dyn, Dynamics) and callable(dyn.update_extras)
    assert isinstance(dyn.dynamics, ConstantVelocity) and dyn.dynamics.alpha == 0.5
    x = near_mean_poses(model, 400, 0.03).reshape(2, 200, len(NAMES))
    extras = dyn.init_extras(x)
    assert extras["accepted"].shape == (2, 200) and extras["accepted"].dtype == torch.bool
    out, stats = dyn.sample_with_stats(x, torch.Generator().manual_seed(0), extras=extras)
    assert out.shape == x.shape and torch.isfinite(out).all()
    assert set(stats) == {"fallback", "accepted", "accepted_first", "tries"}
    assert all(v.shape == (2, 200) for v in stats.values()) and stats["accepted"].dtype == torch.bool
    accepted, first = stats["accepted"].float().mean(-1), stats["accepted_first"].float().mean(-1)
    assert (accepted >= first).all() and (accepted > 0.95).all()
    assert (stats["tries"] >= 1).all() and (stats["tries"][stats["accepted_first"]] == 1).all()
    # accepted particles are ones eq. 6 can accept; the prediction moved them by ~sigma_phi only
    assert (model.accept_probability(out)[stats["accepted"]] > 0).all()
    assert (out - x).abs().max() < 0.2
    # the per-particle extra of the final particles says the same
    new = dyn.update_extras(out, x, extras)
    assert set(new) == {"velocity", "accepted"} and (new["accepted"] | ~stats["accepted"]).all()
    assert not hasattr(dyn, "stats")  # nothing of a call is kept on the module


def test_action_constrained_retries_are_bounded():
    model = tiny_model(std=torch.full((4, 2), 1e-6))  # accepts (almost) nothing
    dyn = ActionConstrained(model, max_tries=3, min_accept=0.0)  # the paper's eq. 6, no fallback
    x = near_mean_poses(model, 50, 0.3)
    out, stats = dyn.sample_with_stats(x, torch.Generator().manual_seed(0), extras=dyn.init_extras(x))
    assert not stats["accepted"].any() and (stats["tries"] == 3).all()
    assert torch.isfinite(out).all()  # the last draws are kept


def test_action_constrained_log_prob_adds_log_acceptance():
    model = tiny_model()
    dyn = ActionConstrained(model, min_accept=0.0)
    x_old = near_mean_poses(model, 30, 0.05)
    extras = {"velocity": 0.01 * torch.ones_like(x_old)}
    x_new = dyn.sample(x_old, torch.Generator().manual_seed(2), extras=extras)
    expected = dyn.dynamics.log_prob(x_new, x_old, extras=extras) + model.accept_probability(x_new).log()
    torch.testing.assert_close(dyn.log_prob(x_new, x_old, extras=extras), expected)
    # with a fallback share m, a rejected pose is 1/m times less likely, never impossible
    floored = ActionConstrained(model, min_accept=0.01)
    far = x_new + 5.0
    lp = floored.log_prob(far, x_old, extras=extras)
    assert torch.isfinite(lp).all()
    torch.testing.assert_close(lp, dyn.dynamics.log_prob(far, x_old, extras=extras) + math.log(0.01))


def test_a_model_that_rejects_everything_falls_back_to_its_plain_dynamics_and_says_so():
    model = tiny_model(std=torch.full((4, 2), 1e-6))  # accepts (almost) nothing
    dyn = ActionConstrained(model, max_tries=5, min_accept=0.05)
    x = near_mean_poses(model, 120, 0.3).reshape(2, 60, len(NAMES))
    extras = dyn.init_extras(x)
    with pytest.warns(UserWarning, match="plain dynamics"):
        out, stats = dyn.sample_with_stats(x, torch.Generator().manual_seed(0), extras=extras)
    # the frame's draws are the plain dynamics' first draws: one try each, same as sampling it directly
    assert stats["fallback"].all() and (stats["tries"] == 1).all() and not stats["accepted"].any()
    plain = dyn.dynamics.sample(
        x.reshape(-1, len(NAMES)),
        torch.Generator().manual_seed(0),
        extras={k: v.reshape(-1, v.shape[-1]) for k, v in extras.items()},
    )
    torch.testing.assert_close(out.reshape(-1, len(NAMES)), plain)
    stats = dyn.frame_stats(out, torch.zeros(2, 60), dyn.update_extras(out, x, extras))
    assert stats["action_fallback"].tolist() == [True, True] and (stats["action_accepted"] == 0).all()


def test_fallback_and_acceptance_reach_the_track_stats_of_every_filter():
    from torchpf.filters import AnnealedParticleFilter

    model = tiny_model(std=torch.full((4, 2), 1e-6))
    dyn = ActionConstrained(model, min_accept=0.05)
    truth = near_mean_poses(model, 1, 0.0)[0]

    def likelihood(x, obs):
        return -0.5 * ((x - obs) ** 2).sum(-1) / 0.1**2

    for pf in (
        ParticleFilter(dyn, likelihood, n_particles=100, progress=False),
        AnnealedParticleFilter(dyn, likelihood, n_particles=100, progress=False, diffusion_std=0.01),
    ):
        with pytest.warns(UserWarning, match="plain dynamics"):
            track = pf.run([truth] * 3, truth.expand(100, -1).clone(), generator=0)
        assert track.stats["action_fallback"].tolist() == [True] * 3
        assert not track.failed.any() and torch.isfinite(track.estimates).all()


def test_a_model_fitted_at_another_frame_rate_is_rescaled_to_the_tracking_rate():
    model = tiny_model(fps=120.0, alpha=0.8)
    at30 = model.at_fps(30.0)
    torch.testing.assert_close(at30.sigma_phi, model.sigma_phi * 4.0)
    torch.testing.assert_close(at30.alpha, torch.full((5,), 0.8**4, dtype=torch.float64))
    assert at30.fps == 30.0 and model.at_fps(120.0) is model
    torch.testing.assert_close(at30.mean_performance, model.mean_performance)
    dyn = ActionConstrained(model, fps=30.0)
    torch.testing.assert_close(dyn.dynamics.sigma, model.sigma_phi * 4.0)


def test_action_constrained_runs_in_a_particle_filter():
    model = tiny_model()
    dyn = ActionConstrained(model, alpha=0.5)
    truth = near_mean_poses(model, 1, 0.0)[0]

    def likelihood(x, obs):
        return -0.5 * ((x - obs) ** 2).sum(-1) / 0.1**2

    pf = ParticleFilter(dyn, likelihood, n_particles=300, progress=False)
    g = torch.Generator().manual_seed(0)
    state = pf.init(truth.expand(300, -1).clone())
    assert state.extras["velocity"].shape == (300, len(NAMES))
    for _ in range(4):
        state = pf.step(state, truth, g)
        accepted = state.extras["accepted"]  # rides with the particles (gathered at resampling)
        assert accepted.shape == (300,) and accepted.dtype == torch.bool
        assert 0.5 < float(accepted.float().mean()) <= 1
    assert torch.isfinite(state.mean()).all() and state.ess() > 1


# ----------------------------------------------------------------------------------- revolute DOFs


def test_the_revolute_mask_decides_what_is_wrapped_and_is_saved(tmp_path):
    # "Knee_Xrotation" made a length: the name rule would call it an angle, the mask says otherwise
    revolute = [False, True, False, True, True]
    model = tiny_model(revolute=revolute)
    assert model.angular.tolist() == [False, True, True] and model.revolute.tolist() == revolute
    theta = near_mean_poses(model, 5, 0.0)
    turned = theta.clone()
    turned[:, 2] += 2 * math.pi
    assert not torch.allclose(model.project(turned), model.project(theta))  # a length is never wrapped
    model.save(tmp_path / "m.npz")
    back = ActionModel.load(tmp_path / "m.npz")
    assert back.revolute.tolist() == revolute
    reordered = ActionModel.load(tmp_path / "m.npz", dof_names=NAMES[::-1])
    assert reordered.revolute.tolist() == revolute[::-1]
    with np.load(tmp_path / "m.npz") as npz:
        assert npz["revolute"].dtype == bool
        assert __import__("json").loads(str(npz["metadata"]))["version"] == 3


def test_alpha_is_stored_per_dof_and_older_scalar_files_are_broadcast(tmp_path):
    alpha = [0.0, 0.1, 0.5, 0.7, 0.9]
    model = tiny_model(alpha=alpha)
    assert model.alpha.shape == (5,) and model.alpha.dtype == torch.float64
    model.save(tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz") as npz:
        assert npz["alpha"].shape == (5,)
        arrays = {k: npz[k] for k in npz.files}
    assert ActionModel.load(tmp_path / "m.npz").alpha.tolist() == alpha
    assert ActionModel.load(tmp_path / "m.npz", dof_names=NAMES[::-1]).alpha.tolist() == alpha[::-1]
    dyn = ActionConstrained(model)  # the default eq. 3 dynamics smooth each DOF with its own alpha
    torch.testing.assert_close(dyn.dynamics.alpha, model.alpha)
    meta = __import__("json").loads(str(arrays["metadata"]))
    meta.update(version=2, alpha=0.25)  # what version 2 wrote: one alpha, in the metadata and as a 0-d array
    arrays.update(metadata=np.array(__import__("json").dumps(meta)), alpha=np.array(0.25))
    np.savez(tmp_path / "v2.npz", **arrays)
    old = ActionModel.load(tmp_path / "v2.npz")
    assert old.alpha.tolist() == [0.25] * 5
    old.save(tmp_path / "v3.npz")  # re-saved in the current version, per DOF
    assert ActionModel.load(tmp_path / "v3.npz").alpha.tolist() == [0.25] * 5
    with pytest.raises(ValueError, match=r"alpha has shape \(3,\), expected \(5,\)"):
        tiny_model(alpha=[0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="alpha must be in"):
        tiny_model(alpha=[0.1, 0.2, 0.3, 0.4, 1.5])


def test_version_1_files_load_with_the_name_rule_and_a_warning(tmp_path):
    model = tiny_model()
    model.save(tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz") as npz:
        arrays = {k: npz[k] for k in npz.files if k != "revolute"}
    meta = __import__("json").loads(str(arrays["metadata"]))
    meta.update(version=1, angular=[True, True, True])  # what version 1 wrote
    arrays["metadata"] = np.array(__import__("json").dumps(meta))
    np.savez(tmp_path / "old.npz", **arrays)
    with pytest.warns(UserWarning, match=r"old\.npz: action-model format version 1 stores no revolute mask"):
        old = ActionModel.load(tmp_path / "old.npz")
    assert old.revolute.tolist() == [False, True, True, True, True]
    theta = near_mean_poses(model, 10, 0.1)
    torch.testing.assert_close(old.project(theta), model.project(theta))
    with np.load(tmp_path / "old.npz") as npz:  # a version-2 file without the mask is malformed
        arrays = {k: npz[k] for k in npz.files}
    arrays["metadata"] = np.array(__import__("json").dumps({**meta, "version": 2}))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ActionModelFormatError, match=r"missing entries \['revolute'\]"):
        ActionModel.load(tmp_path / "bad.npz")


def test_action_constrained_with_a_skeleton_checks_its_joint_types():
    model = tiny_model()
    skel = SimpleNamespace(dof_names=NAMES[::-1], dof_revolute=torch.tensor([True, True, True, True, False]))
    dyn = ActionConstrained(model, skeleton=skel)
    assert dyn.model.dof_names == NAMES[::-1]  # in the skeleton's pose layout
    wrong = SimpleNamespace(dof_names=NAMES, dof_revolute=torch.tensor([False, True, False, True, True]))
    with pytest.raises(ValueError, match=r"Knee_Xrotation.*refit"):
        ActionConstrained(model, skeleton=wrong)


def test_action_constrained_adapts_a_duck_typed_dynamics_once():
    class Walk:  # plain object: sample(x, generator) / log_prob(new, old), no extras
        def sample(self, x, generator=None):
            return x + 0.01 * torch.randn(x.shape, generator=generator, dtype=x.dtype)

        def log_prob(self, x_new, x_old):
            return torch.zeros(x_new.shape[:-1], dtype=x_new.dtype)

    model = tiny_model()
    dyn = ActionConstrained(model, Walk(), min_accept=0.0)
    x = near_mean_poses(model, 20, 0.02)
    extras = dyn.init_extras(x)
    assert set(extras) == {"accepted"}
    out = dyn.sample(x, torch.Generator().manual_seed(0), extras=extras)
    assert out.shape == x.shape
    torch.testing.assert_close(dyn.log_prob(out, x, extras=extras), model.accept_probability(out).log())


# ----------------------------------------------------------------------------------- beyond rejection


def test_soft_prior_is_a_gaussian_around_the_matched_posture_and_its_test_matches_it():
    model = tiny_model()
    theta = near_mean_poses(model, 4000, 0.1, seed=3)
    p = model.soft_accept_probability(theta)
    assert ((p > 0) & (p <= 1)).all()
    at_mean = model.pose(
        model.mean_performance, torch.zeros(model.n_postures, len(NAMES), dtype=torch.float64)
    )
    assert (model.soft_accept_probability(at_mean) > 0.5).all()
    freq = model.accepts_soft(theta, torch.Generator().manual_seed(1)).double().mean()
    assert abs(float(freq) - float(p.mean())) < 0.03
    dyn = ActionConstrained(model, mode="soft", min_accept=0.0)
    x_old = near_mean_poses(model, 30, 0.05)
    extras = {"velocity": torch.zeros_like(x_old)}
    x_new = dyn.sample(x_old, torch.Generator().manual_seed(2), extras=extras)
    torch.testing.assert_close(
        dyn.log_prob(x_new, x_old, extras=extras),
        dyn.dynamics.log_prob(x_new, x_old, extras=extras) + model.soft_accept_probability(x_new).log(),
    )
    with pytest.raises(ValueError, match="mode"):
        ActionConstrained(model, mode="hard")


def test_phase_advance_follows_the_mean_performance_and_its_proposal_density_is_exact():
    from torchpf.filters.state import ParticleState
    from torchpf.proposals import GaussianRandomWalk

    model = tiny_model()
    base = torch.zeros(model.n_postures, len(NAMES), dtype=torch.float64)
    on_mean = model.pose(model.mean_performance, base)
    moved = model.project(on_mean + model.phase_step(on_mean, 1.0))
    torch.testing.assert_close(moved, model.mean_performance.roll(-1, 0))  # one posture ahead, cyclic
    half = model.project(on_mean + model.phase_step(on_mean, 0.5))
    torch.testing.assert_close(half, 0.5 * (model.mean_performance + model.mean_performance.roll(-1, 0)))

    dyn = GaussianRandomWalk(torch.full((len(NAMES),), 0.05, dtype=torch.float64))
    q = ActionProposal(model, dyn, fps=15.0, beta=0.25)  # model at 30 fps: half a posture per frame
    assert q.advance == 2.0
    parents = near_mean_poses(model, 300, 0.02)
    state = ParticleState(parents, torch.zeros(300), torch.zeros(()), {}, {})
    x, log_q = q.sample(state, None, torch.Generator().manual_seed(0))
    assert x.shape == parents.shape and torch.isfinite(log_q).all()
    from torchpf.distributions import diag_normal_log_prob

    expected = torch.logaddexp(
        math.log(0.25) + dyn.log_prob(x, parents),
        math.log(0.75) + diag_normal_log_prob(x, q.mean(parents), q.noise),
    )
    torch.testing.assert_close(log_q, expected)

    # in a filter: the correction weights keep it finite and tracking
    def likelihood(x, obs):
        return -0.5 * ((x - obs) ** 2).sum(-1) / 0.1**2

    pf = ParticleFilter(dyn, likelihood, proposal=q, n_particles=200, progress=False)
    track = pf.run([parents[0]] * 3, parents[:1].expand(200, -1).clone(), generator=0)
    assert not track.failed.any() and torch.isfinite(track.estimates).all()


def test_log_density_is_the_probabilistic_pca_mixture_density():
    """Against scipy: each mean posture is a Gaussian over the P posture DOFs with covariance
    ``U^T diag((n_sigma σ_k)²) U + v (I - U^T U)`` (v the discarded variance per direction), mixed
    uniformly; and the soft prior it extends is the aSpace part without its normalisers."""
    from scipy.stats import multivariate_normal

    model = tiny_model(explained_variance=[0.5, 0.1], explained_variance_ratio=[0.6, 0.12])
    v = model.residual_variance
    assert v == pytest.approx((0.5 / 0.6) * (1 - 0.72) / 1)
    theta = near_mean_poses(model, 30, spread=0.3, seed=9)
    theta[:, model.posture_index] += 0.05  # off the aSpace too
    U = model.components.numpy()
    P = U.shape[1]
    x = model.postures(theta).numpy()
    ref = []
    for k in range(model.n_postures):
        mean = model.pca_mean.numpy() + model.mean_performance[k].numpy() @ U
        s = model.n_sigma * model.std[k].numpy()
        cov = U.T @ np.diag(s**2) @ U + v * (np.eye(P) - U.T @ U)
        ref.append(multivariate_normal(mean, cov).logpdf(x))
    ref = np.logaddexp.reduce(np.stack(ref), axis=0) - np.log(model.n_postures)
    np.testing.assert_allclose(model.log_density(theta).numpy(), ref, rtol=1e-10, atol=1e-10)
    # without stored explained variances there is no residual term: the aSpace mixture alone
    bare = tiny_model()
    assert bare.residual_variance is None
    assert torch.isfinite(bare.log_density(theta)).all()
