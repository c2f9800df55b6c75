"""load_body_model on small synthetic files in exactly SMPL's layouts, and on bad files."""
import pickle

import numpy as np
import pytest
import scipy.sparse
from support.legacy_files import write_chumpy_pickle
from softras_cl.fitting.models.body_loaders import SMPL_JOINT_NAMES, load_body_model
from test_body_model import random_model, random_params


def smpl_entries(model, root=2**32 - 1) -> dict:
    """SMPL's keys for ``model`` as the published .pkl holds them (uint32 kintree_table whose
    root parent is 2**32 - 1, csc J_regressor, extra keys SMPL files carry)."""
    parents = model.parents.copy()
    parents[0] = root
    return {"v_template": model.v_template, "shapedirs": model.shapedirs,
            "posedirs": model.posedirs,
            "J_regressor": scipy.sparse.csc_matrix(model.J_regressor),
            "kintree_table": np.stack([parents, np.arange(model.n_joints)]).astype(np.uint32),
            "weights": model.weights, "f": model.faces.astype(np.uint32),
            "J": model.rest_joints(np.zeros(model.n_betas)), "bs_type": "lrotmin",
            "bs_style": "lbs"}


def assert_same_pose(a, b):
    p = random_params()
    np.testing.assert_allclose(a.forward(**p)[0].vertices, b.forward(**p)[0].vertices, atol=1e-12)
    np.testing.assert_allclose(a.forward(**p)[0].joints, b.forward(**p)[0].joints, atol=1e-12)


def test_smpl_pickle_with_chumpy_arrays(tmp_path):
    model = random_model()
    path = tmp_path / "basicModel_neutral.pkl"
    write_chumpy_pickle(path, smpl_entries(model), chumpy_keys=("shapedirs", "v_template"))
    loaded = load_body_model(path)
    np.testing.assert_array_equal(loaded.parents, model.parents)
    assert loaded.faces.dtype == np.int32
    assert_same_pose(loaded, model)


def test_smpl_npz_by_content_not_extension(tmp_path):
    model = random_model(sparse=False)
    entries = smpl_entries(model, root=-1)
    entries["J_regressor"] = entries["J_regressor"].toarray()
    entries["kintree_table"] = entries["kintree_table"].astype(np.int64)
    entries["kintree_table"][0, 0] = -1
    del entries["bs_type"], entries["bs_style"]
    path = tmp_path / "smpl_converted.bin"
    with open(path, "wb") as f:
        np.savez(f, **entries)
    loaded = load_body_model(path)
    assert loaded.n_joints == 5 and loaded.joint_names[0] == "joint_0"
    assert_same_pose(loaded, model)


def test_smpl_without_posedirs_and_smpl_joint_names(tmp_path):
    """24 joints get SMPL's joint names; posedirs may be absent."""
    rng = np.random.default_rng(0)
    n_verts, n_joints = 30, 24
    parents = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17,
                        18, 19, 20, 21])
    weights = rng.random((n_verts, n_joints))
    entries = {"v_template": rng.normal(size=(n_verts, 3)),
               "shapedirs": rng.normal(size=(n_verts, 3, 2)),
               "J_regressor": scipy.sparse.csc_matrix(rng.random((n_joints, n_verts))),
               "kintree_table": np.stack([parents, np.arange(n_joints)]),
               "weights": weights / weights.sum(1, keepdims=True),
               "f": rng.integers(0, n_verts, (10, 3))}
    path = tmp_path / "m.pkl"
    write_chumpy_pickle(path, entries, chumpy_keys=("shapedirs",))
    loaded = load_body_model(path)
    assert loaded.posedirs is None and loaded.joint_names == list(SMPL_JOINT_NAMES)


def test_truncated_files(tmp_path):
    model = random_model()
    pkl, npz = tmp_path / "m.pkl", tmp_path / "m.npz"
    write_chumpy_pickle(pkl, smpl_entries(model), chumpy_keys=("shapedirs",))
    model.save(npz)
    for path in (pkl, npz):
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        with pytest.raises(ValueError, match=str(path.name)):
            load_body_model(path)


def test_wrong_keys_lists_keys_and_layouts(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, vertices=np.zeros((3, 3)), faces=np.zeros((1, 3), int))
    with pytest.raises(ValueError, match=r"keys found: \['faces', 'vertices'\].*SMPL's.*"
                                         r"project's"):
        load_body_model(path)
    pkl = tmp_path / "other.pkl"
    with open(pkl, "wb") as f:
        pickle.dump({"v_template": np.zeros((3, 3))}, f, protocol=2)
    with pytest.raises(ValueError, match="unknown body model layout"):
        load_body_model(pkl)


def test_project_file_missing_key_and_bad_format(tmp_path):
    model = random_model()
    model.save(tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz") as z:
        entries = dict(z)
    del entries["weights"]
    np.savez(tmp_path / "missing.npz", **entries)
    with pytest.raises(ValueError, match=r"needs keys \['weights'\]"):
        load_body_model(tmp_path / "missing.npz")
    np.savez(tmp_path / "future.npz", **{**entries, "format": np.array("softras-cl-body-9")})
    with pytest.raises(ValueError, match="unknown body model format"):
        load_body_model(tmp_path / "future.npz")


def test_kintree_and_weights_size_mismatch(tmp_path):
    model = random_model()
    entries = smpl_entries(model)
    entries["kintree_table"] = entries["kintree_table"][:, :4]
    write_chumpy_pickle(tmp_path / "a.pkl", entries, chumpy_keys=("shapedirs",))
    with pytest.raises(ValueError, match=r"a.pkl: weights must have shape \(V, 4\) to match "
                                         "kintree_table's 4 joints"):
        load_body_model(tmp_path / "a.pkl")
    entries = smpl_entries(model)
    entries["kintree_table"] = entries["kintree_table"][::-1]
    write_chumpy_pickle(tmp_path / "b.pkl", entries, chumpy_keys=("shapedirs",))
    with pytest.raises(ValueError, match="kintree_table row 1 must list the joints"):
        load_body_model(tmp_path / "b.pkl")
    entries = smpl_entries(model)
    entries["J_regressor"] = entries["J_regressor"][:, :-1]
    write_chumpy_pickle(tmp_path / "c.pkl", entries, chumpy_keys=("shapedirs",))
    with pytest.raises(ValueError, match=r"J_regressor must have shape \(5, 40\)"):
        load_body_model(tmp_path / "c.pkl")
