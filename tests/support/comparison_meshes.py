"""Meshes shared by the comparison tests (ray cast and Mitsuba)."""
import numpy as np
import trimesh

from softras_cl.io.meshes import Mesh


def icosphere() -> Mesh:
    m = trimesh.creation.icosphere(3)
    return Mesh(np.asarray(m.vertices, float), np.asarray(m.faces))


def torus() -> Mesh:
    """Non-convex, with self-occlusion at elevation 40 degrees."""
    m = trimesh.creation.torus(0.7, 0.3)
    return Mesh(np.asarray(m.vertices, float), np.asarray(m.faces)).normalized()


def textured_sphere() -> Mesh:
    """Sphere with a spherical uv map and a smooth procedural texture."""
    m = trimesh.creation.icosphere(3)
    v = np.asarray(m.vertices, float)
    uvs = np.stack([0.5 + np.arctan2(v[:, 0], v[:, 2]) / (2 * np.pi),
                    0.5 + np.arcsin(np.clip(v[:, 1], -1, 1)) / np.pi], 1)
    yy, xx = np.mgrid[0:64, 0:128]
    texture = np.stack([0.5 + 0.4 * np.sin(xx / 7.0), 0.5 + 0.4 * np.cos(yy / 5.0),
                        0.5 + 0.3 * np.sin((xx + yy) / 11.0)], -1)
    return Mesh(v, np.asarray(m.faces), uvs=uvs, texture=texture)
