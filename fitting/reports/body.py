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

    from softras_cl.io.images import to_srgb

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
