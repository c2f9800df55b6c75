"""Every kernel variant, forward and backward, at tiny sizes: the sweep run under Oclgrind.

    oclgrind --data-races --uninitialized --check-api python scripts/oclgrind_sweep.py

Under `oclgrind` the only OpenCL platform is Oclgrind's simulator, which reports out-of-bounds
accesses, data races and uses of uninitialised memory on stderr; this program drives every
kernel variant through the public API (SoftRasterizer and Renderer) on an 11 x 13 image and
checks that every output and gradient is finite. It exits 1 on a non-finite value or an
exception, 2 when there is no Oclgrind device (it sets SOFTRAS_CL_DEVICE=oclgrind, so
softras_cl picks Oclgrind's platform by name, unless --any-device). The Oclgrind
reports themselves are judged by tests/validate/test_oclgrind.py, which runs this program and
fails on any of them. docs/oclgrind.md lists the variants.

--any-device runs the same sweep on whatever device softras_cl would choose (a quick check of
finiteness on PoCL); --list prints the variants and exits; --only SUBSTRING runs the variants
whose name contains it.
"""
from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import sys
import time

import numpy as np
import pyopencl as cl

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.cl.device import ENV_VAR, select_device
from softras_cl.errors import InputError
from softras_cl.raster import rasterizer
from softras_cl.raster.reduce import GradSums
from softras_cl.scene.camera import Camera
from softras_cl.scene.meshes import icosphere
from softras_cl.scene.renderer import Renderer
from softras_cl.scene.shading import LambertLight, PhongLight, SHLight

H, W = 13, 11   # odd, non-square, neither side a multiple of a tile (8 or 16 x 8, 4 x 8 in float64)


def pixel_centre(col: int, row: int) -> tuple[float, float]:
    """NDC of a pixel centre (docs/conventions.md): the shorter side (W here) spans [-1, 1]."""
    s = min(W, H)
    return (2 * col + 1 - W) / s, (H - 2 * row - 1) / s


# One face per entry, three vertices of its own: (x, y, z) per corner, screen space, CCW unless
# named otherwise. Some are dropped before any kernel (zero area, behind the camera, all beyond
# far, back-facing when single-sided); the rest overlap, straddle near or far, run off the image
# into the padding columns or rows, are thinner than a pixel or have corners on pixel centres.
_C0, _C4 = pixel_centre(0, 0), pixel_centre(4, 4)
FACES = [
    ("large", [(-0.8, -0.9, 2.0), (0.7, -0.6, 3.0), (-0.2, 0.9, 2.5)]),
    ("back-facing", [(-0.5, -0.4, 2.2), (0.2, 0.8, 2.4), (0.6, -0.5, 2.6)]),
    ("covers image", [(-4.0, -4.0, 6.0), (4.0, -4.0, 6.0), (0.0, 4.0, 6.0)]),
    ("straddles near", [(-0.7, 0.1, 0.5), (0.1, 0.2, 3.0), (-0.3, 0.8, 3.0)]),
    ("straddles far", [(0.0, -0.9, 4.0), (0.8, -0.9, 14.0), (0.4, -0.1, 14.0)]),
    ("needle", [(-0.8, 0.5, 2.0), (0.8, 0.52, 2.0), (0.8, 0.5201, 2.0)]),
    ("sub-pixel", [(0.1, -0.2, 1.5), (0.13, -0.2, 1.5), (0.11, -0.17, 1.5)]),
    ("corners on pixel centres", [(_C0[0], _C0[1], 2.2), (_C0[0], _C4[1], 2.2), (_C4[0], _C0[1], 2.2)]),
    ("into padding columns", [(0.75, -0.3, 1.8), (1.6, -0.2, 1.8), (0.8, 0.4, 1.8)]),
    ("into padding rows", [(-0.6, -1.0, 1.9), (0.4, -1.6, 1.9), (0.3, -0.8, 1.9)]),
    ("off screen", [(2.5, 2.5, 2.0), (3.0, 2.5, 2.0), (2.7, 3.0, 2.0)]),
    ("zero area", [(0.2, 0.2, 2.0), (0.2, 0.2, 2.0), (0.4, 0.5, 2.0)]),
    ("collinear", [(-0.5, -0.5, 2.0), (0.0, 0.0, 2.0), (0.5, 0.5, 2.0)]),
    ("behind camera", [(-0.3, -0.3, -1.0), (0.3, -0.3, 2.0), (0.0, 0.3, 2.0)]),
    ("beyond far", [(-0.3, -0.3, 20.0), (0.3, -0.3, 20.0), (0.0, 0.3, 20.0)]),
]
NEAR, FAR = 1.0, 10.0


