"""Small synthetic face model files written in exactly the layouts of BFM 2009, BFM 2017 and FLAME.

The geometry is a 6 x 5 grid (30 vertices) bulging toward +z, like the front of a face, with
triangles counter-clockwise seen from +z in our convention; each writer converts to its format's
units, index base and winding. Every writer returns the source arrays in the file's own layout.
"""
from __future__ import annotations

import pickle
import sys
import types

import h5py
import numpy as np
import scipy.io
import scipy.sparse

from support.legacy_files import write_chumpy_pickle

NX, NY = 6, 5
N_V = NX * NY


def grid_face() -> tuple[np.ndarray, np.ndarray]:
    """(vertices (30, 3) metres, faces (40, 3) counter-clockwise seen from +z)."""
    x, y = np.meshgrid(np.linspace(-0.08, 0.08, NX), np.linspace(-0.1, 0.1, NY))
    z = 0.05 * (1.0 - (x / 0.1) ** 2 - (y / 0.12) ** 2)
    vertices = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    faces = []
    for i in range(NY - 1):
        for j in range(NX - 1):
            a, b, c, d = i * NX + j, i * NX + j + 1, (i + 1) * NX + j + 1, (i + 1) * NX + j
            faces += [(a, b, c), (a, c, d)]
    return vertices, np.array(faces, dtype=np.int64)


def face_normals(vertices, faces) -> np.ndarray:
    v = np.asarray(vertices)[faces]
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


def _orthonormal(rng, rows: int, k: int) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(rows, k)))
    return q


def write_bfm2009(path, k_shape=4, k_tex=3, seed=0, v73=False) -> dict:
    """01_MorphableModel.mat layout: micrometres, colours 0..255, tl 1-based and clockwise."""
    rng = np.random.default_rng(seed)
    vertices, faces = grid_face()
    data = {
        "shapeMU": (vertices * 1e6).reshape(-1, 1).astype(np.float32),
        "shapePC": _orthonormal(rng, 3 * N_V, k_shape).astype(np.float32),
        "shapeEV": np.linspace(5000.0, 1000.0, k_shape).reshape(-1, 1).astype(np.float32),
        "texMU": rng.uniform(60, 200, size=(3 * N_V, 1)).astype(np.float32),
        "texPC": _orthonormal(rng, 3 * N_V, k_tex).astype(np.float32),
        "texEV": np.linspace(40.0, 10.0, k_tex).reshape(-1, 1).astype(np.float32),
        "tl": (faces[:, [0, 2, 1]] + 1).astype(np.float64),  # MATLAB doubles, clockwise
        "segbin": np.ones((N_V, 4), dtype=np.uint8),
    }
    if v73:
        _write_mat73(path, data)
    else:
        scipy.io.savemat(path, data)
    return data


def _write_mat73(path, data: dict) -> None:
    """A MATLAB v7.3 file: HDF5 after a 512-byte text header, arrays stored transposed."""
    with h5py.File(path, "w", userblock_size=512) as f:
        for key, value in data.items():
            f.create_dataset(key, data=np.asarray(value).T)
    with open(path, "r+b") as f:
        f.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 "
                b"schema 1.00 .".ljust(116))


def _statismo(f: h5py.File, group: str, mean, basis, variance, version) -> None:
    f.create_dataset(f"{group}/model/mean", data=mean.astype(np.float32))
    f.create_dataset(f"{group}/model/pcaBasis", data=basis.astype(np.float32))
    f.create_dataset(f"{group}/model/pcaVariance", data=variance.astype(np.float32))
    f.create_dataset(f"{group}/model/noiseVariance", data=np.float32(0.0))
    if version is not None:
        f.create_dataset(f"{group}/version/majorVersion", data=np.int32(version[0]))
        f.create_dataset(f"{group}/version/minorVersion", data=np.int32(version[1]))


