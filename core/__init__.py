"""Everything that is not Blender. No module in this package imports bpy;
numpy-only modules (forest, binding, camera, avatar, stream reading) never import torch."""
