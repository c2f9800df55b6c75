"""Renderer.forward / backward of device-resident inputs (pyopencl arrays on renderer.queue): the
camera projection, normals, Lambert/SH shading and their vjps on the device (kernels in
softras_cl.scene.device_kernels), then the device-resident rasteriser. The images and the
vertex/albedo gradients stay on the device; the camera's and the light's parameter gradients are
summed on the device and read back as numpy (tens of floats), finished on the host (rodrigues_vjp,
the light direction's normalisation).

Bad input raises the numpy path's error, word for word: what an argument is (shape, dtype) is
checked from its metadata, its values (NaN/Inf, vertices behind a perspective camera, face indices)
by device counts; when one fails, the numpy forward runs on downloaded copies and raises.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from softras_cl.raster.device_inputs import ValueChecks, any_bad, is_device_array, on_host, standin
from softras_cl.raster.device_arrays import DeviceArrays
from softras_cl.scene import shading
from softras_cl.scene.device_incidence import DeviceIncidence, IncidenceCache
from softras_cl.scene.device_kernels import CAMERA_PRODUCTS, SceneKernels, camera_params
from softras_cl.scene.render_inputs import (RenderContext, RenderOutput, _check_albedo, _light_vector,
                                           _light_vector_vjp, _raster_grads, _views)
from softras_cl.scene.rotation import rodrigues_vjp

ARRAY_ARGS = ("vertices", "faces", "albedo", "face_textures", "texture_image", "uvs")


class DeviceTools:
    """The device helpers of one renderer: scene kernels, raster array kernels, value checks and
    the incidence lists of its face arrays."""

    def __init__(self, ctx, queue):
        self.queue = queue
        self.kernels = SceneKernels(ctx, queue)
        self.arrays = DeviceArrays(ctx, queue)
        self.checks = ValueChecks(ctx)
        self.incidence = IncidenceCache(queue, self.kernels)


@dataclass
class Normals:
    """Device normals of one forward (float64): unit (B*N, 3) and length (B*N,) (N = V vertex
    normals, F face normals), the face edges e1, e2 (B*F, 3), and whether they are per vertex."""
    unit: cla.Array
    length: cla.Array
    e1: cla.Array
    e2: cla.Array
    per_vertex: bool


@dataclass
class DeviceState:
    """What the device backward needs from one forward.

    verts: (V, 3) or (B, V, 3) float64 world vertices, shared when 2-D; params (B, CAMERA_PARAMS)
    camera parameters; cam (B, V, 3) camera-frame points; screen (B, V, 3) [x_ndc, y_ndc, Z], the
    rasteriser's vertices; incidence (None when unlit); normals
    (None when unlit); albedo: the float64 albedo shaded (vertex: (V, 3) shared or (B, V, 3);
    face: (B*F, 3)); irradiance (B*N, 3) and cosines (B*N,) (Lambert) of the shading; light_vec:
    the light's device vector (Lambert: unit direction, ambient, directional; SH: coefficients *
    A_l; one such row per view for a ViewLights) and light_len the direction's length (Lambert,
    one per light); batch B, n_vertices V.
    """
    verts: cla.Array
    params: cla.Array
    cam: cla.Array
    screen: cla.Array
    incidence: DeviceIncidence | None = None
    normals: Normals | None = None
    albedo: cla.Array | None = None
    irradiance: cla.Array | None = None
    cosines: cla.Array | None = None
    light_vec: cla.Array | None = None
    light_len: np.ndarray | None = None
    batch: int = 1
    n_vertices: int = 0


def uses_device(args: dict) -> bool:
    """Whether any array argument of Renderer.forward is a pyopencl array."""
    return any(is_device_array(args.get(n)) for n in ARRAY_ARGS)


def _check_context(name: str, value, ctx) -> None:
    if is_device_array(value) and value.context.int_ptr != ctx.int_ptr:
        raise ValueError(f"{name} is a pyopencl array of another OpenCL context than this renderer's: "
                         "make it on renderer.queue (or copy it there through the host)")


def raise_numpy_error(renderer, args: dict, cameras, light) -> None:
    """Run the numpy forward on host copies of args (it raises the error the device checks found)."""
    host = {n: on_host(v) for n, v in args.items()}
    renderer.forward(host["vertices"], host["faces"], cameras, albedo=host.get("albedo"), light=light,
                     face_textures=host.get("face_textures"), texture_image=host.get("texture_image"),
                     uvs=host.get("uvs"))
    raise RuntimeError("the device checks found bad values that the numpy path did not")


def _shape_only(value):
    """A float64 numpy stand-in of a device array's shape (zero strides, no memory); numpy
    arrays as they are."""
    if not is_device_array(value):
        return value
    return np.lib.stride_tricks.as_strided(np.zeros(1), shape=value.shape, strides=(0,) * value.ndim,
                                           writeable=False)


def check_metadata(renderer, args: dict, cameras, light) -> None:
    """Context, dtypes and shapes of the device arguments, from their metadata; anything the numpy
    path would refuse raises its error (the numpy forward on host copies)."""

    for name in ARRAY_ARGS:
        _check_context(name, args.get(name), renderer.context)
    vertices, faces, albedo = args["vertices"], args["faces"], args.get("albedo")
    ok = (getattr(vertices, "dtype", np.dtype(np.float64)).kind == "f"
          and (albedo is None or getattr(albedo, "dtype", np.dtype(np.float64)).kind == "f")
          and getattr(faces, "dtype", np.dtype(np.int64)).kind in "iu")
    try:
        _, verts, _ = _views(cameras, _shape_only(vertices), renderer.settings.image_size)
        shape = np.shape(faces)
        if len(shape) != 2 or shape[1] != 3 or shape[0] == 0 or 0 in np.shape(vertices):
            ok = False
        _check_albedo(standin(albedo), verts.shape)
        if (renderer.shading in ("vertex", "face") and albedo is not None and len(np.shape(albedo)) == 3
                and np.shape(albedo)[0] != verts.shape[0]):
            ok = False       # the numpy path's shading refuses an albedo batch of 1 for B > 1 views
    except (ValueError, TypeError):
        ok = False
    kind = type(light[0]) if isinstance(light, (list, tuple)) and light else type(light)
    if issubclass(kind, shading.PhongLight) and renderer.shading in ("vertex", "face"):
        raise ValueError("light: the device-resident Renderer shades with LambertLight and SHLight; a "
                         "PhongLight needs numpy inputs (its view directions are not on the device yet)")
    if not ok:
        raise_numpy_error(renderer, args, cameras, light)


def to_device_args(tools: DeviceTools, args: dict) -> dict:
    """The arguments with numpy arrays uploaded (None and device arrays as they are)."""
    return {n: v if v is None or is_device_array(v) else cla.to_device(tools.queue, np.ascontiguousarray(v))
            for n, v in args.items()}


def project(tools: DeviceTools, cameras: list, verts: cla.Array) -> DeviceState:
    """Project the float64 world vertices (V, 3) or (B, V, 3) with B cameras: a DeviceState with
    the camera-frame points and the screen vertices (B, V, 3) float64."""
    k, batch = tools.kernels, len(cameras)
    n_vertices = verts.shape[-2]
    params = cla.to_device(tools.queue, camera_params(cameras))
    screen, cam = k.empty((batch, n_vertices, 3)), k.empty((batch, n_vertices, 3))
    k("project", batch * n_vertices, screen, cam, verts, params, np.int64(n_vertices), np.int32(verts.ndim == 2))
    return DeviceState(verts, params, cam, screen, batch=batch, n_vertices=n_vertices)


def value_counts(tools: DeviceTools, state: DeviceState, albedo, check_values: bool = True) -> list:
    """Device counts of bad values: camera points non-finite or behind a perspective camera, and
    (check_values) albedo NaN/Inf."""
    counts = [tools.kernels.count("behind", state.cam, state.params, np.int64(state.n_vertices))]
    if albedo is not None and check_values:
        counts.append(tools.checks.count_bad_floats(albedo, False))
    return counts


def face_normals_device(tools: DeviceTools, state: DeviceState, per_vertex: bool) -> Normals:
    """Face cross products of the state's vertices, normalised per face, or summed onto the
    vertices over the incidence list then normalised (per_vertex)."""
    k, inc, batch = tools.kernels, state.incidence, state.batch
    n_faces, n_vertices = inc.n_faces, state.n_vertices
    cross, e1, e2 = (k.empty((batch * n_faces, 3)) for _ in range(3))
    k("face_cross", batch * n_faces, cross, e1, e2, state.verts, inc.faces, np.int64(n_faces),
      np.int64(n_vertices), np.int32(state.verts.ndim == 2))
    if per_vertex:
        summed = k.empty((batch * n_vertices, 3))
        k("vertex_sums", summed.shape[0], summed, cross, inc.start, inc.entries, np.int64(n_vertices),
          np.int64(n_faces), np.int32(3), np.float64(1.0))
        cross = summed
    unit, length = k.empty(cross.shape), k.empty(cross.shape[0])
    k("normalize", cross.shape[0], unit, length, cross)
    return Normals(unit, length, e1, e2, per_vertex)


def _per_view(light) -> tuple[list, bool]:
    """(the lights: one, or one per view of a ViewLights; whether they are per view)."""
    if isinstance(light, shading.ViewLights):
        return light.lights, True
    return [light], False


def shade_device(tools: DeviceTools, state: DeviceState, light, albedo: cla.Array, n_items: int) -> cla.Array:
    """Colours (B*N, 3) of the state's normals lit by a LambertLight or SHLight (or a ViewLights
    of them: one per view); albedo (n_items, 3) shared by the batch or (B*N, 3). Saves
    irradiance (and cosines) in the state."""
    k, n = tools.kernels, state.normals.unit.shape[0]
    colors, irr = k.empty((n, 3)), k.empty((n, 3))
    shared = np.int32(albedo.shape[0] != n)
    lights, per_view = _per_view(light)
    stride = np.int64(n // state.batch if per_view else 0)
    kind = type(lights[0])
    if issubclass(kind, shading.SHLight):
        state.light_vec = cla.to_device(tools.queue, np.concatenate([(l.coefficients * shading.SH_A).ravel()
                                                                     for l in lights]))
        k("sh", n, colors, irr, state.normals.unit, albedo, state.light_vec, np.int64(n_items), shared, stride)
    elif kind is shading.LambertLight:
        units, lengths = zip(*(shading._normalize(l.direction) for l in lights))
        state.light_vec = cla.to_device(tools.queue, np.concatenate(
            [np.concatenate([u, l.ambient, l.directional]) for u, l in zip(units, lights)]))
        state.light_len = np.array(lengths)
        state.cosines = k.empty(n)
        k("lambert", n, colors, irr, state.cosines, state.normals.unit, albedo, state.light_vec,
          np.int64(n_items), shared, stride)
    else:
        raise ValueError(f"light must be a LambertLight or SHLight on the device path, got {kind.__name__}")
    state.albedo, state.irradiance = albedo, irr
    return colors


def shade_vjp_device(tools: DeviceTools, state: DeviceState, light, g_colors: cla.Array) -> tuple:
    """(normals gradient (B*N, 3), albedo gradient (B*N, 3), {light parameter: numpy gradient,
    stacked over the views (B, ...) for a ViewLights}) of the shading, for the colour cotangent
    g_colors (B*N, 3) float64."""
    k, n = tools.kernels, g_colors.shape[0]
    g_n, g_albedo = k.empty((n, 3)), k.empty((n, 3))
    n_items = state.albedo.shape[0] if state.albedo.shape[0] != n else n
    shared = np.int32(state.albedo.shape[0] != n)
    unit = state.normals.unit
    lights, per_view = _per_view(light)
    stride, groups = (np.int64(n // state.batch), state.batch) if per_view else (np.int64(0), 1)
    if issubclass(type(lights[0]), shading.SHLight):
        products = k.empty((groups, n // groups, 27))
        k("sh_vjp", n, g_n, g_albedo, products, g_colors, unit, state.albedo, state.irradiance,
          state.light_vec, np.int64(n_items), shared, stride)
        sums = k.sum_products(products).get().reshape(groups, 3, 9) * shading.SH_A
        return g_n, g_albedo, dict(coefficients=sums if per_view else sums[0])
    products = k.empty((groups, n // groups, 9))
    k("lambert_vjp", n, g_n, g_albedo, products, g_colors, unit, state.albedo, state.irradiance,
      state.cosines, state.light_vec, np.int64(n_items), shared, stride)
    sums = k.sum_products(products).get()
    units = state.light_vec.get().reshape(groups, 9)[:, :3]
    direction = np.stack([shading._normalize_vjp(u, length, g[6:9])
                          for u, length, g in zip(units, np.atleast_1d(state.light_len), sums)])
    grads = dict(ambient=sums[:, 0:3], directional=sums[:, 3:6], direction=direction)
    return g_n, g_albedo, grads if per_view else {name: g[0] for name, g in grads.items()}


def normals_vjp_device(tools: DeviceTools, state: DeviceState, g_normals: cla.Array) -> cla.Array:
    """Vertex gradient (B, V, 3) of the normals' cotangent g_normals (B*N, 3)."""
    k, inc, nrm, batch = tools.kernels, state.incidence, state.normals, state.batch
    n_faces, n_vertices = inc.n_faces, state.n_vertices
    g_cross = k.empty(g_normals.shape)
    k("normalize_vjp", g_normals.shape[0], g_cross, nrm.unit, nrm.length, g_normals)
    corners = k.empty((batch * n_faces, 9))
    k("cross_vjp", batch * n_faces, corners, g_cross, g_cross, nrm.e1, nrm.e2, inc.faces, np.int64(n_faces),
      np.int64(n_vertices), np.int32(nrm.per_vertex))
    out = k.empty((batch, n_vertices, 3))
    k("vertex_sums", batch * n_vertices, out, corners, inc.start, inc.entries, np.int64(n_vertices),
      np.int64(3 * n_faces), np.int32(1), np.float64(1.0))
    return out


