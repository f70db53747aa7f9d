"""Fitting action models: building blocks against closed forms, synchronisation recovering a known time warp,
and the acceptance test on held-out performances (procedural generator and real CMU mocap)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from torchpf.assets import path as asset_path
from torchpf.skeleton import Skeleton
from training import ActionModelFitter, fit_action_model
from training.align import resample
from training.dynamics import constant_velocity_errors
from training.fit import select_posture_dofs
from training.mocap import CMU_SCALE, Motion, bvh_motion, read_bvh
from training.synthetic import PerformerStyle, generate

CMU = Path(__file__).resolve().parents[2].parent / "shared" / "mocap" / "cmu"
CMU_TRAIN = ("07_01", "07_06", "08_09", "08_10")  # walks of subjects 07 and 08
CMU_HELD_OUT = ("16_21", "16_31", "35_02", "35_30")  # walks of subjects 16 and 35
CMU_RUNS = ("16_46", "35_24", "35_26")  # run/jog


def _random_in_limit_poses(n: int, seed: int = 0) -> torch.Tensor:
    skel = Skeleton.from_urdf(asset_path("human.urdf"))
    lo, hi = skel.lower.double(), skel.upper.double()
    return lo + (hi - lo) * torch.rand(
        n, len(lo), generator=torch.Generator().manual_seed(seed), dtype=torch.float64
    )


def _rate(model, motions, seed=0) -> float:
    """Fraction of frames (at the model's fps) that one draw of eq. 6 accepts."""
    g = torch.Generator().manual_seed(seed)
    frames = torch.cat([torch.from_numpy(resample(m.angles.numpy(), m.fps, model.fps)) for m in motions])
    return float(model.accepts(frames, g).double().mean())


# ----------------------------------------------------------------------------------- building blocks


def test_posture_dofs_leave_out_root_and_hands():
    names = Skeleton.from_urdf(asset_path("human.urdf")).dof_names
    posture = select_posture_dofs(names)
    assert not [n for n in posture if n.startswith("Hips_")]
    assert not [n for n in posture if any(k in n.lower() for k in ("hand", "finger", "thumb"))]
    assert "LeftUpLeg_Xrotation" in posture and "LeftForeArm_Zrotation" in posture and len(posture) == 66
    assert len(select_posture_dofs(names, exclude_root=False, exclude=())) == 96


def test_alpha_and_sigma_phi_recover_the_generating_process():
    """Data made by Rius eq. 3 with a known alpha and noise: the fitter finds both."""
    rng = np.random.default_rng(1)
    alpha, sigma, T, D = 0.6, 0.01, 2000, 3
    delta = np.zeros((T, D))
    v = np.zeros(D)
    for t in range(1, T):
        delta[t] = v + sigma * rng.normal(size=D)
        v = alpha * v + (1 - alpha) * delta[t]
    angles = np.cumsum(delta, 0)
    names = ["Root_Xposition", "A_Xrotation", "B_Xrotation", "C_Xrotation"]
    motion = Motion(names, 30.0, np.concatenate([np.zeros((T, 1)), angles], 1))
    fitter = ActionModelFitter(n_components=2, cyclic=False, max_iter=1).fit([motion])
    assert fitter.alpha_.shape == (4,)  # per DOF (Rius §3.1); the constant root's is arbitrary
    np.testing.assert_allclose(fitter.alpha_[1:], alpha, atol=0.06)
    torch.testing.assert_close(fitter.model_.alpha, torch.from_numpy(fitter.alpha_))
    np.testing.assert_allclose(fitter.sigma_phi_[1:], sigma, rtol=0.1)
    assert fitter.sigma_phi_[0] == 0.0
    err = constant_velocity_errors(np.diff(angles, axis=0), 0.0)
    np.testing.assert_allclose(err, np.diff(angles, n=2, axis=0))  # alpha = 0: the second difference


def test_configuration_errors():
    walk = [generate("walk", 60, 30.0, seed=0)]
    with pytest.raises(TypeError):
        ActionModelFitter(n_compnents=5)  # typo: unknown options raise
    with pytest.raises(ValueError, match="n_components"):
        ActionModelFitter(n_components=1.5).fit(walk)
    with pytest.raises(ValueError, match="at least one performance"):
        ActionModelFitter().fit([])
    other = Motion(walk[0].dof_names[:-1], 30.0, walk[0].angles[:, :-1], name="short")
    with pytest.raises(ValueError, match="short: DOFs differ"):
        ActionModelFitter().fit(walk + [other])


# ----------------------------------------------------------------------------------- synchronisation


def _warp(motion: Motion, tau: np.ndarray, name: str) -> Motion:
    """``out[i] = motion(tau[i])`` by linear interpolation (tau in frames, monotone)."""
    a = motion.angles.numpy()
    i0 = np.minimum(np.floor(tau).astype(int), len(a) - 2)
    w = (tau - i0)[:, None]
    return Motion(motion.dof_names, motion.fps, (1 - w) * a[i0] + w * a[i0 + 1], name=name)


def test_cyclic_synchronisation_recovers_a_known_time_warp():
    a = generate("walk", 240, 30.0, seed=1, name="a")
    i = np.arange(230)
    tau = 0.9 * i + 6.0 * np.sin(4 * np.pi * i / 230)  # speed between 0.57x and 1.23x, monotone
    b = _warp(a, tau, "b")
    others = [generate("walk", 120, 30.0, seed=s) for s in (2, 3)]
    fitter = ActionModelFitter(n_components=5, cyclic=True).fit([a, b, *others])
    assert fitter.converged_
    K = fitter.n_postures_
    phase_a = np.unwrap(fitter.paths_[0].astype(float), period=K)  # continuous phase of a's frames
    expected = np.interp(tau, np.arange(len(phase_a)), phase_a) % K
    err = np.abs((fitter.paths_[1] - expected + K / 2) % K - K / 2)
    assert err.mean() < 0.5 and err.max() <= 1.5, (err.mean(), err.max())  # in mean postures
    np.testing.assert_array_equal(fitter.align(b), fitter.paths_[1])  # align() = the fit's alignment


def test_acyclic_synchronisation_recovers_a_known_time_warp():
    style = PerformerStyle(tempo=0.25, phase=0.0)  # one bend in 4 s: down and back up
    a = generate("bend", 120, 30.0, style=style, seed=4, name="a")
    u = np.arange(100) / 99
    tau = 119 * u + 6.0 * np.sin(2 * np.pi * u)  # 100 frames for a's 120, speed 0.82x .. 1.58x
    b = _warp(a, tau, "b")
    fitter = ActionModelFitter(n_components=5, cyclic=False).fit([a, b])
    assert not fitter.cyclic_ and fitter.paths_[0][0] == 0 and fitter.paths_[0][-1] == fitter.n_postures_ - 1
    expected = np.interp(tau, np.arange(120), fitter.paths_[0].astype(float))
    err = np.abs(fitter.paths_[1] - expected)
    assert err.mean() < 0.5 and err.max() <= 1.5, (err.mean(), err.max())  # in mean postures


# ----------------------------------------------------------------------------------- acceptance rates


def test_generator_walk_model_accepts_held_out_walks_not_other_actions():
    train = [generate("walk", 120, 30.0, seed=k) for k in range(6)]
    fitter = ActionModelFitter(n_components=5, action="walk").fit(train)
    model = fitter.model_
    assert fitter.cyclic_ and 28 <= fitter.n_postures_ <= 40  # one gait cycle ~1.0-1.25 s at 30 fps
    # the aSpace is the sklearn PCA of the training postures
    x = np.concatenate([model.postures(m.angles).numpy() for m in train])
    np.testing.assert_allclose(
        model.project(torch.cat([m.angles for m in train])).numpy(), fitter.pca_.transform(x), atol=1e-10
    )
    rates = {
        "walk (held-out performers)": _rate(
            model, [generate("walk", 120, 30.0, seed=k) for k in (100, 101, 102)]
        ),
        "bend": _rate(model, [generate("bend", 120, 30.0, seed=k) for k in (200, 201)]),
        "wave": _rate(model, [generate("wave", 120, 30.0, seed=k) for k in (300, 301)]),
        "random in-limit poses": float(
            model.accepts(_random_in_limit_poses(5000), torch.Generator()).double().mean()
        ),
    }
    print("generator acceptance rates:", {k: round(v, 4) for k, v in rates.items()})
    walk = rates.pop("walk (held-out performers)")
    assert walk > 0.5
    assert all(rate < walk / 20 for rate in rates.values()), rates


@pytest.mark.skipif(not CMU.is_dir(), reason=f"CMU mocap clips not found at {CMU}")
def test_cmu_walk_model_accepts_held_out_walks_not_runs_or_random_poses():
    def load(stem):
        return bvh_motion(read_bvh(CMU / f"{stem}.bvh"), CMU_SCALE)[1:]  # frame 0 is a rest pose

    train = [load(s) for s in CMU_TRAIN]
    # D=8 rather than the paper's 13: two training subjects do not span the posture variation of new ones,
    # and the trailing components then only accept the training subjects (Rius §4 warns of this trade-off).
    fitter = ActionModelFitter(n_components=8, action="walk", fps=30.0).fit(train)
    model = fitter.model_
    assert fitter.cyclic_ and 27 <= fitter.n_postures_ <= 40 and fitter.converged_
    assert 0.0 < float(model.alpha[model.posture_index].median()) < 1.0
    rates = {
        "training walks (07, 08)": _rate(model, train),
        "held-out walks (16, 35)": _rate(model, [load(s) for s in CMU_HELD_OUT]),
        "run/jog": _rate(model, [load(s) for s in CMU_RUNS]),
        "random in-limit poses": float(
            model.accepts(_random_in_limit_poses(5000), torch.Generator()).double().mean()
        ),
    }
    print("CMU acceptance rates:", {k: round(v, 4) for k, v in rates.items()})
    walk = rates["held-out walks (16, 35)"]
    assert rates["training walks (07, 08)"] > 0.6
    assert walk > 0.1
    assert rates["run/jog"] < walk / 10 and rates["random in-limit poses"] < walk / 10, rates


def test_fit_action_model_returns_a_model_with_the_contract_api(tmp_path):
    train = [generate("walk", 90, 30.0, seed=k) for k in range(3)]
    model = fit_action_model(train, n_components=0.9, action="walk")
    assert 1 <= model.n_components < 13 and float(model.explained_variance_ratio.sum()) >= 0.9
    model.save(tmp_path / "walk.npz")
    back = type(model).load(tmp_path / "walk.npz", dof_names=train[0].dof_names)
    theta = train[0].angles
    assert back.accepts(theta).shape == (90,)
    assert torch.equal(back.alpha, model.alpha) and back.action == "walk"


def test_fit_with_a_skeleton_takes_its_joint_types():
    train = [generate("walk", 60, 30.0, seed=k) for k in range(2)]
    skel = Skeleton.from_urdf(asset_path("human.urdf"))
    model = fit_action_model(train, n_components=4, action="walk", skeleton=skel)
    index = [skel.dof_names.index(n) for n in model.dof_names]
    assert model.revolute.tolist() == skel.dof_revolute[index].tolist()
    by_name = fit_action_model(train, n_components=4, action="walk")  # the name rule agrees on human.urdf
    torch.testing.assert_close(model.mean_performance, by_name.mean_performance)
    with pytest.raises(ValueError, match="DOFs the skeleton lacks"):
        fit_action_model(train, n_components=4, skeleton=Skeleton.from_urdf(asset_path("fontmarty22.urdf")))


def test_leave_one_out_validation_exposes_too_many_components():
    """With 4 performers, D=13 fits the performers rather than the action: left-out walks are rejected."""
    walks = [generate("walk", 90, 30.0, seed=k) for k in range(4)]
    rates = {d: ActionModelFitter(n_components=d, validate=True).fit(walks) for d in (5, 13)}
    assert rates[5].validation_acceptance_.shape == (4,)
    assert rates[13].validation_acceptance_.mean() < rates[13].train_acceptance_ / 10
    assert rates[5].validation_acceptance_.mean() > 10 * rates[13].validation_acceptance_.mean()
    assert ActionModelFitter(n_components=5).fit(walks).validation_acceptance_ is None


def test_auto_components_choose_by_leave_one_performer_out_validation():
    """``n_components="auto"``: per performer a model without them; the largest D (then the smallest n_sigma)
    that still accepts half of the left-out performer's frames and no random in-limit pose."""
    from training.fit import ValidationCurve, performer_of, select_n_components

    walks = [generate("walk", 60, 15.0, seed=k, name=f"{k:02d}_01") for k in range(3)]
    assert performer_of("07_01") == "07" and performer_of("walk") == "walk"
    curve = select_n_components(walks, candidates=(2, 4, 8), n_sigmas=(2.0, 4.0), n_random=500, fps=15.0)
    assert curve.performers == ["00", "01", "02"] and curve.heldout.shape == (2, 3, 3)
    assert curve.random.shape == (2, 3) and np.isnan(curve.negative).all()
    assert (curve.heldout[1] >= curve.heldout[0] - 1e-12).all()  # a wider test accepts more
    mean = curve.heldout.mean(1)
    k, c = curve.n_sigmas.index(curve.chosen_n_sigma), curve.candidates.index(curve.chosen)
    if "largest D" in curve.rule:
        assert mean[k, c] >= 0.5 and curve.random[k, c] < 0.01
        bigger = [j for j, d in enumerate(curve.candidates) if d > curve.chosen]
        assert not any(((mean[:, j] >= 0.5) & (curve.random[:, j] < 0.01)).any() for j in bigger)
    again = ValidationCurve.from_dict(curve.as_dict())
    assert again.table() == curve.table() and "*" in curve.table()

    fitter = ActionModelFitter(action="walk", fps=15.0, candidates=(2, 4, 8), n_sigma=2.0).fit(walks)
    model = fitter.model_
    assert model.n_components == fitter.validation_curve_.chosen
    assert model.n_sigma == fitter.validation_curve_.chosen_n_sigma
    assert model.training_data["info"]["validation"]["chosen"] == model.n_components
    with pytest.raises(ValueError, match="at least two performances"):
        select_n_components(walks[:1], candidates=(2,))


def test_truncated_models_are_the_leading_dimensions():
    walks = [generate("walk", 60, 15.0, seed=k) for k in range(2)]
    model = ActionModelFitter(n_components=6, fps=15.0).fit(walks).model_
    small = model.truncated(3, n_sigma=3.0)
    assert small.n_components == 3 and small.n_sigma == 3.0 and model.truncated(6) is model
    torch.testing.assert_close(small.mean_performance, model.mean_performance[:, :3])
    x = walks[0].angles.double()
    torch.testing.assert_close(small.project(x), model.project(x)[..., :3])
    with pytest.raises(ValueError, match="n_components"):
        model.truncated(7)


# scikit-learn's estimator checks that apply to a fitter of performances (not of numeric X): the parameter API
SKLEARN_API_CHECKS = (
    "check_estimator_cloneable",
    "check_estimator_repr",
    "check_no_attributes_set_in_init",
    "check_parameters_default_constructible",
    "check_get_params_invariance",
    "check_set_params",
    "check_do_not_raise_errors_in_init_or_set_params",
    "check_estimators_unfitted",
)


@pytest.mark.parametrize("check", SKLEARN_API_CHECKS)
def test_the_fitter_passes_sklearn_estimator_checks(check):
    from sklearn.utils import estimator_checks

    getattr(estimator_checks, check)("ActionModelFitter", ActionModelFitter())


def test_the_fitter_follows_the_sklearn_estimator_contract():
    from sklearn.base import clone
    from sklearn.exceptions import NotFittedError

    walks = [generate("walk", 60, 15.0, seed=k) for k in range(2)]
    fitter = ActionModelFitter(n_components=3, action="walk", exclude=["hand"], negatives=walks[:1])
    params = fitter.get_params(deep=True)
    assert params["n_components"] == 3 and params["exclude"] == ["hand"] and params["negatives"] is not None
    assert set(params) == set(ActionModelFitter().get_params())  # every __init__ parameter, nothing else
    assert fitter.set_params(n_components=2, n_sigma=3.0) is fitter and fitter.n_components == 2
    with pytest.raises(ValueError, match="Invalid parameter 'bogus'"):
        fitter.set_params(bogus=1)
    with pytest.raises(NotFittedError, match="call fit"):
        fitter.align(walks[0])
    fitter.fit(walks, None)  # sklearn's fit(X, y=None)
    twin = clone(fitter)
    assert not hasattr(twin, "model_") and twin.get_params()["n_components"] == 2
    assert twin.fit(walks).model_.n_components == 2 and twin.model_.n_sigma == 3.0
    torch.testing.assert_close(twin.model_.mean_performance, fitter.model_.mean_performance)
    config = fitter.model_.training_data["info"]["config"]  # the JSON config in the file: no Motions in it
    assert "negatives" not in config and config["exclude"] == ["hand"] and config["n_components"] == 2
