"""Files in and out: images (sRGB <-> linear), meshes (trimesh), landmark files."""
