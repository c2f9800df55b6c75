"""The photometric term on the OpenCL device: a photo's face region against a device render.

Mirrors fitting.losses.GemanMcClure (robust) and fitting.losses.image_l2 (plain) with a fixed
mask, the numpy reference. Set up once per photometric stage (the region and the robust scale
are fixed within a stage); per evaluation one kernel over the region's pixels and one ordered
sum, and only the loss value comes back.
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from softras_cl.scene.device_kernels import SceneKernels


class DevicePhotoLoss:
    """loss(rgb) -> (value, gradient): the term over the pixels of mask.

    kernels: SceneKernels with FIT_KERNELS; target (H, W, 3) float64 linear RGB; mask (H, W) bool;
    scale: the Geman-McClure scale s > 0, or None for plain squared errors. The value is that of
    GemanMcClure(target, scale, mask)(rgb) (mean over the region of each pixel's kernel), or of
    image_l2(rgb, target, mask) (mean over the region's pixels and channels).
    """

    def __init__(self, kernels: SceneKernels, target, mask, scale: float | None):
        self.kernels, queue = kernels, kernels.queue
        target = np.asarray(target, np.float64)
        self.shape = (1,) + target.shape
        keep = np.flatnonzero(np.asarray(mask, bool))
        self.n = len(keep)
        self.robust = scale is not None
        self.scale = float(scale) if self.robust else 1.0
        # the mean runs over the region's pixels (robust) or its pixels and channels (plain)
        self.total = float(max(self.n, 1) * (1 if self.robust else 3))       # (an empty region sums to 0)
        self.pixel = cla.to_device(queue, keep.astype(np.int64))
        self.weights = cla.to_device(queue, np.ones(max(self.n, 1)))
        self.target = cla.to_device(queue, np.ascontiguousarray(target.reshape(-1, 3)[keep]))
        self.grad = kernels.zeros(self.shape)     # only the region's entries change
        self.rho = kernels.empty(max(self.n, 1))

    def __call__(self, rgb: cla.Array, grad_scale: float = 1.0) -> tuple[cla.Array, cla.Array]:
        """rgb (1, H, W, 3) float64 device -> (the sum of the region's weighted kernel values,
        (1, 1) on the device: the value is it over ``total``; dL/d(rgb) * grad_scale as a
        (1, H, W, 3) device array, this loss's buffer, overwritten by the next call)."""
        if self.n == 0:
            return self.kernels.zeros((1, 1)), self.grad
        if rgb.dtype != np.float64 or not rgb.flags.c_contiguous:       # a float32 raster's image
            rgb = rgb.astype(np.float64)
        self.kernels("photo_loss", self.n, self.rho, self.grad, rgb, self.target, self.pixel, self.weights,
                     np.float64(self.scale), np.float64(self.total), np.float64(grad_scale),
                     np.int32(self.robust))
        return self.kernels.sum_products(self.rho.reshape(1, self.n, 1)), self.grad
