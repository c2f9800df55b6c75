"""`softras-cl compare MESH`: the soft rasteriser at sharp settings against an independent
renderer (a trimesh/Embree ray cast through every pixel centre), same camera, same shading.

Reports silhouette IoU, depth relative error on interior pixels, and PSNR/SSIM (scikit-image)
of the shaded image, and writes a side-by-side PNG with a difference map. Untextured meshes are
lit by the paper's Lambert light per vertex (Gouraud), which the ray cast interpolates with
its hit's 3D barycentrics; textured meshes are drawn unlit, the ray cast sampling the texture
bilinearly at the hit's perspective-correct uv.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softras_cl.scene.camera import Camera
from softras_cl.io.meshes import Mesh
from softras_cl.validate.raycast import RayCastImage, raycast
from softras_cl.scene.renderer import Renderer
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.shading import LambertLight, shade_vertices

# softras-cl's sigma and gamma against the independent references (ray cast, Mitsuba): sharper
# than the fits' sharp render (softras_cl.scene.renderer.SHARP; sigma 10x, gamma 100x smaller)
REFERENCE_SHARP = dict(sigma=1e-7, gamma=1e-6)
GREY = 0.7


@dataclass
class Comparison:
    """Both renders (H, W[, 3] linear RGB on the background; depth NaN outside) and the metrics."""
    ours_rgb: np.ndarray
    ours_alpha: np.ndarray
    ours_depth: np.ndarray
    ref_rgb: np.ndarray
    ref: RayCastImage
    metrics: dict


def default_camera(size: int, azimuth_deg: float = 30.0, elevation_deg: float = 20.0,
                   fov_deg: float = 30.0, radius: float = 1.0) -> Camera:
    """Camera looking at the origin from where a sphere of `radius` fills ~80% of the image."""
    distance = radius / np.sin(np.radians(fov_deg) / 2) / 0.8
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = distance * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    return Camera.look_at(eye, (0.0, 0.0, 0.0), fov_deg=fov_deg, image_size=(size, size))


def compare_mesh(mesh: Mesh, camera: Camera, background=(1.0, 1.0, 1.0), dtype: str = "float32",
                 light: LambertLight | None = None, dist_eps: float = 0.49) -> Comparison:
    """Render `mesh` both ways with `camera` and measure the differences."""
    light = light or LambertLight()
    settings = RasterSettings(image_size=tuple(camera.image_size), outputs=("rgb", "alpha", "depth"),
                              double_sided=True, background=tuple(background), dtype=dtype,
                              near=0.1, far=100.0, dist_eps=dist_eps, **REFERENCE_SHARP)
    ref = raycast(mesh.vertices, mesh.faces, camera)
    if mesh.texture is not None and mesh.uvs is not None:
        out = Renderer(settings, shading="none").forward(
            mesh.vertices, mesh.faces, camera, texture_image=mesh.texture[None], uvs=mesh.uvs)
        ref_rgb = _textured(mesh, ref, background)
    else:
        albedo = mesh.colors if mesh.colors is not None else np.full(mesh.vertices.shape, GREY)
        out = Renderer(settings, shading="vertex").forward(mesh.vertices, mesh.faces, camera,
                                                           albedo=albedo, light=light)
        ref_rgb = _gouraud(mesh, albedo, light, camera, ref, background)
    ours_rgb, ours_alpha = out.rgb[0].astype(np.float64), out.alpha[0].astype(np.float64)
    ours_depth = np.where(ours_alpha > 0.5, out.depth[0], np.nan)
    return Comparison(ours_rgb, ours_alpha, ours_depth, ref_rgb, ref,
                      metrics(ours_rgb, ours_alpha, ours_depth, ref_rgb, ref))


def _gouraud(mesh: Mesh, albedo, light, camera: Camera, ref: RayCastImage, background) -> np.ndarray:
    """Lambert colours at the vertices (same shading code as ours), interpolated at each hit with
    its 3D barycentrics, i.e. perspective-correct, as the rasteriser does."""
    colors, _ = shade_vertices(mesh.vertices[None], mesh.faces, np.asarray(albedo)[None], light,
                                camera.center())
    corner = colors[0][mesh.faces[np.maximum(ref.face, 0)]]           # (H, W, 3 corners, 3)
    rgb = (corner * ref.bary[..., None]).sum(axis=2)
    return np.where(ref.mask[..., None], rgb, np.asarray(background))


def _textured(mesh: Mesh, ref: RayCastImage, background) -> np.ndarray:
    """Bilinear clamp-to-edge texture lookup at the hit's uv (docs/conventions.md)."""
    tex = mesh.texture
    th, tw = tex.shape[:2]
    uv = (mesh.uvs[mesh.faces[np.maximum(ref.face, 0)]] * ref.bary[..., None]).sum(axis=2)
    fx, fy = uv[..., 0] * tw - 0.5, (1.0 - uv[..., 1]) * th - 0.5
    x0, y0 = np.floor(fx), np.floor(fy)
    tx, ty = (fx - x0)[..., None], (fy - y0)[..., None]
    xs = [np.clip(x0 + i, 0, tw - 1).astype(int) for i in (0, 1)]
    ys = [np.clip(y0 + j, 0, th - 1).astype(int) for j in (0, 1)]
    rgb = ((1 - ty) * ((1 - tx) * tex[ys[0], xs[0]] + tx * tex[ys[0], xs[1]])
           + ty * ((1 - tx) * tex[ys[1], xs[0]] + tx * tex[ys[1], xs[1]]))
    return np.where(ref.mask[..., None], rgb, np.asarray(background))


