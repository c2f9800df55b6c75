"""The renderer's small float64 test scene, shared by tests/scene (the renderer against finite
differences) and tests/interop (the bridges against the numpy API): a jittered icosphere, two
cameras looking at it and one light of each kind."""
from __future__ import annotations

import numpy as np

from softras_cl.scene.camera import Camera
from softras_cl.scene.meshes import icosphere
from softras_cl.scene.shading import LambertLight, PhongLight, SHLight


def sphere_scene(seed=0):
    """vertices (V, 3) world (icosphere(1), radius 0.6, jittered), faces (F, 3), albedo (V, 3)."""
    rng = np.random.default_rng(seed)
    v, f = icosphere(1, radius=0.6)
    return v + rng.normal(scale=0.03, size=v.shape), f, rng.uniform(0.2, 0.9, v.shape)


def two_cameras(image_size: tuple[int, int]) -> list[Camera]:
    """Two perspective cameras on the sphere from different sides, making (H, W) images."""
    return [Camera.look_at((0.4, 0.5, 3.0), (0.0, 0.05, 0.0), fov_deg=35, image_size=image_size),
            Camera.look_at((-1.5, 0.3, 2.2), (0.05, 0.0, 0.0), fov_deg=40, image_size=image_size)]


LIGHTS = {
    "lambert": LambertLight(ambient=(0.3, 0.4, 0.5), directional=(0.6, 0.5, 0.4), direction=(0.3, 1.0, 0.6)),
    "phong": PhongLight(ambient=0.3, directional=0.6, direction=(0.5, 0.8, 0.7), specular=0.3, shininess=5.0),
    "sh": SHLight(np.random.default_rng(3).normal(scale=0.3, size=(3, 9)) + SHLight.ambient(0.8).coefficients),
}
