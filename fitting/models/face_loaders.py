"""Readers for the face model files users bring, and for landmark-mapping files.

Every reader returns a ``FaceModel`` in the project's convention (metres, y up, the face looking
along +z, faces counter-clockwise from outside, albedo in [0, 1], coefficients in standard
deviations). The layout is detected from the file's content, not its extension.

Format facts used (the formats' documentation and their maintainers' statements, no code):

- BFM 2009 ``01_MorphableModel.mat``: shapeMU (3V, 1), shapePC (3V, K) orthonormal columns,
  shapeEV (K, 1) standard deviations (not variances), texMU/texPC/texEV alike with colours in
  0..255, ``tl`` (F, 3) 1-based triangles, xyz interleaved per vertex. Units are micrometres
  (BFM maintainers, unibas-gravis/basel-face-model-viewer, GitHub #20). Its triangles are clockwise
  seen from the front, the opposite of the OpenGL convention, so two corners are swapped here.
  No expression model. MATLAB v7.3 files (HDF5) hold the same variables, stored transposed.
- BFM 2017/2019 ``.h5`` (statismo layout): groups shape/, color/, expression/ each with
  model/mean (3V,), model/pcaBasis (3V, K), model/pcaVariance (K,) (variances: std = sqrt),
  and representer/points (3, V), representer/cells (3, F) 0-based, counter-clockwise. Units are
  millimetres (same thread); colours in [0, 1]. statismo files of version 0.9 or 1.x store an
  orthonormal pcaBasis; version 0.8, or no ``version`` group, stores pcaBasis * sqrt(variance).
  A model instance is shape mean + shape part + expression mean + expression part.
- FLAME ``generic_model.pkl`` (Python 2 pickle with chumpy arrays): v_template (V, 3) metres,
  shapedirs (V, 3, 400): the first 300 identity, the last 100 expression directions, scaled so
  the coefficients (betas) have unit variance; f (F, 3). posedirs, J_regressor, weights and
  kintree_table (the jaw, neck and eyeball joints and the pose correctives) are ignored: this
  face model does not model pose. FLAME has no albedo: a constant grey 0.5, no basis. Its
  landmarks come from separate embedding files (see ``read_landmark_mapping``).
"""
from __future__ import annotations

import pickle
import zipfile
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from softras_cl.fitting.models.face_model import FORMAT, FaceModel
from softras_cl.fitting.models.legacy_pickle import load_legacy_pickle

if TYPE_CHECKING:        # h5py and scipy.io are imported by the readers that use them (start-up)
    import h5py

SUPPORTED_LAYOUTS = ("project .npz (FaceModel.save, key 'format' = 'softras-cl-face-1')",
                     "BFM 2009 .mat (01_MorphableModel.mat: shapeMU, shapePC, shapeEV, texMU, "
                     "texPC, texEV, tl; MATLAB v5 or v7.3)",
                     "BFM 2017/2019 .h5 (shape/, color/, expression/ statismo groups)",
                     "FLAME .pkl (generic_model.pkl: v_template, shapedirs, f)")

_BFM2009_KEYS = ("shapeMU", "shapePC", "shapeEV", "texMU", "texPC", "texEV", "tl")
_BFM2017_KEYS = ("shape/model/mean", "shape/model/pcaBasis", "shape/model/pcaVariance",
                 "shape/representer/points", "shape/representer/cells")
_FLAME_KEYS = ("v_template", "shapedirs", "f")
_FLAME_N_SHAPE = 300
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def _unknown(path: Path, found) -> ValueError:
    listed = ", ".join(sorted(str(k) for k in found)) or "nothing readable"
    return ValueError(f"{path}: unknown face model layout (found: {listed}); supported layouts: "
                      + "; ".join(SUPPORTED_LAYOUTS))


