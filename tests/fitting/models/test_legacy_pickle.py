import pickle

import numpy as np
import pytest
import scipy.sparse

from support.legacy_files import write_chumpy_pickle
from softras_cl.fitting.models.legacy_pickle import load_legacy_pickle


def test_chumpy_arrays_and_sparse_matrices_come_back_as_numpy_and_scipy(tmp_path):
    rng = np.random.default_rng(0)
    shapedirs = rng.normal(size=(5, 3, 2))
    regressor = scipy.sparse.random(4, 5, density=0.5, format="csc", random_state=1)
    path = tmp_path / "model.pkl"
    write_chumpy_pickle(path, {"shapedirs": shapedirs, "J_regressor": regressor,
                               "f": np.arange(6, dtype=np.uint32).reshape(2, 3), "name": "m"},
                        chumpy_keys=("shapedirs",))
    loaded = load_legacy_pickle(path)
    np.testing.assert_array_equal(loaded["shapedirs"], shapedirs)
    assert scipy.sparse.issparse(loaded["J_regressor"])
    np.testing.assert_array_equal(loaded["J_regressor"].toarray(), regressor.toarray())
    np.testing.assert_array_equal(loaded["f"], np.arange(6).reshape(2, 3))
    assert loaded["name"] == "m"


def test_not_a_pickle_names_the_file(tmp_path):
    path = tmp_path / "junk.pkl"
    path.write_bytes(b"not a pickle at all")
    with pytest.raises(ValueError, match="junk.pkl"):
        load_legacy_pickle(path)


def test_pickle_that_is_not_a_dict_is_refused(tmp_path):
    path = tmp_path / "list.pkl"
    path.write_bytes(pickle.dumps([1, 2, 3]))
    with pytest.raises(ValueError, match="expected a pickled dict"):
        load_legacy_pickle(path)
