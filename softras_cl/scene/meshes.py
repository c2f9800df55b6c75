"""Built-in meshes: icospheres, and the screen-space sphere used by the demo and benchmarks."""
from __future__ import annotations

import numpy as np


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """Unit icosahedron: vertices (12, 3) float64, faces (20, 3) int64, outward CCW."""
    t = (1.0 + 5.0 ** 0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
                  [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
                  [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
                  [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                  [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    # Make every face outward CCW (normal . centroid > 0): valid since the solid is convex.
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inward = np.einsum("ij,ij->i", n, v[f].sum(1)) < 0
    f[inward] = f[inward, ::-1]
    return v, f


def _subdivide(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split each face into 4 through its edge midpoints (shared, projected to the unit sphere)."""
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])      # (3F, 2)
    uniq, inv = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
    mid = v[uniq].sum(1)
    mid /= np.linalg.norm(mid, axis=1, keepdims=True)
    m01, m12, m20 = (len(v) + inv.reshape(-1)).reshape(3, -1)
    a, b, c = f.T
    faces = np.concatenate([np.stack(x, 1) for x in
                            ([a, m01, m20], [b, m12, m01], [c, m20, m12], [m01, m12, m20])])
    return np.concatenate([v, mid]), faces


def icosphere(subdivisions: int, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Geodesic sphere centred at the origin.

    Returns vertices (V, 3) float64 on the sphere of `radius`, V = 10 * 4**s + 2, all distinct,
    and faces (F, 3) int32, F = 20 * 4**s, counter-clockwise seen from outside (right-handed
    cross product of the edges points outward).
    """
    if subdivisions < 0:
        raise ValueError(f"subdivisions must be >= 0, got {subdivisions}")
    v, f = _icosahedron()
    for _ in range(subdivisions):
        v, f = _subdivide(v, f)
    return v * float(radius), f.astype(np.int32)


def screen_space_sphere(subdivisions: int, radius: float = 0.8, z_near: float = 2.0,
                        z_far: float = 3.6, colors: bool = True):
    """The raster benchmark's scene: an icosphere seen by a camera on its +z axis.

    Screen space: x, y in NDC (x right, y up) equal the sphere's x, y (radius `radius`, centred);
    z is view depth, `zc - s * z_sphere` with zc = (z_near + z_far) / 2 and s scaling the sphere's
    z so depth spans exactly [z_near, z_far] (s = 1 for the defaults: z from 2.0 to 3.6). The
    camera looks along +z (towards larger depth), so faces towards it are counter-clockwise in
    NDC: doubled signed area (x1-x0)(y2-y0) - (x2-x0)(y1-y0) > 0 (docs/conventions.md).

    Returns (vertices (V, 3) float64, faces (F, 3) int32) or, with colors=True,
    (vertices, faces, colors (V, 3) float64 in [0, 1], smooth: 0.5 + 0.5 * unit normal).
    """
    unit, faces = icosphere(subdivisions)
    zc, s = (z_near + z_far) / 2.0, (z_far - z_near) / 2.0
    verts = np.stack([radius * unit[:, 0], radius * unit[:, 1], zc - s * unit[:, 2]], axis=1)
    if not colors:
        return verts, faces
    return verts, faces, 0.5 + 0.5 * unit
