"""The subdivision forest, face binding and the Avatar. Blender tier: numpy and stdlib only."""
