"""Training step, augmentation, checkpoints and weight publishing."""