def face_albedo_to_vertices(tools: DeviceTools, state: DeviceState, g_face: cla.Array) -> cla.Array:
    """(B, V, 3): each face's albedo gradient (B*F, 3) divided by 3 and added to its corners."""
    k, inc = tools.kernels, state.incidence
    out = k.empty((state.batch, state.n_vertices, 3))
    k("vertex_sums", out.size // 3, out, g_face, inc.start, inc.entries, np.int64(state.n_vertices),
      np.int64(inc.n_faces), np.int32(3), np.float64(3.0))
    return out


def camera_vjp_device(tools: DeviceTools, state: DeviceState, g_screen: cla.Array, extra, with_camera: bool):
    """(vertex gradient (B, V, 3) = the projection's plus `extra` (B, V, 3) or None, per-view
    (B, CAMERA_PRODUCTS) numpy sums of the camera products or None)."""
    k, batch, n_vertices = tools.kernels, state.batch, state.n_vertices
    g_verts = k.empty((batch, n_vertices, 3))
    products = k.empty((batch, n_vertices, CAMERA_PRODUCTS)) if with_camera else g_verts
    k("project_vjp", batch * n_vertices, g_verts, products, tools.arrays.contiguous(g_screen, np.float64),
      state.cam, state.verts, state.params, g_verts if extra is None else extra, np.int64(n_vertices),
      np.int32(state.verts.ndim == 2), np.int32(extra is not None), np.int32(with_camera))
    sums = k.sum_products(products).get() if with_camera else None
    return g_verts, sums


