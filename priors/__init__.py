"""priors: motion models and importance distributions for articulated tracking (depends on torchpf)."""
