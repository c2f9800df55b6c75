"""The face fit's landmark term on the OpenCL device, the sliding jaw contour included.

Mirrors FaceObjective.landmark_term (fitting.recipes.face) and ContourLandmarks.choose /
points_3d / points_3d_vjp (fitting.recipes.contour), the numpy reference: which faces turn
towards the camera, which candidate edges lie on the occluding contour, the nearest one to each
turned jaw landmark, the 68 points, their weighted squared pixel distances, and the gradient
onto the world vertices and the focal length. Nothing comes back to the host per evaluation but
the term's value and focal gradient (read with the rest of the evaluation's sums).

The choice of a contour edge is an argmin over distances computed with numpy's expressions
operation for operation, first smallest first (a tie breaks to the same, lowest, edge); the
loss's sums run in another order than numpy's pairwise ones (parity to ~1e-14 relative).
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from softras_cl.fitting.device.kernels import FIT_KERNELS, LANDMARK_PREAMBLE
from softras_cl.scene.device_kernels import SceneKernels, camera_params

CHUNK = 256            # contour candidates per item of the argmin's first pass


def contour_tables(contour, n_landmarks: int) -> dict:
    """A fitting.recipes.contour.ContourLandmarks (None: no sliding point) as int32 numpy tables:
    cand_edge / cand_point (M,) each sliding point's candidate edges in ascending order and the
    point; chunks (C, 2) the first and end candidate of each argmin chunk (a point's candidates
    split in runs of CHUNK); point_chunks (N + 1,) each point's first chunk; point_face (N,) the
    face of each point's fixed landmark; edge_verts / edge_faces (E, 2); faces (F, 3) the model's;
    point_of (L,) the sliding point of each landmark, -1 for a fixed one."""
    point_of = np.full(n_landmarks, -1, np.int32)
    if contour is None:
        empty = np.zeros(0, np.int32)
        return dict(cand_edge=empty, cand_point=empty, chunks=empty, point_chunks=np.zeros(1, np.int32),
                    point_face=empty, edge_verts=empty, edge_faces=empty, faces=empty, point_of=point_of)
    per_point = [np.nonzero(row)[0] for row in contour.candidate_edges]
    starts = np.cumsum([0] + [len(c) for c in per_point])
    chunks = [(first, min(first + CHUNK, end)) for start, end in zip(starts[:-1], starts[1:])
              for first in range(start, end, CHUNK)]
    point_of[contour.points] = np.arange(len(contour.points))
    return dict(cand_edge=np.concatenate(per_point), cand_point=np.repeat(np.arange(len(per_point)), np.diff(starts)),
                chunks=np.array(chunks), point_chunks=np.cumsum([0] + [-(-len(c) // CHUNK) for c in per_point]),
                point_face=contour.model.landmark_faces[contour.points], edge_verts=contour.edges.vertices,
                edge_faces=contour.edges.faces, faces=contour.model.faces, point_of=point_of)


class DeviceLandmarks:
    """FaceObjective.landmark_term of one objective on the device.

    queue: the objective's queue; model: the (tied) FaceModel; targets (L, 2) working pixels;
    weights (L,); contour: a ContourLandmarks or None; image_size (H, W); robust: the
    objective's landmark_robust (None: squared distances)."""

    def __init__(self, queue, model, targets, weights, contour, image_size, robust: float | None = None):
        self.kernels = SceneKernels(queue.context, queue, extra=FIT_KERNELS, preamble=LANDMARK_PREAMBLE)
        tables = contour_tables(contour, model.n_landmarks)
        self.n, self.n_faces = model.n_landmarks, len(tables["faces"])
        self.n_candidates, self.n_chunks = len(tables["cand_edge"]), len(tables["chunks"])
        self.tables = {name: self._upload(value, np.int32) for name, value in tables.items()}
        self.targets = self._upload(targets, np.float64)
        self.weights = self._upload(weights, np.float64)
        self.corners = self._upload(model.faces[model.landmark_faces], np.int32)
        self.bary = self._upload(model.landmark_bary, np.float64)
        h, w = image_size
        self.sizes = (np.float64(min(h, w)), np.float64(w), np.float64(h))
        self.robust = np.float64(0.0 if robust is None else robust)      # the kernel's 0: squared distances

    def _upload(self, value, dtype) -> cla.Array:
        """A device copy of value (an empty one as one element: OpenCL has no empty buffers)."""
        value = np.ascontiguousarray(value, dtype)
        return cla.to_device(self.kernels.queue, value if value.size else np.zeros(1, dtype))

    def _empty(self, n: int, dtype=np.float64) -> cla.Array:
        return self.kernels.empty(max(n, 1), dtype)

    def __call__(self, world: cla.Array, camera, g_world: cla.Array, weight: float) -> cla.Array:
        """The term at world vertices (V, 3) float64 seen by camera (a perspective Camera): adds
        weight x its gradient to g_world (V, 3) float64 and returns (2,) float64 on the device:
        the term's value and dL/d(focal)."""
        k, c = self.kernels, self.tables
        params = cla.to_device(k.queue, camera_params([camera])[0])
        front = self._empty(self.n_faces, np.int8)
        k("front_faces", self.n_faces, front, world, c["faces"])
        dist, frac = self._empty(self.n_candidates), self._empty(self.n_candidates)
        k("contour_distances", self.n_candidates, dist, frac, c["cand_edge"], c["cand_point"], front, c["point_face"],
          c["edge_verts"], c["edge_faces"], world, params, self.targets, *self.sizes)
        best, which = self._empty(self.n_chunks), self._empty(self.n_chunks, np.int32)
        k("contour_chunk_min", self.n_chunks, best, which, dist, c["chunks"])
        points, edge, t = k.empty((self.n, 3)), k.empty(self.n, np.int32), k.empty(self.n)
        k("landmark_points", self.n, points, edge, t, c["point_of"], c["point_chunks"], best, which, c["cand_edge"],
          frac, c["edge_verts"], self.corners, self.bary, world)
        out, g_points = k.empty(2), k.empty((self.n, 3))
        k("landmark_loss", 1, out, g_points, points, self.targets, self.weights, params, np.int64(self.n),
          *self.sizes, self.robust)
        k("landmark_scatter", 1, g_world, g_points, edge, t, c["edge_verts"], self.corners, self.bary,
          np.int64(self.n), np.float64(weight))
        return out
