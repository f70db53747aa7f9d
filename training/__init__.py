"""training: mocap I/O and fitting of action models from mocap CSV (depends on priors, torchpf).

* :mod:`training.mocap`: ``load_bvh``, ``load_csv``, ``save_csv``, ``Motion``.
* :mod:`training.synthetic`: the procedural motion generator (the embedded default data).
* :mod:`training.fit`: ``fit_action_model`` / ``ActionModelFitter`` (Rius eq. 1-5).
* :mod:`training.align`: resampling, period estimation, DTW and DBA (the synchronisation of Rius §2).
"""

from importlib import import_module

_LAZY = {
    "Motion": "training.mocap",
    "load_bvh": "training.mocap",
    "load_csv": "training.mocap",
    "save_csv": "training.mocap",
    "fit_action_model": "training.fit",
    "ActionModelFitter": "training.fit",
}


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'training' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
