"""torchpf: particle-filter tracking of 3D human pose in PyTorch.

The engine package: kinematics (URDF skeletons with a fused FK kernel), geometry, cameras, likelihoods,
particle filters, metrics and synthetic observations. ``priors`` (motion models, proposals) and ``training``
(mocap I/O, action models) build on it; this package never imports them.

Shape glossary used in every docstring:

==========  =====================================================
``...``     free leading batch dims (independent sequences, ...)
``N``       particles
``T``       time steps (frames)
``J``       body joints (positions)
``D``       degrees of freedom (the pose vector theta)
``C``       capsules (bones)
``K``       points (image or 3D)
``V``       cameras (views)
==========  =====================================================

Conventions: metres, radians, seconds; world frame right-handed with z up; column vectors; weights are
log-weights normalised with ``logsumexp``; randomness goes through an explicit ``torch.Generator``.

Example::

    from torchpf import Skeleton, assets
    skel = Skeleton.from_urdf(assets.path("human.urdf"))
    joints = skel.fk(torch.zeros(1000, len(skel.dof_names)))   # (1000, J, 3)
"""

from importlib import import_module
from importlib.util import find_spec

from torchpf._version import __version__ as __version__

if find_spec("cv2") is None:  # either OpenCV distribution provides cv2; installing one is the user's choice
    import warnings

    warnings.warn(
        "torchpf needs OpenCV (the cv2 module) for cameras, masks and sensors: install one of "
        "`pip install 'torchpf[opencv]'` (opencv-python-headless) or `pip install opencv-python`",
        stacklevel=2,
    )

# Public names resolved lazily so that `import torchpf` stays cheap and a heavy optional piece (OpenCV,
# pytorch-kinematics) is only loaded when used.
_LAZY = {
    "Skeleton": "torchpf.skeleton",
    "Camera": "torchpf.camera",
    "ParticleFilter": "torchpf.filters",
    "AnnealedParticleFilter": "torchpf.filters",
    "PartitionedParticleFilter": "torchpf.filters",
    "MCMCParticleFilter": "torchpf.filters",
    "Tracker": "torchpf.tracker",
    "TrackResult": "torchpf.tracker",
}


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'torchpf' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