def camera_grads(cameras: list, sums: np.ndarray, focal_only: bool) -> list:
    """Per-view camera gradients from the (B, CAMERA_PRODUCTS) sums: dicts of rotation (3,),
    translation (3,), focal (2,) (focal alone when focal_only), numpy float64."""
    out = []
    for cam, s in zip(cameras, sums):
        k = cam._ndc_scale()
        focal = np.array([k * s[12], -k * s[13]])
        if focal_only:
            out.append(dict(focal=focal))
            continue
        rotation = rodrigues_vjp(cam._rodrigues[1], s[3:12].reshape(3, 3))["omega"]
        out.append(dict(rotation=rotation, translation=s[0:3].copy(), focal=focal))
    return out


def forward_device(renderer, args: dict, cameras, light, grads: tuple, roi, run: dict, check_values: bool = True):
    """Renderer.forward of device-resident inputs (args: the ARRAY_ARGS by name): a RenderOutput
    of pyopencl images whose context holds a DeviceState. check_values: Renderer.forward's."""
    from softras_cl.scene.camera import Camera

    tools = renderer.device_tools
    single_camera = isinstance(cameras, Camera)
    light = light if light is not None else shading.LambertLight()
    check_metadata(renderer, args, cameras, light)
    cams, _, batched = _views(cameras, _shape_only(args["vertices"]), renderer.settings.image_size)
    renderer.check_run(run, len(cams))
    light = shading.view_lights(light, len(cams))
    dev = to_device_args(tools, args)
    verts = tools.arrays.contiguous(dev["vertices"], np.float64)
    albedo = None if dev["albedo"] is None else tools.arrays.contiguous(dev["albedo"], np.float64)
    state = project(tools, cams, verts)
    if any_bad(value_counts(tools, state, albedo, check_values)):
        raise_numpy_error(renderer, args, cameras, light)
    if renderer.shading != "none":
        if albedo is None:
            raise ValueError(f"albedo is required with shading={renderer.shading!r}")
        state.incidence = tools.incidence.get(dev["faces"], state.n_vertices, unchanged=not check_values)
    color_args = _color_args(renderer, tools, state, dev, albedo, light)
    raster = renderer._rasterizer(cams[0].projection, color_args, light)
    out = raster.forward(state.screen, dev["faces"], grads=_raster_grads(grads, renderer.shading), roi=roi,
                         check_values=check_values, **color_args, **run)
    saved = RenderContext(raster, out, cams, (), None, light, grads, batched, single_camera,
                          None if args.get("albedo") is None else tuple(args["albedo"].shape), renderer, state)
    return RenderOutput(out.rgb, out.alpha, out.depth, saved)