_kept_buffers: list = []


def keep_buffers_alive() -> None:
    """Never release an OpenCL buffer while the sweep runs (a workaround for Oclgrind 21.10).

    Oclgrind's --uninitialized plugin keeps a buffer's shadow (which bytes are initialised) after
    the buffer is released. A later buffer that gets the same slot and is never written by the
    host inherits the old, smaller shadow: the kernels' stores past its end are dropped from the
    shadow and loads there read as uninitialised, so correct kernels get false reports. Keeping
    every buffer alive gives each new buffer a fresh slot (the sweep's buffers are tiny).
    """
    base = cl.Buffer
    if getattr(base, "_kept_alive", False):
        return

    class KeptBuffer(base):
        _kept_alive = True

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            _kept_buffers.append(self)

    cl.Buffer = KeptBuffer


def skip_pyopencl_nvidia_probe() -> None:
    """Stop pyopencl asking non-NVIDIA devices for NVIDIA's compute capability.

    pyopencl queries CL_DEVICE_COMPUTE_CAPABILITY_MAJOR_NV for every kernel it creates and
    catches the CL_INVALID_VALUE other drivers return; `--check-api` reports each such call as
    an API error, so without this every kernel would add one report that is not ours.
    """
    import pyopencl.characterize as characterize
    probe = characterize.nv_compute_capability
    if getattr(probe, "_skips_others", False):
        return

    def nvidia_only(dev):
        return probe(dev) if "nvidia" in dev.platform.name.lower() else None

    nvidia_only._skips_others = True
    characterize.nv_compute_capability = nvidia_only


def raster_scene(batch: int, texture: str, tex_res: int = 2, seed: int = 0, crowd: int = 0) -> tuple:
    """(vertices (B, V, 3), faces (F, 3), colour inputs for `texture`): FACES and `crowd` more small
    faces over the top-left 16 x 8 pixels, each face moved a little in x, y after the first item
    (a shift keeps degenerate faces degenerate)."""
    rng = np.random.default_rng(seed)
    base = np.array([corner for _, corners in FACES for corner in corners], np.float64)
    if crowd:
        centres = np.array(pixel_centre(4, 3)) + rng.uniform(-0.3, 0.3, (crowd, 1, 2))
        xy = centres + rng.uniform(-0.2, 0.2, (crowd, 3, 2))
        base = np.concatenate([base, np.dstack([xy, rng.uniform(1.5, 5.0, (crowd, 3, 1))]).reshape(-1, 3)])
    n_v, n_f = len(base), len(base) // 3
    vertices = np.repeat(base[None], batch, 0)
    shift = rng.normal(scale=0.02, size=(batch - 1, n_f, 1, 2))
    vertices[1:, :, :2] += np.broadcast_to(shift, (batch - 1, n_f, 3, 2)).reshape(batch - 1, n_v, 2)
    faces = np.arange(n_v).reshape(-1, 3)
    colors = {
        "vertex": lambda: dict(colors=rng.uniform(0, 1, (batch, n_v, 3))),
        "face": lambda: dict(face_textures=rng.uniform(0, 1, (batch, n_f, tex_res, tex_res, 3))),
        "uv": lambda: dict(texture_image=rng.uniform(0, 1, (batch, 5, 7, 3)),
                           uvs=rng.uniform(-0.1, 1.1, (batch, n_v, 2))),
    }[texture]()
    return vertices, faces, colors


def raster_settings(**kw) -> RasterSettings:
    base = dict(image_size=(H, W), sigma=1e-3, gamma=1e-2, dist_eps=1e-4, near=NEAR, far=FAR,
                double_sided=True, outputs=("rgb", "alpha", "depth"), background=(0.2, 0.3, 0.4))
    return RasterSettings(**{**base, **kw})


def _finite(what: str, value) -> None:
    if value is None:
        return
    if isinstance(value, dict):
        for k, v in value.items():
            _finite(f"{what}[{k}]", v)
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _finite(f"{what}[{i}]", v)
    elif not np.all(np.isfinite(np.asarray(value))):
        raise AssertionError(f"{what} has non-finite values")


