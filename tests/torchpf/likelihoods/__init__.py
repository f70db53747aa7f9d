"""Likelihood tests (a package: its basenames mirror torchpf/likelihoods/ and may recur elsewhere)."""
