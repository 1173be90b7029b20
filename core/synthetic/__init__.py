"""The synthetic head dataset (not shipped in the extension). Reporting tier (numpy, trimesh)."""