def interior(mask: np.ndarray) -> np.ndarray:
    """Pixels whose 3 x 3 neighbourhood lies entirely inside `mask`."""
    padded = np.pad(mask, 1)
    h, w = mask.shape
    return np.all([padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                   for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)


def metrics(rgb, alpha, depth, ref_rgb, ref: RayCastImage) -> dict:
    """Silhouette IoU, depth relative error on interior pixels, PSNR/SSIM of the shaded image."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    ours = alpha > 0.5
    union = (ours | ref.mask).sum()
    iou = (ours & ref.mask).sum() / union if union else float("nan")
    inner = interior(ours & ref.mask)
    rel = np.abs(depth[inner] - ref.depth[inner]) / ref.depth[inner]
    with np.errstate(divide="ignore"):     # identical images: PSNR inf (see invalid_metrics)
        psnr = float(peak_signal_noise_ratio(ref_rgb, np.clip(rgb, 0, 1), data_range=1.0))
    return dict(silhouette_iou=float(iou), silhouette_pixels=int(ours.sum()),
                reference_pixels=int(ref.mask.sum()),
                depth_rel_err_max=float(rel.max()) if rel.size else float("nan"),
                depth_rel_err_mean=float(rel.mean()) if rel.size else float("nan"),
                interior_pixels=int(inner.sum()),
                psnr_db=psnr,
                ssim=float(structural_similarity(ref_rgb, np.clip(rgb, 0, 1), channel_axis=2, data_range=1.0)))


def invalid_metrics(m: dict) -> dict[str, str]:
    """{metric name: why it has no finite value} for the metrics of :func:`metrics` that are NaN
    or infinite (empty: every metric is a number)."""
    why = {}
    if not m.get("reference_pixels") and not m.get("silhouette_pixels"):
        empty = "neither renderer covers any pixel (zero-area faces, or the mesh is outside the view)"
    elif not m.get("reference_pixels") or not m.get("silhouette_pixels"):
        who = "the reference" if not m.get("reference_pixels") else "softras-cl"
        empty = f"{who} covers no pixel"
    else:
        empty = "no pixel lies inside both silhouettes with its 8 neighbours"
    reasons = dict(silhouette_iou=empty, depth_rel_err_max=empty, depth_rel_err_mean=empty,
                   psnr_db="the images are identical (PSNR is infinite)",
                   ssim="SSIM is undefined for these images")
    for key, value in m.items():
        if isinstance(value, float) and not np.isfinite(value):
            why[key] = reasons.get(key, "not a finite number")
    return why


def degenerate(m: dict) -> str | None:
    """Why the comparison measures nothing (no pixel covered by both renderers, so no IoU or
    depth error), or None when it is a valid comparison. An infinite PSNR alone (identical
    images over a covered silhouette) is valid."""
    if m.get("interior_pixels", 0) > 0 and np.isfinite(m["silhouette_iou"]):
        return None
    bad = invalid_metrics(m)
    return bad.get("silhouette_iou") or bad.get("depth_rel_err_max") or "no pixel to compare"


def json_metrics(m: dict) -> dict:
    """The metrics with NaN and infinities as None (strict JSON), and "invalid": {name: reason}
    for each of them when there are any."""
    bad = invalid_metrics(m)
    out = {k: (None if k in bad else v) for k, v in m.items()}
    if bad:
        out["invalid"] = bad
    return out


def save_comparison(result: Comparison, path: Path, title: str = "",
                    reference: str = "ray cast (trimesh/Embree)") -> None:
    """PNG: ours | reference | |difference| (x10) | depth difference, with the metrics as title."""
    from matplotlib.figure import Figure

    from softras_cl.srgb import to_srgb

    m = result.metrics
    fig = Figure(figsize=(16, 4.6))
    axes = fig.subplots(1, 4)
    panels = [(to_srgb(np.clip(result.ours_rgb, 0, 1)), "softras-cl (sigma 1e-7, gamma 1e-6)"),
              (to_srgb(np.clip(result.ref_rgb, 0, 1)), reference),
              (np.clip(10 * np.abs(result.ours_rgb - result.ref_rgb), 0, 1), "|difference| x 10")]
    for ax, (img, name) in zip(axes, panels):
        ax.imshow(img)
        ax.set_title(name)
    diff = np.abs(result.ours_depth - result.ref.depth) / result.ref.depth
    im = axes[3].imshow(np.log10(np.maximum(diff, 1e-12)), cmap="magma", vmin=-12, vmax=-2)
    axes[3].set_title("depth relative error (log10)")
    fig.colorbar(im, ax=axes[3], fraction=0.046)
    for ax in axes:
        ax.axis("off")
    extra = f"   shadowed px {m['shadowed_pixels']}" if "shadowed_pixels" in m else ""
    fig.suptitle(f"{title}  IoU {m['silhouette_iou']:.4f}   depth rel. err. max {m['depth_rel_err_max']:.1e}   "
                 f"PSNR {m['psnr_db']:.1f} dB   SSIM {m['ssim']:.4f}{extra}")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