def _color_args(renderer, tools: DeviceTools, state: DeviceState, dev: dict, albedo, light) -> dict:
    """The rasteriser's colour arguments (device arrays) of the renderer's shading."""

    if renderer.shading == "none":
        given = dict(colors=dev["albedo"], face_textures=dev["face_textures"],
                     texture_image=dev["texture_image"], uvs=dev["uvs"])
        return {k: v for k, v in given.items() if v is not None}
    batch, n_vertices = state.batch, state.n_vertices
    if renderer.shading == "pixel":
        state.normals = face_normals_device(tools, state, per_vertex=True)
        colors = tools.arrays.broadcast(albedo.reshape(1, *albedo.shape), batch, np.float64) if albedo.ndim == 2 else albedo
        return dict(colors=colors, normals=state.normals.unit.reshape(batch, n_vertices, 3),
                    light=_light_vector(light))
    if renderer.shading == "vertex":
        state.normals = face_normals_device(tools, state, per_vertex=True)
        flat = albedo.reshape(-1, 3)
        colors = shade_device(tools, state, light, flat, n_vertices)
        return dict(colors=colors.reshape(batch, n_vertices, 3))
    inc, k = state.incidence, tools.kernels
    state.normals = face_normals_device(tools, state, per_vertex=False)
    face_albedo = k.empty((batch * inc.n_faces, 3))
    k("face_albedo", face_albedo.shape[0], face_albedo, albedo, inc.faces, np.int64(inc.n_faces),
      np.int64(n_vertices), np.int32(albedo.ndim == 2))
    colors = shade_device(tools, state, light, face_albedo, inc.n_faces)
    return dict(face_textures=colors.reshape(batch, inc.n_faces, 1, 1, 3))