def _drawn(out, s: RasterSettings) -> None:
    """Fail when the image shows no face (the sweep would then exercise nothing)."""
    if out.alpha is not None:
        drawn = out.alpha.max() > 0.5
    elif out.depth is not None:
        drawn = out.depth.min() < s.far
    else:
        drawn = np.abs(out.rgb - np.asarray(s.background)).max() > 0.1
    if not drawn:
        raise AssertionError("no face drawn")


def _cotangents(out, rng, skip=()) -> dict:
    """Random dL/d(output) for each output produced, except those named in skip (left None)."""
    return {f"grad_{n}": rng.normal(size=getattr(out, n).shape)
            for n in ("rgb", "alpha", "depth") if getattr(out, n) is not None and n not in skip}


def roi_mask(batch: int, per_item: bool) -> np.ndarray:
    """(H, W) bool region of interest (the top-left tile's lower rows and the tile below), or
    (B, H, W) with a different region per item (the second one in the bottom-right tile)."""
    mask = np.zeros((batch if per_item else 1, H, W), bool)
    mask[0, 5:10, 2:6] = True
    mask[1:, 10:, 8:] = True
    return mask if per_item else mask[0]


@contextlib.contextmanager
def without_int64_atomics():
    """Build the rasteriser's kernels as for a device without cl_khr_int64_base_atomics."""
    real = rasterizer.has_int64_atomics
    rasterizer.has_int64_atomics = lambda device: False
    try:
        yield
    finally:
        rasterizer.has_int64_atomics = real


def run_raster(batch: int, grads: tuple, tex_res: int = 2, skip_cot: tuple = (),
               faces_per_item: bool = False, roi: str | None = None, lanes: int | None = None,
               float_sums: bool = False, crowd: int = 0, int64_atomics: bool = True,
               device_setup: bool = False, **kw) -> None:
    """One SoftRasterizer forward (and backward when grads); float_sums: the gradient reductions
    accumulate in the kernel dtype, as on a device without cl_khr_fp64; crowd: that many more
    faces in one tile (raster_scene); int64_atomics False: the uv texel gradients' fallback;
    device_setup: the faces set up by kernel face_setup (else, on so few faces, by the host)."""
    if not int64_atomics:
        with without_int64_atomics():
            return run_raster(batch, grads, tex_res, skip_cot, faces_per_item, roi, lanes, float_sums, crowd,
                              device_setup=device_setup, **kw)
    s = raster_settings(**kw)
    vertices, faces, colors = raster_scene(batch, s.texture, tex_res, crowd=crowd)
    if "rgb" not in s.outputs:
        colors = {}
    if s.lighting != "none":
        normals = np.random.default_rng(2).normal(size=vertices.shape)
        light = (np.r_[0.3, 0.4, 0.5, 0.6, 0.5, 0.4, 0.36, 0.8, 0.48, np.zeros(18)]
                 if s.lighting == "lambert" else np.random.default_rng(3).normal(scale=0.3, size=27))
        colors = dict(colors, normals=normals, light=light)
    if faces_per_item:
        faces = np.repeat(faces[None], batch, 0)
    if roi is not None:
        colors = dict(colors, roi=roi_mask(batch, roi == "per item"))
    raster = SoftRasterizer(s, lanes=lanes)
    if device_setup:
        raster.device_setup_faces = 0
    if float_sums:
        raster.sums = GradSums(raster.ctx, raster.queue, raster.pool, raster.real, raster.lanes, False)
    plain = raster.forward(vertices, faces, **colors)
    _finite("forward", [plain.rgb, plain.alpha, plain.depth])
    _drawn(plain, s)
    if not grads:
        return
    out = raster.forward(vertices, faces, grads=grads, **colors)
    _finite("forward with state", [out.rgb, out.alpha, out.depth])
    g = raster.backward(out, **_cotangents(out, np.random.default_rng(1), skip_cot))
    _finite("gradients", g)


RENDER_LIGHTS = {
    "lambert": LambertLight(ambient=(0.3, 0.4, 0.5), directional=(0.6, 0.5, 0.4), direction=(0.3, 1.0, 0.6)),
    "phong": PhongLight(ambient=0.3, directional=0.6, direction=(0.5, 0.8, 0.7), specular=0.3, shininess=5.0),
    "sh": SHLight(np.random.default_rng(3).normal(scale=0.3, size=(3, 9)) + SHLight.ambient(0.8).coefficients),
}


