import pickle
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

from support.face_files import (N_V, face_normals, grid_face, write_bfm2009, write_bfm2017,
                        write_deca_embedding, write_flame, write_flame_static_embedding)
from softras_cl.fitting.models.face_loaders import read_landmark_mapping
from softras_cl.fitting.models.face_loaders import load_face_model

DEMO = Path(__file__).resolve().parents[3] / "fitting" / "models" / "data" / "demo_face.npz"


def one_std(model, prefix):
    """(K, V, 3): one standard deviation of each component, as the model defines it."""
    return getattr(model, f"{prefix}_basis") * getattr(model, f"{prefix}_std")[:, None, None]


def assert_front_faces_toward_plus_z(model):
    assert np.all(face_normals(model.mean_shape, model.faces)[:, 2] > 0)


# -- BFM 2009 ------------------------------------------------------------------------------------
@pytest.mark.parametrize("v73", [False, True], ids=["mat-v5", "mat-v7.3"])
def test_bfm2009_units_colors_and_winding(tmp_path, v73):
    path = tmp_path / "01_MorphableModel.mat"
    src = {k: np.asarray(v, dtype=np.float64) for k, v in write_bfm2009(path, v73=v73).items()}
    m = load_face_model(path)
    vertices, faces = grid_face()
    np.testing.assert_allclose(m.mean_shape, src["shapeMU"].reshape(-1, 3) * 1e-6, rtol=1e-12)
    np.testing.assert_allclose(m.mean_shape, vertices, atol=1e-7)  # micrometres -> metres
    expected = (src["shapePC"] * src["shapeEV"].reshape(-1) * 1e-6).T.reshape(4, N_V, 3)
    np.testing.assert_allclose(one_std(m, "id"), expected, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(m.albedo_mean, src["texMU"].reshape(-1, 3) / 255.0, rtol=1e-12)
    tex = (src["texPC"] * src["texEV"].reshape(-1) / 255.0).T.reshape(3, N_V, 3)
    np.testing.assert_allclose(one_std(m, "albedo"), tex, rtol=1e-12, atol=1e-20)
    np.testing.assert_array_equal(m.faces, faces)  # 1-based clockwise -> 0-based CCW
    assert_front_faces_toward_plus_z(m)
    assert (m.n_exp, m.n_landmarks, m.n_dense) == (0, 0, 0)
    assert "Basel Face Model 2009" in m.attribution


def test_bfm2009_detected_by_content_not_extension(tmp_path):
    path = tmp_path / "model.bin"
    write_bfm2009(path)
    assert load_face_model(path).n_id == 4


def test_bfm2009_inconsistent_shapes_are_named(tmp_path):
    path = tmp_path / "bad.mat"
    src = write_bfm2009(path)
    src["shapePC"] = src["shapePC"][:-3]
    scipy.io.savemat(path, src)
    with pytest.raises(ValueError, match=r"shapePC must have shape \(90, 4\)"):
        load_face_model(path)


# -- BFM 2017 ------------------------------------------------------------------------------------
def test_bfm2017_units_variances_and_expression_mean(tmp_path):
    path = tmp_path / "model2017-1_face12_nomouth.h5"
    src = write_bfm2017(path)
    m = load_face_model(path)
    expected_mean = (src["shape"]["mean"] + src["expression"]["mean"]).reshape(-1, 3) * 1e-3
    np.testing.assert_allclose(m.mean_shape, expected_mean, rtol=1e-12)
    for prefix, group, scale in (("id", "shape", 1e-3), ("exp", "expression", 1e-3), ("albedo", "color", 1.0)):
        g = src[group]
        expected = (g["U"] * np.sqrt(g["variance"]) * scale).T.reshape(-1, N_V, 3)
        np.testing.assert_allclose(one_std(m, prefix), expected, rtol=1e-6, atol=1e-12, err_msg=prefix)
    np.testing.assert_allclose(m.albedo_mean, src["color"]["mean"].reshape(-1, 3), rtol=1e-12)
    np.testing.assert_array_equal(m.faces, src["cells"].T)
    assert (m.n_id, m.n_exp, m.n_albedo) == (4, 3, 2)
    assert_front_faces_toward_plus_z(m)


@pytest.mark.parametrize("version", [(0, 8), None], ids=["v0.8", "no-version"])
def test_bfm2017_old_statismo_scaled_basis_gives_the_same_model(tmp_path, version):
    new, old = tmp_path / "new.h5", tmp_path / "old.h5"
    write_bfm2017(new, version=(0, 9))
    write_bfm2017(old, version=version)
    a, b = load_face_model(new), load_face_model(old)
    for prefix in ("id", "exp", "albedo"):
        np.testing.assert_allclose(one_std(b, prefix), one_std(a, prefix), rtol=1e-5, atol=1e-12)
        np.testing.assert_allclose(getattr(b, f"{prefix}_std"), getattr(a, f"{prefix}_std"), rtol=1e-12)


def test_bfm2017_basis_that_contradicts_its_version_is_refused(tmp_path):
    path = tmp_path / "mislabelled.h5"
    write_bfm2017(path, version=(0, 9), scaled_basis=True)
    with pytest.raises(ValueError, match="pcaBasis column 0 has norm .* version 0.9 implies 1"):
        load_face_model(path)


def test_bfm2017_without_expression_group(tmp_path):
    path = tmp_path / "noexp.h5"
    src = write_bfm2017(path, expression=False)
    m = load_face_model(path)
    assert m.n_exp == 0
    np.testing.assert_allclose(m.mean_shape, src["shape"]["mean"].reshape(-1, 3) * 1e-3, rtol=1e-12)


# -- FLAME ---------------------------------------------------------------------------------------
def test_flame_splits_300_shape_100_expression_unit_std(tmp_path):
    path = tmp_path / "generic_model.pkl"
    src = write_flame(path)
    m = load_face_model(path)
    np.testing.assert_array_equal(m.mean_shape, src["v_template"])
    assert (m.n_id, m.n_exp, m.n_albedo, m.n_landmarks, m.n_dense) == (300, 100, 0, 0, 0)
    np.testing.assert_array_equal(m.id_std, np.ones(300))
    np.testing.assert_array_equal(m.exp_std, np.ones(100))
    np.testing.assert_array_equal(m.id_basis[7], src["shapedirs"][:, :, 7])
    np.testing.assert_array_equal(m.exp_basis[3], src["shapedirs"][:, :, 303])
    rng = np.random.default_rng(0)
    betas = rng.normal(size=400)
    np.testing.assert_allclose(m.shape(betas[:300], betas[300:])[0],
                               src["v_template"] + src["shapedirs"] @ betas, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(m.albedo_mean, 0.5)
    np.testing.assert_array_equal(m.faces, src["f"])
    assert_front_faces_toward_plus_z(m)
    assert "FLAME" in m.attribution


# -- unknown layouts and damaged files -----------------------------------------------------------
def test_npz_with_other_keys_lists_them(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, vertices=np.zeros((3, 3)), triangles=np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"unknown face model layout \(found: triangles, vertices\).*BFM 2017"):
        load_face_model(path)


def test_mat_with_other_variables_lists_them(tmp_path):
    path = tmp_path / "other.mat"
    scipy.io.savemat(path, {"meshV": np.zeros((3, 3)), "meshF": np.ones((1, 3))})
    with pytest.raises(ValueError, match=r"unknown face model layout \(found: meshF, meshV\)"):
        load_face_model(path)


def test_h5_with_other_groups_lists_them(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("points", data=np.zeros((3, 3)))
        f.create_group("meta")
    with pytest.raises(ValueError, match=r"unknown face model layout \(found: meta, points\)"):
        load_face_model(path)


def test_pickle_with_other_keys_lists_them(tmp_path):
    path = tmp_path / "other.pkl"
    path.write_bytes(pickle.dumps({"verts": np.zeros(3)}, protocol=2))
    with pytest.raises(ValueError, match=r"unknown face model layout \(found: verts\)"):
        load_face_model(path)


@pytest.mark.parametrize("writer, name", [
    (lambda p: write_bfm2009(p), "a.mat"),
    (lambda p: write_bfm2017(p), "a.h5"),
    (lambda p: write_flame(p, k_shape=4, k_exp=2), "a.pkl"),
])
def test_truncated_files_give_a_clear_error(tmp_path, writer, name):
    path = tmp_path / name
    writer(path)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"a\.(mat|h5|pkl)"):
        load_face_model(path)


def test_truncated_project_npz(tmp_path):
    from test_face_model import make_model
    path = tmp_path / "face.npz"
    make_model().save(path)
    path.write_bytes(path.read_bytes()[:-200])
    with pytest.raises(ValueError, match="damaged or truncated"):
        load_face_model(path)


def test_project_npz_of_another_version(tmp_path):
    path = tmp_path / "face.npz"
    np.savez(path, format=np.str_("softras-cl-face-9"))
    with pytest.raises(ValueError, match="'softras-cl-face-9' is not supported"):
        load_face_model(path)


def test_project_npz_written_before_the_dense_fields_loads_without_them(tmp_path):
    """The demo file with its dense (Face Mesh) arrays taken out, as files written before they
    existed: every other field loads the same, the dense term is unavailable."""
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    demo = load_demo_face_model()
    with np.load(DEMO) as data:
        old = {k: data[k] for k in data.files if not k.startswith("dense_")}
    np.savez_compressed(tmp_path / "old.npz", **old)
    model = load_face_model(tmp_path / "old.npz")
    assert not model.has_dense and model.n_dense == 0
    for key in ("mean_shape", "id_basis", "exp_basis", "albedo_mean", "faces", "landmark_bary"):
        np.testing.assert_array_equal(getattr(model, key), getattr(demo, key), err_msg=key)


def test_project_npz_with_half_a_dense_correspondence(tmp_path):
    from test_face_model import make_model
    path = tmp_path / "half.npz"
    make_model().save(path)
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    np.savez(path, **arrays, dense_faces=np.zeros(3, np.int32), dense_use=np.ones(3, bool))
    with pytest.raises(ValueError, match=r"half.npz: softras-cl-face-1 file has dense_faces, "
                                         r"dense_use but lacks dense_bary"):
        load_face_model(path)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.mat"):
        load_face_model(tmp_path / "nope.mat")


# -- landmark mappings ---------------------------------------------------------------------------
FACES_IDX = np.array([0, 5, 17, 33, 39])
BARY = np.array([[0.2, 0.3, 0.5], [1, 0, 0], [0.1, 0.1, 0.8], [0.6, 0.2, 0.2], [1 / 3, 1 / 3, 1 / 3]])


def test_landmarks_from_face_bary_text_rows(tmp_path):
    mat = tmp_path / "m.mat"
    write_bfm2009(mat)
    lmk = tmp_path / "bfm_68.txt"
    np.savetxt(lmk, np.column_stack([FACES_IDX, BARY]))
    m = load_face_model(mat, landmarks=lmk)
    np.testing.assert_array_equal(m.landmark_faces, FACES_IDX)
    np.testing.assert_allclose(m.landmark_bary, BARY)
    tri = m.mean_shape[m.faces[FACES_IDX]]
    np.testing.assert_allclose(m.landmarks(m.mean_shape)[0], np.einsum("lj,ljc->lc", BARY, tri))


@pytest.mark.parametrize("suffix", [".txt", ".npy"])
def test_vertex_index_landmarks(tmp_path, suffix):
    _, faces = grid_face()
    path = tmp_path / f"vertices{suffix}"
    idx = np.array([0, 7, 29, 14])
    if suffix == ".npy":
        np.save(path, idx)
    else:
        path.write_text("\n".join(map(str, idx)) + "\n")
    faces_idx, bary = read_landmark_mapping(path, faces, N_V)
    assert faces_idx.dtype == np.int32
    np.testing.assert_array_equal(faces[faces_idx, np.argmax(bary, axis=1)], idx)
    np.testing.assert_array_equal(bary.sum(axis=1), 1.0)
    assert set(np.unique(bary)) == {0.0, 1.0}


def test_flame_static_embedding_pickle(tmp_path):
    flame = tmp_path / "generic_model.pkl"
    write_flame(flame, k_shape=4, k_exp=2)
    emb = tmp_path / "flame_static_embedding.pkl"
    write_flame_static_embedding(emb, FACES_IDX, BARY)
    m = load_face_model(flame, landmarks=emb)
    np.testing.assert_array_equal(m.landmark_faces, FACES_IDX)
    np.testing.assert_allclose(m.landmark_bary, BARY)


def test_deca_npy_dict_without_torch(tmp_path):
    _, faces = grid_face()
    idx = np.resize(FACES_IDX, 68)
    bary = np.resize(BARY, (68, 3))
    path = tmp_path / "landmark_embedding.npy"
    write_deca_embedding(path, idx, bary)
    faces_idx, b = read_landmark_mapping(path, faces, N_V)
    np.testing.assert_array_equal(faces_idx, idx)
    np.testing.assert_allclose(b, bary)


def test_npz_embedding(tmp_path):
    _, faces = grid_face()
    path = tmp_path / "emb.npz"
    np.savez(path, lmk_face_idx=FACES_IDX, lmk_b_coords=BARY)
    faces_idx, b = read_landmark_mapping(path, faces, N_V)
    np.testing.assert_array_equal(faces_idx, FACES_IDX)


@pytest.mark.parametrize("content, message", [
    ("0\n7\n30\n", r"landmark 2 has vertex index 30, out of range \[0, 30\)"),
    ("40 1 0 0\n", r"landmark 0 has face index 40, out of range \[0, 40\)"),
    ("3 0.5 0.5 0.5\n", "barycentric weights of landmark 0 sum to 1.5"),
    ("1 1 0\n2 0 1\n", r"got a table of shape \(2, 3\)"),
    ("1 0.5 0.5 0\n2 1\n", "not a table of numbers"),
    ("2.5\n", "vertex indices must be integers"),
    ("", "no landmarks"),
    ("eye left\n", "not a table of numbers"),
])
def test_bad_mapping_files_name_file_and_problem(tmp_path, content, message):
    _, faces = grid_face()
    path = tmp_path / "map.txt"
    path.write_text(content)
    with pytest.raises(ValueError, match=f"map.txt.*{message}"):
        read_landmark_mapping(path, faces, N_V)


def test_unused_vertex_landmark(tmp_path):
    _, faces = grid_face()
    path = tmp_path / "map.txt"
    path.write_text("3\n")
    with pytest.raises(ValueError, match="landmark 0 is vertex 3, which no face uses"):
        read_landmark_mapping(path, faces[np.all(faces != 3, axis=1)], N_V)


def test_embedding_with_mismatched_counts_or_unknown_keys(tmp_path):
    _, faces = grid_face()
    path = tmp_path / "emb.npz"
    np.savez(path, lmk_face_idx=FACES_IDX, lmk_b_coords=BARY[:4])
    with pytest.raises(ValueError, match=r"lmk_face_idx has 5 landmarks but lmk_b_coords has shape \(4, 3\)"):
        read_landmark_mapping(path, faces, N_V)
    np.savez(path, landmark_indices=FACES_IDX)
    with pytest.raises(ValueError, match="no landmark embedding found.*landmark_indices"):
        read_landmark_mapping(path, faces, N_V)


def test_loading_the_demo_model_imports_neither_h5py_nor_scipy_io_nor_sparse():
    """Their imports are slow and only the BFM readers (and sparse regressors of legacy
    pickles) need them (fit-face's start-up)."""
    import subprocess
    import sys

    code = ("import sys; from softras_cl.fitting.models.face_loaders import load_demo_face_model; "
            "load_demo_face_model(); print(sorted(m for m in ('h5py', 'scipy.io', 'scipy.sparse') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
