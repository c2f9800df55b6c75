"""Detail texture of a face fit: the photo's albedo on the fitted mesh, after the model fit.

The model fit (``fitting.recipes.face``) explains a photo with a smooth PCA albedo; this step
keeps its shape, pose and SH light and reads the skin's detail from the photo itself:

1. **UV layout** (:func:`cylindrical_uvs`, :func:`uv_layout`): the model's mean face unrolled
   about a vertical axis 10 cm behind its nose tip in the mid plane x = 0 (``u`` = arc length
   around the axis, ``v`` = height, one
   scale for both), centred so that the mirror image x -> -x of a symmetric model is the flip
   u -> 1 - u of the texture. Each texel knows the triangle under it and its barycentric
   weights (softras-cl rasterises the mesh in uv space; where uv triangles overlap, the one
   farther from the axis wins).
2. **Un-lighting** (:func:`estimate_texture`): each texel's surface point is projected into the
   full-size photo; its albedo is photo / shading, the shading being the fitted SH irradiance
   at the interpolated vertex normal (what the vertex-shaded render uses).
3. **Visibility and confidence**: a texel is seen when its point faces the camera, is the
   surface shown at the four pixels its colour is read from (depth buffer of the photo's
   render: no occluder, no background at a silhouette), lies inside the photo, and the shading
   is not too dark to divide by. Its confidence is the cosine of the view angle
   times a ramp rising over ``ramp`` texels from the edge of the seen area.
4. **Fill**: the photo's albedo takes over where the confidence reaches ``full_weight``;
   elsewhere it blends with the mirror texel's photo albedo (when that one is seen) and then
   with the fitted model albedo, so seams fade instead of cutting.

:func:`render_textured` draws the textured face lit by the fitted light (softras-cl's uv
texture path times the vertex shading); fitting.reports.face.save_textured_obj writes OBJ + MTL + PNG.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softras_cl.raster.rasterizer import SoftRasterizer
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.renderer import Renderer
from softras_cl.scene.shading import SHLight, shade_vertices, vertex_normals

__all__ = ["TEXTURE_SIZE", "UVLayout", "FaceTexture", "cylindrical_uvs", "uv_layout", "face_uv_layout",
           "full_photo_scene", "estimate_texture", "render_textured"]

TEXTURE_SIZE = 512       # texels a side: about twice the face's pixels in a 512 px photo
AXIS_DEPTH = 0.10        # the unrolling axis, metres behind the face's frontmost point (the nose tip)
UV_MARGIN = 0.02         # empty border of the layout, as a fraction of its side
SHADING_FLOOR = 0.05     # irradiance below which a texel is not un-lit (albedo = photo / shading)
MIN_COS = 0.1            # a texel seen more obliquely than this counts as unseen
DEPTH_TOLERANCE = 0.003  # metres a texel may lie behind the depth buffer and still be seen


@dataclass(frozen=True)
class UVLayout:
    """Texture coordinates of a mesh and what lies under each texel.

    uvs (V, 2) float64 in [0, 1] (u right, v up; texel row 0 is v = 1); face (S, S) int64: the
    triangle under each texel centre, -1 for none; bary (S, S, 3) float64: its barycentric
    weights (zeros where face is -1); faces (F, 3) int: the mesh's triangles.
    """
    uvs: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    faces: np.ndarray

    @property
    def size(self) -> int:
        return self.face.shape[0]

    @property
    def covered(self) -> np.ndarray:
        """(S, S) bool: texels with a triangle under them."""
        return self.face >= 0

    def interpolate(self, values) -> np.ndarray:
        """Per-vertex values (V, C) -> (S, S, C) float64 at the texel centres (0 where uncovered)."""
        values = np.asarray(values, np.float64)
        corners = values[self.faces[np.maximum(self.face, 0)]]          # (S, S, 3, C)
        return np.einsum("ijk,ijkc->ijc", self.bary, corners)


@dataclass
class FaceTexture:
    """The detail texture of a fit (S x S texels, linear RGB).

    albedo (S, S, 3): the texture to render and write (every texel filled); observed (S, S, 3):
    photo / shading where seen (0 elsewhere); seen (S, S) bool; confidence (S, S) in [0, 1];
    model (S, S, 3): the fitted model albedo; layout: the UVLayout.
    """
    albedo: np.ndarray
    observed: np.ndarray
    seen: np.ndarray
    confidence: np.ndarray
    model: np.ndarray
    layout: UVLayout


# ---------------------------------------------------------------------------------------------
# uv layout
# ---------------------------------------------------------------------------------------------

def cylindrical_uvs(points, axis_z: float, margin: float = UV_MARGIN) -> np.ndarray:
    """uvs (V, 2) float64 of points (V, 3) (model frame: y up, face along +z, x = 0 the mid
    plane): arc length around the vertical axis through (0, *, axis_z) and height, one scale,
    centred on u = 0.5 (x -> -x maps u -> 1 - u) and fitted into [margin, 1 - margin]."""
    p = np.asarray(points, np.float64)
    theta = np.arctan2(p[:, 0], p[:, 2] - axis_z)
    radius = float(np.median(np.hypot(p[:, 0], p[:, 2] - axis_z)))
    s, t = theta * radius, p[:, 1] - 0.5 * (p[:, 1].min() + p[:, 1].max())
    span = max(2.0 * np.abs(s).max(), np.ptp(t)) / (1.0 - 2.0 * margin)
    return np.stack([0.5 + s / span, 0.5 + t / span], axis=1)


def _uv_raster(uvs, faces, size: int, colors, priority) -> np.ndarray:
    """Rasterise the mesh in uv space (one vertex per face corner) with per-corner colours
    (3F, 3); the nearest (smallest priority, (V,) in [0, 1]) triangle wins. -> (S, S, 3)."""
    corners = np.asarray(faces).reshape(-1)
    screen = np.concatenate([2.0 * uvs[corners] - 1.0, 1.0 + priority[corners, None]], axis=1)
    settings = RasterSettings(image_size=(size, size), sigma=1e-9, gamma=1e-4, near=0.5, far=3.0,
                              dtype="float64", color_agg="hard", alpha_agg="hard",
                              perspective_correct=False, outputs=("rgb",))
    flat = np.arange(len(corners)).reshape(-1, 3)
    return SoftRasterizer(settings).forward(screen, flat, colors=colors).rgb[0]


def uv_layout(uvs, faces, size: int = TEXTURE_SIZE, priority=None) -> UVLayout:
    """The UVLayout of a mesh with uvs (V, 2) and faces (F, 3) on an S x S texture; priority
    (V,) in [0, 1] (default 0) decides between overlapping uv triangles, smaller wins."""
    uvs = np.asarray(uvs, np.float64)
    faces = np.asarray(faces, np.int64)
    priority = np.zeros(len(uvs)) if priority is None else np.asarray(priority, np.float64)
    bary = _uv_raster(uvs, faces, size, np.tile(np.eye(3), (len(faces), 1)), priority)
    ids = _uv_raster(uvs, faces, size, np.repeat(np.arange(1.0, len(faces) + 1), 3)[:, None]
                     * np.ones(3), priority)
    face = np.rint(ids[..., 0]).astype(np.int64) - 1
    bary = np.where((face >= 0)[..., None], bary, 0.0)
    return UVLayout(uvs, face, bary, faces)


def face_uv_layout(model, size: int = TEXTURE_SIZE) -> UVLayout:
    """The layout of a face model: cylindrical uvs of its mean shape; where uv triangles
    overlap, the surface farther from the axis (the outer one) wins."""
    mean = model.mean_shape
    axis_z = mean[:, 2].max() - AXIS_DEPTH
    radius = np.hypot(mean[:, 0], mean[:, 2] - axis_z)
    priority = (radius.max() - radius) / max(np.ptp(radius), 1e-12)
    return uv_layout(cylindrical_uvs(mean, axis_z), model.faces, size, priority)


# ---------------------------------------------------------------------------------------------
# un-lighting
# ---------------------------------------------------------------------------------------------

def full_photo_scene(fit, photo_size, out_size=None):
    """A hard-alpha FaceScene of the full photo (H, W) drawn at out_size (h, w) pixels (default
    the photo's own; the same aspect, e.g. a multiple or fraction of it), and the fitted values
    with that image's focal length. -> (FaceScene, dict)."""
    from softras_cl.fitting.recipes.face import FaceScene

    h, w = (int(n) for n in (photo_size if out_size is None else out_size))
    scale = w / float(photo_size[1])
    cx, cy = fit.crop.to_full([fit.scene.principal])[0]
    settings = fit.scene.settings
    scene = FaceScene(fit.scene.model, (h, w), settings.dtype, alpha_agg="hard",
                      depth_range=(settings.near, settings.far),
                      principal=((cx + 0.5) * scale - 0.5, (cy + 0.5) * scale - 0.5))
    return scene, dict(fit.values, focal=fit.values["focal"] / fit.crop.scale * scale)


def _depth_buffer(scene, values, world) -> np.ndarray:
    """(H, W) view depth of the nearest surface (far where none), z-buffered."""
    settings = scene.settings.replace(sigma=1e-9, gamma=1e-4, color_agg="hard", alpha_agg="hard",
                                      outputs=("depth",))
    out = Renderer(settings, shading="none").forward(
        world, scene.model.faces, scene.camera(values["focal"][0]))
    return out.depth[0]


def _bilinear(image, xy) -> np.ndarray:
    """image (H, W, C) sampled at pixel positions xy (N, 2) (x right, y down; clamped)."""
    from scipy.ndimage import map_coordinates

    coords = xy[:, ::-1].T
    return np.stack([map_coordinates(image[..., c], coords, order=1, mode="nearest")
                     for c in range(image.shape[-1])], axis=-1)


def _visible(depth, xy, z, far: float, slack) -> np.ndarray:
    """(N,) bool: points at pixels xy (N, 2) with view depth z (N,) that the four pixels their
    bilinear sample reads all show: every one covered by the face (depth buffer (H, W) < far)
    and none nearer than the point by more than DEPTH_TOLERANCE + slack (N,) (the depth the
    point's own surface changes by over a pixel): no occluder, no background mixed into the
    colour at a silhouette; inside the image."""
    h, w = depth.shape
    inside = (xy[:, 0] >= 0) & (xy[:, 0] <= w - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= h - 1)
    x0 = np.clip(np.floor(xy[:, 0]).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(xy[:, 1]).astype(int), 0, h - 2)
    footprint = np.stack([depth[y0 + dy, x0 + dx] for dy in (0, 1) for dx in (0, 1)])
    covered = footprint.max(axis=0) < far
    return inside & covered & (z <= footprint.min(axis=0) + DEPTH_TOLERANCE + slack)


def _texel_geometry(scene, values, layout: UVLayout) -> dict:
    """Per covered texel (N = covered count): pixel xy (N, 2), view depth z (N,), cosine of the
    view angle (N,) and SH irradiance (N, 3) under the fitted light."""
    world, _ = scene.geometry(values)
    faces = scene.model.faces
    covered = layout.covered
    points = layout.interpolate(world)[covered]
    normals = layout.interpolate(vertex_normals(world[None], faces)[0][0])[covered]
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    xy, _ = scene.camera(values["focal"][0]).project_pixels(points)
    irradiance, _ = shade_vertices(world[None], faces, np.ones((1, len(world), 3)), SHLight(values["sh"]))
    view = -points / np.linalg.norm(points, axis=1, keepdims=True)
    return dict(xy=xy, z=-points[:, 2], cos=np.einsum("nc,nc->n", normals, view),
                irradiance=layout.interpolate(irradiance[0])[covered], world=world)


def _confidence(seen, covered, cos, ramp: float) -> np.ndarray:
    """(S, S): cos of the view angle times a ramp over ``ramp`` texels from the edge of the
    seen area (texels outside the layout do not count as an edge); 0 where unseen."""
    from scipy.ndimage import distance_transform_edt

    distance = distance_transform_edt(seen | ~covered)
    return np.where(seen, np.clip(cos, 0.0, 1.0) * np.clip(distance / ramp, 0.0, 1.0), 0.0)


def _fill_uncovered(texture, covered) -> np.ndarray:
    """Texels outside the layout take their nearest covered texel's colour, so bilinear
    sampling at the triangles' edges never mixes in a blank."""
    from scipy.ndimage import distance_transform_edt

    _, (rows, cols) = distance_transform_edt(~covered, return_indices=True)
    return texture[rows, cols]


def blend_sources(observed, weight, model) -> np.ndarray:
    """The texture from the photo's albedo observed (S, S, 3) with weight (S, S) in [0, 1], its
    mirror image (u -> 1 - u) where this side is not seen, and the model albedo (S, S, 3) where
    neither is: w o + (1 - w) (w' o' + (1 - w') m), primes for the mirrored texel."""
    mirrored, weight_m = observed[:, ::-1], weight[:, ::-1]
    w, wm = weight[..., None], weight_m[..., None]
    return w * observed + (1.0 - w) * (wm * mirrored + (1.0 - wm) * model)


def estimate_texture(fit, photo, size: int = TEXTURE_SIZE, ramp: float = 8.0,
                     full_weight: float = 0.3, layout: UVLayout | None = None) -> FaceTexture:
    """The detail texture of a FaceFit from its photo (H, W, 3) linear RGB at full size.

    size: texels a side (ignored when a layout is given: its size); ramp: texels over which the
    confidence rises from a visibility edge; full_weight: the confidence from which the
    photo's albedo is used alone. See the module docstring.
    """
    photo = np.asarray(photo, np.float64)[..., :3]
    scene, values = full_photo_scene(fit, photo.shape[:2])
    layout = face_uv_layout(scene.model, size) if layout is None else layout
    size = layout.size
    geo = _texel_geometry(scene, values, layout)
    covered = layout.covered
    slack = geo["z"] / values["focal"][0] / np.maximum(geo["cos"], MIN_COS)   # one pixel of the surface
    visible = _visible(_depth_buffer(scene, values, geo["world"]), geo["xy"], geo["z"], scene.settings.far, slack)
    lit = geo["irradiance"].min(axis=1) > SHADING_FLOOR
    seen_n = visible & lit & (geo["cos"] > MIN_COS)
    observed = np.zeros((size, size, 3))
    observed[covered] = np.where(seen_n[:, None], _bilinear(photo, geo["xy"])
                                 / np.maximum(geo["irradiance"], SHADING_FLOOR), 0.0)
    seen = np.zeros((size, size), bool)
    seen[covered] = seen_n
    cos = np.zeros((size, size))
    cos[covered] = geo["cos"]
    confidence = _confidence(seen, covered, cos, ramp)
    model = layout.interpolate(scene.model.albedo(values["albedo"])[0])
    albedo = blend_sources(observed, np.clip(confidence / full_weight, 0.0, 1.0), model)
    albedo = _fill_uncovered(np.clip(albedo, 0.0, 1.0), covered)
    return FaceTexture(albedo, observed, seen, confidence, model, layout)


# ---------------------------------------------------------------------------------------------
# rendering and writing
# ---------------------------------------------------------------------------------------------

def render_textured(scene, values, texture: FaceTexture, sigma: float, gamma: float):
    """The face with its detail texture under the fitted SH light: (rgb (H, W, 3), alpha (H, W))
    float64. The uv texture render (unlit) times the vertex shading of a white albedo."""
    settings = scene.settings.replace(sigma=sigma, gamma=gamma)
    world, _ = scene.geometry(values)
    camera = scene.camera(values["focal"][0])
    unlit = Renderer(settings, shading="none").forward(
        world, scene.model.faces, camera, texture_image=texture.albedo, uvs=texture.layout.uvs)
    shading = scene.render(values, sigma, gamma, albedo=np.ones_like(world), world=world)
    return unlit.rgb[0] * shading.rgb[0], unlit.alpha[0]