def run_render(batch: int, shading: str, light: str | None, texture: str = "vertex",
               projection: str = "perspective", dtype: str = "float32", roi: bool = False,
               layout: str = "auto") -> None:
    rng = np.random.default_rng(4)
    v, f = icosphere(0, radius=0.6)
    v = v + rng.normal(scale=0.03, size=v.shape)
    eyes = [(0.4, 0.5, 3.0), (-1.5, 0.3, 2.2)][:batch]
    if projection == "perspective":
        cams = [Camera.look_at(e, (0.0, 0.05, 0.0), fov_deg=35, image_size=(H, W)) for e in eyes]
    else:
        cams = [Camera.orthographic(e, (0.0, 0.05, 0.0), scale=0.8, image_size=(H, W)) for e in eyes]
    cameras = cams[0] if batch == 1 else cams
    s = RasterSettings(image_size=(H, W), sigma=1e-3, gamma=1e-2, near=0.5, far=10.0,
                       outputs=("rgb", "alpha", "depth"), dtype=dtype, layout=layout)
    inputs = dict(albedo=rng.uniform(0.2, 0.9, v.shape))
    if shading == "none" and texture == "face":
        inputs = dict(face_textures=rng.uniform(0, 1, (batch, len(f), 2, 2, 3)))
    elif shading == "none" and texture == "uv":
        inputs = dict(texture_image=rng.uniform(0, 1, (batch, 6, 5, 3)),
                      uvs=rng.uniform(0, 1, (len(v), 2)))
    groups = ("vertices", "albedo", "camera") + (("light",) if light else ())
    renderer = Renderer(s, shading=shading)
    lit = dict(light=RENDER_LIGHTS[light]) if light else {}
    out = renderer.forward(v, f, cameras, grads=groups, roi=roi_mask(batch, True) if roi else None,
                           **inputs, **lit)
    _finite("render", [out.rgb, out.alpha, out.depth])
    _drawn(out, s)
    g = renderer.backward(out, **_cotangents(out, rng))
    _finite("render gradients", g)


def sphere_face_model():
    """A FaceModel on an icosphere (162 vertices, 320 faces; a random 68 faces carry the
    landmarks), with small random bases: the device face objective's kernels at a size Oclgrind
    simulates in seconds."""
    from softras_cl.fitting.models.face_model import FaceModel

    rng = np.random.default_rng(6)
    v, f = icosphere(2, radius=0.09)
    n = len(v)
    lmk = rng.choice(len(f), 68, replace=False)
    bary = rng.dirichlet(np.ones(3), 68)
    return FaceModel(v, rng.normal(0, 0.002, (4, n, 3)), np.ones(4), rng.normal(0, 0.002, (3, n, 3)), np.ones(3),
                     np.full((n, 3), 0.5), rng.normal(0, 0.05, (2, n, 3)), np.ones(2), f, lmk, bary)


def run_face_objective() -> None:
    """The device face objective's landmark stage (model bases, pose, front faces, the sliding
    jaw's contour candidates and argmin, the landmark term, the vjps) at a turned pose, and its
    photometric term's kernel (robust and plain) on random images. Its renders take the
    rasteriser's device-resident path, whose pyopencl scan kernels Oclgrind reports
    (docs/oclgrind.md), so the render is left to the render variants above."""
    from softras_cl.fitting.device.kernels import FIT_KERNELS
    from softras_cl.fitting.device.photo import DevicePhotoLoss
    from softras_cl.fitting.recipes import face
    from softras_cl.fitting.recipes.contour import jaw_candidates
    from softras_cl.fitting.solver import Stage
    from softras_cl.scene.device_kernels import SceneKernels
    import pyopencl.array as cla

    model, rng = sphere_face_model(), np.random.default_rng(7)
    values = dict(id=rng.normal(size=4), exp=rng.normal(size=3), albedo=rng.normal(size=2),
                  sh=np.zeros((3, 9)), rotation=np.radians([5.0, 60.0, 0.0]), translation=np.array([0.0, 0.0, -0.6]),
                  focal=np.array([30.0]))
    objective = face.DeviceFaceObjective(face.FaceScene(model, (H, W)), np.zeros((H, W, 3)), rng.uniform(0, 10, (68, 2)),
                                    focal0=30.0, contour=jaw_candidates(model))
    loss, grads, _ = objective(values, Stage("landmarks", ("id",), dict(landmarks=1.0, id_prior=1.0)))
    _finite("face objective", [np.array(loss), *grads.values()])
    queue = objective.device_model.queue
    kernels = SceneKernels(queue.context, queue, extra=FIT_KERNELS)
    for scale in (None, 0.1):
        photo = DevicePhotoLoss(kernels, rng.random((H, W, 3)), rng.random((H, W)) < 0.5, scale)
        total, grad = photo(cla.to_device(queue, rng.random((1, H, W, 3))))
        _finite("photo term", [total.get(), grad.get()])


