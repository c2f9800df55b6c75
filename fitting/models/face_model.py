"""Linear morphable face model: shape (identity + expression), albedo and landmarks.

A ``FaceModel`` holds float64 numpy arrays in one convention whatever file it came from:

- geometry in metres, model frame with y up and the face looking along +z;
- ``faces`` counter-clockwise seen from outside (the visible side), so face normals
  ``cross(v1 - v0, v2 - v0)`` point toward +z on the front of the face;
- albedo in linear RGB, nominally in [0, 1] (never clipped here);
- every coefficient in units of one standard deviation: ``shape(c_id, c_exp) = mean_shape +
  sum_k c_id[k] id_std[k] id_basis[k] + sum_k c_exp[k] exp_std[k] exp_basis[k]``, so the
  Gaussian prior of a model is simply ``sum(c ** 2)``.

Every map from coefficients is linear and comes with its exact vector-Jacobian product in the
project's convention: ``vertices, ctx = model.shape(c_id, c_exp)`` and
``model.shape_vjp(ctx, grad)`` -> a dict by argument name (likewise ``albedo`` and
``landmarks``, ``dense_points``). Bases are used through (K, 3V) views of the
(K, V, 3) arrays, with the standard deviations applied to the K-vector: the same BLAS matvec as a
pre-scaled matrix, without a second copy of bases that reach hundreds of megabytes.

Loaders for the file formats users bring (BFM 2009, BFM 2017, FLAME, the project's .npz) live in
``face_loaders``; ``load_face_model`` picks one from the file's content.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from softras_cl.checks import check_shape, index_array, nonnegative, real_array
from softras_cl.errors import InputError

FORMAT = "softras-cl-face-1"

_ARRAY_FIELDS = ("mean_shape", "id_basis", "id_std", "exp_basis", "exp_std", "albedo_mean",
                 "albedo_basis", "albedo_std", "faces", "landmark_faces", "landmark_bary")
_INT_FIELDS = ("faces", "landmark_faces")
# The optional dense correspondence (MediaPipe Face Mesh's 468 points on the demo face)
_DENSE_FIELDS = ("dense_faces", "dense_bary", "dense_use")


def _as_float(name: str, value, shape: tuple, expected: str) -> np.ndarray:
    """Contiguous finite float64 array (the array itself if it already is one), shape-checked.

    ``shape`` holds ints and None (any size); ``expected`` is the human-readable shape.
    """
    return np.ascontiguousarray(real_array(name, value, shape, expected))


def _as_index(name: str, value, shape: tuple, expected: str, upper: int, what: str) -> np.ndarray:
    """Contiguous int32 index array, shape-checked, every entry in [0, upper)."""
    return np.ascontiguousarray(index_array(name, value, upper, what, shape, expected), dtype=np.int32)


def _basis_and_std(prefix: str, basis, std, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    basis = _as_float(f"{prefix}_basis", basis, (None, n_vertices, 3), f"(K_{prefix}, {n_vertices}, 3)")
    k = basis.shape[0]
    std = _as_float(f"{prefix}_std", std, (k,), f"({k},) to match {prefix}_basis")
    return basis, nonnegative(f"{prefix}_std", std)


def _surface_map(prefix: str, faces_idx, bary, n_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Validated points on a mesh's surface: ``{prefix}_faces`` (N,) int32 triangle per point and
    ``{prefix}_bary`` (N, 3) float64 barycentric weights in it, each row summing to 1."""
    faces_idx = _as_index(f"{prefix}_faces", faces_idx, (None,), "(N,)", n_faces, "faces")
    n = faces_idx.shape[0]
    bary = _as_float(f"{prefix}_bary", bary, (n, 3), f"({n}, 3) to match {prefix}_faces")
    sums = bary.sum(axis=1)
    if n and not np.allclose(sums, 1.0, atol=1e-4):
        bad = int(np.argmax(np.abs(sums - 1.0)))
        raise ValueError(f"FaceModel: {prefix}_bary row {bad} sums to {sums[bad]:.6g}, "
                         "expected 1 (barycentric weights)")
    return faces_idx, bary


