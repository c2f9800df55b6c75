"""What a face fit leaves on disk (``softras-cl fit-face --out DIR``).

- ``face.ply``: the fitted shape (identity + expression, model frame) with albedo vertex colours;
- ``face_textured.obj`` + ``.mtl`` + ``.png``: the same mesh with uvs and its detail texture (the
  photo's albedo, un-lit by the fitted light: ``fitting.recipes.face_texture``);
- ``overlay.png``: the render with the detail texture over the photo, ``overlay_model.png`` the
  model alone (at the photo's resolution, at most OVERLAY_MAX px; the photo shows through the
  eye and mouth openings);
- ``figure.png``: photo with its landmarks / model fit with the fitted landmarks / fit with the
  detail texture / error maps in the face region / model and detail albedo / shading;
- ``params.json`` and ``params.npz``: every fitted block, the camera of the full-size photo
  (K, R, t), the metrics (``psnr_face_db``: the model alone, what the fit optimises;
  ``psnr_face_db_textured``: with the detail texture), where the landmarks came from
  (``landmarks_input``: a file, or the detected face's number, box, score and why it was chosen)
  and the settings used;
- ``landmarks_detected.pts``: the 68 points the fit was given (from the file or the detector) and
  ``landmarks_fitted.pts``: the fitted model's 68 landmarks projected into the photo (both iBUG
  .pts, 1-based pixel coordinates of the full photo);
- ``detection.json`` (detected landmarks only): every face found, which one was fitted and why
  (fitting.detection.Detection.to_json);
- ``loss_curve.png``, ``history.json``, ``checkpoint.npz``: written by the solver.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from softras_cl.scene.rotation import axis_angle_to_matrix
from softras_cl.io.images import PNG_OPTIONS, write_image
from softras_cl.io.meshes import save_mesh
from softras_cl.io.outputs import atomic_path, write_figure, write_json, write_text
from softras_cl.scene.renderer import SHARP   # the report renders: the fitted surface, drawn sharp
from softras_cl.scene.shading import SHLight
from softras_cl.fitting.keypoints import ibug68
from softras_cl.fitting.metrics import psnr
from softras_cl.fitting.recipes.face import CAMERA_ROTATION, FaceFit, FaceScene
from softras_cl.fitting.recipes.face_texture import FaceTexture, estimate_texture, full_photo_scene, render_textured
from softras_cl.fitting.detection import PhotoLandmarks
from softras_cl.io.landmarks import write_pts
from softras_cl.provenance import provenance
from softras_cl.srgb import to_srgb

OVERLAY_MAX = 1024       # longest side of overlay.png (the photo's own size when smaller)
# Samples a side per pixel of the pictures. One sample per pixel draws the thin creases of the
# fitted surface (under the lower lip, the chin's underside: sub-pixel, downward-facing
# triangles, dark under a light from above) as dotted lines; averaged samples draw them as the
# faint continuous shadows they are, and anti-alias the outline.
SUPERSAMPLE = 3
PANEL_INCHES = (3.4, 3.2)   # figure.png: width and height of one panel's cell
TITLE_INCHES = 0.3         # the band above the panels for the figure's title
OPENING_GROWTH = 1.15    # each opening's polygon grown about its centre (the lids' thickness)


def photo_scene(fit: FaceFit, photo_size, scale: float = 1.0) -> tuple[FaceScene, dict]:
    """A hard-alpha scene of the full photo (H, W) resized by ``scale``, and the fitted values
    with the focal length of that image."""
    out_size = tuple(max(1, round(n * scale)) for n in photo_size)
    return full_photo_scene(fit, photo_size, out_size)


def display_scene(fit: FaceFit, samples: int = 1) -> FaceScene:
    """The working image's scene with hard alpha (no seams between triangles): for pictures;
    ``samples`` per pixel a side (the focal length then scales by as much: :func:`_sampled`)."""
    h, w = fit.image.shape[:2]
    cx, cy = fit.scene.principal
    settings = fit.scene.settings
    return FaceScene(fit.scene.model, (h * samples, w * samples), settings.dtype, alpha_agg="hard",
                     depth_range=(settings.near, settings.far),
                     principal=((cx + 0.5) * samples - 0.5, (cy + 0.5) * samples - 0.5))


def _sampled(fit: FaceFit, photo_size=None, scale: float = 1.0, k: int = SUPERSAMPLE):
    """(scene, values) drawing k x k samples per pixel of the working image (photo_size None)
    or of the full photo (H, W) resized by scale."""
    if photo_size is None:
        return display_scene(fit, k), dict(fit.values, focal=fit.values["focal"] * k)
    h, w = (max(1, round(n * scale)) for n in photo_size)
    return full_photo_scene(fit, photo_size, (h * k, w * k))


def _downsample(image: np.ndarray, k: int) -> np.ndarray:
    """(h k, w k, ...) -> (h, w, ...): the mean of each k x k block."""
    h, w = image.shape[0] // k, image.shape[1] // k
    return image.reshape(h, k, w, k, *image.shape[2:]).mean(axis=(1, 3))


def opening_mask(scene: FaceScene, values: dict, growth: float = OPENING_GROWTH) -> np.ndarray:
    """(H, W) bool: inside the fitted eye and inner-mouth outlines (ibug68.OPENINGS) of the
    scene's image, each grown by ``growth`` about its centre: the openings the face models close
    with a cap (eyes) or a slit (mouth), where the pictures show the photo, as a skin model does
    not draw eyes or teeth."""
    from skimage.draw import polygon

    world, _ = scene.geometry(values)
    points, _ = scene.camera(values["focal"][0]).project_pixels(scene.model.landmarks(world)[0])
    inside = np.zeros(scene.image_size, bool)
    for outline in ibug68.OPENINGS:
        pts = points[list(outline)]
        pts = pts.mean(0) + growth * (pts - pts.mean(0))
        inside[polygon(pts[:, 1], pts[:, 0], inside.shape)] = True
    return inside


def draw(scene: FaceScene, values: dict, k: int, texture: FaceTexture | None = None,
         openings: bool = True, **overrides) -> tuple[np.ndarray, np.ndarray]:
    """The face drawn at k x k samples per pixel and averaged: (rgb premultiplied by alpha
    (h, w, 3), alpha (h, w)), h, w = the scene's size / k. texture: draw the detail texture
    (else the model albedo, or ``overrides`` albedo= / light= of FaceScene.render); openings:
    leave the eye and mouth openings empty, for the photo to show through. Only the window
    around the face (:func:`face_window`) is rendered: the same picture, zeros elsewhere."""
    h, w = (n // k for n in scene.image_size)
    rgb, alpha = np.zeros((h, w, 3)), np.zeros((h, w))
    rows, cols = face_window(scene, values, k)
    if rows.stop > rows.start and cols.stop > cols.start:
        window, sharp = window_scene(scene, rows, cols, k)
        rgb[rows, cols], alpha[rows, cols] = _draw_all(window, values, k, texture, openings, sharp, **overrides)
    return rgb, alpha


def _draw_all(scene: FaceScene, values: dict, k: int, texture: FaceTexture | None, openings: bool,
              sharp: tuple, **overrides) -> tuple[np.ndarray, np.ndarray]:
    """:func:`draw` over the scene's whole image, rendered with (sigma, gamma) = sharp."""
    if texture is not None:
        rgb, alpha = render_textured(scene, values, texture, *sharp)
    else:
        out = scene.render(values, *sharp, **overrides)
        rgb, alpha = out.rgb[0], out.alpha[0]
    if openings:
        alpha = alpha * ~opening_mask(scene, values)
    return _downsample(rgb * alpha[..., None], k), _downsample(alpha, k)


