"""The likelihood base: a body computed once from the poses, handed to every cue, and the registry of cues.

A cue maps a :class:`Body` (the skeleton in poses ``theta``: joint positions and capsules, from one forward
kinematics) and one frame's observation to log-likelihoods. :meth:`Likelihood.forward` computes the body
and calls :meth:`Likelihood.log_likelihood_body`; :class:`~torchpf.likelihoods.ProductLikelihood` computes
it once and hands it to each of its terms, so several cues share one FK without any hidden cache.

Cues register by name in :data:`LIKELIHOODS` (``silhouette``, ``dual_silhouette``, ``silhouette_distance``,
``overlap``, ``pointcloud``, ``keypoints``, ``chamfer``, ``skin``, and the prior term ``self_collision``),
which :func:`~torchpf.likelihoods.make_likelihood` and the tracker's ``--likelihood`` read.

Example::

    body = Body.of(skel, theta)                     # theta (..., N, D): one FK
    sil.log_likelihood_body(body, frame)            # (..., N), same as sil(theta, frame)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import nn

from torchpf.distributions import flatten_batch
from torchpf.observations import Frame, PointCloud, Silhouettes
from torchpf.registry import Registry

__all__ = ["LIKELIHOODS", "Body", "Likelihood"]

LIKELIHOODS: Registry[type] = Registry("likelihood")
"""Likelihood classes by name (``LIKELIHOODS.get("silhouette")``); an unknown name raises a ValueError that
lists the registered ones."""


@dataclass(frozen=True, eq=False)
class Body:
    """The body model in a batch of poses, computed once and shared by the likelihood terms.

    Attributes:
        theta: (B, D) poses, the leading dims ``batch`` of the caller's (..., D) flattened into B.
        batch: the leading dims (``...``) to restore on the way out.
        joints: (B, J, 3) world joint positions (m), ``skeleton.fk(theta)``.
        ends: (B, C, 2, 3) parent and child joint of each bone, the capsule axes (Hauberg §5).
        radii: (C,) capsule radii (m), dtype and device of ``theta``.

    What the cues derive from the body and could share (the capsules projected into a rig) is kept by
    :meth:`shared` for the body's lifetime: one evaluation of a product likelihood.
    """

    theta: torch.Tensor
    batch: torch.Size
    joints: torch.Tensor
    ends: torch.Tensor
    radii: torch.Tensor
    _shared: dict = field(default_factory=dict, repr=False)

    def shared(self, key, owner, build):
        """``build()``, computed once per ``key`` for this body and handed to every cue that asks with the
        same ``key`` and the same ``owner`` object (e.g. the camera rig the capsules are projected into: the
        silhouette and dual-silhouette terms of a product likelihood project the same capsules into the
        same cameras). The value is kept with its owner, so an owner's ``id`` is never reused while the body
        lives; another owner under the same key rebuilds."""
        hit = self._shared.get(key)
        if hit is not None and hit[0] is owner:
            return hit[1]
        value = build()
        self._shared[key] = (owner, value)
        return value

    @classmethod
    def of(cls, skeleton, theta: torch.Tensor, bone_index: torch.Tensor | None = None) -> Body:
        """One forward kinematics of ``theta`` (..., D) for ``skeleton`` (anything with ``fk``, ``bones``
        (C pairs of (parent, child) joint indices) and ``radii`` (C,), normally a :class:`torchpf.Skeleton`);
        the capsules are the bones' joint pairs, as in ``Skeleton.capsules``. ``bone_index`` (C, 2): the
        bones as a tensor already on the right device (default: made from ``skeleton.bones``)."""
        flat, batch = flatten_batch(theta, 1)
        joints = skeleton.fk(flat)
        if bone_index is None:
            bone_index = _bone_index(skeleton)
        return cls.from_joints(skeleton, flat, batch, joints, bone_index)

    @classmethod
    def from_joints(cls, skeleton, theta, batch, joints, bone_index) -> Body:
        """The body of already computed joint positions ``joints`` (B, J, 3) of poses ``theta`` (B, D)."""
        B, C = joints.shape[0], bone_index.shape[0]
        # index_select: its backward is one index_add (advanced indexing's accumulates through a sort)
        ends = joints.index_select(1, bone_index.to(joints.device).reshape(-1)).view(B, C, 2, 3)
        radii = skeleton.radii.to(device=joints.device, dtype=joints.dtype)
        return cls(theta, batch, joints, ends, radii)

    def rows(self, t: torch.Tensor, event_dims: int) -> torch.Tensor:
        """An observation tensor ``(*obs_batch, *event)`` aligned with the B flattened poses: ``(B, *event)``.

        ``obs_batch`` (a batch of independent sequences) must be a prefix of :attr:`batch`, e.g. ``(S,)``
        observations for ``(S, N, D)`` poses; each pose gets its sequence's entry. Without leading dims
        ``t`` is returned as is (one observation shared by every pose broadcasts).
        """
        lead = t.ndim - event_dims
        if lead <= 0:
            return t
        self.check_batch(t.shape[:lead])
        event = t.shape[lead:]
        t = t.reshape(*t.shape[:lead], *[1] * (len(self.batch) - lead), *event).expand(*self.batch, *event)
        return t.reshape(-1, *event)

    def check_batch(self, obs_batch: Sequence[int]) -> None:
        """Raise unless a batched observation's leading dims ``obs_batch`` are a prefix of the poses'."""
        if tuple(self.batch[: len(obs_batch)]) != tuple(obs_batch):
            raise ValueError(
                f"observations batched as {tuple(obs_batch)} do not match the poses' leading dims "
                f"{tuple(self.batch)}: a batch of sequences needs (S, ...) observations for (S, N, D) poses"
            )

    def capsules(self, bones: Sequence[int] | None = None):
        """Capsule ends ``a``, ``b`` (B, C', 3) and radii (C',) of all bones or of the subset ``bones``."""
        ends, radii = self.ends, self.radii
        if bones is not None:
            ends, radii = ends[:, bones], radii[bones]
        return ends[..., 0, :], ends[..., 1, :], radii


class Likelihood(nn.Module):
    """Base class of the cues: observation selection, the body computed once, batch dims restored.

    Subclasses set ``obs_type`` (the container class), ``obs_field`` (its name in :class:`Frame`) and
    ``needs_cameras`` (whether the constructor takes cameras after the skeleton), and implement
    ``_log_lik(body, obs) -> (B,)`` on the flattened body.

    Args:
        skeleton: anything :meth:`Body.of` accepts, normally a :class:`torchpf.Skeleton`.
        bones: optional subset of capsule indices the cue scores (e.g. one partition's limbs).

    Scale parameters (a cue's ``sigma``, the overlap's ``beta``) are 0-dim float64 tensors made by
    :meth:`scale_parameter`: buffers by default (they move with ``.to()``), ``nn.Parameter`` s where the
    cue's ``learnable`` argument names them (``True``: all of them), so that an optimiser can fit them, e.g.
    by maximising the filter's log-evidence (``ParticleFilter.run(..., grad=True)``).
    """

    #: names of the scale parameters a subclass registers with :meth:`scale_parameter`
    scales: tuple[str, ...] = ()

    obs_type: type = object
    obs_field: str = ""
    needs_cameras: bool = False

    def __init__(self, skeleton, bones: Sequence[int] | None = None):
        super().__init__()
        self.skeleton = skeleton
        self.bones = None if bones is None else list(bones)
        # The bones as an index buffer, so that it moves with the module and no FK call builds it.
        self.register_buffer("bone_index", _bone_index(skeleton), persistent=False)

    def scale_parameter(self, name: str, value, learnable: bool | Sequence[str] = False) -> None:
        """Register ``name`` as a 0-dim float64 tensor holding ``value``: an ``nn.Parameter`` if
        ``learnable`` is True or names it, else a buffer. An unknown name in ``learnable`` raises."""
        if not isinstance(learnable, bool):
            unknown = set(learnable) - set(self.scales)
            if unknown:
                raise ValueError(
                    f"{type(self).__name__}: learnable names {sorted(unknown)}; it has {list(self.scales)}"
                )
        value = torch.as_tensor(value, dtype=torch.float64).detach().clone().reshape(())
        if learnable is True or (not isinstance(learnable, bool) and name in learnable):
            self.register_parameter(name, nn.Parameter(value))
        else:
            self.register_buffer(name, value)

    def select(self, obs):
        """This cue's container in ``obs`` (the container itself, a :class:`Frame` or a dict holding it under
        ``obs_field``), or None when the frame has none (the cue then contributes 0)."""
        if obs is None or isinstance(obs, self.obs_type):
            return obs
        if isinstance(obs, Frame):
            return getattr(obs, self.obs_field)
        if isinstance(obs, Mapping):
            return obs.get(self.obs_field)
        if isinstance(obs, torch.Tensor) and self.obs_type in (PointCloud, Silhouettes):
            return self.obs_type(obs)
        raise TypeError(
            f"{type(self).__name__} expects a {self.obs_type.__name__} or a Frame with field "
            f"{self.obs_field!r}, got {type(obs).__name__}"
        )

    def body(self, theta: torch.Tensor) -> Body:
        """The body of poses ``theta`` (..., D) for this cue's skeleton (one forward kinematics)."""
        return Body.of(self.skeleton, theta, self.bone_index)

    def forward(self, theta: torch.Tensor, obs) -> torch.Tensor:
        """Log-likelihood (..., N) of poses ``theta`` (..., N, D) given one frame's ``obs``."""
        if self.select(obs) is None:
            return theta.new_zeros(theta.shape[:-1])
        return self.log_likelihood_body(self.body(theta), obs)

    def log_likelihood_and_grad(self, theta: torch.Tensor, obs) -> tuple[torch.Tensor, torch.Tensor]:
        """Log-likelihood (..., N) of poses ``theta`` (..., N, D) and its gradient in ``theta`` (..., N, D),
        both detached, whatever the grad mode.

        Autograd runs from the joint positions down (projection, the cue); the step through forward
        kinematics is the tree's vector-Jacobian product (:func:`torchpf.kinematics.jacobian.pose_gradient`)
        instead of back-propagation through the FK kernel, which for a gradient-based refinement of a few
        poses is most of the backward pass (:mod:`torchpf.refine`). A skeleton without the tree kernel
        (``fk_with_axes``) falls back on autograd through ``fk``. Equal to autograd to rounding.
        """
        flat, batch = flatten_batch(theta.detach(), 1)
        sel = self.select(obs)
        if sel is None:
            return flat.new_zeros(batch), torch.zeros_like(theta)
        skeleton = self.skeleton
        with torch.enable_grad():
            if not hasattr(skeleton, "fk_with_axes"):
                x = flat.clone().requires_grad_(True)
                loglik = self.log_likelihood_body(Body.of(skeleton, x, self.bone_index), sel)
                (grad,) = torch.autograd.grad(loglik.sum(), x)
                return loglik.detach().reshape(batch), grad.reshape(theta.shape)
            from torchpf.kinematics.jacobian import pose_gradient

            with torch.no_grad():
                axes, pivots, joints = skeleton.fk_with_axes(flat)  # batch last: (D, 3, B), (J, 3, B)
            leaf = joints.permute(2, 0, 1).requires_grad_(True)  # (B, J, 3)
            loglik = self.log_likelihood_body(
                Body.from_joints(skeleton, flat, batch, leaf, self.bone_index), sel
            )
            (g,) = torch.autograd.grad(loglik.sum(), leaf)
        grad = pose_gradient(skeleton.tree, torch.stack([axes, pivots], 1), joints, g.permute(1, 2, 0))
        return loglik.detach().reshape(batch), grad.t().reshape(theta.shape)

    def log_likelihood_body(self, body: Body, obs) -> torch.Tensor:
        """Log-likelihood (..., N) of an already computed :class:`Body` given one frame's ``obs``."""
        sel = self.select(obs)
        if sel is None:
            return body.theta.new_zeros(body.batch)
        return self._log_lik(body, sel).reshape(body.batch)

    def _log_lik(self, body: Body, obs) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError


def _bone_index(skeleton) -> torch.Tensor:
    return torch.as_tensor(skeleton.bones, dtype=torch.long).reshape(-1, 2)


def resolve_joints(skeleton, joints) -> list[int]:
    """Joint indices of ``joints`` (names or indices; None: all of ``skeleton.joint_names``)."""
    names = list(skeleton.joint_names)
    if joints is None:
        return list(range(len(names)))
    out = []
    for j in joints:
        if isinstance(j, int):
            out.append(j)
        elif j in names:
            out.append(names.index(j))
        else:
            raise ValueError(f"unknown joint {j!r}; the skeleton has {names}")
    return out
