"""Synthetic faces rendered by Mitsuba 3's path tracer: photos softras-cl did not make.

`softras-cl bench face --renderers mitsuba` fits these, so the fit's own image formation (SH
light evaluated per vertex, no shadows, one bounce, rasterised) is not also the one that made
the photo. The scene of one face (everything in the fit's world frame: camera at the origin
looking down -z, y up):

- Geometry and camera: the true face mesh (world vertices of the truth) with interpolated vertex
  normals and the true per-vertex albedo as a mesh attribute (clipped to [0, 0.95]: a diffuse
  reflectance must stay below 1), seen by the same pinhole camera (focal, principal point;
  mitsuba.sensor_dict). Each pixel averages ``spp`` rays through random points of its area, so
  edges are anti-aliased, unlike the sharp softras-cl photo.
- Light: the truth's SH light, scaled by 1 - SUN_SHARE, as an environment map (sh_radiance: a
  Lambertian surface lit by it shows exactly softras-cl's SH shading, up to shadows and
  clipping negative radiance at 0), plus a sun (a `directional` emitter) along the SH light's
  first-order direction, mirrored to the camera's side of the face when it points away (a sun
  behind the face would light none of what the camera sees), whose light alone would give
  SUN_SHARE x the SH light's ambient colour at normal incidence. The sun casts sharp shadows
  (nose, brows), the environment soft ones.
- Path tracing: `path` integrator, max_depth 4 (up to three bounces: light reflected by the
  cheeks onto the nose sides and into the eye sockets), emitters hidden from the camera so the
  face's alpha is its pixel coverage; the photo is the render composited over the sample's
  background.
"""
from __future__ import annotations

import numpy as np

from softras_cl.errors import InputError
from softras_cl.scene.shading import SH_A, SH_Y0, sh_basis
from softras_cl.validate.mitsuba import _check_mesh, _mesh, _mitsuba, sensor_dict

SUN_SHARE = 0.4          # the sun's share of the light; the environment keeps 1 - SUN_SHARE
MAX_DEPTH = 4
DEFAULT_SPP = 64
ENVMAP_HEIGHT = 64       # lat-long map of 64 x 128 texels: ample for a second-order SH light
MAX_ALBEDO = 0.95


def envmap_directions(height: int) -> np.ndarray:
    """(height, 2 height, 3) unit directions of the texel centres of a Mitsuba `envmap`
    lat-long bitmap (its local frame: y up, u = atan2(x, -z) / 2 pi, v = acos(y) / pi)."""
    v, u = np.meshgrid((np.arange(height) + 0.5) / height, (np.arange(2 * height) + 0.5) / (2 * height),
                       indexing="ij")
    theta, phi = np.pi * v, 2.0 * np.pi * u
    return np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)], -1)


def sh_radiance(sh, directions) -> np.ndarray:
    """Radiance (..., 3) from directions (..., 3) of the environment whose irradiance E(n) makes
    a Lambertian surface of reflectance rho show rho * E(n) / pi = softras-cl's SHLight shading
    albedo * sum_i L_i A_i Y_i(n): pi * sum_i L_i Y_i(direction) (Ramamoorthi-Hanrahan: the
    clamped-cosine convolution scales band l by A_l). Negative values are kept (see sun_and_sky)."""
    return np.pi * sh_basis(directions) @ np.asarray(sh, np.float64).T


