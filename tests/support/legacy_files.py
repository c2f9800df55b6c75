"""Write pickles the way Python 2-era SMPL/FLAME files were written: chumpy ``Ch`` arrays and
scipy sparse matrices, without chumpy installed (a stand-in module named ``chumpy.ch``)."""
from __future__ import annotations

import pickle
import sys
import types

import numpy as np


class _Ch:
    """Pickles like chumpy.ch.Ch: class chumpy.ch.Ch, state = its __dict__ holding 'x'."""

    def __init__(self, x):
        self.x = np.asarray(x)
        self.dterms = ["x"]


def write_chumpy_pickle(path, entries: dict, chumpy_keys=()) -> None:
    """Pickle ``entries`` (protocol 2) with the arrays named in ``chumpy_keys`` as chumpy Ch."""
    module = types.ModuleType("chumpy.ch")
    _Ch.__module__, _Ch.__qualname__ = "chumpy.ch", "Ch"
    module.Ch = _Ch
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch")}
    sys.modules["chumpy"] = types.ModuleType("chumpy")
    sys.modules["chumpy.ch"] = module
    try:
        data = {k: (_Ch(v) if k in chumpy_keys else v) for k, v in entries.items()}
        with open(path, "wb") as f:
            pickle.dump(data, f, protocol=2)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
