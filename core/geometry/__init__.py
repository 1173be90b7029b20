"""Geometry helpers: cameras, rotations, spherical harmonics. Blender tier: numpy and stdlib only."""
