"""The face fit's objective with its heavy work on the OpenCL device.

DeviceFaceObjective is fitting.recipes.face.FaceObjective (the numpy reference, which it
subclasses: the same stages, terms, weights and stage set-up) with these on the device, in
buffers that live across evaluations: the model's shape and albedo bases (fitting.device.model),
the pose, the render and its backward (Renderer's device-resident path: projection, normals, SH
shading, rasteriser), the photometric term over the face region and its sum (fitting.device.photo),
and the vjps back to the coefficients and the pose. Per evaluation the coefficients, rotation and
translation go up; the loss, its gradient's blocks and the world vertices come down.

Still on the host: the landmark and dense terms with the sliding contour, which read the world
vertices (V, 3) (their gradient goes back up as one (V, 3) array), the priors (on the parameter
vector itself), and each photometric stage's set-up (one numpy render: the face region and the
robust scale). In float64 the loss and gradient equal the numpy objective's to about 1e-12
relative (tests/fitting/device).
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from softras_cl.fitting import losses
from softras_cl.fitting.device.model import DeviceFaceModel
from softras_cl.fitting.device.photo import DevicePhotoLoss
from softras_cl.fitting.recipes.face import FaceObjective
from softras_cl.fitting.solver import Stage


class DeviceFaceObjective(FaceObjective):
    """FaceObjective's ``(values, stage) -> (loss, grads, terms)`` evaluated on the device of
    the scene's renderer (it needs cl_khr_fp64). Arguments as FaceObjective's; device_model: the
    DeviceFaceModel to share (a half-resolution copy shares its parent's), None to upload the
    scene's model."""

    def __init__(self, *args, device_model: DeviceFaceModel | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        queue = self.scene.renderer.queue
        if device_model is None or device_model.queue != queue:
            device_model = DeviceFaceModel(self.scene.model, queue)
        self.device_model = device_model
        self.device_faces = device_model.device_faces(self.scene.faces)
        self._photo_loss: DevicePhotoLoss | None = None

    def _level_options(self) -> dict:
        return dict(device_model=self.device_model)

    def __call__(self, values: dict, stage: Stage):
        w = stage.weights
        geometry = self.device_model.geometry(values)
        terms = self.point_terms(values, geometry.world_host, w)
        g_photo = None
        if w.get("photo"):
            value, g = self.photo(values, geometry.world, stage)
            g_photo = g.pop("world")
            terms["photo"] = (value, g)
        loss, grads, weighted = losses.weighted_sum(terms | self.prior_terms(values, w), w)
        g_world = self._world_cotangent(grads.pop("world", None), g_photo, float(w.get("photo", 0.0)))
        if g_world is not None:
            for name, g in self.device_model.geometry_vjp(geometry, g_world).items():
                grads[name] = grads.get(name, 0.0) + g
        return loss, grads, weighted

    def _world_cotangent(self, host, photo, photo_weight: float):
        """dL/d(world) on the device: the weighted host terms' (V, 3) numpy sum, then plus
        photo_weight times the photometric term's device gradient, the order of weighted_sum."""
        if photo is None:
            return None if host is None else cla.to_device(self.device_model.queue, np.ascontiguousarray(host))
        if host is None:
            out = cla.zeros(self.device_model.queue, photo.shape, np.float64)
        else:
            out = cla.to_device(self.device_model.queue, np.ascontiguousarray(host, np.float64))
        self.device_model.add(out, photo, photo_weight)
        return out

    def start_stage(self, values: dict, stage: Stage) -> None:
        super().start_stage(values, stage)
        self._photo_loss = DevicePhotoLoss(self.device_model.kernels, self.image, self.mask, self.photo_scale)

    def photo_term(self, values: dict, world: cla.Array, sigma: float, gamma: float) -> tuple[float, dict]:
        """FaceObjective.photo_term on device world vertices (V, 3) float64: the same sum over the
        face region; gradients "world" (V, 3) on the device, albedo, sh and focal numpy."""
        albedo = self.device_model.albedo(values["albedo"])
        out = self.scene.render(values, sigma, gamma, grads=("vertices", "albedo", "light", "focal"),
                                albedo=albedo, world=world, roi=self.mask, faces=self.device_faces)
        count = self._photo_loss.total
        value, g_rgb = self._photo_loss(out.rgb, grad_scale=count)
        g_img = self.scene.renderer.backward(out, grad_rgb=g_rgb)
        return value * count, dict(world=g_img["vertices"], albedo=self.device_model.albedo_vjp(g_img["albedo"]),
                                   sh=g_img["light"]["coefficients"], focal=np.array([g_img["focal"].sum()]))
