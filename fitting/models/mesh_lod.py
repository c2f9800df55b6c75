"""Coarser face lists over a model's own vertices, for fits that compare a blurred, low-resolution
image (a level of detail for the mesh, beside the image pyramid's).

Vertex clustering (Rossignac and Borrel, "Multi-resolution 3D approximations for rendering
complex scenes", 1993): space is cut into cubes of side ``cell``; every vertex of a cube stands
in for all of them; triangles whose corners fall into fewer than three cubes disappear. The
vertex kept in each cube is one of the mesh's own (the one nearest the cube's vertex centroid),
so a coarse face list indexes the model's vertex array as it is: shape, albedo, landmarks and
their gradients are untouched, only the faces drawn change.
"""
from __future__ import annotations

import numpy as np

from softras_cl.checks import index_array, real_array


def median_edge_length(points: np.ndarray, faces: np.ndarray) -> float:
    """Median length of the triangles' edges: points (V, 3) float64, faces (F, 3) int."""
    corners = points[faces]                                          # (F, 3, 3)
    return float(np.median(np.linalg.norm(corners[:, [1, 2, 0]] - corners, axis=2)))


def cluster_representatives(points: np.ndarray, cell: float) -> np.ndarray:
    """(V,) int64: for every vertex, the vertex that stands in for its cube of side ``cell``
    (cubes aligned at the origin): the one nearest the cube's vertex centroid, ties to the
    lower index."""
    _, cube = np.unique(np.floor(points / cell).astype(np.int64), axis=0, return_inverse=True)
    cube = cube.ravel()
    n = int(cube.max()) + 1
    count = np.bincount(cube, minlength=n)
    centroid = np.stack([np.bincount(cube, points[:, k], n) for k in range(3)], axis=1) / count[:, None]
    distance = np.linalg.norm(points - centroid[cube], axis=1)
    order = np.lexsort((np.arange(len(points)), distance, cube))     # by cube, nearest first
    first = np.ones(len(order), bool)
    first[1:] = cube[order[1:]] != cube[order[:-1]]
    kept = np.empty(n, np.int64)
    kept[cube[order[first]]] = order[first]
    return kept[cube]


def cluster_faces(points, faces, cell: float) -> np.ndarray:
    """The face list of ``faces`` (F, 3) over ``points`` (V, 3) after vertex clustering with
    cubes of side ``cell`` (model units): (F', 3) int32 indices into the same points, every
    corner a kept vertex, corner order (hence orientation) as in the original triangle; a
    triangle whose corners merge, or that repeats an earlier one's corners, or whose area is
    zero, is left out. Deterministic."""
    points = real_array("points", points, (None, 3), "(V, 3)")
    faces = index_array("faces", faces, len(points), "vertices", (None, 3), "(F, 3)")
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be a positive length, got {cell!r}")
    merged = cluster_representatives(points, cell)[faces]
    distinct = ((merged[:, 0] != merged[:, 1]) & (merged[:, 1] != merged[:, 2])
                & (merged[:, 0] != merged[:, 2]))
    merged = merged[distinct]
    _, first = np.unique(np.sort(merged, axis=1), axis=0, return_index=True)
    merged = merged[np.sort(first)]
    corners = points[merged]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    return np.ascontiguousarray(merged[area > 0], dtype=np.int32)


def coarse_faces(points, faces, edges: float) -> np.ndarray:
    """``faces`` (F, 3) clustered over ``points`` (V, 3) (a model's mean or template shape) with
    cubes of ``edges`` median edge lengths: (F', 3) int32 (see :func:`cluster_faces`)."""
    points = real_array("points", points, (None, 3), "(V, 3)")
    return cluster_faces(points, faces, edges * median_edge_length(points, np.asarray(faces)))
