import numpy as np
import pytest

from support.face_files import face_normals, grid_face
from softras_cl.fitting.models.face_loaders import load_demo_face_model, load_face_model
from softras_cl.errors import InputError
from softras_cl.fitting.models.face_model import FaceModel


def make_model(k_id=4, k_exp=3, k_alb=2, n_lmk=5, seed=0) -> FaceModel:
    rng = np.random.default_rng(seed)
    vertices, faces = grid_face()
    v = len(vertices)
    bary = rng.uniform(0.1, 1.0, size=(n_lmk, 3))
    return FaceModel(mean_shape=vertices, id_basis=rng.normal(size=(k_id, v, 3)),
                     id_std=rng.uniform(0.001, 0.01, k_id), exp_basis=rng.normal(size=(k_exp, v, 3)),
                     exp_std=rng.uniform(0.001, 0.01, k_exp), albedo_mean=rng.uniform(0.2, 0.8, (v, 3)),
                     albedo_basis=rng.normal(size=(k_alb, v, 3)), albedo_std=rng.uniform(0.01, 0.1, k_alb),
                     faces=faces, landmark_faces=rng.integers(0, len(faces), n_lmk),
                     landmark_bary=bary / bary.sum(axis=1, keepdims=True), name="test face",
                     attribution="synthetic, CC0")


def central_jacobian(f, x, eps=1e-6):
    cols = []
    for i in range(x.size):
        d = np.zeros_like(x)
        d[i] = eps
        cols.append((f(x + d) - f(x - d)).reshape(-1) / (2 * eps))
    return np.stack(cols, axis=1)


