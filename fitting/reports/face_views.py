"""What a fit of one person over several photos leaves on disk (`fit-face A B C --same-person`).

- ``face.ply``: the shared identity's neutral face (expression 0, model frame) with the shared
  albedo as vertex colours;
- ``photos/NAME/``: per photo, everything a single-photo fit writes
  (fitting.reports.face.write_outputs: face.ply with that photo's expression, the detail
  texture, overlay.png, overlay_model.png, figure.png, params.json/.npz with its camera,
  landmarks_detected.pts and landmarks_fitted.pts, detection.json for detected landmarks);
- ``figure.png``: one row per photo: the photo with its landmarks, the model fit over it;
- ``params.json`` and ``params.npz``: every fitted block of the joint fit (``id``, ``albedo``;
  ``exp.k``, ``sh.k``, ``rotation.k``, ``translation.k``, ``focal.k`` of photo k), each photo's
  inputs (path, SHA-256 of the photo and landmarks), camera (K, R, t of the full photo) and
  metrics, the mean metrics and the settings used;
- ``loss_curve.png``, ``history.json``, ``checkpoint.npz``: written by the solver.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from softras_cl.srgb import to_srgb
from softras_cl.io.meshes import save_mesh
from softras_cl.io.outputs import atomic_path, write_figure, write_json
from softras_cl.fitting.recipes.face_views import FaceViewsFit
from softras_cl.fitting.reports.face import SUPERSAMPLE, camera_matrices, composite, display_scene, draw, write_outputs
from softras_cl.provenance import provenance

PHOTOS = "photos"        # subfolder of --out holding one folder per photo


def save_identity_mesh(fit: FaceViewsFit, path: Path) -> None:
    """The shared identity's neutral face with the shared albedo's colours."""
    model = fit.views[0].scene.model
    shape = model.shape(fit.values["id"], np.zeros(model.n_exp))[0]
    save_mesh(path, shape, model.faces, colors=np.clip(model.albedo(fit.values["albedo"])[0], 0.0, 1.0))


def save_figure(fit: FaceViewsFit, names: list[str], path: Path, metrics: dict) -> None:
    """One row per photo: the working image with its landmarks, the model fit over it with the
    fitted landmarks."""
    from matplotlib.figure import Figure

    rows = len(fit.views)
    fig = Figure(figsize=(6.4, 3.2 * rows + 0.4))
    axes = np.asarray(fig.subplots(rows, 2)).reshape(rows, 2)
    srgb = lambda x: to_srgb(np.clip(x, 0, 1))                                # noqa: E731
    for (ax_photo, ax_fit), view, name, m in zip(axes, fit.views, names, metrics["views"]):
        scene = display_scene(view, SUPERSAMPLE)
        values = dict(view.values, focal=view.values["focal"] * SUPERSAMPLE)
        ax_photo.imshow(srgb(view.image))
        ax_photo.scatter(*view.landmarks.T, s=4, c="lime")
        ax_photo.set_title(name, fontsize=9)
        ax_fit.imshow(srgb(composite(draw(scene, values, SUPERSAMPLE), view.image)))
        ax_fit.scatter(*view.fitted_landmarks().T, s=4, c="cyan")
        ax_fit.set_title(f"{m['landmark_error_px_full']:.2f} px, {m['psnr_face_db']:.1f} dB", fontsize=9)
        ax_photo.axis("off")
        ax_fit.axis("off")
    fig.suptitle(f"one identity over {rows} photos: landmark error {metrics['landmark_error_px_full']:.2f} px, "
                 f"face-region PSNR {metrics['psnr_face_db']:.1f} dB (means)", fontsize=10)
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def write_views_outputs(fit: FaceViewsFit, photos: list[np.ndarray], landmarks: list, names: list[str],
                        inputs: list[dict], out_dir, metrics: dict, run_config=None, extra: dict | None = None) -> dict:
    """Write every output of a joint fit into ``out_dir`` (each file replaced atomically);
    returns the metrics written (each photo's with its detail-texture PSNR).

    photos: the full-size photos (H_k, W_k, 3) linear RGB; landmarks: each photo's
    fitting.detection.PhotoLandmarks (the points fitted, where they came from); names: one
    folder name per photo;
    inputs: one JSON-able dict per photo (its path and digests) for params.json; metrics: what
    fit.metrics() returned; run_config, extra: as for fitting.reports.face.write_outputs.
    """
    out = Path(out_dir)
    save_identity_mesh(fit, out / "face.ply")
    per_view = []
    for view, photo, found, name, m, source in zip(fit.views, photos, landmarks, names, metrics["views"], inputs):
        per_view.append(write_outputs(view, photo, found, out / PHOTOS / name, metrics=m, run_config=run_config,
                                      extra=dict(source, same_person=True)))
    metrics = dict(metrics, views=per_view)
    save_figure(fit, names, out / "figure.png", metrics)
    with atomic_path(out / "params.npz") as tmp:
        np.savez(tmp, **{k: np.asarray(v) for k, v in fit.values.items()})
    cameras = [camera_matrices(view, photo.shape[:2]) for view, photo in zip(fit.views, photos)]
    doc = dict(metrics=metrics, interrupted=fit.result.interrupted, outcomes=fit.result.outcomes,
               model=fit.views[0].scene.model.name,
               photos=[dict(source, name=name, folder=f"{PHOTOS}/{name}", photo_size=list(photo.shape[:2]),
                            camera={k: v.tolist() for k, v in cam.items()})
                       for source, name, photo, cam in zip(inputs, names, photos, cameras)],
               params={k: np.asarray(v).tolist() for k, v in fit.values.items()},
               provenance=provenance(run_config), **(extra or {}))
    write_json(out / "params.json", doc)
    return metrics