def _file_kind(path: Path) -> str:
    """'zip', 'npy', 'hdf5', 'mat5', 'pickle' or 'other', from the first bytes of the file."""
    with open(path, "rb") as f:
        head = f.read(1024)
    if head.startswith(b"PK\x03\x04"):
        return "zip"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith(_HDF5_MAGIC) or head[512:520] == _HDF5_MAGIC:  # .mat v7.3: 512-byte header
        return "hdf5"
    if head.startswith(b"MATLAB"):
        return "mat5"
    if head[:1] in (b"\x80", b"(", b"}"):  # pickle protocol >= 2, 0, 1
        return "pickle"
    return "other"


def load_face_model(path, landmarks=None) -> FaceModel:
    """Read a face model file (layout detected from its content) -> FaceModel.

    ``landmarks``: optional landmark-mapping file (``read_landmark_mapping``) that replaces the
    model's landmarks. Raises FileNotFoundError if the file is missing, ValueError naming the file
    for an unknown layout (listing what was found and the layouts supported) or a damaged file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"face model file not found: {path}")
    if landmarks is not None and not Path(landmarks).is_file():
        raise FileNotFoundError(f"landmark-mapping file not found: {landmarks}")
    readers = {"zip": _read_project_npz, "hdf5": _read_hdf5, "mat5": _read_bfm2009_mat5,
               "pickle": _read_flame}
    kind = _file_kind(path)
    if kind not in readers:
        raise _unknown(path, ["a file that is none of .npz, HDF5, MATLAB or pickle"])
    try:
        model = readers[kind](path)
    except (OSError, EOFError, KeyError, zipfile.BadZipFile, _mat_read_error()) as e:
        raise ValueError(f"{path}: damaged or truncated face model file ({type(e).__name__}: {e})") from e
    if landmarks is not None:
        faces_idx, bary = read_landmark_mapping(landmarks, model.faces, model.n_vertices)
        model = model.with_landmarks(faces_idx, bary)
    return model


# -- project .npz ------------------------------------------------------------------------------
def _read_project_npz(path: Path) -> FaceModel:
    with np.load(path, allow_pickle=False) as data:
        keys = set(data.files)
        if "format" not in keys:
            raise _unknown(path, keys)
        fmt = str(data["format"])
        if fmt != FORMAT:
            raise ValueError(f"{path}: face model format {fmt!r} is not supported (expected {FORMAT!r})")
        needed = ("mean_shape", "id_basis", "id_std", "exp_basis", "exp_std", "albedo_mean",
                  "albedo_basis", "albedo_std", "faces", "landmark_faces", "landmark_bary")
        missing = [k for k in needed if k not in keys]
        if missing:
            raise ValueError(f"{path}: {FORMAT} file lacks {', '.join(missing)}")
        fields = {k: data[k] for k in needed}
        fields |= _dense_fields(data, keys, path)
        text = {k: str(data[k]) if k in keys else "" for k in ("name", "attribution")}
    return FaceModel(**fields, **text)


def _dense_fields(data, keys: set, path: Path) -> dict:
    """The optional dense correspondence of a project .npz: dense_faces and dense_bary together
    (dense_use optional), or nothing (files written before it existed load without it)."""
    present = [k for k in ("dense_faces", "dense_bary", "dense_use") if k in keys]
    if present and not {"dense_faces", "dense_bary"} <= set(present):
        missing = sorted({"dense_faces", "dense_bary"} - set(present))
        raise ValueError(f"{path}: {FORMAT} file has {', '.join(present)} but lacks "
                         f"{', '.join(missing)} (the dense correspondence needs dense_faces and "
                         "dense_bary)")
    return {k: data[k] for k in present}


# -- BFM 2009 ----------------------------------------------------------------------------------
def _column(name: str, value, path: Path) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim != 2 or 1 not in a.shape:
        raise ValueError(f"{path}: BFM 2009 {name} must be a column vector, got shape {a.shape}")
    return a.reshape(-1)


def _bfm2009_model(v: dict, path: Path, name: str) -> FaceModel:
    """FaceModel from the BFM 2009 variables (MATLAB shapes: column vectors, (3V, K), (F, 3))."""
    mean = _column("shapeMU", v["shapeMU"], path)
    if mean.size % 3:
        raise ValueError(f"{path}: BFM 2009 shapeMU has {mean.size} entries, not 3 per vertex")
    n_v = mean.size // 3
    shape_std = _column("shapeEV", v["shapeEV"], path)
    tex_std = _column("texEV", v["texEV"], path)
    tex_mean = _column("texMU", v["texMU"], path)
    bases = {}
    for key, std in (("shapePC", shape_std), ("texPC", tex_std)):
        pc = np.asarray(v[key], dtype=np.float64)
        if pc.shape != (3 * n_v, std.size):
            raise ValueError(f"{path}: BFM 2009 {key} must have shape ({3 * n_v}, {std.size}), "
                             f"got {pc.shape}")
        bases[key] = pc.T.reshape(std.size, n_v, 3)
    if tex_mean.size != 3 * n_v:
        raise ValueError(f"{path}: BFM 2009 texMU must have {3 * n_v} entries, got {tex_mean.size}")
    tl = np.asarray(v["tl"])
    if tl.ndim != 2 or tl.shape[1] != 3:
        raise ValueError(f"{path}: BFM 2009 tl must have shape (F, 3), got {tl.shape}")
    faces = tl.astype(np.int64)[:, [0, 2, 1]] - 1  # 1-based, clockwise from the front -> CCW
    empty = np.zeros((0, n_v, 3))
    return FaceModel(mean_shape=mean.reshape(n_v, 3) * 1e-6, id_basis=bases["shapePC"],
                     id_std=shape_std * 1e-6, exp_basis=empty, exp_std=np.zeros(0),
                     albedo_mean=tex_mean.reshape(n_v, 3) / 255.0, albedo_basis=bases["texPC"],
                     albedo_std=tex_std / 255.0, faces=faces, name=name,
                     attribution="Basel Face Model 2009 (Paysan et al., AVSS 2009), University "
                                 "of Basel; used under its licence")


def _mat_read_error() -> type:
    """scipy's MatReadError; the except clause evaluating this runs only when a reader failed,
    so loading the demo model does not import scipy.io (slow)."""
    from scipy.io.matlab import MatReadError

    return MatReadError


def _read_bfm2009_mat5(path: Path) -> FaceModel:
    import scipy.io

    try:
        data = scipy.io.loadmat(path)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{path}: damaged or truncated MATLAB file ({e})") from e
    found = [k for k in data if not k.startswith("__")]
    if not all(k in data for k in _BFM2009_KEYS):
        raise _unknown(path, found)
    return _bfm2009_model(data, path, f"BFM 2009 ({path.name})")


# -- HDF5: BFM 2017 and BFM 2009 saved as MATLAB v7.3 -----------------------------------------
def _read_hdf5(path: Path) -> FaceModel:
    import h5py

    with h5py.File(path, "r") as f:
        if all(k in f for k in _BFM2017_KEYS):
            return _read_bfm2017(f, path)
        if all(k in f for k in _BFM2009_KEYS):
            # MATLAB v7.3 stores column-major arrays, which h5py sees transposed
            variables = {k: np.asarray(f[k]).T for k in _BFM2009_KEYS}
            return _bfm2009_model(variables, path, f"BFM 2009 ({path.name})")
        raise _unknown(path, list(f.keys()))


def _statismo_version(f: h5py.File, group: str) -> tuple[int, int]:
    """(major, minor) from <group>/version; statismo treats a file without one as 0.8."""
    if f"{group}/version/majorVersion" not in f:
        return 0, 8
    return int(np.asarray(f[f"{group}/version/majorVersion"])), \
        int(np.asarray(f[f"{group}/version/minorVersion"]))


def _statismo_model(f: h5py.File, group: str, n_v: int, path: Path):
    """(mean (V, 3), basis (K, V, 3) orthonormal, std (K,)) of one statismo model group."""
    mean = np.asarray(f[f"{group}/model/mean"], dtype=np.float64).reshape(-1)
    stored = np.asarray(f[f"{group}/model/pcaBasis"], dtype=np.float64)
    variance = np.asarray(f[f"{group}/model/pcaVariance"], dtype=np.float64).reshape(-1)
    if mean.size != 3 * n_v or stored.shape != (3 * n_v, variance.size):
        raise ValueError(f"{path}: {group}/model has mean {mean.shape} and pcaBasis {stored.shape}; "
                         f"expected ({3 * n_v},) and ({3 * n_v}, {variance.size}) for {n_v} vertices")
    if np.any(variance < 0):
        raise ValueError(f"{path}: {group}/model/pcaVariance has negative entries")
    std = np.sqrt(variance)
    version = _statismo_version(f, group)
    orthonormal = version[0] >= 1 or version == (0, 9)
    if not orthonormal and version != (0, 8):
        raise ValueError(f"{path}: {group} has statismo version {version[0]}.{version[1]}; "
                         "supported: 0.8, 0.9, 1.x")
    expected_norms = np.ones_like(std) if orthonormal else std
    norms = np.linalg.norm(stored, axis=0)
    if not np.allclose(norms, expected_norms, rtol=1e-2, atol=1e-6):
        bad = int(np.argmax(np.abs(norms - expected_norms)))
        raise ValueError(f"{path}: {group}/model/pcaBasis column {bad} has norm {norms[bad]:.6g}, "
                         f"but statismo version {version[0]}.{version[1]} implies "
                         f"{expected_norms[bad]:.6g}")
    basis = stored if orthonormal else stored / np.where(std > 0, std, 1.0)
    return mean.reshape(n_v, 3), basis.T.reshape(variance.size, n_v, 3), std


def _read_bfm2017(f: h5py.File, path: Path) -> FaceModel:
    points = np.asarray(f["shape/representer/points"])
    cells = np.asarray(f["shape/representer/cells"])
    if points.ndim != 2 or points.shape[0] != 3 or cells.ndim != 2 or cells.shape[0] != 3:
        raise ValueError(f"{path}: shape/representer/points and cells must have shapes (3, V) "
                         f"and (3, F), got {points.shape} and {cells.shape}")
    n_v = points.shape[1]
    mean, id_basis, id_std = _statismo_model(f, "shape", n_v, path)
    if "expression/model/pcaBasis" in f:
        exp_mean, exp_basis, exp_std = _statismo_model(f, "expression", n_v, path)
        mean = mean + exp_mean
    else:
        exp_basis, exp_std = np.zeros((0, n_v, 3)), np.zeros(0)
    if "color/model/pcaBasis" in f:
        albedo_mean, albedo_basis, albedo_std = _statismo_model(f, "color", n_v, path)
    else:
        albedo_mean, albedo_basis, albedo_std = np.full((n_v, 3), 0.5), np.zeros((0, n_v, 3)), np.zeros(0)
    return FaceModel(mean_shape=mean * 1e-3, id_basis=id_basis, id_std=id_std * 1e-3,
                     exp_basis=exp_basis, exp_std=exp_std * 1e-3, albedo_mean=albedo_mean,
                     albedo_basis=albedo_basis, albedo_std=albedo_std, faces=cells.T,
                     name=f"BFM 2017 ({path.name})",
                     attribution="Basel Face Model 2017 (Gerig et al., FG 2018), University of "
                                 "Basel; used under its licence")


# -- FLAME -------------------------------------------------------------------------------------
def _read_flame(path: Path) -> FaceModel:
    """FLAME pickle -> FaceModel: shapedirs[..., :300] identity, the rest expression (none if
    K <= 300), all with std 1; grey albedo; pose entries ignored (module docstring)."""
    data = load_legacy_pickle(path)
    if not all(k in data for k in _FLAME_KEYS):
        raise _unknown(path, data.keys())
    template = np.asarray(data["v_template"], dtype=np.float64)
    dirs = np.asarray(data["shapedirs"], dtype=np.float64)
    n_v = template.shape[0]
    if template.shape != (n_v, 3) or dirs.ndim != 3 or dirs.shape[:2] != (n_v, 3):
        raise ValueError(f"{path}: FLAME v_template must be (V, 3) and shapedirs (V, 3, K); got "
                         f"{template.shape} and {dirs.shape}")
    basis = np.moveaxis(dirs, 2, 0)  # (K, V, 3)
    n_id = min(_FLAME_N_SHAPE, basis.shape[0])
    return FaceModel(mean_shape=template, id_basis=basis[:n_id], id_std=np.ones(n_id),
                     exp_basis=basis[n_id:], exp_std=np.ones(basis.shape[0] - n_id),
                     albedo_mean=np.full((n_v, 3), 0.5), albedo_basis=np.zeros((0, n_v, 3)),
                     albedo_std=np.zeros(0), faces=np.asarray(data["f"]).astype(np.int64),
                     name=f"FLAME ({path.name})",
                     attribution="FLAME (Li, Bolkart et al., SIGGRAPH Asia 2017), Max Planck "
                                 "Institute for Intelligent Systems; used under its licence")


# -- landmark-mapping files --------------------------------------------------------------------
class _TorchStub:
    """Stand-in for any torch object in a pickle; those entries are not used."""

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        pass


class _NoTorchUnpickler(pickle.Unpickler):
    """Unpickles DECA-style .npy dicts without torch: torch objects become _TorchStub."""

    def find_class(self, module, name):
        if module.split(".")[0] == "torch":
            return _TorchStub
        if module.startswith("numpy.core"):  # numpy 2 moved numpy.core to numpy._core
            module = "numpy._core" + module[len("numpy.core"):]
        return super().find_class(module, name)


def _read_npy(path: Path):
    """Array from a .npy; a pickled object array (a dict saved with np.save) -> its object."""
    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                  else np.lib.format.read_array_header_2_0)
        _, _, dtype = header(f)
        if not dtype.hasobject:
            f.seek(0)
            return np.load(f, allow_pickle=False)
        array = _NoTorchUnpickler(f, encoding="latin1").load()
    return array.item() if isinstance(array, np.ndarray) and array.shape == () else array


def _mapping_from_dict(data, path: Path):
    for faces_key, bary_key in (("full_lmk_faces_idx", "full_lmk_bary_coords"),
                                ("lmk_face_idx", "lmk_b_coords")):
        if faces_key in data and bary_key in data:
            faces_idx = np.asarray(data[faces_key]).reshape(-1)
            bary = np.asarray(data[bary_key], dtype=np.float64)
            if bary.size != 3 * faces_idx.size:
                raise ValueError(f"landmark-mapping file {path}: {faces_key} has {faces_idx.size} "
                                 f"landmarks but {bary_key} has shape {bary.shape}")
            return faces_idx, bary.reshape(-1, 3)
    raise ValueError(f"landmark-mapping file {path}: no landmark embedding found (keys: "
                     f"{', '.join(sorted(map(str, data.keys())))}); expected full_lmk_faces_idx + "
                     "full_lmk_bary_coords or lmk_face_idx + lmk_b_coords")


def _raw_mapping(path: Path):
    """(vertex indices (L,), None) or (face indices (L,), bary (L, 3)) as stored in the file."""
    kind = _file_kind(path)
    if kind == "zip":
        with np.load(path, allow_pickle=False) as data:
            return _mapping_from_dict({k: data[k] for k in data.files}, path)
    if kind == "pickle":
        return _mapping_from_dict(load_legacy_pickle(path), path)
    if kind == "npy":
        table = _read_npy(path)
        if isinstance(table, dict):
            return _mapping_from_dict(table, path)
    else:
        if not path.read_bytes().strip():
            raise ValueError(f"landmark-mapping file {path}: no landmarks (empty file)")
        try:
            table = np.loadtxt(path, ndmin=2)
        except ValueError as e:
            raise ValueError(f"landmark-mapping file {path}: not a table of numbers ({e})") from e
    table = np.asarray(table, dtype=np.float64)
    if table.ndim == 1 or (table.ndim == 2 and table.shape[1] == 1):
        return table.reshape(-1), None
    if table.ndim == 2 and table.shape[1] == 4:
        return table[:, 0], table[:, 1:]
    raise ValueError(f"landmark-mapping file {path}: expected one vertex index per row or rows of "
                     f"'face_index b0 b1 b2', got a table of shape {table.shape}")


def _as_indices(values, upper: int, what: str, path: Path) -> np.ndarray:
    values = np.asarray(values)
    if values.size == 0:
        raise ValueError(f"landmark-mapping file {path}: no landmarks")
    if not np.all(np.isfinite(values.astype(np.float64))) or np.any(values != np.round(values)):
        raise ValueError(f"landmark-mapping file {path}: {what} indices must be integers")
    idx = values.astype(np.int64)
    bad = np.flatnonzero((idx < 0) | (idx >= upper))
    if bad.size:
        raise ValueError(f"landmark-mapping file {path}: landmark {bad[0]} has {what} index "
                         f"{idx[bad[0]]}, out of range [0, {upper})")
    return idx


def _vertex_landmarks(vertices: np.ndarray, faces: np.ndarray, path: Path):
    """Vertex landmarks as (face index, one-hot barycentric row) in the first face using them."""
    faces_idx, bary = np.zeros(len(vertices), np.int64), np.zeros((len(vertices), 3))
    for i, v in enumerate(vertices):
        hits = np.argwhere(faces == v)
        if hits.size == 0:
            raise ValueError(f"landmark-mapping file {path}: landmark {i} is vertex {v}, which "
                             "no face uses")
        faces_idx[i], bary[i, hits[0, 1]] = hits[0, 0], 1.0
    return faces_idx.astype(np.int32), bary


def read_landmark_mapping(path, faces, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Landmark definition for a mesh -> (face index (L,) int32, barycentric weights (L, 3) float64).

    Layouts (detected from content): text or .npy with L vertex indices (one per row) or L rows
    ``face_index b0 b1 b2``; FLAME's static embedding pickle (lmk_face_idx (51,), lmk_b_coords
    (51, 3)); the DECA-style .npy dict (full_lmk_faces_idx (1, 68), full_lmk_bary_coords
    (1, 68, 3); torch entries of that file are skipped without importing torch); an .npz with
    either pair of keys. Vertex landmarks become a one-hot row in the first face using the vertex.
    ``faces`` (F, 3) int and ``n_vertices`` describe the mesh. Raises ValueError naming the file
    for indices out of range, malformed tables or barycentric rows not summing to 1.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"landmark-mapping file not found: {path}")
    faces = np.asarray(faces)
    first, bary = _raw_mapping(path)
    if bary is None:
        return _vertex_landmarks(_as_indices(first, n_vertices, "vertex", path), faces, path)
    faces_idx = _as_indices(first, len(faces), "face", path)
    sums = bary.sum(axis=1)
    bad = np.flatnonzero(~np.isfinite(sums) | (np.abs(sums - 1.0) > 1e-4))
    if bad.size:
        raise ValueError(f"landmark-mapping file {path}: barycentric weights of landmark {bad[0]} "
                         f"sum to {sums[bad[0]]:.6g}, expected 1")
    return faces_idx.astype(np.int32), bary


def load_demo_face_model() -> FaceModel:
    """The demo face model shipped as package data (``softras_cl.fitting.models/data/demo_face.npz``).

    Raises FileNotFoundError if the file is not in the installed package.
    """
    ref = resources.files("softras_cl.fitting.models").joinpath("data/demo_face.npz")
    if not ref.is_file():
        raise FileNotFoundError(
            "the demo face model data/demo_face.npz is missing from the installed package "
            "softras_cl.fitting.models; it is built by the demo face model script in scripts/ "
            "(reinstall the package after building it)")
    with resources.as_file(ref) as path:
        return load_face_model(path)
