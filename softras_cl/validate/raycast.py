"""An independent reference renderer: one ray per pixel centre, cast with trimesh (Embree).

Used by `softras-cl compare` and the tests to check silhouettes, depth and shading of the soft
rasteriser at sharp settings. Same conventions as the rasteriser (docs/scene.md): pixel (u, v)
centres at integer pixel coordinates, depth = camera-frame Z.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from softras_cl.errors import InputError
from softras_cl.scene.camera import Camera


@dataclass
class RayCastImage:
    """Per-pixel results of the ray cast; H x W arrays.

    mask: bool, a ray hit the mesh; depth: camera-frame Z of the hit (NaN where no hit);
    face: index of the face hit (-1 where none); bary: (H, W, 3) barycentrics of the hit in that
    face (3D, i.e. perspective-correct).
    """
    mask: np.ndarray
    depth: np.ndarray
    face: np.ndarray
    bary: np.ndarray


def pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """World-space origins and unit directions (H*W, 3) of the rays through every pixel centre,
    row-major from the top-left pixel."""
    h, w = camera.image_size
    v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    a, b = ((u - camera.cx) / camera.fx).ravel(), ((v - camera.cy) / camera.fy).ravel()
    rot_t = camera.rotation_matrix().T
    if camera.projection == "perspective":
        directions = np.stack([a, b, np.ones_like(a)], 1) @ rot_t.T
        origins = np.broadcast_to(camera.center(), directions.shape)
    else:
        origins = (np.stack([a, b, np.zeros_like(a)], 1) - camera.translation) @ rot_t.T
        directions = np.broadcast_to(rot_t[:, 2], origins.shape)
    return np.ascontiguousarray(origins), directions / np.linalg.norm(directions, axis=1, keepdims=True)


def raycast(vertices: np.ndarray, faces: np.ndarray, camera: Camera) -> RayCastImage:
    """Nearest hit of each pixel's ray with the mesh (vertices (V, 3) world, faces (F, 3)).

    InputError (exit 2 on the command line) saying what to install when embreex (the optional
    extra `validate`) is missing.
    """
    if not trimesh.ray.has_embree:
        raise InputError('the ray-cast reference needs embreex, in the optional extra: '
                         'pip install "softras-cl[validate]"')
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces), process=False)
    origins, directions = pixel_rays(camera)
    locations, ray_index, face_index = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    h, w = camera.image_size
    mask = np.zeros(h * w, bool)
    depth = np.full(h * w, np.nan)
    face = np.full(h * w, -1, np.int64)
    bary = np.zeros((h * w, 3))
    if len(ray_index):
        cam = locations @ camera.rotation_matrix().T + camera.translation
        mask[ray_index], depth[ray_index], face[ray_index] = True, cam[:, 2], face_index
        bary[ray_index] = trimesh.triangles.points_to_barycentric(mesh.triangles[face_index], locations)
    return RayCastImage(mask.reshape(h, w), depth.reshape(h, w), face.reshape(h, w), bary.reshape(h, w, 3))
