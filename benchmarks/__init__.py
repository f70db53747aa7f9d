"""Throughput and accuracy runs that print tables (never timed tests); run from the repository root.

Each module is a command, ``python -m benchmarks.<name> --help``: ``fk``, ``filters``, ``likelihoods``,
``ik``, ``importance``, ``action_prior``, ``evaluate``. They build on the library's own rules (the equal
likelihood budget of :data:`torchpf.filters.registry.FILTERS`, the one Fontmarty Table 5), and the tests
import :mod:`benchmarks.evaluate` as a module. Figures and the commands that printed them: ``BENCHMARKS.md``.
"""
