"""The whole differentiable render path: mesh -> camera -> shading -> soft rasteriser, and back.

    world vertices ──Camera.project──▶ screen vertices ─┐
          │                                              ├─▶ SoftRasterizer ─▶ rgb, alpha, depth
          └─normals──▶ light.shade(albedo) ─▶ colours ──┘

`Renderer.backward` runs the vector-Jacobian products of those stages in reverse and returns
gradients for exactly the groups asked for in `forward(grads=...)`: "vertices" (world),
"albedo" (or the unlit colour input), "camera" (rotation, translation, focal per view),
"focal" (the focal lengths alone, for a caller that needs no other camera gradient) and
"light" (its parameters). Conventions: docs/scene.md and docs/conventions.md.

A renderer draws with one rasteriser per kernel variant its inputs need (texture mode, lighting,
projection; a fit uses one), at any sigma, gamma, near and far given per call.
"""
from __future__ import annotations

import numpy as np

from softras_cl.cl.device import resolve_context
from softras_cl.scene import device_render, shading
from softras_cl.scene.render_inputs import (RenderContext, RenderOutput, _check_albedo, _light_vector,
                                           _light_vector_vjp, _raster_grads, _views)
from softras_cl.scene.camera import Camera, ProjectionContext
from softras_cl.scene.rotation import rodrigues_vjp
from softras_cl.raster.corners import scatter_corners
from softras_cl.raster.rasterizer import RUN_FIELDS, SoftRasterizer
from softras_cl.raster.settings import RasterSettings

SHADINGS = ("vertex", "face", "pixel", "none")
# (sigma, gamma) of a sharp render, e.g. a fit's result drawn for its metrics and reports: D falls
# below 1e-4 within 0.003 NDC of an edge (0.4 pixel at 256 x 256), and the nearest surface wins.
SHARP = (1e-6, 1e-4)
GRAD_GROUPS = ("vertices", "albedo", "camera", "light", "focal")


