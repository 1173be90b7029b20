"""FLAME model loading (restricted unpickler), forward and rig. Blender tier: numpy and stdlib only."""
