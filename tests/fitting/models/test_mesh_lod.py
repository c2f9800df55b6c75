"""Coarse face lists by vertex clustering (fitting/models/mesh_lod.py)."""
import numpy as np
import pytest

from softras_cl.fitting.models.mesh_lod import (cluster_faces, cluster_representatives, coarse_faces,
                                                median_edge_length)
from softras_cl.fitting.models.face_loaders import load_demo_face_model


def grid_mesh(n: int, size: float = 1.0):
    """An n x n grid of squares over [0, size]^2 at z = 0, two counter-clockwise triangles each
    (normals +z): points ((n+1)^2, 3), faces (2 n^2, 3)."""
    y, x = np.mgrid[0:n + 1, 0:n + 1] * (size / n)
    points = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + 1, i.ravel() + n + 2, i.ravel() + n + 1
    return points, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def areas(points, faces):
    """Signed z of each triangle's doubled-area normal (positive: counter-clockwise from +z)."""
    p = points[faces]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2]


def test_a_cell_smaller_than_the_spacing_keeps_every_face():
    points, faces = grid_mesh(6)
    np.testing.assert_array_equal(cluster_faces(points, faces, 0.5 / 6), faces)


def test_clustered_grid_keeps_its_vertices_orientation_and_most_of_its_area():
    points, faces = grid_mesh(24)
    coarse = cluster_faces(points, faces, 3.0 / 24)
    assert coarse.dtype == np.int32 and len(coarse) < len(faces) / 4
    kept = np.unique(cluster_representatives(points, 3.0 / 24))
    assert np.isin(coarse, kept).all()                       # only the vertices standing in
    assert (areas(points, coarse) > 0).all()                 # counter-clockwise, none degenerate
    assert len({tuple(sorted(f)) for f in coarse.tolist()}) == len(coarse)
    # the kept vertices sit inside the square, so only a border strip under a cell can be lost
    assert 0.75 < 0.5 * areas(points, coarse).sum() <= 1.0 + 1e-12


def test_each_cube_keeps_the_vertex_nearest_its_centroid():
    points = np.array([[0.1, 0.1, 0.1], [0.5, 0.5, 0.5], [0.8, 0.8, 0.8], [1.5, 0.2, 0.2]])
    rep = cluster_representatives(points, 1.0)
    np.testing.assert_array_equal(rep, [1, 1, 1, 3])
    # a tie goes to the lower index
    np.testing.assert_array_equal(cluster_representatives(np.array([[0.75, 0.5, 0.5], [0.25, 0.5, 0.5]]), 1.0), [0, 0])


def test_the_demo_face_at_two_edges_draws_the_same_surface_with_a_third_of_the_faces():
    model = load_demo_face_model()
    coarse = coarse_faces(model.mean_shape, model.faces, 2.0)
    assert len(coarse) < len(model.faces) / 2.5 and coarse.max() < model.n_vertices
    np.testing.assert_array_equal(coarse, coarse_faces(model.mean_shape, model.faces, 2.0))   # deterministic
    full_area = np.linalg.norm(np.cross(*(model.mean_shape[model.faces[:, k]] - model.mean_shape[model.faces[:, 0]]
                                          for k in (1, 2))), axis=1).sum()
    p = model.mean_shape[coarse]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    assert 0.97 < area / full_area < 1.01
    assert median_edge_length(model.mean_shape, coarse) > 1.5 * median_edge_length(model.mean_shape, model.faces)


@pytest.mark.parametrize("points, faces, cell, says", [
    (np.zeros((3, 3)), np.array([[0, 1, 2]]), 0.0, "cell must be a positive length"),
    (np.zeros((3, 3)), np.array([[0, 1, 2]]), np.nan, "cell must be a positive length"),
    (np.zeros((3, 3)), np.array([[0, 1, 3]]), 1.0, "faces"),
    (np.zeros((3, 2)), np.array([[0, 1, 2]]), 1.0, "points"),
])
def test_bad_input_is_named(points, faces, cell, says):
    with pytest.raises(ValueError, match=says):
        cluster_faces(points, faces, cell)
