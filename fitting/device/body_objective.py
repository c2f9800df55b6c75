"""The body fit's objective with its image stages on the OpenCL device.

DeviceBodyEvaluation is mixed into fitting.recipes.body.BodyObjective (the numpy reference) and
its photo variant (fitting.recipes.body_photo.BodyPhotoObjective): the same stages, terms and
weights. An evaluation that renders poses the drawn vertices on the device (DeviceSkin: shape
and pose blendshapes, linear blend skinning), renders them through the Renderer's device path,
takes the silhouette and image terms and their cotangents there (DeviceBodyImages), runs the
render's backward and the skinning's vjp, and reads back in one transfer the terms' three sums
and the skinning's cotangent sums (SkinCotangents: tens of floats).

On the host: the joints (rest positions, rotations, the kinematic chain and its vjp: tens of
floats), the priors, the joint term, the photo objective's keypoint and depth terms (they read
a few surface vertices, posed on the host as in the reference), and the evaluations that do not
render. In float64 the loss and gradient equal the numpy objective's to about 1e-12 relative
(tests/fitting/device/test_body_objective.py).
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from softras_cl.fitting import losses
from softras_cl.fitting.device.body_model import DeviceSkin
from softras_cl.raster.device_arrays import read_together


class DeviceBodyImages:
    """BodyObjective.image_terms on the device, for one target: its alpha (H, W), care weights
    (H, W; None: all 1) and colours (H, W, 3; None: a silhouette target) and the background
    (3,) uploaded once. kernels: a SceneKernels with BODY_KERNELS."""

    def __init__(self, kernels, target, background):
        self.kernels, queue = kernels, kernels.queue
        self.n_pixels = target.alpha.size
        self.has_rgb = target.rgb is not None
        care = np.ones(self.n_pixels) if target.care is None else target.care
        self.alpha, self.care = _flat(queue, target.alpha), _flat(queue, care)
        self.rgb = _flat(queue, target.rgb if self.has_rgb else np.zeros(1))
        self.background = _flat(queue, background)

    def __call__(self, out, w_silhouette: float, w_image: float) -> tuple[cla.Array, cla.Array, cla.Array | None]:
        """The render ``out`` (a device RenderOutput, alpha (1, H, W), rgb (1, H, W, 3) for a
        colour target) -> (the sums (1, 3): I, U and the squared errors, on the device;
        dL/d(alpha) (1, H, W) and dL/d(rgb) (1, H, W, 3) or None of the terms weighted by
        w_silhouette and w_image, float64 on the device)."""
        k, n, flag = self.kernels, self.n_pixels, np.int32(self.has_rgb)
        alpha = _float64(out.alpha)
        rgb = _float64(out.rgb) if self.has_rgb else self.rgb
        terms = k.empty((1, n, 3))
        k("body_image_terms", n, terms, alpha, rgb, self.alpha, self.care, self.rgb, self.background, flag)
        sums = k.sum_products(terms)
        g_alpha = k.empty(alpha.shape)
        g_rgb = k.empty(rgb.shape) if self.has_rgb else self.rgb
        k("body_image_grads", n, g_alpha, g_rgb, sums, alpha, rgb, self.alpha, self.care, self.rgb, self.background,
          np.float64(losses.IOU_EPS), np.float64(n), np.float64(w_silhouette), np.float64(w_image), flag)
        return sums, g_alpha, g_rgb if self.has_rgb else None

    def terms(self, sums: np.ndarray) -> dict:
        """{"silhouette": (value, {}), and "image" for a colour target} of the sums read back
        (3,): the values of BodyObjective.image_terms (their gradients went to the render)."""
        inter, union, squares = (float(v) for v in sums.reshape(3))
        terms = {"silhouette": ((union - inter) / (union + losses.IOU_EPS) * self.n_pixels, {})}
        if self.has_rgb:
            terms["image"] = (squares, {})
        return terms


def _flat(queue, values) -> cla.Array:
    """A flat float64 device copy of values (any shape)."""
    return cla.to_device(queue, np.ascontiguousarray(values, np.float64).reshape(-1))


def _float64(image: cla.Array) -> cla.Array:
    """A float32 raster's image as float64 (a float64 one as it is)."""
    return image if image.dtype == np.float64 and image.flags.c_contiguous else image.astype(np.float64)


class DeviceDrawn:
    """What an objective draws, on the device: its drawn vertices' DeviceSkin, the face list
    and part colours uploaded, and the image terms (DeviceBodyImages)."""

    def __init__(self, objective, queue):
        posed = objective.posed(True)
        model = objective.scene.model
        self.skin = DeviceSkin(model, None if posed.subset is None else posed.subset.ids, queue)
        self.faces = cla.to_device(queue, np.ascontiguousarray(posed.faces, np.int32))
        self.colors = cla.to_device(queue, np.ascontiguousarray(posed.colors, np.float64))
        self.images = DeviceBodyImages(self.skin.kernels, objective.target, objective.scene.config.background)


class DeviceBodyEvaluation:
    """BodyObjective's evaluations that render, on the device of the scene's renderer (it needs
    cl_khr_fp64): a mixin, first base of a BodyObjective subclass
    (fitting.recipes.body.DeviceBodyObjective, fitting.recipes.body_photo.DeviceBodyPhotoObjective),
    whose hooks it overrides. Arguments as the objective's."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._drawn: DeviceDrawn | None = None

    @property
    def drawn(self) -> DeviceDrawn:
        """The device buffers of the drawn vertices and the target (made at the first render)."""
        if self._drawn is None:
            self._drawn = DeviceDrawn(self, self.scene.renderer.queue)
        return self._drawn

    def host_posed(self, renders: bool):
        return self.posed(False)        # the drawn vertices are posed on the device

    def draw(self, values: dict, stage, state, body_ctx):
        drawn, w = self.drawn, stage.weights
        vertices, v_posed, transforms = drawn.skin.forward(values, body_ctx)
        renderer = self.scene.renderer_for(self.render_changes)
        albedo = drawn.colors if "rgb" in renderer.settings.outputs else None
        out = renderer.forward(vertices, drawn.faces, self.scene.camera, albedo=albedo, grads=("vertices",),
                               sigma=stage.sigma, gamma=stage.gamma, check_values=False)
        sums, g_alpha, g_rgb = drawn.images(out, float(w.get("silhouette", 0.0)), float(w.get("image", 0.0)))
        g_vertices = renderer.backward(out, grad_rgb=g_rgb, grad_alpha=g_alpha)["vertices"]
        sums, *skin_sums = read_together([sums, *drawn.skin.vjp(g_vertices, v_posed, transforms)])
        return drawn.images.terms(sums), drawn.skin.cotangents(*skin_sums)

    def drawing_vjp(self, skin, g: dict, g_vertices):
        return g_vertices, skin