def _interpolate(bary: np.ndarray, corners: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Points (N, 3): barycentric weights bary (N, 3) of the corner vertices corners (N, 3)."""
    return np.einsum("lj,ljc->lc", bary, verts[corners])


def _interpolate_vjp(bary: np.ndarray, corners: np.ndarray, grad: np.ndarray, n_vertices: int):
    """The adjoint of _interpolate: grad (N, 3) -> dL/d(vertices) (n_vertices, 3)."""
    out = np.zeros((n_vertices, 3))
    np.add.at(out, corners.reshape(-1), (bary[:, :, None] * grad[:, None, :]).reshape(-1, 3))
    return out


def _coeffs(name: str, value, k: int) -> np.ndarray:
    """Coefficients (k,) float64 (NaN passes, for the solver to report), or ValueError naming
    ``name``."""
    return check_shape(name, np.asarray(value, dtype=np.float64), (k,))


@dataclass(frozen=True)
class LinearContext:
    """What a FaceModel vjp needs from its forward. Every map of the model is linear, so its
    adjoint needs no values from the forward: only the output's shape (rows, 3), the shape the
    cotangent must have."""
    output_shape: tuple[int, int]


class FaceModel:
    """A linear morphable face model (see the module docstring for every convention).

    Fields (float64 unless said otherwise; V vertices, F faces, L landmarks):
        mean_shape (V, 3) metres; id_basis (K_id, V, 3), id_std (K_id,);
        exp_basis (K_exp, V, 3), exp_std (K_exp,) (K_exp may be 0);
        albedo_mean (V, 3) linear RGB; albedo_basis (K_alb, V, 3), albedo_std (K_alb,) (K_alb may be 0);
        faces (F, 3) int32, counter-clockwise from outside;
        landmark_faces (L,) int32 face index per landmark; landmark_bary (L, 3) barycentric
        weights in that face (L may be 0; 68 in iBUG 300-W order when known);
        dense_faces (N,) int32, dense_bary (N, 3), dense_use (N,) bool: optional dense points
        on the surface (the demo face: MediaPipe Face Mesh's 468 points in its order) and which
        of them a fit should use; None when the model has none (``has_dense``);
        name, attribution: free text, kept through ``save``/``load_face_model``.
    Every field is validated here; a ValueError names the field and the expected shape.
    """

    def __init__(self, mean_shape, id_basis, id_std, exp_basis, exp_std, albedo_mean,
                 albedo_basis, albedo_std, faces, landmark_faces=None, landmark_bary=None,
                 name: str = "", attribution: str = "", dense_faces=None, dense_bary=None,
                 dense_use=None):
        self.mean_shape = _as_float("mean_shape", mean_shape, (None, 3), "(V, 3)")
        v = self.mean_shape.shape[0]
        if v == 0:
            raise ValueError("FaceModel: mean_shape must have at least one vertex, got shape (0, 3)")
        self.id_basis, self.id_std = _basis_and_std("id", id_basis, id_std, v)
        self.exp_basis, self.exp_std = _basis_and_std("exp", exp_basis, exp_std, v)
        self.albedo_mean = _as_float("albedo_mean", albedo_mean, (v, 3), f"({v}, 3)")
        self.albedo_basis, self.albedo_std = _basis_and_std("albedo", albedo_basis, albedo_std, v)
        self.faces = _as_index("faces", faces, (None, 3), "(F, 3)", v, "vertices")
        if self.faces.shape[0] == 0:
            raise ValueError("FaceModel: faces must have at least one triangle, got shape (0, 3)")
        if landmark_faces is None:
            landmark_faces = np.zeros(0, np.int32)
        if landmark_bary is None:
            landmark_bary = np.zeros((0, 3))
        self.landmark_faces, self.landmark_bary = _surface_map(
            "landmark", landmark_faces, landmark_bary, self.faces.shape[0])
        self._set_dense(dense_faces, dense_bary, dense_use)
        self.name, self.attribution = str(name), str(attribution)
        self._id_flat = self.id_basis.reshape(self.n_id, 3 * v)          # (K, 3V) views
        self._exp_flat = self.exp_basis.reshape(self.n_exp, 3 * v)
        self._alb_flat = self.albedo_basis.reshape(self.n_albedo, 3 * v)
        self._lmk_vertices = self.faces[self.landmark_faces]             # (L, 3) vertex indices

    # -- sizes ------------------------------------------------------------------------------
    @property
    def n_vertices(self) -> int:
        return self.mean_shape.shape[0]

    @property
    def n_id(self) -> int:
        return self.id_basis.shape[0]

    @property
    def n_exp(self) -> int:
        return self.exp_basis.shape[0]

    @property
    def n_albedo(self) -> int:
        return self.albedo_basis.shape[0]

    @property
    def n_landmarks(self) -> int:
        return self.landmark_faces.shape[0]

    def __repr__(self) -> str:
        return (f"FaceModel({self.name!r}: {self.n_vertices} vertices, {self.faces.shape[0]} faces, "
                f"id {self.n_id}, exp {self.n_exp}, albedo {self.n_albedo}, "
                f"{self.n_landmarks} landmarks)")

    # -- shape ------------------------------------------------------------------------------
    def shape(self, id_coeffs, exp_coeffs) -> tuple[np.ndarray, LinearContext]:
        """Vertices (V, 3) float64 for coefficients in standard deviations: id (K_id,), exp
        (K_exp,); and the context for shape_vjp."""
        c_id = _coeffs("id_coeffs", id_coeffs, self.n_id)
        c_exp = _coeffs("exp_coeffs", exp_coeffs, self.n_exp)
        flat = self.mean_shape.reshape(-1) + (c_id * self.id_std) @ self._id_flat
        if self.n_exp:
            flat = flat + (c_exp * self.exp_std) @ self._exp_flat
        return flat.reshape(self.n_vertices, 3), LinearContext((self.n_vertices, 3))

    def radius_bound(self, id_coeffs, exp_coeffs) -> float:
        """An upper bound (metres) on every vertex's distance from the model's origin for these
        coefficients, without computing the shape: the mean shape's farthest vertex plus, per
        component, |coefficient| x std x its farthest displacement."""
        farthest = self._farthest
        c_id = np.abs(np.asarray(id_coeffs, np.float64))
        c_exp = np.abs(np.asarray(exp_coeffs, np.float64))
        return float(farthest["mean"] + c_id @ farthest["id"] + c_exp @ farthest["exp"])

    @cached_property
    def _farthest(self) -> dict:
        """radius_bound's terms: the mean's farthest vertex, each component's std x farthest displacement."""
        def reach(basis, std):                  # (K,); (0,) for a model without the component
            return std * np.linalg.norm(basis, axis=2).max(axis=1)
        return dict(mean=float(np.linalg.norm(self.mean_shape, axis=1).max()),
                    id=reach(self.id_basis, self.id_std), exp=reach(self.exp_basis, self.exp_std))

    def shape_vjp(self, ctx: LinearContext, grad_vertices) -> dict:
        """grad_vertices (V, 3) = dL/d(vertices) -> {"id_coeffs": (K_id,), "exp_coeffs": (K_exp,)}
        float64, J^T grad."""
        g = self._cotangent("grad_vertices", grad_vertices, ctx)
        return {"id_coeffs": self.id_std * (self._id_flat @ g),
                "exp_coeffs": self.exp_std * (self._exp_flat @ g)}

    def _cotangent(self, name: str, grad, ctx: LinearContext) -> np.ndarray:
        """A cotangent of the output ctx describes, flattened to (rows * 3,) float64."""
        rows = ctx.output_shape[0]
        return _as_float(name, grad, ctx.output_shape, f"({rows}, 3)").reshape(-1)

    # -- albedo -----------------------------------------------------------------------------
    def albedo(self, coeffs) -> tuple[np.ndarray, LinearContext]:
        """Per-vertex albedo (V, 3) float64, linear RGB, not clipped, for coeffs (K_alb,) in std
        units; and the context for albedo_vjp."""
        c = _coeffs("albedo coeffs", coeffs, self.n_albedo)
        flat = self.albedo_mean.reshape(-1) + (c * self.albedo_std) @ self._alb_flat
        return flat.reshape(self.n_vertices, 3), LinearContext((self.n_vertices, 3))

    def albedo_vjp(self, ctx: LinearContext, grad) -> dict:
        """grad (V, 3) = dL/d(albedo) -> {"coeffs": (K_alb,)} float64, J^T grad."""
        return {"coeffs": self.albedo_std * (self._alb_flat @ self._cotangent("grad", grad, ctx))}

    # -- landmarks --------------------------------------------------------------------------
    def landmarks(self, vertices) -> tuple[np.ndarray, LinearContext]:
        """3D landmarks (L, 3) float64, barycentric interpolation of vertices (V, 3) in each
        face; and the context for landmarks_vjp."""
        verts = _as_float("vertices", vertices, (self.n_vertices, 3), f"({self.n_vertices}, 3)")
        points = _interpolate(self.landmark_bary, self._lmk_vertices, verts)
        return points, LinearContext((self.n_landmarks, 3))

    def landmarks_vjp(self, ctx: LinearContext, grad) -> dict:
        """grad (L, 3) = dL/d(landmarks) -> {"vertices": (V, 3)} float64, J^T grad."""
        g = self._cotangent("grad", grad, ctx).reshape(-1, 3)
        return {"vertices": _interpolate_vjp(self.landmark_bary, self._lmk_vertices, g,
                                             self.n_vertices)}

    # -- dense points -----------------------------------------------------------------------
    def _set_dense(self, dense_faces, dense_bary, dense_use) -> None:
        """Validate and store the optional dense correspondence (all None: the model has none;
        dense_use None: every point is used)."""
        if dense_faces is None and dense_bary is None:
            if dense_use is not None:
                raise ValueError("FaceModel: dense_use given without dense_faces and dense_bary")
            self.dense_faces = self.dense_bary = self.dense_use = None
            return
        if dense_faces is None or dense_bary is None:
            missing = "dense_faces" if dense_faces is None else "dense_bary"
            raise ValueError(f"FaceModel: {missing} is missing; dense_faces and dense_bary "
                             "come together")
        self.dense_faces, self.dense_bary = _surface_map("dense", dense_faces, dense_bary,
                                                         self.faces.shape[0])
        n = self.dense_faces.shape[0]
        if dense_use is None:
            dense_use = np.ones(n, bool)
        use = np.asarray(dense_use)
        if use.shape != (n,) or use.dtype != np.bool_:
            raise ValueError(f"FaceModel: dense_use must be a bool array of shape ({n},) to match "
                             f"dense_faces, got {use.dtype} {use.shape}")
        self.dense_use = np.ascontiguousarray(use)
        self._dense_vertices = self.faces[self.dense_faces]               # (N, 3) vertex indices

    @property
    def has_dense(self) -> bool:
        """Whether the model carries dense points (dense_faces / dense_bary)."""
        return self.dense_faces is not None

    @property
    def n_dense(self) -> int:
        """Number of dense points (0 without them)."""
        return self.dense_faces.shape[0] if self.has_dense else 0

    def _require_dense(self) -> None:
        if not self.has_dense:
            raise InputError(
                f"face model {self.name or '(unnamed)'} has no dense landmark correspondence "
                "(dense_faces / dense_bary): the dense landmark term needs one; the shipped demo "
                "face model has MediaPipe Face Mesh's 468 points "
                "(scripts/build_face_mesh_correspondence.py adds them to a softras-cl-face-1 file)")

    def dense_points(self, vertices) -> tuple[np.ndarray, LinearContext]:
        """3D dense points (N, 3) float64 (every point, used or not: select with dense_use) on
        vertices (V, 3); and the context for dense_points_vjp. InputError if the model has none."""
        self._require_dense()
        verts = _as_float("vertices", vertices, (self.n_vertices, 3), f"({self.n_vertices}, 3)")
        return (_interpolate(self.dense_bary, self._dense_vertices, verts),
                LinearContext((self.n_dense, 3)))

    def dense_points_vjp(self, ctx: LinearContext, grad) -> dict:
        """grad (N, 3) = dL/d(dense points) -> {"vertices": (V, 3)} float64, J^T grad."""
        self._require_dense()
        g = self._cotangent("grad", grad, ctx).reshape(-1, 3)
        return {"vertices": _interpolate_vjp(self.dense_bary, self._dense_vertices, g,
                                             self.n_vertices)}

    # -- derived models ---------------------------------------------------------------------
    def _fields(self) -> dict:
        return ({k: getattr(self, k) for k in _ARRAY_FIELDS + _DENSE_FIELDS}
                | {"name": self.name, "attribution": self.attribution})

    def truncated(self, n_id: int | None = None, n_exp: int | None = None,
                  n_albedo: int | None = None) -> "FaceModel":
        """A model keeping the first n_id / n_exp / n_albedo components (None: keep all)."""
        fields = self._fields()
        for prefix, n, total in (("id", n_id, self.n_id), ("exp", n_exp, self.n_exp),
                                 ("albedo", n_albedo, self.n_albedo)):
            if n is None:
                continue
            if not 0 <= n <= total:
                raise ValueError(f"truncated: n_{prefix} must be in [0, {total}], got {n}")
            fields[f"{prefix}_basis"] = fields[f"{prefix}_basis"][:n]
            fields[f"{prefix}_std"] = fields[f"{prefix}_std"][:n]
        return FaceModel(**fields)

    def with_landmarks(self, faces_idx, bary) -> "FaceModel":
        """The same model with landmarks faces_idx (L,) int and bary (L, 3) (rows summing to 1)."""
        return FaceModel(**(self._fields() | {"landmark_faces": faces_idx, "landmark_bary": bary}))

    # -- file -------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write the project's .npz (key 'format' = 'softras-cl-face-1' plus one key per field;
        the dense fields only when the model has them)."""
        arrays = {k: getattr(self, k) for k in _ARRAY_FIELDS}
        if self.has_dense:
            arrays |= {k: getattr(self, k) for k in _DENSE_FIELDS}
        np.savez_compressed(Path(path), format=np.str_(FORMAT), name=np.str_(self.name),
                            attribution=np.str_(self.attribution), **arrays)
