"""The face fit's objective with its heavy work on the OpenCL device.

DeviceFaceEvaluation is mixed into fitting.recipes.face.FaceObjective (the numpy reference) as
fitting.recipes.face.DeviceFaceObjective: the same stages, terms, weights and stage set-up, with
these on the device, in
buffers that live across evaluations: the model's shape and albedo bases (fitting.device.model),
the pose, the landmark term with the sliding jaw contour (fitting.device.landmarks), the render
and its backward (Renderer's device-resident path: projection, normals, SH shading, rasteriser),
the photometric term over the face region and its sum (fitting.device.photo), and the vjps back
to the coefficients and the pose. Per evaluation the coefficients, rotation, translation and
camera go up; the terms' values and the gradient's blocks come down (the renderer's backward
reads its camera and light sums, then one transfer takes the rest).

Still on the host: the priors (on the parameter vector itself), the dense landmark term when a
stage weighs it (the world vertices come down for it, its gradient goes back up), and each
photometric stage's set-up (one numpy render: the face region and the robust scale). In float64
the loss and gradient equal the numpy objective's to about 1e-12 relative (tests/fitting/device).
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from softras_cl.fitting import losses
from softras_cl.fitting.device.landmarks import DeviceLandmarks
from softras_cl.fitting.device.model import DeviceFaceModel, DeviceGeometry
from softras_cl.fitting.device.photo import DevicePhotoLoss
from softras_cl.fitting.solver import Stage


class DeviceFaceEvaluation:
    """FaceObjective's ``(values, stage) -> (loss, grads, terms)`` evaluated on the device of
    the scene's renderer (it needs cl_khr_fp64): a mixin, first base of a FaceObjective
    subclass (fitting.recipes.face.DeviceFaceObjective), whose methods it overrides and calls.
    Arguments as FaceObjective's; device_model: the DeviceFaceModel to share (a half-resolution
    copy shares its parent's), None to upload the scene's model."""

    def __init__(self, *args, device_model: DeviceFaceModel | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        queue = self.scene.renderer.queue
        if device_model is None or device_model.queue != queue:
            device_model = DeviceFaceModel(self.scene.model, queue)
        self.device_model = device_model
        self.device_faces = device_model.device_faces(self.scene.faces)
        self._photo_loss: DevicePhotoLoss | None = None
        self._device_landmarks: DeviceLandmarks | None = None

    def _level_options(self) -> dict:
        return dict(device_model=self.device_model)

    def geometry(self, values: dict) -> DeviceGeometry:
        """The placed shape of values on the device (DeviceFaceModel.geometry)."""
        return self.device_model.geometry(values)

    def combine(self, values: dict, stage: Stage, geometry: DeviceGeometry, photo: tuple | None):
        """FaceObjective.combine on the device's geometry and photometric term (world and
        albedo gradients on the device)."""
        w, model = stage.weights, self.device_model
        g_world, reads, terms = model.zeros(), {}, {}
        # the world cotangent collects each term's weighted gradient in weighted_sum's order
        if w.get("landmarks"):
            reads["landmarks"] = self.device_landmarks(geometry.world, self.scene.camera(values["focal"][0]), g_world,
                                                       float(w["landmarks"]))
        if w.get("dense"):                      # on the host: the world vertices come down
            value, g = self.dense_term(values, geometry.world.get())
            model.add(g_world, g.pop("world"), float(w["dense"]))
            terms["dense"] = (value, g)
        if photo is not None:
            value, g = photo
            model.add(g_world, g.pop("world"), float(w["photo"]))
            reads["albedo"] = g.pop("albedo")
            terms["photo"] = (value, g)
        grads, read = model.geometry_vjp(geometry, g_world, reads)
        if "albedo" in read:
            terms["photo"][1]["albedo"] = read["albedo"]
        if "landmarks" in read:
            value, g_focal = read["landmarks"]
            terms = {"landmarks": (value, dict(focal=np.array([g_focal])))} | terms
        loss, host_grads, weighted = losses.weighted_sum(terms | self.prior_terms(values, w), w)
        for name, g in host_grads.items():
            grads[name] = grads[name] + g if name in grads else g
        return loss, grads, weighted

    @property
    def device_landmarks(self) -> DeviceLandmarks:
        """The landmark term on the device (made at its first use)."""
        if self._device_landmarks is None:
            self._device_landmarks = DeviceLandmarks(self.device_model.queue, self.scene.model, self.target,
                                                     self.landmark_weights, self.contour, self.scene.image_size,
                                                     self.landmark_robust)
        return self._device_landmarks

    def start_stage(self, values: dict, stage: Stage) -> None:
        super().start_stage(values, stage)
        self._photo_loss = DevicePhotoLoss(self.device_model.kernels, self.image, self.mask, self.photo_scale)

    # what fitting.recipes.face.photo_terms_together asks of each objective (FaceObjective's)
    check_render_values = False       # the world vertices and albedo come from its own kernels

    def drawn_faces(self) -> cla.Array:
        return self.device_faces

    def photo_albedo(self, values: dict) -> tuple:
        """(the render's albedo (V, 3) on the device, no context)."""
        return self.device_model.albedo(values["albedo"]), None

    def photo_loss(self, rgb: cla.Array) -> tuple:
        """(the region's sum (1, 1) on the device, dL/d(rgb) (1, H, W, 3) on the device) of a
        device render rgb (1, H, W, 3): DevicePhotoLoss at this stage's region and scale."""
        return self._photo_loss(rgb, grad_scale=self._photo_loss.total)

    def photo_value(self, total: cla.Array) -> float:
        count = self._photo_loss.total
        # the mean times the count, as the numpy term rounds it (not the sum as read)
        return float(total.get()[0, 0]) / count * count

    def photo_grads(self, albedo_ctx, g_world: cla.Array, g_albedo: cla.Array, g_sh: np.ndarray,
                    g_focal: np.ndarray) -> dict:
        """The gradients world (V, 3) and albedo (K_alb,) on the device, sh and focal numpy."""
        return dict(world=g_world, albedo=self.device_model.albedo_vjp(g_albedo), sh=g_sh, focal=np.array([g_focal.sum()]))
