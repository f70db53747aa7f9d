"""training: mocap I/O and fitting of action models from mocap CSV (depends on priors, torchpf)."""
