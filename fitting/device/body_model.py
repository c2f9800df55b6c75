"""A body model's vertices posed on the OpenCL device: the vertex half of BodyModel.forward and
its vjp (fitting.models.body_model, the numpy reference).

The joints stay on the host: their rest positions, rotations and the kinematic chain are tens of
floats, and forward gives them (the BodyContext of a forward over a few or no vertices). The S
vertices a fit draws are posed here from buffers uploaded once: their rest shape, their shape
and pose blendshapes (one DeviceBasis: v_posed = template + [shapedirs | posedirs] @ [betas,
pose features]) and their skinning weights (CSR). Per evaluation the betas, the pose features and
the J joint transforms go up; the vjp leaves on the device the sums forward_vjp needs
(SkinCotangents), for the caller to read with its other sums in one transfer.
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from softras_cl.fitting.device.body_kernels import BODY_KERNELS, BODY_PREAMBLE
from softras_cl.fitting.device.kernels import FIT_KERNELS
from softras_cl.fitting.device.model import DeviceBasis
from softras_cl.fitting.models.body_model import BodyContext, SkinCotangents, pose_features
from softras_cl.scene.device_kernels import SceneKernels


class DeviceSparse:
    """A sparse float64 matrix (scipy CSR, any shape (R, N)) on the device, for the body kernels'
    row loops (fitting.device.body_kernels)."""

    def __init__(self, queue, matrix):
        m = matrix.tocsr()
        m.sort_indices()
        self.row_start = cla.to_device(queue, m.indptr.astype(np.int32))
        self.col = cla.to_device(queue, m.indices.astype(np.int32) if m.nnz else np.zeros(1, np.int32))
        self.weight = cla.to_device(queue, m.data.astype(np.float64) if m.nnz else np.zeros(1))

    @property
    def args(self) -> tuple:
        return self.row_start, self.col, self.weight


class DeviceSkin:
    """The vertices ``ids`` (S,) int of a BodyModel posed on ``queue`` (None: all V in order)."""

    def __init__(self, model, ids, queue):
        import scipy.sparse

        self.model = model
        ids = np.arange(model.n_vertices) if ids is None else np.asarray(ids, np.int64)
        self.n_vertices, self.n_joints, self.n_betas = len(ids), model.n_joints, model.n_betas
        self.kernels = SceneKernels(queue.context, queue, extra=FIT_KERNELS | BODY_KERNELS, preamble=BODY_PREAMBLE)
        rows = [np.moveaxis(model.shapedirs[ids], 2, 0).reshape(model.n_betas, -1)]
        if model.posedirs is not None:
            rows.append(np.moveaxis(model.posedirs[ids], 2, 0).reshape(model.posedirs.shape[2], -1))
        basis = np.concatenate(rows)
        self.blendshapes = DeviceBasis(self.kernels, model.v_template[ids], basis, np.ones(len(basis)))
        weights = scipy.sparse.csr_matrix(model.weights[ids])
        self.skin, self.skin_t = DeviceSparse(queue, weights), DeviceSparse(queue, weights.T)

    def forward(self, values: dict, ctx: BodyContext) -> tuple[cla.Array, cla.Array, cla.Array]:
        """The S vertices (S, 3) float64 on the device of the body of the blocks ``values``
        (betas (B,), translation (3,); BodyModel.forward's), posed by the joint transforms of
        ``ctx`` (a forward of the same values): (vertices, v_posed (S, 3), the uploaded
        transforms) - :meth:`vjp` takes the last two."""
        coeffs = [np.asarray(values["betas"], np.float64)]
        if self.model.posedirs is not None:
            coeffs.append(pose_features(ctx.rot_local))
        v_posed = self.blendshapes.apply(np.concatenate(coeffs))
        transforms = cla.to_device(self.kernels.queue, np.concatenate(
            [np.concatenate([ctx.rot_global.reshape(-1, 9), ctx.offsets], axis=1).ravel(),
             np.asarray(values["translation"], np.float64)]))
        vertices = self.kernels.empty((self.n_vertices, 3))
        self.kernels("skin", self.n_vertices, vertices, v_posed, transforms, *self.skin.args, np.int64(self.n_joints))
        return vertices, v_posed, transforms

    def vjp(self, g_vertices: cla.Array, v_posed: cla.Array, transforms: cla.Array) -> list[cla.Array]:
        """dL/d(vertices) (S, 3) float64 on the device -> the device arrays [rotations and
        offsets (J, 12), blendshape coefficients (B [+ 9 (J - 1)],), vertex sums (1, 12)]:
        :meth:`cotangents` makes SkinCotangents of them once read back."""
        k, s = self.kernels, self.n_vertices
        g_posed, products = k.empty((s, 3)), k.empty((1, s, 12))
        k("skin_vjp", s, g_posed, products, g_vertices, v_posed, transforms, *self.skin.args)
        joint_sums = k.empty((self.n_joints, 12))
        k("sparse_times", joint_sums.size, joint_sums, products, *self.skin_t.args, np.int64(12))
        return [joint_sums, self.blendshapes.vjp(g_posed), k.sum_products(products)]

    def cotangents(self, joint_sums: np.ndarray, coeffs: np.ndarray, vertex_sums: np.ndarray) -> SkinCotangents:
        """SkinCotangents of :meth:`vjp`'s arrays read back (numpy, its shapes)."""
        b = self.n_betas
        return SkinCotangents(rotations=joint_sums[:, :9].reshape(-1, 3, 3), offsets=joint_sums[:, 9:],
                              betas=coeffs[:b], pose_features=coeffs[b:] if self.model.posedirs is not None else None,
                              translation=vertex_sums.reshape(12)[9:])
