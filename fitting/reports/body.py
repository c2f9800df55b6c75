"""What a body fit leaves on disk (``softras-cl fit-body --out DIR``).

- ``body.ply``: the fitted, posed mesh (model frame = world frame of the camera) with the part
  colours;
- ``overlay.png``: the fitted body (sharp render) blended half over the target, at the target's
  resolution (at most OVERLAY_MAX px), with the fitted joints (and the given ones) drawn;
- ``params.json`` and ``params.npz``: the fitted blocks, the posed joints (3D, metres) and their
  pixels in the full-size target, the camera (K, R, t of the full-size target), the metrics and
  the settings used;
- ``loss_curve.png``, ``history.json``, ``checkpoint.npz``: written by the solver.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from softras_cl.io.meshes import save_mesh
from softras_cl.io.outputs import atomic_path, write_figure, write_json
from softras_cl.fitting.recipes.body import BodyFit, BodyScene
from softras_cl.fitting.reports.face import SHARP
from softras_cl.provenance import provenance

OVERLAY_MAX = 1024


def full_size_scene(fit: BodyFit, max_side: int = OVERLAY_MAX) -> BodyScene:
    """The fit's scene at the target's full size (its longer side capped at ``max_side``)."""
    h, w = fit.target.full_size
    scale = min(1.0, max_side / max(h, w))
    return BodyScene(fit.scene.model, (max(1, round(h * scale)), max(1, round(w * scale))), fit.scene.config)


def save_overlay(fit: BodyFit, target: np.ndarray, path: Path) -> None:
    """Half-blend of the sharp render over the target (H, W[, 3|4]) with the joints drawn."""
    from matplotlib.figure import Figure
    from skimage.transform import resize

    from softras_cl.srgb import to_srgb

    scene = full_size_scene(fit)
    state, _ = scene.pose(fit.values)
    out = scene.render(state.vertices, *SHARP)
    img = np.asarray(target, np.float64)
    img = np.repeat(img[..., None], 3, -1) if img.ndim == 2 else img[..., :3]
    img = resize(img, scene.image_size, order=1, anti_aliasing=True)
    alpha = 0.5 * out.alpha[0][..., None]
    blend = alpha * out.rgb[0] + (1.0 - alpha) * img
    h, w = scene.image_size
    fig = Figure(figsize=(w / 100, h / 100), dpi=100)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.imshow(to_srgb(np.clip(blend, 0, 1)))
    uv, _ = scene.camera.project_pixels(state.joints)
    for j, p in enumerate(scene.model.parents[1:], start=1):
        ax.plot(uv[[p, j], 0], uv[[p, j], 1], "-", c="white", lw=1)
    ax.scatter(*uv.T, s=6, c="cyan", zorder=3)
    if fit.target.joints is not None:
        given = (fit.target.joints + 0.5) / fit.target.scale * (h / fit.target.full_size[0]) - 0.5
        seen = fit.target.joint_weights > 0
        ax.scatter(*given[seen].T, s=6, c="lime", marker="x", zorder=3)
    ax.set(xlim=(-0.5, w - 0.5), ylim=(h - 0.5, -0.5))
    ax.axis("off")
    write_figure(fig, path, dpi=100)


def camera_matrices(camera) -> dict:
    """A Camera in OpenCV form: pixel = K (R X + t) / Z."""
    K = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])
    return dict(K=K, R=camera.rotation_matrix(), t=np.asarray(camera.translation, np.float64))


def write_outputs(fit: BodyFit, target: np.ndarray, out_dir, extra: dict | None = None,
                  run_config=None, metrics: dict | None = None) -> dict:
    """Write every output of a fit into ``out_dir`` (each file replaced atomically); returns the
    metrics written (``metrics``: those of ``fit.metrics()`` if the caller has them already).

    target: the full-size target as given to fit_body; extra: more JSON-able facts for
    params.json; run_config: the run's effective configuration, recorded with the versions,
    device and command line under "provenance" (default: the fit's BodyFitConfig).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics = fit.metrics() if metrics is None else metrics
    state, _ = fit.scene.pose(fit.values)
    save_mesh(out / "body.ply", state.vertices, fit.scene.model.faces, colors=fit.scene.colors)
    save_overlay(fit, target, out / "overlay.png")
    camera = full_size_scene(fit, max(fit.target.full_size)).camera
    arrays = {**{k: np.asarray(v) for k, v in fit.values.items()}, **camera_matrices(camera),
              "joints_3d": state.joints, "joints_px": camera.project_pixels(state.joints)[0]}
    with atomic_path(out / "params.npz") as tmp:
        np.savez(tmp, **arrays)
    config = fit.scene.config
    doc = dict(metrics=metrics, interrupted=fit.result.interrupted, outcomes=fit.result.outcomes,
               target_size=list(fit.target.full_size), working_size=list(fit.scene.image_size),
               camera=dict(distance=config.distance, height=config.height, fov_deg=config.fov_deg),
               joint_names=fit.scene.model.joint_names,
               params={k: np.asarray(v).tolist() for k, v in arrays.items()},
               provenance=provenance(config if run_config is None else run_config), **(extra or {}))
    write_json(out / "params.json", doc)
    return metrics


# ---------------------------------------------------------------------------------------------
# fits of a photo (fitting.recipes.body_photo): the detection's pictures as well
# ---------------------------------------------------------------------------------------------

def _photo_axes(image: np.ndarray, scale: float, ax) -> None:
    from softras_cl.srgb import to_srgb

    h, w = image.shape[:2]
    ax.imshow(to_srgb(np.clip(image, 0, 1)), extent=(-0.5, w * scale - 0.5, h * scale - 0.5, -0.5))
    ax.set(xlim=(-0.5, w * scale - 0.5), ylim=(h * scale - 0.5, -0.5))
    ax.axis("off")


def draw_keypoints(fit, ax, scale: float) -> None:
    """The used detected keypoints (green crosses, size by weight) and the fitted model points
    (cyan dots), joined, on axes of the photo drawn at ``scale``."""
    detected = (fit.layout.detected(fit.detection.keypoints, fit.detection.visibility)[0] + 0.5) * scale - 0.5
    fitted = (fit.fitted_keypoints_full() + 0.5) * scale - 0.5
    used = fit.weights > 0
    for a, b in zip(detected[used], fitted[used]):
        ax.plot([a[0], b[0]], [a[1], b[1]], "-", c="yellow", lw=0.8)
    ax.scatter(*detected[used].T, s=14 + 30 * fit.weights[used], c="lime", marker="x", zorder=3,
               label="detected (used)")
    ax.scatter(*detected[~used].T, s=10, c="red", marker="x", zorder=3, label="detected (not used)")
    ax.scatter(*fitted.T, s=10, c="cyan", zorder=4, label="fitted")


def save_photo_figures(fit, photo: np.ndarray, out: Path, metrics: dict) -> None:
    """keypoints.png (the photo with the detected and fitted keypoints), mask.png (the
    detector's person mask, 8-bit) and figure.png (photo + keypoints | mask against the fit's
    silhouette | overlay)."""
    from matplotlib.figure import Figure
    from PIL import Image

    h, w = photo.shape[:2]
    scale = min(1.0, OVERLAY_MAX / max(h, w))
    fig = Figure(figsize=(w * scale / 100, h * scale / 100), dpi=100)
    ax = fig.add_axes([0, 0, 1, 1])
    _photo_axes(photo, scale, ax)
    draw_keypoints(fit, ax, scale)
    write_figure(fig, out / "keypoints.png", dpi=100)
    with atomic_path(out / "mask.png") as tmp:
        Image.fromarray(np.round(255 * np.clip(fit.detection.mask, 0, 1)).astype(np.uint8)).save(tmp, format="png")
    state, _ = fit.scene.pose(fit.values)
    sharp = fit.scene.render(state.vertices, *SHARP).alpha[0]
    fig = Figure(figsize=(10, 3.8))
    axes = fig.subplots(1, 3)
    small = 300 / max(h, w)
    _photo_axes(photo, small, axes[0])
    draw_keypoints(fit, axes[0], small)
    axes[0].set_title(f"keypoints: {metrics['keypoint_error_px_full']:.1f} px", fontsize=9)
    axes[1].imshow(np.stack([fit.target.alpha, sharp, np.zeros_like(sharp)], -1))
    axes[1].set_title(f"mask (red) / fit (green): IoU {metrics['silhouette_iou']:.3f}", fontsize=9)
    axes[1].axis("off")
    axes[2].imshow(np.asarray(Image.open(out / "overlay.png")))
    axes[2].set_title("fit over the photo", fontsize=9)
    axes[2].axis("off")
    fig.tight_layout()
    write_figure(fig, out / "figure.png", dpi=100)


def write_photo_outputs(fit, photo: np.ndarray, out_dir, extra: dict | None = None, run_config=None,
                        metrics: dict | None = None) -> dict:
    """write_outputs of a fit of a photo (fitting.recipes.body_photo.BodyPhotoFit; photo (H, W, 3)
    linear RGB), then keypoints.png, mask.png and figure.png; params.json also holds the
    detection (keypoints, visibility, box, score, people), the keypoints used with their
    weights, the field of view's source and the objective fitted ("keypoints" for a photo with
    no hip in view: fitting.recipes.body_photo.fit_objective)."""
    metrics = fit.metrics() if metrics is None else metrics
    extra = dict(extra or {}, detection=fit.detection.to_json(), fov_source=fit.fov_source, objective=fit.objective,
                 keypoints=dict(names=list(fit.layout.names), detector=fit.layout.detector.tolist(),
                                weights=fit.weights.round(4).tolist(),
                                fitted_px=fit.fitted_keypoints_full().round(2).tolist()))
    write_outputs(fit, photo, out_dir, extra=extra, run_config=run_config, metrics=metrics)
    save_photo_figures(fit, photo, Path(out_dir), metrics)
    return metrics