def sphere_body_model():
    """A BodyModel on an icosphere (162 vertices) with a chain of three joints, each vertex
    skinned by two of them, random shape and pose blendshapes: the device body objective's
    kernels at a size Oclgrind simulates in seconds."""
    from softras_cl.fitting.models.body_model import BodyModel

    rng = np.random.default_rng(8)
    v, f = icosphere(2, radius=0.5)
    n, joints = len(v), 3
    weights = np.zeros((n, joints))
    pairs = rng.integers(0, joints - 1, n)
    share = rng.uniform(0.2, 0.8, n)
    weights[np.arange(n), pairs], weights[np.arange(n), pairs + 1] = share, 1.0 - share
    regressor = np.zeros((joints, n))
    regressor[np.arange(joints), rng.choice(n, joints, replace=False)] = 1.0
    return BodyModel(v, rng.normal(0, 0.01, (n, 3, 4)), regressor, [-1, 0, 1], weights, f,
                     posedirs=rng.normal(0, 0.01, (n, 3, 9 * (joints - 1))))


def run_body_objective() -> None:
    """The device body objective's own kernels: the drawn vertices posed (blendshapes, sparse
    skinning) and the skinning's vjp, on a small body with pose blendshapes; the silhouette and
    image terms with their cotangents on random images, with a care mask and without colours.
    Its render is left to the Renderer variants above, as the face objective's is."""
    import pyopencl.array as cla
    from softras_cl.cl.device import get_context, select_device
    from softras_cl.fitting.device.body_model import DeviceSkin
    from softras_cl.fitting.device.body_objective import DeviceBodyImages
    from softras_cl.fitting.recipes.body import BodyTarget

    model, rng = sphere_body_model(), np.random.default_rng(9)
    values = dict(betas=rng.normal(size=4), body_pose=rng.normal(0, 0.3, (2, 3)), global_rotation=rng.normal(0, 0.3, 3),
                  translation=rng.normal(0, 0.1, 3))
    ids = np.sort(rng.choice(model.n_vertices, 100, replace=False))
    state, ctx = model.forward(*values.values(), subset=model.subset(ids[:0]))
    skin = DeviceSkin(model, ids, get_context(select_device())[1])
    vertices, v_posed, transforms = skin.forward(values, ctx)
    sums = skin.vjp(cla.to_device(skin.kernels.queue, rng.normal(size=(len(ids), 3))), v_posed, transforms)
    _finite("body skinning", [vertices.get(), *(a.get() for a in sums)])
    for rgb, care in ((rng.random((H, W, 3)), rng.random((H, W))), (None, None)):
        images = DeviceBodyImages(skin.kernels, BodyTarget(rgb, rng.random((H, W)), None, None, 1.0, (H, W), care),
                                  (0.1, 0.2, 0.3))
        out = argparse.Namespace(alpha=cla.to_device(skin.kernels.queue, rng.random((1, H, W))),
                                 rgb=cla.to_device(skin.kernels.queue, rng.random((1, H, W, 3))))
        totals, g_alpha, g_rgb = images(out, 3.0, 1.0)
        _finite("body image terms", [totals.get(), g_alpha.get()] + ([] if g_rgb is None else [g_rgb.get()]))


