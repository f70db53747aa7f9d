"""Kinematics: the kinematic tree of a skeleton and what is computed on it.

* :mod:`torchpf.kinematics.tree`: :class:`KinematicTree`, the skeleton's topology as public index tensors
  (parents, DOF runs, depth levels, revolute mask, bones, DOF owners, the torso/limb partition), and
  :func:`body_partition` (Fontmarty Table 2).
* :mod:`torchpf.kinematics.urdf`: URDF reading (text, pytorch-kinematics chain, flattened frames, capsule
  radii) and writing (:func:`~torchpf.kinematics.urdf.build_urdf`).
* :mod:`torchpf.kinematics.jacobian`: the tree Jacobian of FK from the DOF axes (and the autograd one).
* :mod:`torchpf.kinematics.symmetry`: mirror-image limbs from the tree and the rest pose, and the DOF map
  that exchanges them (:func:`~torchpf.kinematics.symmetry.limb_swaps`).
* :mod:`torchpf.kinematics.aba`: the articulated-body solve of ``(JᵀWJ + diag) δ = JᵀW r`` (Featherstone),
  eager tensors or the fused numba kernel (:mod:`torchpf.kinematics._aba_cpu`).

:class:`torchpf.skeleton.Skeleton` (the FK kernel) builds the tree; :mod:`torchpf.ik` (the
Levenberg-Marquardt loop of Hauberg eq. 7) consumes it through the Jacobian and the ABA.

Example::

    from torchpf.kinematics import body_partition
    skel = Skeleton.from_urdf(torchpf.assets.path("human.urdf"))
    skel.tree.parents, skel.tree.dof_revolute       # (J,) long, (D,) bool
    torso, limbs = body_partition(skel)             # DOF indices (Fontmarty's two partitions)
"""

from torchpf.kinematics.tree import KinematicTree, body_partition

__all__ = ["KinematicTree", "body_partition"]
