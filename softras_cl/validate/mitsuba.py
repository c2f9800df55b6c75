"""Mitsuba 3 as an independent reference renderer: `softras-cl compare MESH
--reference mitsuba`.

Optional extra (`pip install softras-cl[validate]`); its `scalar_rgb` variant needs nothing else.
The scene is built in memory with Mitsuba's Python dict API and sampled so that it computes
exactly what the soft rasteriser computes at sharp settings:

- Camera: a `perspective` sensor whose to_world matrix is built from our Camera (OpenCV frame:
  x right, y down, z forward). Mitsuba's camera frame has +x pointing to the image's LEFT and +y
  up (its look_at makes the camera's +x the image's left), so the to_world rotation is
  R^T diag(-1, -1, 1), translation the camera centre. fov is given across the image width
  (fov_axis "x") from fx; the principal point (cx, cy) becomes principal_point_offset_x/y
  = -((cx + 0.5) - W/2) / W, -((cy + 0.5) - H/2) / H (signs and units measured: hits reproject
  onto our pixel centres to 1e-5 px). Square pixels only (fx == fy), perspective only.
- Pixel centres: a `stratified` sampler with sample_count 1 and jitter false, and a `box`
  reconstruction filter, i.e. one ray through each pixel centre, no filtering across pixels.
- Light: a `directional` emitter with irradiance pi * I travelling along -l; a `diffuse` BSDF
  (reflectance rho / pi) then gives rho * I * max(0, n . l) exactly, our Lambert light with
  ambient 0 (a `constant` emitter would add Monte Carlo noise, so there is no ambient term).
  Rendered with the `direct` integrator (one emitter sample, no BSDF samples: the light is a
  delta, so the result is deterministic). Mitsuba casts shadows, the rasteriser does not: on
  non-convex meshes the pixels in shadow differ (compare_mitsuba counts them).
- Normals and albedo, shading="face" (the default, what compare uses): the mesh gets no vertex
  normals, so Mitsuba shades with the geometric face normal normalize((v1 - v0) x (v2 - v0)),
  and the reflectance is a `mesh_attribute` texture of the per-face attribute "face_color" =
  the mean of the face's corner albedo. That is exactly softras-cl's Renderer(shading="face")
  (face normal, face albedo = mean of its corners, constant over the face). The alternative,
  shading="pixel", gives Mitsuba our area-weighted vertex normals (it interpolates and
  normalises them per hit: smooth shading normals) and the albedo as the per-vertex attribute
  "vertex_color" (interpolated with the hit's barycentrics), i.e. per-pixel Lambert. Our
  shading="vertex" (Gouraud: lit at the vertices, colours interpolated) has no Mitsuba
  counterpart.
- Textured meshes are drawn unlit by softras-cl (compare.py); here the mesh then carries an
  `area` emitter whose radiance is a `bitmap` texture (bilinear, clamp, raw linear values) of
  its uvs (v flipped: Mitsuba's v runs down the image) over a black BSDF, so each pixel shows
  the texture at its hit.
- Depth and mask: the `aov` integrator's position AOV ("pos:position") converted to
  camera-frame Z here (its depth AOV is measured from the near plane along the ray); the mask is
  where that depth AOV is > 0 (a hit); "prim:prim_index" gives the face hit.
Mitsuba's scalar variants work in float32, and its ray-triangle test (Embree) is not watertight:
a ray within ~1e-5 px of an edge shared by two triangles can slip between them and hit the
surface behind (seen once at 256^2 on the test torus: one pixel, depth 9% off).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softras_cl.errors import InputError
from softras_cl.scene.camera import Camera
from softras_cl.validate.compare import GREY, REFERENCE_SHARP, Comparison, metrics
from softras_cl.io.meshes import Mesh

VARIANT = "scalar_rgb"
MITSUBA_SHADINGS = ("face", "pixel")


def mitsuba_available() -> bool:
    """True when the `mitsuba` package (with its scalar_rgb variant) can be imported."""
    try:
        import mitsuba
    except ImportError:
        return False
    return VARIANT in mitsuba.variants()


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError as e:
        # a missing optional extra is fixed by the user, like a bad option (exit code 2)
        raise InputError("the Mitsuba reference needs the optional extra: pip install "
                         "'softras-cl[validate]' (or pip install mitsuba)") from e
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


@dataclass
class MitsubaImage:
    """Per-pixel results of the Mitsuba render; H x W arrays (RayCastImage-like for metrics()).

    rgb (H, W, 3) linear radiance (0 where no hit); mask bool, a camera ray hit the mesh;
    depth camera-frame Z of the hit (NaN where no hit); face index of the face hit (-1 where
    none).
    """
    rgb: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    face: np.ndarray


# ---- scene ------------------------------------------------------------------------------------
def _unit(name: str, value) -> np.ndarray:
    v = np.asarray(value, np.float64)
    if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) == 0:
        raise ValueError(f"{name} must be a finite non-zero 3-vector, got {np.asarray(value).tolist()}")
    return v / np.linalg.norm(v)


def _rgb3(name: str, value) -> np.ndarray:
    v = np.broadcast_to(np.asarray(value, np.float64), (3,)) if np.ndim(value) == 0 else np.asarray(value, np.float64)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"{name} must be a number or an RGB triple, got shape {np.shape(value)}")
    return v.copy()


def sensor_dict(camera: Camera, vertices: np.ndarray | None = None, spp: int = 1, alpha: bool = False) -> dict:
    """Mitsuba `perspective` sensor (with its film and sampler) equivalent to `camera`.

    spp 1: one ray through each pixel centre; spp > 1: an `independent` sampler, rays through
    uniform random points of each pixel averaged by the box filter (the pixel-area mean, as a
    camera's pixel sees it). alpha: an RGBA film (alpha: the fraction of the pixel's rays that
    hit something)."""
    mi = _mitsuba()
    if camera.projection != "perspective":
        raise ValueError(f"the Mitsuba reference supports perspective cameras only, got {camera.projection!r}")
    if not math.isclose(camera.fx, camera.fy, rel_tol=1e-12):
        raise ValueError(f"the Mitsuba reference needs square pixels (fx == fy), got fx={camera.fx}, fy={camera.fy}")
    h, w = camera.image_size
    R = camera.rotation_matrix()
    to_world = np.eye(4)
    to_world[:3, :3] = R.T @ np.diag([-1.0, -1.0, 1.0])       # Mitsuba camera: +x image-left, +y up
    to_world[:3, 3] = camera.center()
    near, far = 1e-2, 1e4
    if vertices is not None:
        z = (np.asarray(vertices, np.float64) @ R.T + camera.translation)[:, 2]
        if z.max() > 0:
            near = min(near, 0.5 * z[z > 0].min())
            far = max(far, 2.0 * z.max())
    return {
        "type": "perspective",
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "fov": math.degrees(2.0 * math.atan(0.5 * w / camera.fx)),
        "fov_axis": "x",
        "principal_point_offset_x": -((camera.cx + 0.5) - 0.5 * w) / w,
        "principal_point_offset_y": -((camera.cy + 0.5) - 0.5 * h) / h,
        "near_clip": near,
        "far_clip": far,
        "sampler": ({"type": "stratified", "sample_count": 1, "jitter": False} if spp == 1
                    else {"type": "independent", "sample_count": int(spp)}),
        "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                 "pixel_format": "rgba" if alpha else "rgb", "component_format": "float32"},
    }


def crop_film(sensor: dict, box, frame) -> tuple[int, int]:
    """Restrict ``sensor``'s film (sensor_dict) to the pixel box (x0, y0, x1, y1) of a subject,
    widened by 2 px (3 px past its far edges) and clipped to ``frame`` (width, height), in
    place: only the subject's pixels are traced. Returns the crop's top-left pixel (x, y)."""
    x0, y0 = (max(int(math.floor(v)) - 2, 0) for v in box[:2])
    x1, y1 = (min(int(math.ceil(v)) + 3, s) for v, s in zip(box[2:], frame))
    sensor["film"].update(crop_offset_x=x0, crop_offset_y=y0, crop_width=x1 - x0, crop_height=y1 - y0)
    return x0, y0


def _mesh(mi, vertices, faces, albedo, shading: str, texture, uvs):
    """mitsuba Mesh from arrays, with its BSDF (and area emitter when textured)."""
    import drjit as dr

    props = mi.Properties()
    textured = texture is not None
    if textured:
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}})
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {
            "type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texture, np.float32)),
            "filter_type": "bilinear", "wrap_mode": "clamp", "raw": True}})
    elif albedo is None:
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [GREY] * 3}})
    else:
        name = "face_color" if shading == "face" else "vertex_color"
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": name}})
    smooth = shading == "pixel" and not textured
    mesh = mi.Mesh("mesh", vertex_count=len(vertices), face_count=len(faces), props=props,
                   has_vertex_normals=smooth, has_vertex_texcoords=textured)
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.scalar.ArrayXf(np.asarray(vertices, np.float32).ravel())
    params["faces"] = dr.scalar.ArrayXu(np.asarray(faces, np.uint32).ravel())
    if smooth:
        from softras_cl.scene.shading import vertex_normals

        normals = vertex_normals(np.asarray(vertices, np.float64)[None], faces)[0][0]
        params["vertex_normals"] = dr.scalar.ArrayXf(normals.astype(np.float32).ravel())
    if textured:
        flipped = np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], 1)          # Mitsuba's v runs down the image
        params["vertex_texcoords"] = dr.scalar.ArrayXf(flipped.astype(np.float32).ravel())
    params.update()
    if albedo is not None and not textured:
        if shading == "face":
            mesh.add_attribute("face_color", 3, dr.scalar.ArrayXf(
                albedo[faces].mean(axis=1).astype(np.float32).ravel()))
        else:
            mesh.add_attribute("vertex_color", 3, dr.scalar.ArrayXf(albedo.astype(np.float32).ravel()))
    return mesh


def _check_mesh(vertices, faces, albedo, texture, uvs):
    v = np.asarray(vertices, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or not np.isfinite(v).all():
        raise ValueError(f"vertices must be a finite (V, 3) array, got shape {v.shape}")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"faces must be a non-empty (F, 3) array: the mesh has no faces (got shape {f.shape})")
    if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"faces must be integer indices into the {len(v)} vertices")
    if albedo is not None:
        albedo = np.asarray(albedo, np.float64)
        if albedo.shape != v.shape or not np.isfinite(albedo).all():
            raise ValueError(f"albedo must be a finite (V, 3) = {v.shape} array, got shape {albedo.shape}")
    if texture is not None:
        texture = np.asarray(texture, np.float64)
        if texture.ndim != 3 or texture.shape[2] != 3 or 0 in texture.shape:
            raise ValueError(f"texture_image must be (Ht, Wt, 3), got shape {texture.shape}")
        uvs = None if uvs is None else np.asarray(uvs, np.float64)
        if uvs is None or uvs.shape != (len(v), 2):
            raise ValueError(f"uvs must be (V, 2) = ({len(v)}, 2) with a texture_image, got "
                             f"{None if uvs is None else uvs.shape}")
    return v, f.astype(np.int64), albedo, texture, uvs


# ---- rendering --------------------------------------------------------------------------------
def render_mitsuba(vertices, faces, camera: Camera, albedo=None, light_direction=(0.0, 1.0, 0.0),
                   irradiance=(1.0, 1.0, 1.0), shading: str = "face", texture_image=None,
                   uvs=None) -> dict:
    """Render a mesh with Mitsuba 3 (scalar_rgb), one ray per pixel centre.

    vertices (V, 3) world, faces (F, 3); camera: a perspective Camera with fx == fy; albedo
    (V, 3) linear RGB or None (grey 0.7); light_direction (3,) towards the light; irradiance:
    the directional light intensity I (number or RGB), so a lit surface shows
    albedo * I * max(0, n . l). shading "face" (face normals, face albedo = mean of its
    corners: softras-cl's shading="face") or "pixel" (interpolated vertex normals and albedo).
    texture_image (Ht, Wt, 3) with uvs (V, 2): draw the texture unlit instead (no light).

    Returns dict(rgb (H, W, 3) linear, 0 where no hit; mask (H, W) bool; depth (H, W)
    camera-frame Z, NaN where no hit; face (H, W) int, -1 where no hit), float64.
    """
    if shading not in MITSUBA_SHADINGS:
        raise ValueError(f"shading must be one of {MITSUBA_SHADINGS}, got {shading!r}")
    v, f, albedo, texture, uvs = _check_mesh(vertices, faces, albedo, texture_image, uvs)
    light = _unit("light_direction", light_direction)
    intensity = _rgb3("irradiance", irradiance)
    mi = _mitsuba()
    scene_dict = {"type": "scene", "sensor": sensor_dict(camera, v),
                  "mesh": _mesh(mi, v, f, albedo, shading, texture, uvs)}
    if texture is None:
        scene_dict["light"] = {"type": "directional", "direction": (-light).tolist(),
                               "irradiance": {"type": "rgb", "value": (math.pi * intensity).tolist()}}
    scene = mi.load_dict(scene_dict)
    direct = mi.load_dict({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})
    rgb = np.array(mi.render(scene, integrator=direct, spp=1), np.float64)[..., :3]
    aov = mi.load_dict({"type": "aov", "aovs": "pos:position,dd:depth,prim:prim_index"})
    mi.render(scene, integrator=aov, spp=1)
    channels = dict(scene.sensors()[0].film().bitmap().split())
    position = np.array(channels["pos"], np.float64)
    mask = np.array(channels["dd"], np.float64) > 0
    z = (position @ camera.rotation_matrix().T + camera.translation)[..., 2]
    face = np.where(mask, np.array(channels["prim"], np.float64), -1).astype(np.int64)
    return dict(rgb=np.where(mask[..., None], rgb, 0.0), mask=mask, depth=np.where(mask, z, np.nan), face=face)


# ---- comparison -------------------------------------------------------------------------------
def default_light_direction(camera: Camera) -> np.ndarray:
    """A headlight: towards the camera along its optical axis (-R[2]). It lights everything the
    camera sees of a convex mesh, and on non-convex ones it leaves the fewest pixels in
    Mitsuba's shadows (the rasteriser has none): a surface point the camera sees can only be
    shadowed where the parallel light rays graze an occluding contour."""
    return -camera.rotation_matrix()[2]


def compare_mitsuba(mesh: Mesh, camera: Camera, background=(0.0, 0.0, 0.0), dtype: str = "float32",
                    light_direction=None, irradiance=(1.0, 1.0, 1.0), shading: str = "face",
                    dist_eps: float = 0.49) -> Comparison:
    """softras-cl at sharp settings (compare.REFERENCE_SHARP, dist_eps) against Mitsuba 3, same camera,
    same shading.

    Untextured meshes: albedo = mesh.colors or grey 0.7, lit by LambertLight(ambient=0,
    directional=irradiance, direction=light_direction (default: default_light_direction, a
    headlight)) with Renderer(shading=shading): "face" (flat: face normals, face albedo = mean of
    its corners, as Mitsuba without vertex normals and with a per-face colour attribute) or
    "pixel" (per-pixel Lambert with interpolated normals and albedo, as Mitsuba with vertex
    normals). Textured meshes: the texture unlit, both ways.

    background: black by default, Mitsuba's own (no environment light: escaped rays carry no
    radiance), so neither image is composited. On a white one, the few pixel centres lying
    within the sharp limit's footprint just past a silhouette edge (0.008 px at 256^2; the
    rasteriser gives them coverage ~0.5-0.75, the ray tracer 0) dominate the PSNR of these
    ambient-free scenes, whose silhouettes are dark (icosphere at 128^2: 36 dB on white, 52 dB
    on black, the interior agreeing to 1e-7).

    Metrics as compare.metrics, plus "shadowed_pixels": pixels whose face faces the light but
    which Mitsuba renders in shadow (the rasteriser has no shadows, so they differ there).
    """
    from softras_cl.scene.renderer import Renderer
    from softras_cl.raster.settings import RasterSettings
    from softras_cl.scene.shading import LambertLight

    settings = RasterSettings(image_size=tuple(camera.image_size), outputs=("rgb", "alpha", "depth"),
                              double_sided=True, background=tuple(background), dtype=dtype,
                              near=0.1, far=100.0, dist_eps=dist_eps, **REFERENCE_SHARP)
    textured = mesh.texture is not None and mesh.uvs is not None
    if textured:
        ref = render_mitsuba(mesh.vertices, mesh.faces, camera, texture_image=mesh.texture, uvs=mesh.uvs)
        out = Renderer(settings, shading="none").forward(
            mesh.vertices, mesh.faces, camera, texture_image=mesh.texture[None], uvs=mesh.uvs)
        shadowed = 0
    else:
        light_direction = default_light_direction(camera) if light_direction is None else light_direction
        albedo = mesh.colors if mesh.colors is not None else np.full(mesh.vertices.shape, GREY)
        light = LambertLight(ambient=0.0, directional=irradiance, direction=light_direction)
        ref = render_mitsuba(mesh.vertices, mesh.faces, camera, albedo, light.direction,
                             light.directional, shading=shading)
        out = Renderer(settings, shading=shading).forward(mesh.vertices, mesh.faces, camera,
                                                          albedo=albedo, light=light)
        shadowed = shadowed_pixels(mesh.vertices, mesh.faces, camera, ref, light.direction)
    image = MitsubaImage(np.where(ref["mask"][..., None], ref["rgb"], np.asarray(background, np.float64)),
                         ref["mask"], ref["depth"], ref["face"])
    ours_rgb, ours_alpha = out.rgb[0].astype(np.float64), out.alpha[0].astype(np.float64)
    ours_depth = np.where(ours_alpha > 0.5, out.depth[0], np.nan)
    m = metrics(ours_rgb, ours_alpha, ours_depth, image.rgb, image)
    m["shadowed_pixels"] = int(shadowed)
    return Comparison(ours_rgb, ours_alpha, ours_depth, image.rgb, image, m)


def shadowed_pixels(vertices, faces, camera: Camera, ref: dict, light_direction) -> int:
    """Number of hit pixels whose face faces the light but whose hit point Mitsuba sees the
    light blocked from (a shadow ray from the hit, offset along the face normal)."""
    from softras_cl.scene.shading import face_normals

    mi = _mitsuba()
    v = np.asarray(vertices, np.float64)
    normals = face_normals(v[None], faces)[0][0]
    light = _unit("light_direction", light_direction)
    hit = ref["mask"] & (ref["face"] >= 0)
    n = normals[ref["face"][hit]]
    lit = n @ light > 0
    # hit points from the camera depth along each pixel's ray
    h, w = camera.image_size
    vv, uu = np.mgrid[0:h, 0:w]
    z = ref["depth"][hit]
    cam_pts = np.stack([(uu[hit] - camera.cx) / camera.fx * z, (vv[hit] - camera.cy) / camera.fy * z, z], 1)
    world = (cam_pts - camera.translation) @ camera.rotation_matrix()
    eps = 1e-4 * float(np.linalg.norm(v.max(0) - v.min(0)))
    scene = mi.load_dict({"type": "scene", "mesh": _mesh(mi, v, np.asarray(faces, np.int64), None, "face", None, None)})
    blocked = 0
    for p, nn in zip(world[lit], n[lit]):
        o = p + eps * nn
        if scene.ray_test(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*light))):
            blocked += 1
    return blocked
