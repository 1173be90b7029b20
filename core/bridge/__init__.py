"""The bpy-free half of the Blender add-on: arrays the preview needs. Blender tier: numpy and stdlib only."""
