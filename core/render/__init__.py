"""Rasterisers: numba CPU kernels, the torch autograd wrapper, gsplat, the dense reference. Training tier (numba, torch)."""
