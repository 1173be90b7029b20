"""Training: trainable avatar, losses, growth, supervision, checkpoints. Training tier (torch, numba)."""