def test_shape_is_mean_plus_std_scaled_directions():
    m = make_model()
    c_id, c_exp = np.array([1.0, -2.0, 0.5, 0.0]), np.array([0.3, 0.0, -1.0])
    expected = m.mean_shape + np.einsum("k,kvc->vc", c_id * m.id_std, m.id_basis) \
        + np.einsum("k,kvc->vc", c_exp * m.exp_std, m.exp_basis)
    np.testing.assert_allclose(m.shape(c_id, c_exp)[0], expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(m.shape(np.zeros(4), np.zeros(3))[0], m.mean_shape)


def test_sizes_and_dtypes():
    m = make_model()
    assert (m.n_vertices, m.n_id, m.n_exp, m.n_albedo, m.n_landmarks) == (30, 4, 3, 2, 5)
    assert m.faces.dtype == np.int32 and m.landmark_faces.dtype == np.int32
    assert m.mean_shape.dtype == np.float64 and m.id_basis.dtype == np.float64
    assert "30 vertices" in repr(m)


def test_shape_vjp_matches_finite_differences_and_dot_product():
    m = make_model()
    rng = np.random.default_rng(1)
    x = rng.normal(size=m.n_id + m.n_exp)
    split = lambda x: (x[:m.n_id], x[m.n_id:])  # noqa: E731
    jac = central_jacobian(lambda x: m.shape(*split(x))[0], x)
    g = rng.normal(size=(m.n_vertices, 3))
    grads = m.shape_vjp(m.shape(*split(x))[1], g)
    g_id, g_exp = grads["id_coeffs"], grads["exp_coeffs"]
    np.testing.assert_allclose(np.concatenate([g_id, g_exp]), jac.T @ g.reshape(-1), rtol=1e-7, atol=1e-12)
    v = rng.normal(size=x.size)
    jv = m.shape(*split(v))[0] - m.mean_shape
    assert np.isclose(np.sum(g * jv), g_id @ v[:m.n_id] + g_exp @ v[m.n_id:], rtol=1e-12)


def test_albedo_and_its_vjp():
    m = make_model()
    rng = np.random.default_rng(2)
    c = rng.normal(size=m.n_albedo)
    expected = m.albedo_mean + np.einsum("k,kvc->vc", c * m.albedo_std, m.albedo_basis)
    albedo, ctx = m.albedo(c)
    np.testing.assert_allclose(albedo, expected, atol=1e-15)
    jac = central_jacobian(lambda x: m.albedo(x)[0], c)
    g = rng.normal(size=(m.n_vertices, 3))
    np.testing.assert_allclose(m.albedo_vjp(ctx, g)["coeffs"], jac.T @ g.reshape(-1), rtol=1e-7, atol=1e-12)
    jv = albedo - m.albedo_mean
    assert np.isclose(np.sum(g * jv), m.albedo_vjp(ctx, g)["coeffs"] @ c, rtol=1e-12)


def test_landmarks_interpolate_in_their_faces_and_vjp_is_exact():
    m = make_model()
    rng = np.random.default_rng(3)
    verts, _ = m.shape(rng.normal(size=4), rng.normal(size=3))
    tri = verts[m.faces[m.landmark_faces]]
    points, ctx = m.landmarks(verts)
    np.testing.assert_allclose(points, np.einsum("lj,ljc->lc", m.landmark_bary, tri))
    jac = central_jacobian(lambda x: m.landmarks(x.reshape(-1, 3))[0], verts.reshape(-1))
    g = rng.normal(size=(m.n_landmarks, 3))
    g_verts = m.landmarks_vjp(ctx, g)["vertices"]
    np.testing.assert_allclose(g_verts.reshape(-1), jac.T @ g.reshape(-1), rtol=1e-7, atol=1e-10)
    dv = rng.normal(size=verts.shape)
    assert np.isclose(np.sum(g * m.landmarks(dv)[0]), np.sum(g_verts * dv), rtol=1e-12)


def with_dense(m: FaceModel, n=7, seed=4) -> FaceModel:
    """The model with n random dense points, every other one unused."""
    rng = np.random.default_rng(seed)
    bary = rng.uniform(0.1, 1.0, size=(n, 3))
    return FaceModel(**(m._fields() | {"dense_faces": rng.integers(0, len(m.faces), n),
                                       "dense_bary": bary / bary.sum(axis=1, keepdims=True),
                                       "dense_use": np.arange(n) % 2 == 0}))


def test_dense_points_interpolate_in_their_faces_and_vjp_is_exact():
    m = with_dense(make_model())
    rng = np.random.default_rng(5)
    verts, _ = m.shape(rng.normal(size=4), rng.normal(size=3))
    points, ctx = m.dense_points(verts)
    expected = np.einsum("nj,njc->nc", m.dense_bary, verts[m.faces[m.dense_faces]])
    np.testing.assert_allclose(points, expected, rtol=0, atol=1e-15)
    jac = central_jacobian(lambda x: m.dense_points(x.reshape(-1, 3))[0], verts.reshape(-1))
    g = rng.normal(size=(m.n_dense, 3))
    g_verts = m.dense_points_vjp(ctx, g)["vertices"]
    np.testing.assert_allclose(g_verts.reshape(-1), jac.T @ g.reshape(-1), rtol=1e-7, atol=1e-10)
    with pytest.raises(ValueError, match=r"grad must have shape \(7, 3\)"):
        m.dense_points_vjp(ctx, np.zeros((6, 3)))


def test_dense_points_through_the_coefficients_match_finite_differences():
    """The chain a fit uses: coefficients -> vertices -> dense points, and back."""
    m = with_dense(make_model())
    rng = np.random.default_rng(6)
    x = rng.normal(size=m.n_id + m.n_exp)
    split = lambda x: (x[:m.n_id], x[m.n_id:])  # noqa: E731
    jac = central_jacobian(lambda x: m.dense_points(m.shape(*split(x))[0])[0], x)
    verts, shape_ctx = m.shape(*split(x))
    _, ctx = m.dense_points(verts)
    g = rng.normal(size=(m.n_dense, 3))
    grads = m.shape_vjp(shape_ctx, m.dense_points_vjp(ctx, g)["vertices"])
    np.testing.assert_allclose(np.concatenate([grads["id_coeffs"], grads["exp_coeffs"]]),
                               jac.T @ g.reshape(-1), rtol=1e-7, atol=1e-12)


def test_dense_fields_kept_by_derived_models_and_saved(tmp_path):
    m = with_dense(make_model())
    assert (m.has_dense, m.n_dense) == (True, 7) and m.dense_faces.dtype == np.int32
    for derived in (m.truncated(n_id=2), m.with_landmarks([0], [[1.0, 0, 0]])):
        np.testing.assert_array_equal(derived.dense_faces, m.dense_faces)
        np.testing.assert_array_equal(derived.dense_use, m.dense_use)
    m.save(tmp_path / "dense.npz")
    back = load_face_model(tmp_path / "dense.npz")
    for key in ("dense_faces", "dense_bary", "dense_use"):
        np.testing.assert_array_equal(getattr(back, key), getattr(m, key), err_msg=key)
    assert back.dense_use.dtype == np.bool_


def test_model_without_dense_points_says_the_term_is_unavailable(tmp_path):
    m = make_model()
    assert (m.has_dense, m.n_dense, m.dense_faces, m.dense_use) == (False, 0, None, None)
    with pytest.raises(InputError, match="test face has no dense landmark correspondence"):
        m.dense_points(m.mean_shape)
    m.save(tmp_path / "plain.npz")
    with np.load(tmp_path / "plain.npz") as data:
        assert "dense_faces" not in data.files


def test_dense_use_defaults_to_every_point():
    m = make_model()
    m = FaceModel(**(m._fields() | {"dense_faces": [0, 3], "dense_bary": np.full((2, 3), 1 / 3)}))
    np.testing.assert_array_equal(m.dense_use, [True, True])


@pytest.mark.parametrize("changes, message", [
    ({"dense_faces": [0, 1]}, "dense_bary is missing; dense_faces and dense_bary come together"),
    ({"dense_bary": np.full((2, 3), 1 / 3)}, "dense_faces is missing"),
    ({"dense_use": np.ones(2, bool)}, "dense_use given without dense_faces and dense_bary"),
    ({"dense_faces": [0, 40], "dense_bary": np.full((2, 3), 1 / 3)},
     r"dense_faces must index faces in \[0, 40\)"),
    ({"dense_faces": [0, 1], "dense_bary": np.full((3, 3), 1 / 3)},
     r"dense_bary must have shape \(2, 3\) to match dense_faces"),
    ({"dense_faces": [0, 1], "dense_bary": np.full((2, 3), 0.5)}, "dense_bary row 0 sums to 1.5"),
    ({"dense_faces": [0, 1], "dense_bary": np.full((2, 3), 1 / 3), "dense_use": [1, 0]},
     r"dense_use must be a bool array of shape \(2,\)"),
])
def test_invalid_dense_fields_are_named(changes, message):
    with pytest.raises(ValueError, match=message):
        FaceModel(**(make_model()._fields() | changes))


def test_vertex_landmark_one_hot_row_picks_the_vertex():
    m = make_model(n_lmk=0).with_landmarks([7], [[0.0, 1.0, 0.0]])
    verts = m.mean_shape
    np.testing.assert_array_equal(m.landmarks(verts)[0][0], verts[m.faces[7, 1]])


def test_empty_expression_and_albedo_bases():
    m = make_model(k_exp=0, k_alb=0, n_lmk=0)
    shape, ctx = m.shape(np.zeros(4), np.zeros(0))
    np.testing.assert_array_equal(shape, m.mean_shape)
    grads = m.shape_vjp(ctx, np.ones((30, 3)))
    g_id, g_exp = grads["id_coeffs"], grads["exp_coeffs"]
    assert g_id.shape == (4,) and g_exp.shape == (0,)
    np.testing.assert_array_equal(m.albedo(np.zeros(0))[0], m.albedo_mean)
    assert m.landmarks(m.mean_shape)[0].shape == (0, 3)


def test_truncated_keeps_the_first_components():
    m = make_model()
    t = m.truncated(n_id=2, n_exp=0)
    assert (t.n_id, t.n_exp, t.n_albedo) == (2, 0, 2)
    np.testing.assert_array_equal(t.id_basis, m.id_basis[:2])
    np.testing.assert_array_equal(t.shape([1.0, 2.0], [])[0], m.shape([1.0, 2.0, 0, 0], [0, 0, 0])[0])
    with pytest.raises(ValueError, match=r"n_id must be in \[0, 4\]"):
        m.truncated(n_id=5)


def test_with_landmarks_replaces_them():
    m = make_model().with_landmarks(np.array([0, 1]), np.array([[1.0, 0, 0], [0.2, 0.3, 0.5]]))
    assert m.n_landmarks == 2
    np.testing.assert_array_equal(m.landmark_faces, [0, 1])


@pytest.mark.parametrize("field, value, message", [
    ("mean_shape", np.zeros((30, 2)), r"mean_shape must have shape \(V, 3\)"),
    ("id_std", np.ones(3), r"id_std must have shape \(4,\)"),
    ("exp_basis", np.zeros((3, 29, 3)), r"exp_basis must have shape \(K_exp, 30, 3\)"),
    ("albedo_mean", np.zeros((29, 3)), r"albedo_mean must have shape \(30, 3\)"),
    ("faces", np.array([[0, 1, 30]]), r"faces must index vertices in \[0, 30\)"),
    ("faces", np.zeros((4, 4), int), r"faces must have shape \(F, 3\)"),
    ("landmark_faces", np.array([0, 1, 2, 3, 40]), r"landmark_faces must index faces in \[0, 40\)"),
    ("landmark_bary", np.full((4, 3), 1 / 3), r"landmark_bary must have shape \(5, 3\)"),
    ("landmark_bary", np.full((5, 3), 0.5), "landmark_bary row 0 sums to 1.5"),
    ("id_std", -np.ones(4), "id_std must be >= 0"),
    ("mean_shape", np.full((30, 3), np.nan), "mean_shape contains NaN"),
])
def test_invalid_fields_are_named(field, value, message):
    m = make_model()
    fields = m._fields() | {field: value}
    with pytest.raises(ValueError, match=message):
        FaceModel(**fields)


def test_wrong_coefficient_and_gradient_shapes():
    m = make_model()
    with pytest.raises(ValueError, match=r"id_coeffs must have shape \(4,\)"):
        m.shape(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match=r"grad_vertices must have shape \(30, 3\)"):
        m.shape_vjp(m.shape(np.zeros(4), np.zeros(3))[1], np.zeros((29, 3)))
    with pytest.raises(ValueError, match=r"grad must have shape \(5, 3\)"):
        m.landmarks_vjp(m.landmarks(m.mean_shape)[1], np.zeros((4, 3)))


def test_save_and_load_round_trip(tmp_path):
    m = make_model()
    path = tmp_path / "face.npz"
    m.save(path)
    with np.load(path, allow_pickle=False) as data:
        assert str(data["format"]) == "softras-cl-face-1"
    back = load_face_model(path)
    for key in ("mean_shape", "id_basis", "id_std", "exp_basis", "exp_std", "albedo_mean",
                "albedo_basis", "albedo_std", "faces", "landmark_faces", "landmark_bary"):
        np.testing.assert_array_equal(getattr(back, key), getattr(m, key), err_msg=key)
    assert (back.name, back.attribution) == ("test face", "synthetic, CC0")
    assert back.faces.dtype == np.int32


def test_grid_face_fixture_faces_point_toward_plus_z():
    vertices, faces = grid_face()
    assert np.all(face_normals(vertices, faces)[:, 2] > 0)


def test_demo_face_model_loads():
    m = load_demo_face_model()
    assert isinstance(m, FaceModel) and m.n_vertices > 0 and m.attribution


def test_demo_face_model_missing_says_so(monkeypatch, tmp_path):
    from importlib import resources

    monkeypatch.setattr(resources, "files", lambda package: tmp_path)     # an empty package folder
    with pytest.raises(FileNotFoundError, match="demo_face.npz is missing"):
        load_demo_face_model()
