"""Small float64 scenes for the bridge tests: the rasteriser's random overlapping screen-space
triangles (as tests/raster uses for its finite differences) and a bumpy icosphere seen by two
cameras under an SH light (support.sphere_scene, as tests/scene). Smooth settings (sigma, gamma large, no cut-off) so
central differences converge."""
from __future__ import annotations

import numpy as np

from softras_cl import RasterSettings
from support.sphere_scene import two_cameras

H, W = 9, 11     # not a multiple of the 8-pixel tile


def raster_settings(**kw) -> RasterSettings:
    base = dict(image_size=(H, W), sigma=2e-3, gamma=3e-2, dist_eps=0.0, near=1.0, far=10.0,
                double_sided=True, outputs=("rgb", "alpha", "depth"), dtype="float64",
                background=(0.2, 0.3, 0.4))
    return RasterSettings(**{**base, **kw})


def raster_scene(seed=0, batch=2, n_vertices=8, n_faces=6, texture="vertex", lit=False) -> dict:
    """vertices (B, V, 3), faces (F, 3) and the colour input of `texture` (+ normals, light)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1.1, 1.1, (batch, n_vertices, 2)) * [W / H, 1.0]
    z = rng.uniform(2.0, 4.0, (batch, n_vertices, 1))
    faces = rng.integers(0, n_vertices, (n_faces, 3))
    faces = faces[np.array([len(set(f)) == 3 for f in faces])]
    scene = dict(vertices=np.concatenate([xy, z], -1), faces=faces)
    if texture == "vertex":
        scene["colors"] = rng.uniform(0, 1, (batch, n_vertices, 3))
    elif texture == "face":
        scene["face_textures"] = rng.uniform(0, 1, (batch, len(faces), 2, 2, 3))
    else:
        scene["texture_image"] = rng.uniform(0, 1, (batch, 4, 5, 3))
        scene["uvs"] = rng.uniform(-0.1, 1.1, (batch, n_vertices, 2))
    if lit:
        n = rng.normal(size=(batch, n_vertices, 3))
        scene["normals"] = n / np.linalg.norm(n, axis=-1, keepdims=True)
        scene["light"] = np.concatenate([[0.3, 0.4, 0.5, 0.6, 0.5, 0.4], [0.3, 0.8, 0.5],
                                         np.zeros(18)]) if lit == "lambert" else \
            rng.normal(scale=0.3, size=27) + np.eye(1, 27, 0)[0]
    return scene


def render_settings(**kw) -> RasterSettings:
    base = dict(image_size=(H, W), sigma=1e-3, gamma=1e-2, dist_eps=0.0, near=0.5, far=10.0,
                outputs=("rgb", "alpha", "depth"), dtype="float64")
    return RasterSettings(**{**base, **kw})


def cameras():
    """support.sphere_scene's two cameras, making (H, W) images."""
    return two_cameras((H, W))