def run_device_shading() -> None:
    """The device-resident Renderer's shading kernels and their vjps (Lambert and SH, one light
    for all views and one per view, albedo shared and per view) on random unit normals of two
    views: its normals and render are left out with the rest of that path (pyopencl's scan)."""
    import pyopencl.array as cla
    from softras_cl.cl.device import get_context, select_device
    from softras_cl.scene import shading
    from softras_cl.scene.device_kernels import SceneKernels
    from softras_cl.scene.device_render import DeviceState, Normals, shade_device, shade_vjp_device

    queue, rng = get_context(select_device())[1], np.random.default_rng(10)
    tools = argparse.Namespace(kernels=SceneKernels(queue.context, queue), queue=queue)
    batch, n = 2, 30
    unit = rng.normal(size=(batch * n, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    normals = Normals(cla.to_device(queue, unit), cla.to_device(queue, np.ones(batch * n)), None, None, True)
    sh = [shading.SHLight(shading.sh_ambient(0.8) + rng.normal(0, 0.1, (3, 9))) for _ in range(batch)]
    lambert = [shading.LambertLight(direction=rng.normal(size=3)) for _ in range(batch)]
    for light in (sh[0], shading.ViewLights(sh), lambert[0], shading.ViewLights(lambert)):
        for rows in (n, batch * n):
            state = DeviceState(None, None, None, None, normals=normals, batch=batch, n_vertices=n)
            albedo = cla.to_device(queue, rng.uniform(0.2, 0.9, (rows, 3)))
            colors = shade_device(tools, state, light, albedo, n)
            g_colors = cla.to_device(queue, rng.normal(size=(batch * n, 3)))
            g_n, g_albedo, g_light = shade_vjp_device(tools, state, light, g_colors)
            _finite("device shading", [colors.get(), g_n.get(), g_albedo.get(), *g_light.values()])


def gpu_layout_variants() -> list[tuple[str, callable]]:
    """The GPU layout's kernels (one pixel per work-item, tiles staged in local memory): the
    build-time flags in 18 combinations, then lighting, outputs, regions of interest, a tile with
    more faces than one local-memory chunk, the uv gradients without 64-bit atomics, renders."""
    out = []
    both = ("vertices", "colors")
    for i, (dtype, texture, (color_agg, alpha_agg)) in enumerate(itertools.product(
            ("float32", "float64"), ("vertex", "face", "uv"),
            (("softmax", "occupancy"), ("hard", "sum"), ("softmax", "hard")))):
        kw = dict(dtype=dtype, metric=("euclidean", "barycentric")[i % 2], texture=texture,
                  color_agg=color_agg, alpha_agg=alpha_agg, perspective_correct=i % 3 != 0)
        batch = 1 + i % 2
        name = (f"gpu-layout raster {dtype} {kw['metric']} {texture} {color_agg}/{alpha_agg} B={batch}"
                + ("" if kw["perspective_correct"] else " linear"))
        out.append((name, lambda b=batch, kw=kw: run_raster(b, both, layout="gpu", **kw)))
    extra = [
        ("lambert per-pixel", 2, both, dict(lighting="lambert")),
        ("sh per-pixel", 1, both, dict(lighting="sh", dtype="float64")),
        ("outputs alpha", 2, ("vertices",), dict(outputs=("alpha",))),
        ("outputs depth hard", 1, ("vertices",), dict(outputs=("depth",), color_agg="hard")),
        ("face texture R=1", 2, both, dict(texture="face", tex_res=1)),
        ("no rgb cotangent", 2, both, dict(skip_cot=("rgb",))),
        ("region of interest per item uv", 2, both, dict(roi="per item", texture="uv")),
        ("crowded tile", 1, both, dict(crowd=300)),
        ("crowded tile float64 face texture", 2, both, dict(crowd=150, dtype="float64", texture="face")),
        ("uv without int64 atomics", 2, both, dict(texture="uv", int64_atomics=False)),
        ("forward only", 2, (), dict()),
        ("depth range per view", 3, both, dict(near=(NEAR, 2.1, 0.4), far=(FAR, 5.0, 3.0))),
    ]
    for label, batch, grads, kw in extra:
        out.append((f"gpu-layout raster {label} B={batch}",
                    lambda b=batch, g=grads, kw=kw: run_raster(b, g, layout="gpu", **kw)))
    for label, batch, shading, light, texture in [("pixel sh", 2, "pixel", "sh", "vertex"),
                                                  ("unlit uv texture", 1, "none", None, "uv")]:
        out.append((f"gpu-layout render {label} B={batch}",
                    lambda b=batch, sh=shading, li=light, t=texture:
                    run_render(b, sh, li, t, layout="gpu")))
    return out


def variants() -> list[tuple[str, callable]]:
    """(name, thunk) of every case the sweep runs."""
    out = []
    both = ("vertices", "colors")
    # the full build-time matrix of the rasteriser, all three outputs, both gradients
    for i, (dtype, metric, texture, color_agg, alpha_agg) in enumerate(itertools.product(
            ("float32", "float64"), ("euclidean", "barycentric"), ("vertex", "face", "uv"),
            ("softmax", "hard"), ("occupancy", "sum", "hard"))):
        kw = dict(dtype=dtype, metric=metric, texture=texture, color_agg=color_agg,
                  alpha_agg=alpha_agg, perspective_correct=i % 2 == 0)
        batch = 1 + i % 2
        name = f"raster {dtype} {metric} {texture} {color_agg}/{alpha_agg} B={batch}" + \
               ("" if kw["perspective_correct"] else " linear")
        out.append((name, lambda b=batch, kw=kw: run_raster(b, both, **kw)))
    # 16 floats per vector (AVX-512 CPUs pick them; Oclgrind's device would pick 8)
    for label, batch, kw in [("default", 2, {}), ("face texture", 1, dict(texture="face")),
                             ("uv texture", 2, dict(texture="uv")),
                             ("hard colours, summed alpha, barycentric", 1, dict(color_agg="hard", alpha_agg="sum", metric="barycentric")),
                             ("sh per-pixel", 2, dict(lighting="sh")),
                             ("region of interest per item", 2, dict(roi="per item"))]:
        out.append((f"raster float32 16 lanes {label} B={batch}",
                    lambda b=batch, kw=kw: run_raster(b, both, dtype="float32", lanes=16, **kw)))
    out += gpu_layout_variants()
    out.append(("device face objective: landmark stage, photometric term", run_face_objective))
    out.append(("device body objective: skinning and its vjp, silhouette and image terms", run_body_objective))
    out.append(("device renderer shading: Lambert and SH, one light and one per view", run_device_shading))
    # the gradient sums as a device without cl_khr_fp64 builds them (float accumulation)
    for label, batch, kw in [("sh per-pixel", 2, dict(lighting="sh")), ("face texture", 1, dict(texture="face"))]:
        out.append((f"raster float32 float gradient sums {label} B={batch}",
                    lambda b=batch, kw=kw: run_raster(b, both, dtype="float32", float_sums=True, **kw)))
    for dtype in ("float32", "float64"):
        extra = [
            ("lambert per-pixel", 2, both, dict(lighting="lambert")),
            ("sh per-pixel", 1, both, dict(lighting="sh")),
            ("sh per-pixel hard", 2, both, dict(lighting="sh", color_agg="hard", alpha_agg="hard")),
            ("lambert per-pixel vertices only", 1, ("vertices",), dict(lighting="lambert")),
            ("lambert per-pixel colours only", 2, ("colors",), dict(lighting="lambert")),
            ("outputs alpha", 2, ("vertices",), dict(outputs=("alpha",))),
            ("outputs depth", 1, ("vertices",), dict(outputs=("depth",))),
            ("outputs depth hard", 2, ("vertices",), dict(outputs=("depth",), color_agg="hard")),
            ("outputs rgb", 1, both, dict(outputs=("rgb",))),
            ("outputs rgb+depth sum", 2, both, dict(outputs=("rgb", "depth"), alpha_agg="sum")),
            ("vertices only", 2, ("vertices",), dict()),
            ("colours only uv", 2, ("colors",), dict(texture="uv")),
            ("colours only face", 1, ("colors",), dict(texture="face")),
            ("face texture R=1", 2, both, dict(texture="face", tex_res=1)),
            ("single-sided", 2, both, dict(double_sided=False)),
            ("paper defaults sigma 1e-5 gamma 1e-4", 2, both, dict(sigma=1e-5, gamma=1e-4)),
            ("dist_eps 0", 1, both, dict(dist_eps=0.0)),
            ("fast maths", 2, both, dict(fast_math=True)),
            ("fast maths sh per-pixel", 1, both, dict(fast_math=True, lighting="sh")),
            ("no rgb cotangent", 2, both, dict(skip_cot=("rgb",))),
            ("only rgb cotangent uv", 2, both, dict(texture="uv", skip_cot=("alpha", "depth"))),
            ("faces per item", 2, both, dict(faces_per_item=True, texture="uv")),
            ("forward only", 2, (), dict()),
            ("region of interest", 1, both, dict(roi="shared")),
            ("region of interest per item uv", 2, both, dict(roi="per item", texture="uv")),
            ("region of interest per item sh per-pixel", 2, both, dict(roi="per item", lighting="sh")),
            ("depth range per view", 3, both, dict(near=(NEAR, 2.1, 0.4), far=(FAR, 5.0, 3.0))),
            ("depth range per view, device face set-up", 3, both,
             dict(near=(NEAR, 2.1, 0.4), far=(FAR, 5.0, 3.0), device_setup=True)),
        ]
        for label, batch, grads, kw in extra:
            out.append((f"raster {dtype} {label} B={batch}",
                        lambda b=batch, g=grads, kw=kw, d=dtype: run_raster(b, g, dtype=d, **kw)))
        renders = [
            ("vertex lambert", 2, "vertex", "lambert", "vertex", "perspective", False),
            ("vertex phong", 1, "vertex", "phong", "vertex", "perspective", False),
            ("vertex sh orthographic", 2, "vertex", "sh", "vertex", "orthographic", False),
            ("face lambert", 1, "face", "lambert", "vertex", "perspective", False),
            ("face sh", 2, "face", "sh", "vertex", "perspective", False),
            ("pixel lambert", 2, "pixel", "lambert", "vertex", "perspective", False),
            ("pixel sh", 1, "pixel", "sh", "vertex", "perspective", False),
            ("pixel sh orthographic", 2, "pixel", "sh", "vertex", "orthographic", False),
            ("unlit vertex colours", 1, "none", None, "vertex", "perspective", False),
            ("unlit face textures", 2, "none", None, "face", "perspective", False),
            ("unlit uv texture", 2, "none", None, "uv", "perspective", False),
            ("unlit uv texture orthographic", 1, "none", None, "uv", "orthographic", False),
            ("pixel lambert region of interest", 2, "pixel", "lambert", "vertex", "perspective", True),
        ]
        for label, batch, shading, light, texture, projection, roi in renders:
            out.append((f"render {dtype} {label} B={batch}",
                        lambda b=batch, sh=shading, li=light, t=texture, p=projection, d=dtype, r=roi:
                        run_render(b, sh, li, t, p, d, r)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--any-device", action="store_true", help="do not insist on Oclgrind's device")
    ap.add_argument("--list", action="store_true", help="print the variants and exit")
    ap.add_argument("--only", default="", help="run only variants whose name contains this")
    ap.add_argument("--release-buffers", action="store_true",
                    help="let buffers be released (shows Oclgrind 21.10's false reports; see "
                         "keep_buffers_alive)")
    args = ap.parse_args(argv)
    cases = [(n, f) for n, f in variants() if args.only in n]
    if args.list:
        print("\n".join(n for n, _ in cases))
        return 0
    if not args.any_device:    # softras_cl's device choice, by name: Oclgrind's simulator
        os.environ[ENV_VAR] = "oclgrind"
    # No programs from softras_cl's binary cache: pyopencl looks up `_source` on a program made
    # from a binary, a clCreateKernel that --check-api reports as CL_INVALID_KERNEL_NAME.
    # (pyopencl's own cache reads PYOPENCL_NO_CACHE at import; the test sets it.)
    os.environ["SOFTRAS_CL_CACHE_DIR"] = "off"
    try:
        device = select_device()
    except InputError as e:
        print(f"oclgrind-sweep: error: no Oclgrind device; run under `oclgrind ...` or pass "
              f"--any-device ({e})", file=sys.stderr)
        return 2
    label = f"{device.platform.name} {device.platform.version} / {device.name}"
    print(f"oclgrind-sweep: device {label}", flush=True)
    skip_pyopencl_nvidia_probe()
    if not args.release_buffers:
        keep_buffers_alive()
    start, failed = time.perf_counter(), 0
    for i, (name, thunk) in enumerate(cases, 1):
        t0 = time.perf_counter()
        # a marker on stderr ties the Oclgrind reports that follow to this variant
        print(f"oclgrind-sweep: variant {name}", file=sys.stderr, flush=True)
        try:
            thunk()
            status = "ok"
        except Exception as e:    # report every failing variant, not only the first
            failed += 1
            status = f"FAILED: {type(e).__name__}: {e}"
        print(f"[{i}/{len(cases)}] {name}: {status} ({time.perf_counter() - t0:.2f} s)", flush=True)
    total = time.perf_counter() - start
    print(f"oclgrind-sweep: {len(cases)} variants, {failed} failed, {total:.1f} s", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
