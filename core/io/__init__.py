"""Files: sequences, datasets, PLY, run folders, atomic writes. Blender tier: numpy and stdlib (PIL lazily for training images)."""