class Renderer:
    """Renders meshes seen by cameras under a light, with gradients for every scene parameter.

    settings: RasterSettings (its `texture`, `lighting` and `perspective_correct` are set by the
    renderer); shading: "vertex" (vertex normals and albedo, Gouraud), "face" (face normals,
    flat; albedo averaged over each face's corners), "pixel" (albedo and normals interpolated
    and lit per pixel in the kernel; Lambert or SH lights) or "none" (unlit: the colour input is
    drawn as it is, with any texture mode); device: a pyopencl.Device or None for the default;
    context, queue: a user's own pyopencl Context / in-order CommandQueue, checked as
    SoftRasterizer checks them (softras_cl.cl.device.resolve_context). `device`, `context` and
    `queue` hold the resolved ones: every rasteriser of the renderer runs on that queue, and
    device-resident inputs (pyopencl arrays) are made on it.

    The settings are fixed for the renderer's life (read-only `settings`); sigma, gamma, near
    and far can be given to each forward instead.
    """

    def __init__(self, settings: RasterSettings, shading: str = "vertex", device=None, context=None,
                 queue=None):
        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        if not isinstance(settings, RasterSettings):
            raise TypeError(f"settings must be a RasterSettings, got {type(settings).__name__}")
        self._base_settings, self.shading = settings, shading
        self.device, self.context, self.queue = resolve_context(device, context, queue)
        self._rasterizers: dict = {}    # (texture, lighting, projection) -> SoftRasterizer

    @property
    def device_tools(self):
        """The device-resident path's kernels and caches (softras_cl.scene.device_render), made
        on first use."""
        if not hasattr(self, "_device_tools"):
            from softras_cl.scene.device_render import DeviceTools

            self._device_tools = DeviceTools(self.context, self.queue)
        return self._device_tools

    @property
    def settings(self) -> RasterSettings:
        """The settings given (read-only: per-call sigma, gamma, near and far go to forward)."""
        return self._base_settings

    def forward(self, vertices, faces, cameras, albedo=None, light=None, face_textures=None,
                texture_image=None, uvs=None, grads=(), roi=None, sigma=None, gamma=None,
                near=None, far=None, check_values: bool = True) -> RenderOutput:
        """Render B views.

        vertices (V, 3) or (B, V, 3) world; faces (F, 3) int; cameras: a Camera or a list of B;
        albedo (V, 3) or (B, V, 3) linear RGB (vertex/face shading, or unlit vertex colours);
        light: shading.LambertLight / PhongLight / SHLight (default: the paper's Lambert), or a
        list of B of one type, one per view (shading "vertex" or "face"; the light gradients then
        stack the views' along a first axis);
        face_textures / texture_image + uvs: unlit textures (shading="none");
        grads: subset of GRAD_GROUPS that backward() will return;
        roi: None or an (H, W) / (B, H, W) bool mask: only the screen tiles holding its pixels
        are rasterised (SoftRasterizer.forward), the rest is background without gradients;
        sigma, gamma, near, far: this call's values of those settings (None: the settings'
        own), checked as RasterSettings checks them.

        Device-resident inputs: when vertices, faces, albedo (or an unlit texture input) is a
        pyopencl.array.Array on this renderer's queue, the projection, normals, shading and
        rasterisation run on the device and the images come back as pyopencl arrays
        (softras_cl.scene.device_render; docs/api.md, "Device-resident calls"). Lights: Lambert
        and SH (a PhongLight needs numpy inputs); needs cl_khr_fp64. check_values=False (device
        inputs only): SoftRasterizer.forward's, and the faces are taken as unchanged in place
        since an earlier call with the same array object; vertices behind a perspective camera
        are refused all the same.
        """
        grads = _check_grad_groups(grads, self.shading)
        args = dict(vertices=vertices, faces=faces, albedo=albedo, face_textures=face_textures,
                    texture_image=texture_image, uvs=uvs)
        run = dict(zip(RUN_FIELDS, (sigma, gamma, near, far)))
        if device_render.uses_device(args):
            return device_render.forward_device(self, args, cameras, light, grads, roi, run, check_values)
        single_camera = isinstance(cameras, Camera)
        cameras, verts, batched = _views(cameras, vertices, self.settings.image_size)
        self.check_run(run, len(cameras))
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"faces must be a non-empty (F, 3) array: the mesh has no faces (got shape {faces.shape})")
        _check_albedo(albedo, verts.shape)
        light = shading.view_lights(light if light is not None else shading.LambertLight(), len(cameras))
        screen, cam_ctx = zip(*(cam.project(v) for cam, v in zip(cameras, verts)))
        screen = np.concatenate(screen, 0)
        color_args, shade_ctx = self._colors(verts, faces, cameras, albedo, light, face_textures,
                                               texture_image, uvs)
        raster = self._rasterizer(cameras[0].projection, color_args, light)
        out = raster.forward(screen, faces, grads=_raster_grads(grads, self.shading), roi=roi, **color_args, **run)
        saved = RenderContext(raster, out, cameras, cam_ctx, shade_ctx, light, grads, batched,
                              single_camera, np.shape(albedo) if albedo is not None else None, self)
        return RenderOutput(out.rgb, out.alpha, out.depth, saved)

    def check_run(self, run: dict, views: int) -> None:
        """ValueError naming the field unless this call's RUN_FIELDS values (None: the settings'
        own) pass RasterSettings' checks with near and far holding one value per view, if a
        sequence; run by forward before any kernel."""
        changes = {name: value for name, value in run.items() if value is not None}
        (self.settings.replace(**changes) if changes else self.settings).depth_ranges(views)

    def backward(self, output: RenderOutput, grad_rgb=None, grad_alpha=None, grad_depth=None) -> dict:
        """Gradients of a scalar loss given dL/d(rgb, alpha, depth) (each None or the output's
        shape). Returns {group: gradient} for the groups passed to forward(grads=...):
        vertices (shape given), albedo (shape given; for unlit textures the texture's shape),
        camera (a dict of rotation (3,), translation (3,), focal (2,) per view: a list when a
        list of cameras was given), focal ((2,) [dL/dfx, dL/dfy] per view, likewise: camera's
        focal without the rest of camera), light (dict of the light's parameters). output:
        what this renderer's forward returned, with grads (ValueError for another's).

        After a device-resident forward the cotangents may be pyopencl arrays (numpy ones are
        uploaded); vertices and albedo gradients come back as float64 pyopencl arrays, camera,
        focal and light gradients as numpy (summed on the device, read back)."""
        saved = self._own_context(output)
        if saved.device is not None:
            return device_render.backward_device(self, saved, grad_rgb, grad_alpha, grad_depth)
        g_raster = saved.raster.backward(saved.raster_out, grad_rgb, grad_alpha, grad_depth)
        g_shade = self._shading_vjp(saved, g_raster)
        camera = "camera" in saved.grads or ("focal" if "focal" in saved.grads else False)
        g_cams = [cam.project_vjp(ctx, g_raster["vertices"][b:b + 1], camera=camera)
                  if "vertices" in g_raster else None
                  for b, (cam, ctx) in enumerate(zip(saved.cameras, saved.cam_ctx))]
        return self._collect(saved, g_raster, g_shade, g_cams)

    def _own_context(self, output) -> RenderContext:
        """output.saved, checked to come from this renderer's forward with grads."""
        if not isinstance(output, RenderOutput):
            raise TypeError(f"output must be the RenderOutput of this renderer's forward, got {type(output).__name__}")
        saved = output.saved
        if saved is None or not saved.grads:
            raise ValueError("output: forward() was called without grads=...; nothing to differentiate")
        if saved.renderer is not self:
            made = saved.raster.settings
            raise ValueError(f"output was made by another Renderer (shading={saved.renderer.shading!r}, "
                             f"image_size={made.image_size}, dtype={made.dtype!r}): call backward on the "
                             "renderer whose forward made it")
        return saved

    # ---- stages ----------------------------------------------------------------------------
    def _colors(self, verts, faces, cameras, albedo, light, face_textures, texture_image, uvs):
        """Raster colour arguments and the shading context (None when unlit)."""
        if self.shading == "none":
            given = dict(colors=albedo, face_textures=face_textures, texture_image=texture_image, uvs=uvs)
            return {k: v for k, v in given.items() if v is not None}, None
        if albedo is None:
            raise ValueError(f"albedo is required with shading={self.shading!r}")
        centres = np.stack([cam.center() for cam in cameras])
        batch_albedo = np.broadcast_to(np.asarray(albedo, np.float64), verts.shape).copy() \
            if np.ndim(albedo) == 2 else np.asarray(albedo, np.float64)
        if self.shading == "vertex":
            colors, ctx = shading.shade_vertices(verts, faces, batch_albedo, light, centres)
            return dict(colors=colors), ctx
        if self.shading == "pixel":
            normals, ctx = shading.vertex_normals(verts, faces)
            return dict(colors=batch_albedo, normals=normals, light=_light_vector(light)), ctx
        face_albedo = batch_albedo[:, faces].mean(axis=2)
        colors, ctx = shading.shade_faces(verts, faces, face_albedo, light, centres)
        return dict(face_textures=colors[:, :, None, None, :]), ctx

    def _rasterizer(self, projection: str, color_args: dict, light) -> SoftRasterizer:
        texture = ("face" if "face_textures" in color_args else
                   "uv" if "texture_image" in color_args else "vertex")
        lighting = ("none" if self.shading != "pixel" else
                    "sh" if isinstance(light, shading.SHLight) else "lambert")
        key = (texture, lighting, projection)
        if key not in self._rasterizers:
            s = self.settings.replace(texture=texture, lighting=lighting,
                                      perspective_correct=projection == "perspective")
            self._rasterizers[key] = SoftRasterizer(s, device=self.device, context=self.context,
                                                     queue=self.queue)
        return self._rasterizers[key]

    def _shading_vjp(self, saved: RenderContext, g_raster: dict) -> dict:
        """Shading vjp (vertices, albedo, camera_center, light parameters), or {} when unlit."""
        g_colors = g_raster.get("colors")
        if saved.shade_ctx is None or g_colors is None:
            return {}
        if self.shading == "pixel":
            return dict(shading.vertex_normals_vjp(saved.shade_ctx, g_raster["normals"]),
                        albedo=g_colors, **_light_vector_vjp(saved.light, g_raster["light"]))
        if self.shading == "vertex":
            return shading.shade_vertices_vjp(saved.shade_ctx, g_colors)
        return shading.shade_faces_vjp(saved.shade_ctx, g_colors[:, :, 0, 0, :])

    def _collect(self, saved: RenderContext, g_raster: dict, g_shade: dict, g_cams: list) -> dict:
        """The groups asked for, from the rasteriser, shading and camera gradients."""
        grads, out = saved.grads, {}
        if "vertices" in grads:
            g = np.stack([c["vertices"] for c in g_cams]) + g_shade.get("vertices", 0.0)
            out["vertices"] = g if saved.batched else g.sum(0)
        if "albedo" in grads:
            out["albedo"] = self._albedo_grad(saved, g_raster, g_shade)
        if "camera" in grads:
            centres = g_shade.get("camera_center")
            per_view = [_camera_grads(cam, ctx, g, None if centres is None else centres[b])
                        for b, (cam, ctx, g) in enumerate(zip(saved.cameras, saved.cam_ctx, g_cams))]
            out["camera"] = ({k: sum(v[k] for v in per_view) for k in per_view[0]}
                             if saved.single_camera else per_view)
        if "focal" in grads:
            out["focal"] = sum(g["focal"] for g in g_cams) if saved.single_camera else [g["focal"] for g in g_cams]
        if "light" in grads:
            out["light"] = {k: g_shade[k] for k in saved.light.params()}
        return out

    def _albedo_grad(self, saved: RenderContext, g_raster: dict, g_shade: dict) -> np.ndarray:
        """dL/d(albedo) in the shape given (the colour input's gradient when unlit)."""
        if self.shading == "none":
            return g_raster["colors"]
        g = g_shade["albedo"]
        if self.shading == "face":   # face albedo = mean of its corners
            mesh = saved.raster_out.saved.mesh
            per_corner = np.repeat(g[:, :, None, :] / 3.0, 3, axis=2)
            g = scatter_corners(per_corner, mesh.faces, mesh.n_vertices)
        return g if len(saved.albedo_shape) == 3 else g.sum(0)


def _camera_grads(camera: Camera, ctx: ProjectionContext, g_proj: dict, g_center) -> dict:
    """Projection gradients plus those reaching the camera centre c = -R^T t through shading
    (ctx: the camera's ProjectionContext)."""
    out = {k: g_proj[k] for k in ("rotation", "translation", "focal")}
    if g_center is not None:
        rot = camera.rotation_matrix()
        out["translation"] = out["translation"] - rot @ g_center
        out["rotation"] = out["rotation"] + rodrigues_vjp(ctx.rotation, -np.outer(camera.translation, g_center))["omega"]
    return out


def _check_grad_groups(grads, shading_mode: str) -> tuple:
    grads = tuple(grads)
    bad = [g for g in grads if g not in GRAD_GROUPS]
    if bad:
        raise ValueError(f"grads must be a subset of {GRAD_GROUPS}, got {grads!r}")
    if "light" in grads and shading_mode == "none":
        raise ValueError("grads asks for 'light' but shading='none' uses no light")
    return grads