def sun_and_sky(sh, sun_share: float = SUN_SHARE, front=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split an SH light (3, 9) into (sky (H, 2H, 3) envmap radiance, clipped at 0; sun direction
    (3,) towards the sun; sun irradiance (3,) for a Mitsuba `directional` emitter). front (3,):
    the side the sun must light (from the face towards the camera), or None for any."""
    sh = np.asarray(sh, np.float64)
    if sh.shape != (3, 9) or not np.isfinite(sh).all():
        raise InputError(f"sh must be a finite (3, 9) array of SH coefficients, got shape {sh.shape}")
    if not 0.0 <= sun_share < 1.0:
        raise InputError(f"sun_share must be in [0, 1), got {sun_share!r}")
    sky = np.clip((1.0 - sun_share) * sh_radiance(sh, envmap_directions(ENVMAP_HEIGHT)), 0.0, None)
    first = sh[:, [3, 1, 2]].mean(axis=0)              # the basis order is (1, y, z, x, ...)
    direction = first / np.linalg.norm(first) if np.linalg.norm(first) > 0 else np.array([0.0, 0.0, 1.0])
    if front is not None and direction @ front < 0:
        front = np.asarray(front, np.float64) / np.linalg.norm(front)
        direction = direction - 2.0 * (direction @ front) * front
    ambient = sh[:, 0] * SH_A[0] * SH_Y0                # the shading of the constant term
    # a directional emitter's irradiance E gives a diffuse surface rho * E cos / pi
    return sky, direction, np.pi * sun_share * ambient


def face_scene_dict(mi, world, faces, albedo, camera, sh, spp: int, sun_share: float = SUN_SHARE) -> dict:
    """The Mitsuba scene dict of one synthetic face (see the module docstring)."""
    front = camera.center() - world.mean(axis=0)
    sky, sun_direction, sun_irradiance = sun_and_sky(sh, sun_share, front)
    return {"type": "scene",
            "sensor": sensor_dict(camera, world, spp=spp, alpha=True),
            "mesh": _mesh(mi, world, faces, np.clip(albedo, 0.0, MAX_ALBEDO), "pixel", None, None),
            "sky": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(sky, np.float32))},
            "sun": {"type": "directional", "direction": (-sun_direction).tolist(),
                    "irradiance": {"type": "rgb", "value": sun_irradiance.tolist()}}}


def render_face_mitsuba(world, faces, albedo, camera, sh, spp: int = DEFAULT_SPP, seed: int = 0,
                        sun_share: float = SUN_SHARE) -> dict:
    """Path-trace a face: world (V, 3) vertices, faces (F, 3), albedo (V, 3) linear RGB, a
    perspective Camera with fx == fy, sh (3, 9) the SH light split by sun_and_sky.

    Returns dict(rgb (H, W, 3) linear, premultiplied by alpha (0 where no ray hit); alpha (H, W)
    the fraction of each pixel's rays that hit the face), float64. ``seed``: the sampler's seed
    (two seeds give two independent noise draws)."""
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 2:
        raise InputError(f"spp must be an integer >= 2 (rays per pixel), got {spp!r}")
    if albedo is None:
        raise InputError("albedo must be a (V, 3) array of per-vertex linear RGB, got None")
    world, faces, albedo, _, _ = _check_mesh(world, faces, albedo, None, None)
    mi = _mitsuba()
    return path_trace(mi, face_scene_dict(mi, world, faces, albedo, camera, sh, spp, sun_share), spp, seed)


def path_trace(mi, scene: dict, spp: int, seed: int) -> dict:
    """Render a scene dict (face_scene_dict, its film RGBA) with the `path` integrator (MAX_DEPTH,
    emitters hidden): dict(rgb (h, w, 3) linear, premultiplied by alpha; alpha (h, w) the
    fraction of each pixel's rays that hit the mesh), float64, over the film (or its crop)."""
    path = mi.load_dict({"type": "path", "max_depth": MAX_DEPTH, "hide_emitters": True})
    image = np.array(mi.render(mi.load_dict(scene), integrator=path, spp=spp, seed=seed), np.float64)
    return dict(rgb=image[..., :3], alpha=image[..., 3])


def composite(render: dict, background: np.ndarray) -> np.ndarray:
    """(H, W, 3) photo in [0, 1]: the premultiplied render over the background (H, W, 3)."""
    return np.clip(render["rgb"] + (1.0 - render["alpha"][..., None]) * background, 0.0, 1.0)


def silhouette_iou(a, b) -> float:
    """Intersection over union of two (H, W) coverage masks thresholded at 0.5."""
    a, b = np.asarray(a) > 0.5, np.asarray(b) > 0.5
    return float((a & b).sum() / max((a | b).sum(), 1))
