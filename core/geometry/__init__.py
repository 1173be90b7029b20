"""Geometry helpers: cameras, rotations, spherical harmonics, the Gaussians type. Blender tier: numpy and stdlib only."""