def backward_device(renderer, saved, grad_rgb, grad_alpha, grad_depth) -> dict:
    """Renderer.backward of a device-resident forward: vertices and albedo gradients as float64
    pyopencl arrays, camera, focal and light gradients as numpy."""
    tools, state, grads = renderer.device_tools, saved.device, saved.grads
    g_raster = saved.raster.backward(saved.raster_out, grad_rgb, grad_alpha, grad_depth)
    g_shade_verts, g_albedo, g_light = _shading_vjp_device(renderer, tools, saved, g_raster)
    out = {}
    camera = {"camera", "focal"} & set(grads)
    if "vertices" in g_raster:
        g_verts, sums = camera_vjp_device(tools, state, g_raster["vertices"], g_shade_verts, bool(camera))
        if "vertices" in grads:
            out["vertices"] = g_verts if saved.batched else tools.arrays.sum_rows(g_verts)
        if camera:
            per_view = camera_grads(saved.cameras, sums, "camera" not in grads)
            if "camera" in grads:
                out["camera"] = ({k: sum(v[k] for v in per_view) for k in per_view[0]}
                                 if saved.single_camera else per_view)
            if "focal" in grads:
                out["focal"] = (sum(v["focal"] for v in per_view) if saved.single_camera
                                else [v["focal"] for v in per_view])
    if "albedo" in grads:
        out["albedo"] = (g_albedo if renderer.shading == "none" or len(saved.albedo_shape) == 3
                         else tools.arrays.sum_rows(g_albedo))
    if "light" in grads:
        out["light"] = {k: g_light[k] for k in saved.light.params()}
    return out


def _shading_vjp_device(renderer, tools: DeviceTools, saved, g_raster: dict) -> tuple:
    """(vertex gradient (B, V, 3) of the shading or None, albedo gradient (B, V, 3) or the colour
    input's, {light parameter: numpy gradient})."""

    state, g_colors = saved.device, g_raster.get("colors")
    if renderer.shading == "none" or g_colors is None:
        return None, g_colors, {}
    batch, n_vertices = state.batch, state.n_vertices
    if renderer.shading == "pixel":
        g_verts = normals_vjp_device(tools, state, g_raster["normals"].reshape(-1, 3))
        return g_verts, g_colors, _light_vector_vjp(saved.light, g_raster["light"].get())
    g_n, g_albedo, g_light = shade_vjp_device(tools, state, saved.light, g_colors.reshape(-1, 3))
    g_verts = normals_vjp_device(tools, state, g_n)
    if renderer.shading == "face":
        g_albedo = face_albedo_to_vertices(tools, state, g_albedo)
    return g_verts, g_albedo.reshape(batch, n_vertices, 3), g_light