def write_bfm2017(path, k_shape=4, k_exp=3, k_col=2, seed=0, version=(0, 9), expression=True,
                  scaled_basis=None) -> dict:
    """BFM 2017 .h5 layout: millimetres, pcaVariance, cells (3, F) 0-based counter-clockwise.

    version None writes no version group (statismo then means 0.8). The pcaBasis stored is
    orthonormal (U) unless scaled_basis (default: version is 0.8 or None) stores U * sqrt(var).
    """
    rng = np.random.default_rng(seed)
    vertices, faces = grid_face()
    scaled = version in (None, (0, 8)) if scaled_basis is None else scaled_basis
    src = {"points": (vertices * 1e3).T, "cells": faces.T.astype(np.int32)}
    with h5py.File(path, "w") as f:
        f.create_dataset("shape/representer/points", data=src["points"].astype(np.float32))
        f.create_dataset("shape/representer/cells", data=src["cells"])
        groups = [("shape", k_shape, 30.0, (vertices * 1e3).reshape(-1)),
                  ("color", k_col, 0.01, rng.uniform(0.2, 0.8, 3 * N_V))]
        if expression:
            groups.append(("expression", k_exp, 10.0, rng.normal(0, 0.5, 3 * N_V)))
        for group, k, var0, mean in groups:
            u = _orthonormal(rng, 3 * N_V, k)
            variance = var0 * np.linspace(1.0, 0.2, k)
            stored = u * np.sqrt(variance) if scaled else u
            _statismo(f, group, mean, stored, variance, version)
            src[group] = {"mean": mean.astype(np.float32).astype(np.float64),
                          "U": u.astype(np.float32).astype(np.float64),
                          "variance": variance.astype(np.float32).astype(np.float64)}
    return src


def write_flame(path, k_shape=300, k_exp=100, seed=0) -> dict:
    """FLAME generic_model.pkl layout: chumpy arrays, a CSC J_regressor, metres."""
    rng = np.random.default_rng(seed)
    vertices, faces = grid_face()
    entries = {
        "v_template": vertices,
        "shapedirs": rng.normal(0, 1e-3, size=(N_V, 3, k_shape + k_exp)),
        "posedirs": rng.normal(0, 1e-3, size=(N_V, 3, 36)),
        "J_regressor": scipy.sparse.csc_matrix(rng.uniform(size=(5, N_V)) * (rng.uniform(size=(5, N_V)) > 0.7)),
        "weights": rng.uniform(size=(N_V, 5)),
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
        "f": faces.astype(np.uint32),
        "bs_type": "lrotmin",
        "bs_style": "lbs",
    }
    write_chumpy_pickle(path, entries, chumpy_keys=("v_template", "shapedirs", "posedirs", "weights"))
    return entries


class _FakeTensor:
    """Pickles under the class name torch.Tensor, like the torch entries of DECA's .npy."""

    def __init__(self, values):
        self.values = values


def write_deca_embedding(path, faces_idx, bary) -> None:
    """DECA-style landmark_embedding.npy: a dict saved with np.save, including torch tensors."""
    module = types.ModuleType("torch")
    _FakeTensor.__module__, _FakeTensor.__qualname__ = "torch", "Tensor"
    module.Tensor = _FakeTensor
    saved = sys.modules.get("torch")
    sys.modules["torch"] = module
    try:
        data = {"static_lmk_faces_idx": np.asarray(faces_idx[17:]),
                "static_lmk_bary_coords": np.asarray(bary[17:]),
                "dynamic_lmk_faces_idx": _FakeTensor([1, 2, 3]),
                "dynamic_lmk_bary_coords": _FakeTensor([0.5]),
                "full_lmk_faces_idx": np.asarray(faces_idx)[None],
                "full_lmk_bary_coords": np.asarray(bary)[None]}
        np.save(path, data, allow_pickle=True)
    finally:
        if saved is None:
            sys.modules.pop("torch", None)
        else:
            sys.modules["torch"] = saved


def write_flame_static_embedding(path, faces_idx, bary) -> None:
    """flame_static_embedding.pkl: a Python 2 pickle of a dict with lmk_face_idx, lmk_b_coords."""
    with open(path, "wb") as f:
        pickle.dump({"lmk_face_idx": np.asarray(faces_idx, dtype=np.int64),
                     "lmk_b_coords": np.asarray(bary)}, f, protocol=2)