def face_window(scene: FaceScene, values: dict, k: int, margin: int = 2) -> tuple[slice, slice]:
    """(rows, cols) slices of the image the scene draws at k x k samples per pixel (its size
    / k) holding every projected vertex, grown by ``margin`` pixels and clipped to the image
    (hard alpha: nothing of the face is drawn outside its triangles)."""
    world, _ = scene.geometry(values)
    xy, _ = scene.camera(values["focal"][0]).project_pixels(world)
    h, w = (n // k for n in scene.image_size)
    (c0, r0), (c1, r1) = (np.floor(xy.min(0) / k) - margin).tolist(), (np.ceil(xy.max(0) / k) + margin).tolist()
    clip = lambda v, n: int(min(max(v, 0), n))                                # noqa: E731
    return slice(clip(r0, h), clip(r1, h)), slice(clip(c0, w), clip(c1, w))


def window_scene(scene: FaceScene, rows: slice, cols: slice, k: int) -> tuple[FaceScene, tuple]:
    """The scene cut to the window (rows, cols) of its image at k samples per pixel (see
    :func:`face_window`), and the (sigma, gamma) that draw there what SHARP draws in the whole
    image: sigma acts on squared distances in units of half the image's shorter side."""
    cx, cy = scene.principal
    size = ((rows.stop - rows.start) * k, (cols.stop - cols.start) * k)
    s = scene.settings
    window = FaceScene(scene.model, size, s.dtype, alpha_agg=s.alpha_agg, depth_range=(s.near, s.far),
                       principal=(cx - cols.start * k, cy - rows.start * k))
    ratio = min(scene.image_size) / min(size)
    return window, (SHARP[0] * ratio * ratio, SHARP[1])


def composite(drawn: tuple[np.ndarray, np.ndarray], image: np.ndarray) -> np.ndarray:
    """A drawn face (see :func:`draw`) over image (h, w, 3) linear RGB."""
    rgb, alpha = drawn
    return rgb + (1.0 - alpha[..., None]) * image


def render_over(fit: FaceFit, photo: np.ndarray, max_side: int = OVERLAY_MAX,
                texture: FaceTexture | None = None) -> np.ndarray:
    """The fitted face (with its detail texture if given) rendered over ``photo`` (H, W, 3)
    linear RGB, downscaled to at most ``max_side`` pixels, the photo showing through the eye
    and mouth openings: (h, w, 3) linear RGB."""
    from skimage.transform import resize

    h, w = photo.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    scene, values = _sampled(fit, (h, w), scale)
    size = (scene.image_size[0] // SUPERSAMPLE, scene.image_size[1] // SUPERSAMPLE)
    image = resize(photo, size, order=1, anti_aliasing=True) if scale < 1.0 else photo
    return composite(draw(scene, values, SUPERSAMPLE, texture), image)


def textured_metrics(fit: FaceFit, texture: FaceTexture) -> dict:
    """Face-region PSNR (sRGB, dB) of the render with the detail texture, on the working image
    and the face region of FaceFit.metrics (whose psnr_face_db is the model alone)."""
    rgb, _ = render_textured(fit.scene, fit.values, texture, *SHARP)
    mask = fit.objective.face_region(fit.values, *SHARP)
    return dict(psnr_face_db_textured=psnr(to_srgb(np.clip(rgb, 0, 1)), to_srgb(np.clip(fit.image, 0, 1)), mask),
                texture_seen_fraction=float(texture.seen.sum() / max(texture.layout.covered.sum(), 1)))


def _error(rgb: np.ndarray, fit: FaceFit) -> np.ndarray:
    """(h, w) mean |sRGB error| in the face region, NaN outside."""
    diff = np.abs(to_srgb(np.clip(rgb, 0, 1)) - to_srgb(np.clip(fit.image, 0, 1))).mean(-1)
    return np.where(fit.mask, diff, np.nan)


def _panels(fit: FaceFit, texture: FaceTexture | None) -> dict:
    """name -> (h, w, 3) sRGB or (h, w) error image, all at the working resolution."""
    scene, values = _sampled(fit)
    n, k = scene.model.n_vertices, SUPERSAMPLE
    srgb = lambda x: to_srgb(np.clip(x, 0, 1))                                # noqa: E731
    model = composite(draw(scene, values, k), fit.image)
    panels = {"photo + landmarks": srgb(fit.image), "model fit + fitted landmarks": srgb(model)}
    if texture is not None:
        panels["fit with the detail texture"] = srgb(composite(draw(scene, values, k, texture), fit.image))
    panels["|error| model (face region, sRGB)"] = _error(fit.scene.render(fit.values, *SHARP).rgb[0], fit)
    panels["model albedo"] = srgb(draw(scene, values, k, openings=False, light=SHLight.ambient(1.0))[0])
    if texture is not None:
        white = dict(values, sh=SHLight.ambient(1.0).coefficients)
        panels["detail albedo"] = srgb(draw(scene, white, k, texture, openings=False)[0])
    panels["shading (grey albedo)"] = srgb(draw(scene, values, k, openings=False, albedo=np.full((n, 3), 0.5))[0])
    if texture is not None:
        panels["|error| with the detail texture"] = _error(
            render_textured(fit.scene, fit.values, texture, *SHARP)[0], fit)
    return panels


def save_figure(fit: FaceFit, path: Path, metrics: dict, texture: FaceTexture | None = None) -> None:
    """photo / model fit / fit with the detail texture / error maps / albedos / shading, with
    the landmarks drawn (one row without a texture, two with one)."""
    from matplotlib.figure import Figure

    panels = _panels(fit, texture)
    cols = 4 if texture is not None else len(panels)
    rows = -(-len(panels) // cols)
    fig = Figure(figsize=(PANEL_INCHES[0] * cols + 0.2, PANEL_INCHES[1] * rows + TITLE_INCHES))
    canvas = _inch_canvas(fig)
    places = _panel_places(fig, rows, cols)
    for (image_box, bar_box), (title, img) in zip(places, panels.items()):
        left, bottom, side = image_box
        extent = (left, left + side, bottom, bottom + side)
        if img.ndim == 2:
            shown = canvas.imshow(img, cmap="magma", vmin=0, vmax=0.2, extent=extent, aspect="auto")
            fig.colorbar(shown, cax=fig.add_axes(bar_box))
        else:
            canvas.imshow(img, extent=extent, aspect="auto")
        canvas.text(left + side / 2, bottom + side + 0.08, title, fontsize=9, ha="center", va="bottom")
    h, w = fit.image.shape[:2]
    for (image_box, _), points, colour in zip(places, (fit.landmarks, fit.fitted_landmarks()), ("lime", "cyan")):
        left, bottom, side = image_box           # pixel centres (u, v) onto the panel, v down
        canvas.scatter(left + (points[:, 0] + 0.5) * side / w, bottom + side - (points[:, 1] + 0.5) * side / h,
                       s=4, c=colour)
    title = (f"landmark error {metrics['landmark_error_px_full']:.2f} px (full size), "
             f"face-region PSNR (sRGB): model {metrics['psnr_face_db']:.1f} dB")
    if "psnr_face_db_textured" in metrics:
        title += f", with the detail texture {metrics['psnr_face_db_textured']:.1f} dB"
    fig.suptitle(title, fontsize=10)
    write_figure(fig, path, dpi=110, **PNG_OPTIONS)


def _inch_canvas(fig):
    """One axes over the whole figure, without axis lines or ticks, whose data units are the
    figure's inches from its lower left corner: every panel of figure.png is drawn into it. One
    axes, not one per panel: setting up an axes' ticks and placing its title cost more than
    drawing its image."""
    width, height = fig.get_size_inches()
    canvas = fig.add_axes((0, 0, 1, 1))
    canvas.set_axis_off()
    canvas.set_xlim(0, width)
    canvas.set_ylim(0, height)
    return canvas


def _panel_places(fig, rows: int, cols: int) -> list:
    """rows x cols (image square (left, bottom, side) in inches, colour-bar axes box in figure
    fractions) at fixed places, row-major: a PANEL_INCHES cell each below the figure's
    TITLE_INCHES title band (and 0.2 inches of right margin for the last colour bar's labels),
    the image square at the cell's lower left, room for a panel title above it and a colour bar
    beside it."""
    width, height = fig.get_size_inches()
    cell_w, cell_h = PANEL_INCHES
    side = cell_h - 0.55
    places = []
    for i in range(rows * cols):
        r, c = divmod(i, cols)
        left, bottom = c * cell_w + 0.1, height - TITLE_INCHES - (r + 1) * cell_h + 0.2
        bar = ((left + side + 0.08) / width, bottom / height, 0.12 / width, side / height)
        places.append(((left, bottom, side), bar))
    return places


def camera_matrices(fit: FaceFit, photo_size) -> dict:
    """The fitted camera for the full photo (H, W) in OpenCV form, with the head pose folded
    in: X_cam = R X_model + t, pixel = K X_cam / Z."""
    scene, values = photo_scene(fit, photo_size)
    f, (cx, cy) = values["focal"][0], scene.principal
    return dict(K=np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]),
                R=CAMERA_ROTATION @ axis_angle_to_matrix(values["rotation"]),
                t=CAMERA_ROTATION @ values["translation"])


def fitted_photo_landmarks(fit: FaceFit) -> np.ndarray:
    """(68, 2) float64: the fitted model's landmarks projected into the full photo (0-based
    pixel centres), where camera_matrices' K, R, t put them."""
    return fit.crop.to_full(fit.fitted_landmarks())


def landmarks_input(found: PhotoLandmarks) -> dict:
    """JSON-ready: where the fit's landmarks came from (source "file", "beside" or the detector's
    name, the file read) and, when detected, the face fitted (its number, box (x, y, w, h),
    the detector's score) and why it was chosen."""
    doc = dict(source=found.source, file=None if found.path is None else str(found.path))
    if found.detection is not None:
        chosen = found.face.to_json()
        doc.update(face=found.index, box=chosen["box"], score=chosen["score"], reason=found.detection.reason,
                   faces_found=len(found.detection.candidates), detection="detection.json")
    return doc


def write_landmarks(fit: FaceFit, found: PhotoLandmarks, out: Path) -> None:
    """landmarks_detected.pts (the points the fit was given), landmarks_fitted.pts and, for
    detected landmarks, detection.json (every face found and the choice) into ``out``."""
    write_pts(out / "landmarks_detected.pts", found.points)
    write_pts(out / "landmarks_fitted.pts", fitted_photo_landmarks(fit))
    if found.detection is not None:
        write_json(out / "detection.json", found.detection.to_json())


def save_textured_obj(path, vertices, faces, uvs, texture) -> None:
    """Write ``path`` (.obj) with ``v``, ``vt`` (one per vertex) and ``f a/a b/b c/c``, its
    material ``<stem>.mtl`` (map_Kd) and the texture ``<stem>.png`` (texture (S, S, 3) linear
    RGB, written sRGB 8-bit) beside it; every file replaced atomically."""
    path = Path(path)
    stem = path.stem
    write_image(path.with_suffix(".png"), np.clip(texture, 0.0, 1.0))
    write_text(path.with_suffix(".mtl"), f"newmtl face\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\n"
                                         f"map_Kd {stem}.png\n")
    vertices, uvs = np.asarray(vertices, np.float64), np.asarray(uvs, np.float64)
    corners = np.repeat(np.asarray(faces, np.int64) + 1, 2, axis=1)        # a/a b/b c/c
    write_text(path, "".join([f"# softras-cl face fit with its detail texture\nmtllib {stem}.mtl\n",
                              _rows("v %.8f %.8f %.8f\n", vertices), _rows("vt %.6f %.6f\n", uvs),
                              "usemtl face\n", _rows("f %d/%d %d/%d %d/%d\n", corners)]))


def _rows(line: str, table: np.ndarray) -> str:
    """``line`` (a %-format of one row) applied to every row of table (N, C), in one format."""
    return (line * len(table)) % tuple(table.ravel().tolist())


def write_outputs(fit: FaceFit, photo: np.ndarray, landmarks: PhotoLandmarks, out_dir,
                  extra: dict | None = None, run_config=None, metrics: dict | None = None) -> dict:
    """Write every output of a fit into ``out_dir`` (each file replaced atomically); returns the
    metrics written (``metrics``: those of ``fit.metrics()`` if the caller has them already).

    photo (H, W, 3) linear RGB at full size; landmarks: the photo's landmarks the fit was given
    (fitting.detection.resolve_landmarks), with where they came from; extra: more JSON-able
    facts for params.json; run_config: the run's effective configuration (e.g. its
    FaceFitConfig), recorded with the versions, device and command line under "provenance".
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics = fit.metrics() if metrics is None else metrics
    values = fit.values
    model = fit.scene.model
    shape = model.shape(values["id"], values["exp"])[0]
    save_mesh(out / "face.ply", shape, model.faces, colors=np.clip(model.albedo(values["albedo"])[0], 0.0, 1.0))
    texture = estimate_texture(fit, photo)
    metrics = dict(metrics, **textured_metrics(fit, texture))
    save_textured_obj(out / "face_textured.obj", shape, model.faces, texture.layout.uvs, texture.albedo)
    write_image(out / "overlay.png", np.clip(render_over(fit, photo, texture=texture), 0.0, 1.0))
    write_image(out / "overlay_model.png", np.clip(render_over(fit, photo), 0.0, 1.0))
    save_figure(fit, out / "figure.png", metrics, texture)
    write_landmarks(fit, landmarks, out)
    cam = camera_matrices(fit, photo.shape[:2])
    arrays = {**{k: np.asarray(v) for k, v in values.items()}, **cam}
    with atomic_path(out / "params.npz") as tmp:
        np.savez(tmp, **arrays)
    doc = dict(metrics=metrics, interrupted=fit.result.interrupted, outcomes=fit.result.outcomes,
               model=model.name, photo_size=list(photo.shape[:2]),
               working_size=list(fit.image.shape[:2]), landmarks_input=landmarks_input(landmarks),
               params={k: np.asarray(v).tolist() for k, v in arrays.items()},
               provenance=provenance(run_config), **(extra or {}))
    write_json(out / "params.json", doc)
    return metrics
