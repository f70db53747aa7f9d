"""Looking at a fitted action model: a text summary and the plots of Rius et al. Fig. 1.

Fig. 1 of the paper shows the first aSpace dimensions of the training performances before (a) and after (b)
synchronisation, with the mean performance ĝ and a band of ± 3σ around it. :func:`plot_synchronisation`
draws the same from the training data stored in the model file (``train_coords``, ``train_lengths``,
``train_phase``, see :mod:`priors.action`):

* *before*: each performance's coordinates against its own frame number (thin lines);
* *after*: each frame placed at the mean posture ``k`` DTW matched it to (for a cyclic action one cycle,
  lines broken where a performance wraps to the next cycle), the mean ĝ_k (thick) and ĝ_k ± 3σ_k (dashed).

Example::

    from priors import ActionModel
    from training.plots import describe, plot_synchronisation
    model = ActionModel.load("walk.npz")
    print(describe(model)); plot_synchronisation(model, "plots/")      # plots/synchronisation.png

or ``python -m training inspect walk.npz --out plots/``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from priors.action import ActionModel
from priors.diffusion import alpha_summary


def describe(model: ActionModel) -> str:
    """A few lines about ``model``: sizes, variance kept, spreads, dynamics parameters, training set."""
    evr = model.explained_variance_ratio.numpy()
    info = (model.training_data or {}).get("info", {})
    perfs = info.get("performances", [])
    lines = [
        f"action model {model.action!r}: {'cyclic' if model.cyclic else 'acyclic'}, "
        f"K={model.n_postures} mean postures at {model.fps:g} fps ({model.n_postures / model.fps:.3g} s)",
        f"  pose vector: {len(model.dof_names)} DOFs; posture: {len(model.posture_dofs)} DOFs; "
        f"aSpace: D={model.n_components} components ({100 * evr.sum():.1f}% of the posture variance)",
        f"  sigma_k (rad): median {np.median(model.std.numpy()):.4g}, range "
        f"[{model.std.min().item():.4g}, {model.std.max().item():.4g}]; Delta (rad): "
        + ", ".join(f"{v:.3g}" for v in model.delta.tolist()),
        f"  acceptance: |phi~ - g_j| < {model.n_sigma:g} sigma_j in every dimension (Rius eq. 6)",
        f"  constant velocity (Rius eq. 3): alpha={alpha_summary(model.alpha)}, sigma_phi median "
        f"{np.median(model.sigma_phi.numpy()):.3g}, max {model.sigma_phi.max().item():.3g} "
        "(rad or m per frame)",
    ]
    if perfs:
        lines.append(f"  trained on {len(perfs)} performances: {', '.join(map(str, perfs))}")
    return "\n".join(lines)


def _split_by_performance(model: ActionModel) -> list[tuple[np.ndarray, np.ndarray]]:
    data = model.training_data
    coords, phase = data["coords"].numpy(), data["phase"].numpy()
    bounds = np.concatenate([[0], np.cumsum(data["lengths"].numpy())])
    return [(coords[a:b], phase[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def plot_synchronisation(
    model: ActionModel, out_dir: str | os.PathLike, n_dims: int = 4, filename: str = "synchronisation.png"
) -> Path:
    """Save Rius Fig. 1 (before / after synchronisation, mean ± 3σ) for the first ``n_dims`` dimensions.

    Returns:
        the path of the PNG written (``out_dir/filename``; the folder is created).

    Raises:
        ValueError: the model carries no training data (built by hand, or saved without it).
    """
    if model.training_data is None:
        raise ValueError(
            f"action model {model.action!r} has no training data to plot (fit it with training.fit)"
        )
    n = max(1, min(int(n_dims), model.n_components))
    perfs = _split_by_performance(model)
    g, s = model.mean_performance.numpy(), model.std.numpy()
    K = model.n_postures
    fig = Figure(figsize=(10, 2.2 * n), constrained_layout=True)
    axes = fig.subplots(n, 2, squeeze=False)
    colours = [f"C{i % 10}" for i in range(len(perfs))]
    for d in range(n):
        before, after = axes[d]
        for (z, p), c in zip(perfs, colours, strict=True):
            before.plot(np.arange(len(z)), z[:, d], lw=0.8, color=c)
            x = p.astype(float)
            if model.cyclic:  # break the line where the performance wraps into its next cycle
                x = np.where(np.r_[False, np.diff(p) < 0], np.nan, x)
            after.plot(x, np.where(np.isnan(x), np.nan, z[:, d]), lw=0.8, color=c, alpha=0.7)
        k = np.arange(K)
        after.plot(k, g[:, d], color="k", lw=2.5, label="mean ĝ")
        after.plot(k, g[:, d] + 3 * s[:, d], "k--", lw=1, label="± 3σ")
        after.plot(k, g[:, d] - 3 * s[:, d], "k--", lw=1)
        before.set_ylabel(f"dim {d + 1} (rad)")
        if d == 0:
            before.set_title("(a) before synchronisation")
            after.set_title("(b) after synchronisation")
            after.legend(loc="upper right", fontsize="small")
    axes[-1][0].set_xlabel(f"frame ({model.fps:g} fps)")
    axes[-1][1].set_xlabel("mean posture k" + (" (one cycle)" if model.cyclic else ""))
    fig.suptitle(
        f"action {model.action!r}: first {n} aSpace dimensions of {len(perfs)} training performances"
    )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / filename
    fig.savefig(path, dpi=100)
    return path


def plot_explained_variance(
    model: ActionModel, out_dir: str | os.PathLike, filename: str = "explained_variance.png"
) -> Path:
    """Save the PCA's explained-variance ratio per component and cumulated; returns the PNG path."""
    evr = model.explained_variance_ratio.numpy()
    fig = Figure(figsize=(5, 3), constrained_layout=True)
    ax = fig.subplots()
    d = np.arange(1, len(evr) + 1)
    ax.bar(d, evr, color="C0", label="per component")
    ax.plot(d, np.cumsum(evr), "k.-", label="cumulated")
    ax.set_xlabel("aSpace dimension")
    ax.set_ylabel("fraction of posture variance")
    ax.set_ylim(0, 1)
    ax.legend(fontsize="small")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / filename
    fig.savefig(path, dpi=100)
    return path
