"""What Renderer.forward and backward share between the numpy path (softras_cl.scene.renderer)
and the device-resident one (softras_cl.scene.device_render): the argument checks, the colour
arguments of per-pixel lighting, and the records a forward hands its backward."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softras_cl.checks import check_finite, float_array
from softras_cl.raster.rasterizer import ForwardImages, RasterOutput, SoftRasterizer
from softras_cl.scene import shading
from softras_cl.scene.camera import Camera, ProjectionContext


@dataclass
class RenderContext:
    """What Renderer.backward needs from one forward call.

    renderer: the Renderer whose forward made it (only its backward takes it);
    raster: the SoftRasterizer drawn with and raster_out its RasterOutput (with its own context);
    cameras: the B Cameras, one per view, and cam_ctx their ProjectionContexts; shade_ctx:
    shading.ShadeContext (vertex or face shading), shading.NormalsContext (pixel shading) or
    None (unlit); light: the light used; grads: the groups backward returns; batched: whether
    the vertices had a batch axis; single_camera: whether one Camera (not a list) was given;
    albedo_shape: the shape of the albedo given (None without one); device: the
    device_render.DeviceState of a device-resident forward (then cam_ctx is empty and shade_ctx
    None), else None.
    """
    raster: SoftRasterizer
    raster_out: RasterOutput
    cameras: list
    cam_ctx: tuple[ProjectionContext, ...]
    shade_ctx: object
    light: object
    grads: tuple
    batched: bool
    single_camera: bool
    albedo_shape: tuple | None
    renderer: "Renderer"
    device: object = None


@dataclass
class RenderOutput(ForwardImages):
    """Images (B, H, W[, 3]) of one Renderer.forward call (ForwardImages), and what backward
    needs."""
    saved: RenderContext | None = None


def _light_vector(light) -> np.ndarray:
    """The 27 light parameters of the per-pixel kernel (settings.lighting, docs/scene.md)."""
    if isinstance(light, shading.SHLight):
        return (light.coefficients * shading.SH_POLY_SCALE).ravel()
    if type(light) is shading.LambertLight:
        direction = light.direction / np.linalg.norm(light.direction)
        return np.concatenate([light.ambient, light.directional, direction, np.zeros(18)])
    if isinstance(light, shading.ViewLights):
        raise ValueError("light: shading='pixel' lights every view with one light (the rasteriser's own); "
                         "a list of one light per view needs shading 'vertex' or 'face'")
    raise ValueError(f"light: shading='pixel' supports LambertLight and SHLight, got {type(light).__name__}")


def _light_vector_vjp(light, grad: np.ndarray) -> dict:
    """Gradient of the 27 kernel light parameters -> the light's own parameters."""
    if isinstance(light, shading.SHLight):
        return dict(coefficients=grad.reshape(3, 9) * shading.SH_POLY_SCALE)
    length = np.linalg.norm(light.direction)
    unit = light.direction / length
    g_unit = grad[6:9]
    return dict(ambient=grad[0:3], directional=grad[3:6], direction=(g_unit - unit * (unit @ g_unit)) / length)


def _views(cameras, vertices, image_size: tuple):
    """(list of B cameras, (B, V, 3) float64 vertices, whether the vertices had a batch axis)."""
    single = isinstance(cameras, Camera)
    cams = [cameras] if single else list(cameras)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise TypeError("cameras must be a Camera or a non-empty list of Camera objects")
    verts = np.asarray(vertices, np.float64)
    if verts.ndim not in (2, 3) or verts.shape[-1] != 3:
        raise ValueError(f"vertices must have shape (V, 3) or (B, V, 3), got {verts.shape}")
    batched = verts.ndim == 3
    batch = verts.shape[0] if batched else len(cams)
    if single:
        cams = cams * batch
    if len(cams) != batch:
        raise ValueError(f"{len(cams)} cameras for a batch of {batch} meshes")
    sizes = {tuple(c.image_size) for c in cams}
    if sizes != {tuple(image_size)}:
        raise ValueError(f"cameras have image_size {sorted(sizes)} but settings.image_size is {image_size}")
    return cams, np.broadcast_to(verts, (batch, *verts.shape[-2:])), batched


def _check_albedo(albedo, verts_shape: tuple) -> None:
    """ValueError naming albedo unless it is None or a finite float (V, 3) or (B, V, 3) array
    (B = 1 or the batch of verts_shape (B, V, 3)), before any shading or kernel runs."""
    if albedo is None:
        return
    batch, n_vertices = verts_shape[:2]
    arr = float_array("albedo", albedo)
    per_vertex = (n_vertices, 3)
    if not (arr.shape == per_vertex or (arr.ndim == 3 and arr.shape[1:] == per_vertex
                                        and arr.shape[0] in (1, batch))):
        batches = "1" if batch == 1 else f"1 or {batch}"
        raise ValueError(f"albedo must have shape ({n_vertices}, 3) or (B, {n_vertices}, 3) with B = "
                         f"{batches} (one RGB colour per vertex), got {arr.shape}")
    check_finite("albedo", arr)


def _raster_grads(grads: tuple, shading_mode: str) -> tuple:
    """What the rasteriser must differentiate for the requested groups."""
    positions = {"vertices", "camera", "focal"} & set(grads)
    colors = {"albedo", "light"} & set(grads) or (positions and shading_mode != "none")
    return (("vertices",) if positions else ()) + (("colors",) if colors else ())
