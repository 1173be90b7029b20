"""Builders shared by the tests (they live in the library so benchmarks can use them too)."""

from progressive_avatars.core.synthetic.shapes import depth6_precision, random_forest, sphere_mesh  # noqa: F401
