"""Built-in meshes: counts, uniqueness, closedness, orientation."""
import numpy as np
import pytest
import trimesh

from softras_cl.scene.meshes import icosphere, screen_space_sphere


def doubled_area(v, f):
    """Doubled signed area in the xy plane, (F,) float64."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])


@pytest.mark.parametrize("s, n_faces", [(0, 20), (1, 80), (3, 1280), (4, 5120), (5, 20480)])
def test_icosphere_counts(s, n_faces):
    v, f = icosphere(s, radius=2.0)
    assert v.dtype == np.float64 and v.shape == (10 * 4**s + 2, 3)
    assert f.dtype == np.int32 and f.shape == (n_faces, 3)
    if s <= 4:
        assert len(trimesh.creation.icosphere(subdivisions=s).faces) == n_faces
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 2.0, rtol=1e-12)
    assert len(np.unique(np.round(v, 9), axis=0)) == len(v)
    assert f.min() == 0 and f.max() == len(v) - 1


def test_icosphere_81920_faces():
    assert icosphere(6)[1].shape == (81920, 3)


@pytest.mark.parametrize("s", [0, 2])
def test_icosphere_closed_and_outward(s):
    v, f = icosphere(s)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)          # each directed edge once
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert (counts == 2).all()                                        # closed 2-manifold
    assert len(v) - len(undirected) + len(f) == 2                     # Euler characteristic
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (np.einsum("ij,ij->i", n, v[f].mean(1)) > 0).all()


def test_screen_space_sphere_scene():
    v, f, col = screen_space_sphere(3)
    assert v.shape == (642, 3) and f.shape == (1280, 3) and col.shape == (642, 3)
    np.testing.assert_allclose([v[:, 2].min(), v[:, 2].max()], [2.0, 3.6], atol=1e-12)
    np.testing.assert_allclose(np.hypot(v[:, 0], v[:, 1]).max(), 0.8, atol=1e-12)
    assert col.min() >= 0 and col.max() <= 1
    # Faces on the near half (towards the camera, small z) are CCW in NDC, far half CW.
    area = doubled_area(v, f)
    zmax, zmin = v[f, 2].max(1), v[f, 2].min(1)
    assert (area[zmax < 2.8] > 0).all() and (area[zmin > 2.8] < 0).all()
    # Front faces cover the projected disk once; the closed mesh's signed areas cancel.
    assert abs(area[area > 0].sum() / 2 - np.pi * 0.8**2) < 0.02 * np.pi * 0.8**2
    assert abs(area.sum()) < 1e-12
    v2, f2 = screen_space_sphere(2, colors=False)
    assert v2.shape == (162, 3) and f2.shape == (320, 3)
