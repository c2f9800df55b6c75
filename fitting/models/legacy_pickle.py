"""Read Python 2 model pickles (SMPL, FLAME) without chumpy or old scipy.

The published SMPL and FLAME ``.pkl`` files were written by Python 2 with chumpy ``Ch`` arrays
and ``scipy.sparse.csc_matrix`` regressors. Unpickling them normally needs chumpy installed
(it does not install on current Python/numpy) and a scipy that still has the old module paths.
Here chumpy and scipy.sparse classes are replaced by small stand-ins while unpickling, and then
turned into numpy arrays / scipy.sparse matrices: a chumpy leaf keeps its value in ``x``.
"""
from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np


class _Stub:
    """Stand-in for a class we must not import: keeps the pickled state for later conversion."""

    qualname = "?"

    def __init__(self, *args, **kwargs):
        self.args = args

    def __setstate__(self, state):
        self.state = state


_NUMPY_2 = int(np.__version__.split(".")[0]) >= 2


def _stub_class(module: str, name: str) -> type:
    return type(name, (_Stub,), {"qualname": f"{module}.{name}"})


class _LegacyUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if module.split(".")[0] == "chumpy" or module.startswith("scipy.sparse"):
            return _stub_class(module, name)
        if module.startswith("numpy.core") and _NUMPY_2:  # numpy 2 moved numpy.core to numpy._core
            module = "numpy._core" + module[len("numpy.core"):]
        return super().find_class(module, name)


def _convert(key: str, value, path: Path):
    if not isinstance(value, _Stub):
        return value
    state = getattr(value, "state", None)
    if not isinstance(state, dict):
        raise ValueError(f"{path}: entry {key!r} is a {value.qualname} without a readable state")
    if value.qualname.startswith("scipy.sparse"):
        shape = state.get("_shape", state.get("shape"))
        fmt = value.qualname.rsplit(".", 1)[-1][:3]
        if fmt not in ("csc", "csr") or shape is None:
            raise ValueError(f"{path}: entry {key!r} is a {value.qualname}; only CSC/CSR "
                             "sparse matrices are supported")
        import scipy.sparse     # here, not at the top: loading a model without one stays fast

        cls = scipy.sparse.csc_matrix if fmt == "csc" else scipy.sparse.csr_matrix
        return cls((state["data"], state["indices"], state["indptr"]), shape=tuple(shape))
    if "x" in state:  # a chumpy leaf (Ch): its value
        return np.asarray(state["x"])
    raise ValueError(f"{path}: entry {key!r} is a chumpy expression ({value.qualname}) that "
                     "cannot be evaluated without chumpy; save the model with plain arrays")


def load_legacy_pickle(path) -> dict:
    """Load a Python 2 (or 3) model pickle whose top level is a dict.

    Returns a dict with the same keys: chumpy arrays become numpy arrays, sparse matrices become
    ``scipy.sparse.csc_matrix``/``csr_matrix``, other values are returned as unpickled (byte
    strings from Python 2 are decoded as latin-1). Raises ValueError naming the file if it is not
    such a pickle.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = _LegacyUnpickler(f, encoding="latin1").load()
    except (pickle.UnpicklingError, EOFError, ImportError, AttributeError, TypeError) as e:
        raise ValueError(f"{path}: not a readable model pickle ({e})") from e
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a pickled dict of model arrays, got {type(data).__name__}")
    return {k: _convert(k, v, path) for k, v in data.items()}
