"""What a face fit leaves on disk (``softras-cl fit-face --out DIR``).

- ``face.ply``: the fitted shape (identity + expression, model frame) with albedo vertex colours;
- ``overlay.png``: the render over the photo (at the photo's resolution, at most OVERLAY_MAX px);
- ``figure.png``: photo with its landmarks / fit with the fitted landmarks / albedo / shading /
  error map in the face region;
- ``params.json`` and ``params.npz``: every fitted block, the camera of the full-size photo
  (K, R, t), the metrics and the settings used;
- ``loss_curve.png``, ``history.json``, ``checkpoint.npz``: written by the solver.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from softras_cl.scene.rotation import axis_angle_to_matrix
from softras_cl.io.images import to_srgb, write_image
from softras_cl.io.meshes import save_mesh
from softras_cl.io.outputs import atomic_path, write_figure, write_json
from softras_cl.scene.shading import SHLight
from softras_cl.fitting.recipes.face import CAMERA_ROTATION, FaceFit, FaceScene
from softras_cl.provenance import provenance

OVERLAY_MAX = 1024       # longest side of overlay.png (the photo's own size when smaller)
SHARP = (1e-6, 1e-4)     # sigma, gamma of the report renders: the fitted surface, drawn sharp


def photo_scene(fit: FaceFit, photo_size, scale: float = 1.0) -> tuple[FaceScene, dict]:
    """A hard-alpha scene of the full photo (H, W) resized by ``scale``, and the fitted values
    with the focal length of that image."""
    settings = fit.scene.settings
    h, w = (max(1, round(n * scale)) for n in photo_size)
    cx, cy = fit.crop.to_full([fit.scene.principal])[0]
    scene = FaceScene(fit.scene.model, (h, w), settings.dtype, alpha_agg="hard",
                      depth_range=(settings.near, settings.far),
                      principal=((cx + 0.5) * scale - 0.5, (cy + 0.5) * scale - 0.5))
    return scene, dict(fit.values, focal=fit.values["focal"] / fit.crop.scale * scale)


def display_scene(fit: FaceFit) -> FaceScene:
    """The working image's scene with hard alpha (no seams between triangles): for pictures."""
    size = fit.image.shape[:2]
    settings = fit.scene.settings
    return FaceScene(fit.scene.model, size, settings.dtype, alpha_agg="hard",
                     depth_range=(settings.near, settings.far), principal=fit.scene.principal)


def render_over(fit: FaceFit, photo: np.ndarray, max_side: int = OVERLAY_MAX) -> np.ndarray:
    """The fitted face rendered over ``photo`` (H, W, 3) linear RGB, downscaled to at most
    ``max_side`` pixels: (h, w, 3) linear RGB."""
    from skimage.transform import resize

    h, w = photo.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    scene, values = photo_scene(fit, (h, w), scale)
    image = resize(photo, scene.image_size, order=1, anti_aliasing=True) if scale < 1.0 else photo
    out = scene.render(values, *SHARP)
    alpha = out.alpha[0][..., None]
    return alpha * out.rgb[0] + (1.0 - alpha) * image


def _panels(fit: FaceFit) -> dict:
    """name -> (h, w, 3) sRGB or (h, w) error image, all at the working resolution."""
    scene, values = display_scene(fit), fit.values
    n = scene.model.n_vertices
    fitted = scene.render(values, *SHARP)
    albedo = scene.render(values, *SHARP, light=SHLight.ambient(1.0))
    shading = scene.render(values, *SHARP, albedo=np.full((n, 3), 0.5))
    alpha = fitted.alpha[0][..., None]
    composite = alpha * fitted.rgb[0] + (1 - alpha) * fit.image
    error = np.where(fit.mask, np.abs(to_srgb(np.clip(fitted.rgb[0], 0, 1))
                                      - to_srgb(np.clip(fit.image, 0, 1))).mean(-1), np.nan)
    return {"photo + landmarks": to_srgb(np.clip(fit.image, 0, 1)),
            "fit + fitted landmarks": to_srgb(np.clip(composite, 0, 1)),
            "albedo": to_srgb(np.clip(albedo.rgb[0], 0, 1)),
            "shading (grey albedo)": to_srgb(np.clip(shading.rgb[0], 0, 1)),
            "|error| in the face region (sRGB)": error}


def save_figure(fit: FaceFit, path: Path, metrics: dict) -> None:
    """photo / fit / albedo / shading / error map, one row, with the landmarks drawn."""
    from matplotlib.figure import Figure

    panels = _panels(fit)
    fig = Figure(figsize=(3.2 * len(panels), 3.6))
    axes = fig.subplots(1, len(panels))
    for ax, (title, img) in zip(axes, panels.items()):
        if img.ndim == 2:
            shown = ax.imshow(img, cmap="magma", vmin=0, vmax=0.2)
            fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
        else:
            ax.imshow(img)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    axes[0].scatter(*fit.landmarks.T, s=4, c="lime")
    axes[1].scatter(*fit.fitted_landmarks().T, s=4, c="cyan")
    fig.suptitle(f"landmark error {metrics['landmark_error_px_full']:.2f} px (full size), "
                 f"face-region PSNR {metrics['psnr_face_db']:.1f} dB (sRGB)", fontsize=10)
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def camera_matrices(fit: FaceFit, photo_size) -> dict:
    """The fitted camera for the full photo (H, W) in OpenCV form, with the head pose folded
    in: X_cam = R X_model + t, pixel = K X_cam / Z."""
    scene, values = photo_scene(fit, photo_size)
    f, (cx, cy) = values["focal"][0], scene.principal
    return dict(K=np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]),
                R=CAMERA_ROTATION @ axis_angle_to_matrix(values["rotation"]),
                t=CAMERA_ROTATION @ values["translation"])


def write_outputs(fit: FaceFit, photo: np.ndarray, out_dir, extra: dict | None = None,
                  run_config=None, metrics: dict | None = None) -> dict:
    """Write every output of a fit into ``out_dir`` (each file replaced atomically); returns the
    metrics written (``metrics``: those of ``fit.metrics()`` if the caller has them already).

    photo (H, W, 3) linear RGB at full size; extra: more JSON-able facts for params.json;
    run_config: the run's effective configuration (e.g. its FaceFitConfig), recorded with the
    versions, device and command line under "provenance".
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics = fit.metrics() if metrics is None else metrics
    values = fit.values
    model = fit.scene.model
    save_mesh(out / "face.ply", model.shape(values["id"], values["exp"])[0], model.faces,
              colors=np.clip(model.albedo(values["albedo"])[0], 0.0, 1.0))
    write_image(out / "overlay.png", np.clip(render_over(fit, photo), 0.0, 1.0))
    save_figure(fit, out / "figure.png", metrics)
    cam = camera_matrices(fit, photo.shape[:2])
    arrays = {**{k: np.asarray(v) for k, v in values.items()}, **cam}
    with atomic_path(out / "params.npz") as tmp:
        np.savez(tmp, **arrays)
    doc = dict(metrics=metrics, interrupted=fit.result.interrupted, outcomes=fit.result.outcomes,
               model=model.name, photo_size=list(photo.shape[:2]),
               working_size=list(fit.image.shape[:2]),
               params={k: np.asarray(v).tolist() for k, v in arrays.items()},
               provenance=provenance(run_config), **(extra or {}))
    write_json(out / "params.json", doc)
    return metrics
