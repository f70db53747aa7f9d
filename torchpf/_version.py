"""The one version source of the distribution: pyproject.toml, ``torchpf.__version__`` and ``--version``."""

__version__ = "0.2.0.dev0"
