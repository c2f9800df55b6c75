"""A face model's bases on the OpenCL device, and the pose that places its shape in the world.

Uploaded once per fit; per evaluation only the coefficients (tens of floats), the rotation and
the translation go up, and only the vjps' sums (tens of floats) come down, in one transfer. Each function mirrors
the numpy one it replaces (fitting.models.face_model.FaceModel.shape / albedo and their vjps,
fitting.recipes.face.FaceScene.geometry / geometry_vjp), which stay as the reference.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from softras_cl.fitting.device.kernels import FIT_KERNELS
from softras_cl.raster.device_arrays import read_together
from softras_cl.scene.device_kernels import SUM_CHUNK, SceneKernels
from softras_cl.scene.rotation import RodriguesContext, rodrigues, rodrigues_vjp


class DeviceBasis:
    """A linear map on the device: coefficients c (K,) -> mean + (c * std) @ basis, (N,) float64.

    kernels: SceneKernels with FIT_KERNELS; mean (N,), basis (K, N), std (K,) float64 (numpy,
    uploaded here)."""

    def __init__(self, kernels: SceneKernels, mean, basis, std):
        self.kernels, queue = kernels, kernels.queue
        self.std = np.asarray(std, np.float64)
        self.n_rows, self.k = int(np.size(mean)), len(self.std)
        self.std_device = cla.to_device(queue, self.std if self.k else np.zeros(1))
        self.mean = cla.to_device(queue, np.ascontiguousarray(mean, np.float64).reshape(-1))
        self.basis = cla.to_device(queue, np.ascontiguousarray(basis, np.float64).reshape(self.k, self.n_rows))
        self.n_chunks = max(1, -(-self.n_rows // SUM_CHUNK))

    def apply(self, coeffs) -> cla.Array:
        """(N,) float64 device array for coeffs (K,) in standard deviations."""
        w = cla.to_device(self.kernels.queue, np.asarray(coeffs, np.float64) * self.std) if self.k else self.mean
        out = self.kernels.empty(self.n_rows)
        self.kernels("basis_apply", self.n_rows, out, self.mean, self.basis, w, np.int64(self.n_rows),
                     np.int64(self.k))
        return out

    def vjp(self, grad: cla.Array) -> cla.Array:
        """grad (N,) device = dL/d(output) -> dL/dc (K,) float64 on the device: std * (basis @ grad)."""
        out = self.kernels.empty(self.k)
        if self.k:
            partial = self.kernels.empty(self.k * self.n_chunks)
            self.kernels("basis_chunk_sums", partial.size, partial, self.basis, grad.reshape(-1),
                         np.int64(self.n_rows), np.int64(self.n_chunks))
            self.kernels("basis_totals", self.k, out, partial, self.std_device, np.int64(self.n_chunks))
        return out


@dataclass
class DeviceGeometry:
    """One evaluation's placed shape: world and shape (V, 3) float64 on the device, rt the
    uploaded R (9) and t (3), rot_ctx the rotation's RodriguesContext."""
    world: cla.Array
    shape: cla.Array
    rt: cla.Array
    rot_ctx: RodriguesContext


class DeviceFaceModel:
    """A FaceModel's shape (identity and expression bases, one DeviceBasis) and albedo basis on the
    queue of a renderer; the same object serves every resolution level of one fit."""

    def __init__(self, model, queue):
        self.model, self.queue = model, queue
        self.kernels = SceneKernels(queue.context, queue, extra=FIT_KERNELS)
        v = model.n_vertices
        self.n_vertices = v
        self.shape_basis = DeviceBasis(
            self.kernels, model.mean_shape,
            np.concatenate([model.id_basis.reshape(model.n_id, 3 * v), model.exp_basis.reshape(model.n_exp, 3 * v)]),
            np.concatenate([model.id_std, model.exp_std]))
        self.albedo_basis = DeviceBasis(self.kernels, model.albedo_mean,
                                        model.albedo_basis.reshape(model.n_albedo, 3 * v), model.albedo_std)
        self.faces: dict = {}

    def device_faces(self, faces: np.ndarray) -> cla.Array:
        """A device copy of a face list (F, 3) int32 (kept: one upload per list and fit)."""
        key = (faces.shape, faces.tobytes())
        if key not in self.faces:
            self.faces[key] = cla.to_device(self.queue, np.ascontiguousarray(faces, np.int32))
        return self.faces[key]

    def geometry(self, values: dict) -> DeviceGeometry:
        """The world vertices of values' id, exp, rotation and translation (FaceScene.geometry),
        on the device."""
        shape = self.shape_basis.apply(np.concatenate([values["id"], values["exp"]]))
        R, rot_ctx = rodrigues(values["rotation"])
        rt = cla.to_device(self.queue, np.concatenate([R.reshape(-1), values["translation"]]).astype(np.float64))
        world = self.kernels.empty(3 * self.n_vertices)
        self.kernels("rigid", self.n_vertices, world, shape, rt)
        return DeviceGeometry(world.reshape(self.n_vertices, 3), shape, rt, rot_ctx)

    def geometry_vjp(self, geometry: DeviceGeometry, g_world: cla.Array, also: dict) -> tuple[dict, dict]:
        """dL/d(world vertices) (V, 3) device -> (dict id, exp, rotation, translation, numpy
        float64, as FaceScene.geometry_vjp; the device float64 arrays ``also`` {name: array}
        read back with them, in one transfer)."""
        v, k = self.n_vertices, self.kernels
        g_shape, products = k.empty(3 * v), k.empty((1, v, 12))
        k("rigid_vjp", v, g_shape, products, g_world, geometry.shape, geometry.rt)
        sums, g_coeffs, *rest = read_together([k.sum_products(products), self.shape_basis.vjp(g_shape), *also.values()])
        sums, n_id = sums.reshape(12), self.model.n_id
        grads = dict(id=g_coeffs[:n_id], exp=g_coeffs[n_id:], translation=sums[:3],
                     rotation=rodrigues_vjp(geometry.rot_ctx, sums[3:].reshape(3, 3))["omega"])
        return grads, dict(zip(also, rest))

    def albedo(self, coeffs) -> cla.Array:
        """Per-vertex albedo (V, 3) float64 on the device (FaceModel.albedo)."""
        return self.albedo_basis.apply(coeffs).reshape(self.n_vertices, 3)

    def albedo_vjp(self, grad: cla.Array) -> cla.Array:
        """dL/d(albedo) (V, 3) device -> dL/d(coeffs) (K_alb,) on the device."""
        return self.albedo_basis.vjp(grad)

    def zeros(self) -> cla.Array:
        """(V, 3) float64 zeros on the device: a world cotangent to add the terms into."""
        return self.kernels.zeros((self.n_vertices, 3))

    def add(self, dst: cla.Array, src, weight: float) -> None:
        """dst += weight * src, element-wise on the device (both float64, one size; a numpy src
        is uploaded)."""
        if not isinstance(src, cla.Array):
            src = cla.to_device(self.queue, np.ascontiguousarray(src, np.float64))
        self.kernels("axpy", dst.size, dst.reshape(-1), src.reshape(-1), np.float64(weight))
