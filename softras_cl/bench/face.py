"""`softras-cl bench face`: face fitting on synthetic photos with known answers.

Each synthetic face is drawn from the model's own prior (identity, expression and albedo
coefficients ~ N(0, 1) clipped at +-2.5), lit by a random SH light (grey ambient plus random
first- and second-order terms and a slight tint), posed at random (yaw +-30, pitch +-15,
roll +-10 degrees) by a camera of random field of view (20-40 degrees) so that the face fills 50-65% of the
image, rendered sharp over a
random smooth background, and given 68 landmarks with Gaussian pixel noise of 1-2 px. Then
it is fitted from the photo and the noisy landmarks alone (the focal length is fitted too), at
several schedule budgets: what accuracy costs in time.

Reported per budget: vertex RMSE of the recovered shape (identity + expression, model frame)
against the true shape in mm, after a similarity (Procrustes with scale) alignment, since one
photo does not tell a face's absolute size, and the same for the mean face as the baseline; the
ratio of the two; the same ratio after a rigid alignment only (scale errors included); the
landmark error in pixels against the noise-free landmarks; the PSNR of the fit in the face
region (sRGB); the relative error of the fitted focal length |f - f*| / f* (median and max
over the faces); the time per fit. A landmarks-only row (the default budget's landmark stage
alone, no photometric stage) is the baseline the photo has to beat: what the photo adds to the
shape, the pose and the focal length is the difference.

--renderers softras,mitsuba also fits Mitsuba 3's path-traced photo of each face
(softras_cl.validate.mitsuba_face: the same truth, camera, background and landmarks, lit by the
SH light as an environment map plus a sun, with cast shadows and bounces): an image the fit's
own renderer did not make. Both photos of a face are fitted one after the other (A B A B), and
the JSON keeps softras-cl's runs under the budget's name, Mitsuba's under "mitsuba/<budget>",
with the Mitsuba photos' checks (silhouette IoU against softras-cl's render of the truth, PSNR
between the two photos, Monte Carlo noise) under "mitsuba".

--yaws 0-15,15-45,45-75 draws --faces faces per bin of |yaw| instead (the sign at random,
pitch and roll as above), with jaw landmarks as an annotator or a detector places them: where a
jaw point of the truth is hidden (its depth behind the truth render's depth at its pixel by more
than OCCLUDED_MM), it moves outwards across the jaw line to the edge of the truth render's
silhouette (alpha 0.5), in the jaw line's order; visible jaw points and the other 51 stay the
projected truth points (:func:`silhouette_jaw`); faces the fit would refuse are drawn again
(:func:`draw_faces`). --contour fixed,sliding
fits every face with each way of placing the jaw landmarks on the model
(FaceFitConfig.contour_landmarks) and compares them per yaw bin.

--landmarks truth,detected fits each face from the true landmarks (with their noise, above) and
from what the detector finds on the photo fitted (MediaPipe Face Mesh, the fit's default
detector: its 68 points and its 468 dense points, found on each renderer's photo of the face;
needs the detect extra); a face the detector misses on any renderer's photo is left out of
every run, and counted per renderer. --dense 0,W fits each face with each dense landmark weight
(FaceFitConfig.dense_weight) and compares them with 0; the dense points are always the
detector's (with --landmarks truth, beside the true 68).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import (add_bench_parser, add_budgets_option, add_model_option, add_output_options,
                                    add_samples_options, check_samples, load_model, print_report)
from softras_cl.errors import InputError, ResultError
from softras_cl.fitting.keypoints import ibug68
from softras_cl.io.outputs import OutputFolder, write_figure, write_json
from softras_cl.provenance import provenance

DEFAULT_BUDGETS = ("fast", "default", "thorough")
LANDMARKS_ONLY = "landmarks-only"    # the baseline row: the default budget without photometric stages
RENDERERS = ("softras", "mitsuba")
DEFAULT_SPP = 256        # Mitsuba rays per pixel: noise ~0.005 RMS linear RGB on the face (0.007 at 128)
NOISE_FACES = 3          # faces whose Mitsuba noise is measured (two extra renders each)
CONTOURS = ("fixed", "sliding")
LANDMARK_SOURCES = ("truth", "detected")
OCCLUDED_MM = 2.0        # a jaw point this far behind the rendered surface is hidden


# ---------------------------------------------------------------------------------------------
# synthetic faces
# ---------------------------------------------------------------------------------------------

def random_truth(model, rng: np.random.Generator, size: int, yaw_bin=None) -> dict:
    """Random known parameters (the fit's blocks, focal in pixels) for a size x size photo;
    yaw_bin (lo, hi) degrees: |yaw| uniform in it (the sign at random) instead of +-30."""
    from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle
    from softras_cl.scene.shading import sh_ambient

    coeffs = {k: np.clip(rng.normal(size=n), -2.5, 2.5)
              for k, n in (("id", model.n_id), ("exp", model.n_exp), ("albedo", model.n_albedo))}
    yaw, pitch, roll = rng.uniform(-30, 30), rng.uniform(-15, 15), rng.uniform(-10, 10)
    if yaw_bin is not None:
        yaw = np.sign(yaw) * rng.uniform(*yaw_bin)
    yaw, pitch, roll = np.radians([yaw, pitch, roll])
    R = axis_angle_to_matrix([0, yaw, 0]) @ axis_angle_to_matrix([pitch, 0, 0]) @ axis_angle_to_matrix([0, 0, roll])
    fov = np.radians(rng.uniform(20, 40))
    focal = 0.5 * size / np.tan(fov / 2)
    lo, hi = model.mean_shape.min(0), model.mean_shape.max(0)
    depth = focal * np.max(hi - lo) / (rng.uniform(0.5, 0.65) * size)   # face fills about 60%
    level = rng.uniform(0.6, 1.0)
    sh = sh_ambient(level)
    sh[:, 1:4] += rng.normal(0, 0.3 * sh[0, 0], 3)             # first order: a light direction
    sh[:, 4:] += rng.normal(0, 0.08 * sh[0, 0], 5)
    sh[:, 0] *= 1.0 + rng.normal(0, 0.03, 3)                    # a slight tint
    offset = rng.uniform(-0.05, 0.05, 2) * depth * size / focal
    centre = R @ ((lo + hi) / 2)                                       # the face's box at the centre
    return dict(coeffs, sh=sh, rotation=matrix_to_axis_angle(R),
                translation=np.array([offset[0], offset[1], -depth]) - centre, focal=np.array([focal]))


def smooth_background(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size, size, 3) linear RGB: a low-frequency random colour field in [0.05, 0.6]."""
    from skimage.transform import resize

    coarse = rng.uniform(0.05, 0.6, (6, 6, 3))
    return resize(coarse, (size, size), order=3, mode="reflect")


def synthetic_face(model, rng: np.random.Generator, size: int = 256, yaw_bin=None) -> dict:
    """One synthetic photo: truth, photo (size, size, 3) linear RGB, landmarks (68, 2) noisy and
    clean, the noise level in px; yaw_bin (lo, hi) degrees: a face turned that far, its jaw
    landmarks on the silhouette (:func:`silhouette_jaw`)."""
    truth = random_truth(model, rng, size, yaw_bin)
    return photograph(model, truth, rng, size, silhouette=yaw_bin is not None)


def photograph(model, truth: dict, rng: np.random.Generator, size: int = 256, silhouette: bool = False) -> dict:
    """The synthetic photo of known parameters ``truth`` (see :func:`random_truth`) over a random
    background, with noisy landmarks: what :func:`synthetic_face` returns; silhouette: hidden jaw
    points moved to the silhouette (:func:`silhouette_jaw`)."""
    from softras_cl.fitting.recipes.face import FaceScene, depth_range
    from softras_cl.scene.renderer import SHARP

    scene = FaceScene(model, (size, size), alpha_agg="hard", depth_range=depth_range(truth["translation"]))
    out = scene.render(truth, *SHARP)
    alpha = out.alpha[0][..., None]
    background = smooth_background(rng, size)
    photo = alpha * out.rgb[0] + (1.0 - alpha) * background
    world, _ = scene.geometry(truth)
    clean, _ = scene.camera(truth["focal"][0]).project_pixels(model.landmarks(world)[0])
    if silhouette:
        clean = silhouette_jaw(scene, truth, clean)
    noise = rng.uniform(1.0, 2.0)
    return dict(truth=truth, photo=np.clip(photo, 0, 1), landmarks=clean + rng.normal(0, noise, clean.shape),
                clean_landmarks=clean, noise_px=noise, background=background, alpha=out.alpha[0])


def draw_faces(model, rng: np.random.Generator, size: int, n: int, yaw_bin=None) -> tuple[list[dict], int]:
    """(n synthetic faces (:func:`synthetic_face`), how many were drawn again): a yaw bin's
    face whose noisy landmarks the fit would refuse as no face's (fitting.keypoints.plausibility: the
    jaw line crossing itself, where silhouette points lie closer together than the noise) is
    replaced by the next one drawn."""
    from softras_cl.fitting.keypoints.plausibility import layout_faults

    faces, redrawn = [], 0
    while len(faces) < n:
        face = synthetic_face(model, rng, size, yaw_bin)
        if yaw_bin is not None and layout_faults(face["landmarks"]):
            redrawn += 1
            continue
        faces.append(face)
    return faces, redrawn


def detect_photos(photos: dict) -> tuple[dict, dict]:
    """MediaPipe on every renderer's photo of each face (sRGB, 8 bits, as a photo file would
    hold it): each photo's fit gets the landmarks found on that photo. photos: renderer ->
    samples of the same faces. Returns (source -> renderer -> samples: "truth" with the true
    landmarks, "detected" with the detected 68, both with the detected dense points (468, 2)
    under "dense" and the detection's seconds; renderer -> faces missed on its photos). A face
    missed on any renderer's photo (no face, landmarks that form no face) is left out of every
    renderer's samples, so that their runs stay paired face for face."""
    found = {renderer: [_detect(sample["photo"]) for sample in samples] for renderer, samples in photos.items()}
    kept = [i for i in range(len(next(iter(photos.values())))) if all(f[i] is not None for f in found.values())]
    by_source = {"truth": {}, "detected": {}}
    for renderer, samples in photos.items():
        detections = [(samples[i], *found[renderer][i]) for i in kept]
        by_source["truth"][renderer] = [dict(sample, **extra) for sample, _, extra in detections]
        by_source["detected"][renderer] = [dict(sample, landmarks=points, face_mesh_landmarks=True, **extra)
                                           for sample, points, extra in detections]
    return by_source, {renderer: sum(f is None for f in faces) for renderer, faces in found.items()}


def _detect(photo: np.ndarray) -> tuple[np.ndarray, dict] | None:
    """(the 68 landmarks (68, 2), dict(dense (468, 2), detect_seconds)) MediaPipe finds on a
    linear-RGB photo (H, W, 3), or None when it finds no face or one whose landmarks form none."""
    from softras_cl.fitting.detection.faces import ImplausibleFaceError, NoFaceError
    from softras_cl.fitting.detection.find import detect_face
    from softras_cl.fitting.recipes.face import detected_dense
    from softras_cl.srgb import to_srgb

    start = time.perf_counter()
    try:
        chosen = detect_face(np.round(to_srgb(photo) * 255).astype(np.uint8), "mediapipe").chosen
    except (NoFaceError, ImplausibleFaceError):
        return None
    return chosen.landmarks.copy(), dict(dense=detected_dense(chosen), detect_seconds=time.perf_counter() - start)


def silhouette_jaw(scene, truth: dict, landmarks: np.ndarray) -> np.ndarray:
    """landmarks (68, 2) pixels, the truth model's points projected, with each hidden jaw point
    (iBUG 0-16; hidden: its view depth more than OCCLUDED_MM behind the depth of softras-cl's
    sharp, z-buffered render of the truth at its pixel) moved outwards across the jaw line to the
    edge of the render's silhouette (the first pixel of alpha <= 0.5, in half-pixel steps),
    as an annotator marks the outline of the face: outwards is the jaw line's outward normal in
    the model's frontal view (x, y; along x on the sides, down at the chin), turned by the
    truth's rotation and projected at the point. The moved points keep their order along the
    jaw (:func:`in_jaw_order`), as an annotator's do. scene: a FaceScene of the photo. Uses
    the render and the truth only, nothing of the fit's own contour code."""
    from softras_cl.scene.renderer import SHARP, Renderer
    from softras_cl.scene.rotation import axis_angle_to_matrix
    from softras_cl.scene.shading import SHLight

    model = scene.model
    settings = scene.settings.replace(outputs=("rgb", "alpha", "depth"), color_agg="hard")
    world, _ = scene.geometry(truth)
    camera = scene.camera(truth["focal"][0])
    out = Renderer(settings, shading="vertex").forward(
        world, scene.faces, camera, albedo=model.albedo(truth["albedo"])[0],
        light=SHLight(truth["sh"]), sigma=SHARP[0], gamma=SHARP[1])
    alpha, depth = out.alpha[0], out.depth[0]
    jaw = model.landmarks(world)[0][ibug68.JAW]
    outward = _jaw_normals(model.landmarks(model.mean_shape)[0][ibug68.JAW, :2])
    ahead, _ = camera.project_pixels(jaw + 1e-3 * outward @ axis_angle_to_matrix(truth["rotation"]).T)
    points, hidden = landmarks.copy(), []
    h, w = alpha.shape
    for j in ibug68.JAW:
        u, v = (int(round(c)) for c in landmarks[j])
        if not (0 <= u < w and 0 <= v < h) or -jaw[j, 2] <= depth[v, u] + OCCLUDED_MM * 1e-3:
            continue                     # outside the image or not hidden (the camera looks down -z)
        step = 0.5 * (ahead[j] - landmarks[j]) / np.linalg.norm(ahead[j] - landmarks[j])
        p = landmarks[j].copy()
        while True:
            u, v = (int(round(c)) for c in p + step)
            if not (0 <= u < w and 0 <= v < h) or alpha[v, u] <= 0.5:
                break
            p = p + step
        points[j] = p + 0.5 * step
        hidden.append(j)
    return in_jaw_order(points, hidden)


def in_jaw_order(points: np.ndarray, moved) -> np.ndarray:
    """points (68, 2) with the jaw points of indices ``moved`` (on the silhouette) reordered
    among themselves until the jaw line crosses itself nowhere between them: while segments
    (i, i+1) and (j, j+1) cross and the points i+1..j were all moved, their order is reversed
    (each reversal shortens the line, so this ends). Points moved independently of each other
    may pass one another where the outline turns (the chin), which no annotator's line does."""
    from softras_cl.fitting.keypoints.plausibility import _segments_cross

    jaw, moved = points[ibug68.JAW], set(moved)
    untangled = False
    while not untangled:
        untangled = True
        for i, j in ((i, j) for i in range(len(jaw) - 2) for j in range(i + 2, len(jaw) - 1)):
            if set(range(i + 1, j + 1)) <= moved and _segments_cross(jaw[i], jaw[i + 1], jaw[j], jaw[j + 1]):
                jaw[i + 1:j + 1] = jaw[i + 1:j + 1][::-1].copy()
                untangled = False
    out = points.copy()
    out[ibug68.JAW] = jaw
    return out


def _jaw_normals(jaw_xy: np.ndarray) -> np.ndarray:
    """(17, 3) unit outward normals of the jaw line jaw_xy (17, 2) in the model's frontal view,
    z = 0: perpendicular to the line through each point's neighbours, away from their centroid."""
    ahead, behind = np.roll(jaw_xy, -1, 0), np.roll(jaw_xy, 1, 0)
    ahead[-1], behind[0] = jaw_xy[-1], jaw_xy[0]
    t = ahead - behind
    n = np.stack([t[:, 1], -t[:, 0]], 1)
    n *= np.sign(np.sum(n * (jaw_xy - jaw_xy.mean(0)), axis=1))[:, None]
    return np.column_stack([n / np.linalg.norm(n, axis=1, keepdims=True), np.zeros(len(n))])


def mitsuba_render(model, truth: dict, size: int, spp: int, seed: int) -> dict:
    """Mitsuba 3's path-traced render of ``truth`` (validate.mitsuba_face.render_face_mitsuba:
    environment + sun light, shadows, bounces) by the camera of the softras-cl photo."""
    from softras_cl.fitting.recipes.face import FaceScene
    from softras_cl.validate.mitsuba_face import render_face_mitsuba

    scene = FaceScene(model, (size, size))
    world, _ = scene.geometry(truth)
    return render_face_mitsuba(world, model.faces, model.albedo(truth["albedo"])[0],
                               scene.camera(truth["focal"][0]), truth["sh"], spp, seed)


def mitsuba_sample(model, sample: dict, spp: int, seed: int = 0) -> dict:
    """``sample`` (from :func:`photograph`) with its photo replaced by Mitsuba's render of the same
    truth over the same background, the same landmarks; "render_check" says how the two photos
    compare: silhouette IoU (coverage > 0.5), RMS difference (linear RGB) and PSNR between them
    where both show the face, and the render's seconds."""
    from softras_cl.validate.mitsuba_face import composite, silhouette_iou

    start = time.perf_counter()
    render = mitsuba_render(model, sample["truth"], sample["photo"].shape[0], spp, seed)
    seconds = time.perf_counter() - start
    photo = composite(render, sample["background"])
    both = (render["alpha"] > 0.5) & (sample["alpha"] > 0.5)
    rms = float(np.sqrt(np.mean((photo[both] - sample["photo"][both]) ** 2)))
    check = dict(silhouette_iou=silhouette_iou(render["alpha"], sample["alpha"]), rms_vs_softras=rms,
                 psnr_vs_softras_db=-20.0 * float(np.log10(rms)), render_seconds=seconds)
    return dict(sample, photo=photo, alpha=render["alpha"], render_check=check)


def mitsuba_noise(model, sample: dict, spp: int) -> float:
    """RMS Monte Carlo noise (linear RGB) of a Mitsuba photo of ``sample`` where the face covers
    the pixel: the RMS difference of two renders of different seeds over sqrt 2."""
    size = sample["photo"].shape[0]
    a, b = (mitsuba_render(model, sample["truth"], size, spp, seed) for seed in (10**6, 10**6 + 1))
    face = (a["alpha"] > 0.5) & (b["alpha"] > 0.5)
    return float(np.sqrt(np.mean((a["rgb"][face] - b["rgb"][face]) ** 2) / 2.0))


# ---------------------------------------------------------------------------------------------
# metrics
# ---------------------------------------------------------------------------------------------

def aligned_rmse(a: np.ndarray, b: np.ndarray, scale: bool = True) -> float:
    """RMS distance between vertex sets a, b (V, 3) after the best rotation + translation (and
    uniform scale, when ``scale``) of a onto b (Procrustes). One photo does not tell a face's
    absolute size (a larger face further away looks the same), so shape is compared up to scale
    by default, as face-reconstruction benchmarks do; scale=False gives the rigid figure."""
    ca, cb = a - a.mean(0), b - b.mean(0)
    U, S, Vt = np.linalg.svd(ca.T @ cb)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    s = float(np.sum(S * np.diag(d)) / np.sum(ca * ca)) if scale else 1.0
    return float(np.sqrt(np.mean(np.sum((s * ca @ (U @ d @ Vt) - cb) ** 2, axis=1))))


def focal_error(fitted: float, true: float) -> float:
    """Relative focal-length error |f - f*| / f* (both in the same pixels)."""
    return abs(float(fitted) - float(true)) / float(true)


def truth_kind_landmarks(fit, model) -> np.ndarray:
    """(68, 2) working-image pixels: the fitted face's landmarks as the truth places them. The
    fit's own (FaceFit.fitted_landmarks) when it ties the landmarks to ``model``'s points; for a
    fit tied to Face Mesh's points (FaceFitConfig.landmark_map) the model's own points on the
    fitted face (fixed jaw points): the fit's own lie where MediaPipe puts them, not where the
    truth's are."""
    tied = fit.scene.model
    if (np.array_equal(tied.landmark_faces, model.landmark_faces)
            and np.array_equal(tied.landmark_bary, model.landmark_bary)):
        return fit.fitted_landmarks()
    world, _ = fit.scene.geometry(fit.values)
    return fit.scene.camera(fit.values["focal"][0]).project_pixels(model.landmarks(world)[0])[0]


def evaluate(fit, sample: dict, model, seconds: float) -> dict:
    """The bench's numbers for one fit of one synthetic face."""
    from softras_cl.scene.renderer import SHARP

    truth = sample["truth"]
    true_shape, _ = model.shape(truth["id"], truth["exp"])
    shape, _ = fit.scene.model.shape(fit.values["id"], fit.values["exp"])
    metrics = fit.metrics()
    landmarks = fit.crop.to_full(truth_kind_landmarks(fit, model))
    focal = fit.values["focal"][0] / fit.crop.scale      # working-image pixels -> the photo's
    region = fit.objective.face_region(fit.values, *SHARP)
    residual = fit.scene.render(fit.values, *SHARP).rgb[0][region] - fit.image[region]
    return dict(rmse_mm=1e3 * aligned_rmse(shape, true_shape),
                mean_face_rmse_mm=1e3 * aligned_rmse(model.mean_shape, true_shape),
                rigid_rmse_mm=1e3 * aligned_rmse(shape, true_shape, scale=False),
                rigid_mean_face_rmse_mm=1e3 * aligned_rmse(model.mean_shape, true_shape, scale=False),
                landmark_error_px=float(np.linalg.norm(landmarks - sample["clean_landmarks"],
                                                       axis=1).mean()),
                psnr_face_db=metrics["psnr_face_db"],
                # linear RGB, working image: what Mitsuba's noise is compared with
                residual_rms=float(np.sqrt(np.mean(residual ** 2))),
                focal_px=float(focal), true_focal_px=float(truth["focal"][0]),
                focal_error=focal_error(focal, truth["focal"][0]),
                seconds=seconds,
                interrupted=fit.result.interrupted)


def summarise(rows: list[dict]) -> dict:
    """Means/medians over the faces of one budget."""
    def mean(k):
        return float(np.mean([r[k] for r in rows]))

    return dict(faces=len(rows), rmse_mm=mean("rmse_mm"), mean_face_rmse_mm=mean("mean_face_rmse_mm"),
                rmse_ratio=mean("rmse_mm") / mean("mean_face_rmse_mm"),
                rigid_rmse_mm=mean("rigid_rmse_mm"), rigid_mean_face_rmse_mm=mean("rigid_mean_face_rmse_mm"),
                rigid_ratio=mean("rigid_rmse_mm") / mean("rigid_mean_face_rmse_mm"),
                landmark_error_px=mean("landmark_error_px"), psnr_face_db=mean("psnr_face_db"),
                residual_rms_median=float(statistics.median(r["residual_rms"] for r in rows)),
                psnr_face_db_min=float(min(r["psnr_face_db"] for r in rows)),
                focal_error_median=float(statistics.median(r["focal_error"] for r in rows)),
                focal_error_max=float(max(r["focal_error"] for r in rows)),
                median_seconds=float(statistics.median(r["seconds"] for r in rows)),
                median_cpu_seconds=float(statistics.median(r.get("cpu_seconds", float("nan")) for r in rows)))


# ---------------------------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------------------------

def budget_config(budget: str, size: int, photo_weight: float | None = None, contour: str | None = None,
                  dense_weight: float | None = None):
    """The FaceFitConfig of a budget name, LANDMARKS_ONLY meaning the default budget's landmark
    stage alone; contour: its contour_landmarks, dense_weight: its dense_weight (None: the
    config's default)."""
    from softras_cl.fitting.recipes.face import FaceFitConfig

    changes = dict(size=size)
    if contour is not None:
        changes["contour_landmarks"] = contour
    if dense_weight is not None:
        changes["dense_weight"] = dense_weight
    if budget == LANDMARKS_ONLY:
        return FaceFitConfig.from_budget("default", photo_weight=photo_weight, photo_stages=(), **changes)
    return FaceFitConfig.from_budget(budget, photo_weight=photo_weight, **changes)


def fit_one(model, sample: dict, config) -> dict:
    """Fit one sample: its evaluate() row, with its CPU seconds, the objective evaluations and
    the solver's outcome of each stage, and the fit itself under "fit"."""
    from softras_cl.fitting.recipes.face import fit_face

    start, cpu = time.perf_counter(), time.process_time()
    fit = fit_face(sample["photo"], sample["landmarks"], model, config, progress=False, dense=sample.get("dense"),
                   face_mesh_landmarks=sample.get("face_mesh_landmarks", False))
    row = evaluate(fit, sample, model, time.perf_counter() - start)
    stages = [h["stage"] for h in fit.result.history]
    # CPU time of the whole process (host and the OpenCL CPU device's threads): on a shared
    # machine it moves less with other users' load than the wall time does
    return dict(row, cpu_seconds=time.process_time() - cpu, fit=fit,
                evaluations={s: stages.count(s) for s in dict.fromkeys(stages)},
                outcomes=dict(fit.result.outcomes))


def run_budget(model, samples: list[dict], budget: str, size: int, progress: bool,
               photo_weight: float | None = None) -> list[dict]:
    """Fit every sample at one budget (or LANDMARKS_ONLY); one fit_one() row per sample."""
    return run_interleaved(model, {"softras": samples}, budget, size, progress, photo_weight)["softras"]


def run_interleaved(model, photos: dict, budget: str, size: int, progress: bool,
                    photo_weight: float | None = None, contour: str | None = None,
                    dense_weight: float | None = None) -> dict:
    """photos: renderer -> samples of the same faces. Fits face 0 of every renderer, then face
    1, ... (A B A B: a load change on the shared machine hits every renderer alike); returns
    renderer -> fit_one() rows. contour, dense_weight: the fits' contour_landmarks and
    dense_weight (None: the default)."""
    from tqdm import tqdm

    config = budget_config(budget, size, photo_weight, contour, dense_weight)
    rows = {renderer: [] for renderer in photos}
    n = len(next(iter(photos.values())))
    for i in tqdm(range(n), desc=f"bench face [{budget}]", disable=not progress):
        for renderer, samples in photos.items():
            rows[renderer].append(fit_one(model, samples[i], config))
    return rows


def save_chart(summary: dict, path: Path) -> None:
    """Shape error and PSNR against CPU time per fit (it moves less than the wall time with the
    shared machine's load), one point per budget, one colour per renderer."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.6))
    ax1, ax2 = fig.subplots(1, 2)
    colours = {"softras": "tab:blue", "mitsuba": "tab:orange"}
    for s in summary.values():
        renderer, budget = s.get("renderer", "softras"), s.get("budget", "")
        for ax, key in ((ax1, "rmse_mm"), (ax2, "psnr_face_db")):
            ax.plot(s["median_cpu_seconds"], s[key], "o", c=colours[renderer])
            ax.annotate(budget, (s["median_cpu_seconds"], s[key]), xytext=(4, 4 if renderer == "softras" else -10),
                        textcoords="offset points", fontsize=8)
    for renderer, colour in colours.items():
        if any(s.get("renderer", "softras") == renderer for s in summary.values()):
            ax2.plot([], [], "o", c=colour, label=f"{renderer} photos")
    base = next(iter(summary.values()))["mean_face_rmse_mm"]
    ax1.axhline(base, ls="--", c="grey", label=f"mean face {base:.2f} mm")
    ax1.axhline(base / 4, ls=":", c="grey", label="target: a quarter of it")
    ax1.set(xlabel="median CPU time per fit [s]", ylabel="shape RMSE up to scale [mm]", ylim=(0, None))
    ax1.legend(fontsize=8)
    ax2.axhline(30, ls=":", c="grey", label="target 30 dB")
    ax2.set(xlabel="median CPU time per fit [s]", ylabel="face-region PSNR [dB]")
    ax2.legend(fontsize=8)
    fig.suptitle("bench face: accuracy against time per budget")
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def save_strip(rows: list[dict], path: Path, n: int = 4) -> None:
    """Photo over fit for the first n faces of a budget."""
    from softras_cl.bench.tools import save_image_strip
    from softras_cl.fitting.reports.face import display_scene
    from softras_cl.scene.renderer import SHARP

    columns = []
    for row in rows[:n]:
        fit = row["fit"]
        out = display_scene(fit).render(fit.values, *SHARP)
        a = out.alpha[0][..., None]
        columns.append((fit.image, a * out.rgb[0] + (1 - a) * fit.image, "synthetic photo",
                        f"fit: {row['rmse_mm']:.2f} mm, {row['psnr_face_db']:.1f} dB"))
    save_image_strip(columns, path, cell=(2.6, 2.7))


def format_table(summary: dict) -> str:
    head = ("renderer", "yaw", "landmarks", "contour", "dense", "budget", "faces", "RMSE mm", "mean-face mm", "ratio", "rigid ratio", "lmk px", "focal err",
            "max focal err", "PSNR dB", "min PSNR", "median s/fit", "median CPU s")
    lines = ["  ".join(f"{h:>12}" for h in head)]
    for name, s in summary.items():
        dense = s.get("dense")
        cells = (s.get("renderer", "softras"), s.get("yaw_bin") or "+-30", s.get("landmarks") or "truth",
                 s.get("contour", "-"), "-" if dense is None else f"{dense:g}", s.get("budget", name), s["faces"], f"{s['rmse_mm']:.3f}", f"{s['mean_face_rmse_mm']:.3f}",
                 f"{s['rmse_ratio']:.3f}", f"{s['rigid_ratio']:.3f}", f"{s['landmark_error_px']:.2f}",
                 f"{100 * s['focal_error_median']:.1f}%", f"{100 * s['focal_error_max']:.1f}%",
                 f"{s['psnr_face_db']:.1f}",
                 f"{s['psnr_face_db_min']:.1f}", f"{s['median_seconds']:.1f}",
                 f"{s.get('median_cpu_seconds', float('nan')):.1f}")
        lines.append("  ".join(f"{c:>12}" for c in cells))
    return "\n".join(lines)


def parse_yaws(text: str | None) -> list[tuple[float, float]]:
    """'0-15,15-45' -> [(0.0, 15.0), (15.0, 45.0)] (|yaw| bins in degrees; None or '' -> []);
    InputError unless each is lo-hi with 0 <= lo < hi <= 90."""
    bins = []
    for part in filter(None, (p.strip() for p in (text or "").split(","))):
        lo, _, hi = part.partition("-")
        try:
            bin_ = (float(lo), float(hi))
        except ValueError:
            bin_ = None
        if bin_ is None or not 0 <= bin_[0] < bin_[1] <= 90:
            raise InputError(f"--yaws must be comma-separated bins lo-hi of |yaw| in degrees with "
                             f"0 <= lo < hi <= 90, e.g. 0-15,15-45,45-75; got {part!r}")
        bins.append(bin_)
    return bins


def parse_names(text: str | None, flag: str, allowed: tuple[str, ...]) -> list[str | None]:
    """'a,b' -> ['a', 'b'] (None or '' -> [None]: the default, runs named as before); InputError
    naming ``flag`` unless each is one of ``allowed``, once."""
    if not text:
        return [None]
    names = [c.strip() for c in text.split(",") if c.strip()]
    if not names or any(c not in allowed for c in names) or len(set(names)) != len(names):
        raise InputError(f"{flag} must name some of {', '.join(allowed)} once each, got {text!r}")
    return names


def parse_contours(text: str | None) -> list[str | None]:
    """--contour: 'fixed,sliding' -> ['fixed', 'sliding'] ([None]: the fit's default)."""
    return parse_names(text, "--contour", CONTOURS)


def parse_landmark_sources(text: str | None) -> list[str | None]:
    """--landmarks: 'truth,detected' -> ['truth', 'detected'] ([None]: the true landmarks)."""
    return parse_names(text, "--landmarks", LANDMARK_SOURCES)


def parse_dense(text: str | None) -> list[float | None]:
    """'0,0.5' -> [0.0, 0.5] (None or '' -> [None]: the fit's default); InputError unless each is
    a number >= 0, once."""
    if not text:
        return [None]
    try:
        weights = [float(w) for w in text.split(",") if w.strip()]
    except ValueError:
        weights = []
    if not weights or any(not (np.isfinite(w) and w >= 0) for w in weights) or len(set(weights)) != len(weights):
        raise InputError(f"--dense must be comma-separated dense landmark weights >= 0, each once, e.g. 0,0.5; "
                         f"got {text!r}")
    return weights


def yaw_name(yaw_bin) -> str:
    """(15.0, 45.0) -> 'yaw 15-45' ('' for None: the standard +-30 faces)."""
    return "" if yaw_bin is None else f"yaw {yaw_bin[0]:g}-{yaw_bin[1]:g}"


COMPARED = ("landmark_error_px", "rmse_mm", "median_seconds")
RUN_KEYS = ("renderer", "yaw_bin", "landmarks", "budget", "contour", "dense")     # what sets a run apart


def paired_comparison(summary: dict, key: str, base, other, labels: tuple[str, str]) -> list[dict]:
    """Runs whose ``key`` is ``base`` against those where it is ``other``, alike in every other
    RUN_KEYS: landmark and shape error and median seconds per fit of each (suffixed by
    ``labels``), and the relative reductions (1 - other / base)."""
    runs = {}
    for s in summary.values():
        rest = tuple((k, s.get(k)) for k in RUN_KEYS if k != key)
        runs.setdefault(rest, {})[s.get(key)] = s
    rows = []
    for rest, by in runs.items():
        if base not in by or other not in by:
            continue
        rows.append(dict(rest, faces=by[base]["faces"],
                         **{f"{k}_{label}": by[v][k] for k in COMPARED for v, label in zip((base, other), labels)},
                         landmark_reduction=1.0 - by[other]["landmark_error_px"] / by[base]["landmark_error_px"],
                         rmse_reduction=1.0 - by[other]["rmse_mm"] / by[base]["rmse_mm"]))
    return rows


def contour_comparison(summary: dict) -> list[dict]:
    """Fixed against sliding jaw points (paired_comparison, suffixes _fixed and _sliding)."""
    return paired_comparison(summary, "contour", "fixed", "sliding", CONTOURS)


def dense_comparison(summary: dict) -> list[dict]:
    """No dense term against each dense weight W > 0 (paired_comparison, suffixes _off and _on,
    the weight under "dense_weight")."""
    weights = sorted({s.get("dense") for s in summary.values() if s.get("dense")})
    return [dict(row, dense_weight=w) for w in weights
            for row in paired_comparison(summary, "dense", 0.0, w, ("off", "on"))]


def format_comparison(rows: list[dict], labels: tuple[str, str] = CONTOURS,
                      title: str = "fixed against sliding jaw points") -> str:
    """paired_comparison() rows (contour_comparison()'s by default) as a table ("" without any)."""
    from softras_cl.bench.tools import format_table as columns_table

    if not rows:
        return ""
    a, b = labels
    extra = [("landmarks", "landmarks", "s")] if any(r.get("landmarks") for r in rows) else []
    extra += [("W", "dense_weight", "g")] if "dense_weight" in rows[0] else []
    return f"{title}:\n" + columns_table(rows, [
        ("renderer", "renderer", "s"), ("yaw", "yaw_bin", "s"), *extra, ("budget", "budget", "s"),
        ("faces", "faces", "d"),
        (f"lmk px {a}", f"landmark_error_px_{a}", ".2f"), (f"lmk px {b}", f"landmark_error_px_{b}", ".2f"),
        ("lmk -%", "landmark_reduction", ".0%"), (f"RMSE mm {a}", f"rmse_mm_{a}", ".3f"),
        (f"RMSE mm {b}", f"rmse_mm_{b}", ".3f"), ("RMSE -%", "rmse_reduction", ".0%"),
        (f"s/fit {a}", f"median_seconds_{a}", ".1f"), (f"s/fit {b}", f"median_seconds_{b}", ".1f")])


def parse_renderers(text: str) -> list[str]:
    """'softras,mitsuba' -> ['softras', 'mitsuba']; InputError unless every name is in RENDERERS
    (and, for mitsuba, unless the package is installed: before any fit runs)."""
    names = [r.strip() for r in text.split(",") if r.strip()]
    if not names or any(r not in RENDERERS for r in names) or len(set(names)) != len(names):
        raise InputError(f"--renderers must name some of {', '.join(RENDERERS)} once each, got {text!r}")
    if "mitsuba" not in names:
        return names
    from softras_cl.validate.mitsuba import mitsuba_available   # with trimesh: ~0.9 s to import

    if not mitsuba_available():
        raise InputError("--renderers mitsuba needs Mitsuba 3: pip install 'softras-cl[validate]' "
                         "(or pip install mitsuba)")
    return names


def format_mitsuba(doc: dict) -> str:
    """The Mitsuba photos' checks under the table: geometry agrees, shading does not, and the
    Monte Carlo noise against the fit's residual on Mitsuba's photos ("" without Mitsuba)."""
    m = doc.get("mitsuba")
    if not m:
        return ""
    residual = [s["residual_rms_median"] for s in doc["summary"].values()
                if s["renderer"] == "mitsuba" and s["budget"] != LANDMARKS_ONLY]
    lines = [f"mitsuba photos ({m['spp']} spp): silhouette IoU against softras-cl's min {m['silhouette_iou_min']:.4f}, "
             f"median {m['silhouette_iou_median']:.4f}; PSNR against softras-cl's photo (face) median "
             f"{m['psnr_vs_softras_db_median']:.1f} dB; median render {m['render_seconds_median']:.1f} s",
             f"Monte Carlo noise RMS (linear RGB, first {len(m['noise_rms'])} faces) "
             + ", ".join(f"{n:.4f}" for n in m["noise_rms"])]
    if residual:
        lines[-1] += f"; median fit residual RMS on mitsuba photos {max(residual):.4f} (largest over budgets)"
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from softras_cl.fitting.recipes.face_settings import BUDGETS

    from softras_cl.bench.tools import parse_budgets

    budgets = parse_budgets(args.budgets, BUDGETS)
    renderers = parse_renderers(args.renderers)
    yaw_bins = parse_yaws(args.yaws) or [None]
    contours = parse_contours(args.contour)
    sources, dense_weights = parse_landmark_sources(args.landmarks), parse_dense(args.dense)
    detect = "detected" in sources or any(dense_weights)
    if detect:
        from softras_cl.fitting.detection.find import check_backend
        check_backend("mediapipe")          # the detector is installed, before any face is drawn
    if args.spp < 2:
        raise InputError(f"--spp must be >= 2 (Mitsuba rays per pixel), got {args.spp}")
    check_samples(args, "--faces", min_size=16)
    with OutputFolder(args.out, "bench face", "--out") as folder:
        out = folder.path
        model = load_model("face", args.model)
        rng = np.random.default_rng(args.seed)
        per_run, summary, rendered = {}, {}, []
        redrawn, missed = {}, {}
        for yaw_bin in yaw_bins:
            samples, redrawn[yaw_name(yaw_bin)] = draw_faces(model, rng, args.size, args.faces, yaw_bin)
            photos = photos_by_renderer(model, samples, renderers, args.spp, not args.json)
            rendered += photos.get("mitsuba", [])
            by_source = dict.fromkeys((None, "truth"), photos)
            if detect:
                by_source, missed[yaw_name(yaw_bin)] = detect_photos(photos)
            # a source without samples: the detector found no face in this bin
            for source, shots in ((s, by_source[s]) for s in sources if by_source[s][renderers[0]]):
                for b, contour, dense in ((b, c, d) for b in [LANDMARKS_ONLY] + budgets for c in contours
                                          for d in dense_weights):
                    for renderer, rows in run_interleaved(model, shots, b, args.size, not args.json,
                                                          args.photo_weight, contour, dense).items():
                        name = run_name(renderer, b, yaw_bin, contour, source, dense)
                        per_run[name] = rows
                        summary[name] = dict(summarise(rows), renderer=renderer, budget=b,
                                             yaw_bin=yaw_name(yaw_bin) or None, landmarks=source, dense=dense,
                                             contour=contour or budget_config(b, args.size).contour_landmarks)
        if not summary:
            raise ResultError(f"the detector found none of the {args.faces * len(yaw_bins)} faces: nothing to fit")
        checks = mitsuba_checks(model, rendered, args.spp) if rendered else {}
        comparison, dense_rows = contour_comparison(summary), dense_comparison(summary)
        doc = dict(size=args.size, seed=args.seed, model=model.name, photo_weight=args.photo_weight,
                   renderers=renderers, yaw_bins=yaw_bins if yaw_bins != [None] else None,
                   redrawn_faces=redrawn if yaw_bins != [None] else None,
                   undetected_faces=missed or None,
                   summary=summary, contour_comparison=comparison, dense_comparison=dense_rows, **checks,
                   faces={name: [{k: v for k, v in r.items() if k != "fit"} for r in rows]
                          for name, rows in per_run.items()},
                   provenance=provenance(dict(options=args)))
        write_json(out / "face.json", doc)
        save_chart(summary, out / "face.png")
        for renderer in renderers:      # the strip of its last run at the last budget (a run may lack faces)
            names = [n for n, s in summary.items() if s["renderer"] == renderer and s["budget"] == budgets[-1]]
            if names:
                save_strip(per_run[names[-1]], out / ("face_strip.png" if renderer == "softras"
                                                      else f"face_{renderer}_strip.png"))
        print_report(doc, args.json,
                     "\n".join(filter(None, (format_table(summary), format_comparison(comparison),
                                            format_comparison(dense_rows, ("off", "on"), "without against with the "
                                                              "dense landmark term"),
                                            format_mitsuba(doc)))))
    return 0


def run_name(renderer: str, budget: str, yaw_bin=None, contour: str | None = None,
             landmarks: str | None = None, dense: float | None = None) -> str:
    """The key of a run in the JSON: the budget for softras-cl's photos of the standard faces
    with the fit's default contour (the keys the bench always had), preceded by "mitsuba/" for
    Mitsuba's photos, "yaw lo-hi/" for a yaw bin's faces and "<landmarks> landmarks/" when
    --landmarks names them, followed by "/<contour> contour" when --contour names it and
    "/dense W" when --dense does."""
    parts = ("" if renderer == "softras" else renderer, yaw_name(yaw_bin),
             "" if landmarks is None else f"{landmarks} landmarks", budget,
             "" if contour is None else f"{contour} contour", "" if dense is None else f"dense {dense:g}")
    return "/".join(filter(None, parts))


def photos_by_renderer(model, samples: list[dict], renderers: list[str], spp: int, progress: bool) -> dict:
    """renderer -> samples of the same faces: softras-cl's photos (``samples``) and Mitsuba's
    (:func:`mitsuba_sample`, each with its render check), as ``renderers`` asks."""
    from tqdm import tqdm

    photos = {"softras": samples} if "softras" in renderers else {}
    if "mitsuba" in renderers:
        photos["mitsuba"] = [mitsuba_sample(model, s, spp, seed=i)
                             for i, s in enumerate(tqdm(samples, desc="mitsuba renders", disable=not progress))]
    return photos


def mitsuba_checks(model, rendered: list[dict], spp: int) -> dict:
    """The JSON's "mitsuba" section over every Mitsuba photo of the run (mitsuba_sample's, all
    yaw bins): their render checks per face, the Monte Carlo noise of the first NOISE_FACES."""
    per_face = [s["render_check"] for s in rendered]
    return dict(mitsuba=dict(
        spp=spp, faces=per_face, noise_rms=[mitsuba_noise(model, s, spp) for s in rendered[:NOISE_FACES]],
        silhouette_iou_min=min(c["silhouette_iou"] for c in per_face),
        silhouette_iou_median=statistics.median(c["silhouette_iou"] for c in per_face),
        psnr_vs_softras_db_median=statistics.median(c["psnr_vs_softras_db"] for c in per_face),
        render_seconds_median=statistics.median(c["render_seconds"] for c in per_face)))


def register(which) -> None:
    """Add `face` to the `softras-cl bench` subparsers."""
    p = add_bench_parser(which, __doc__, "face", help="face fitting on synthetic photos with known answers")
    add_samples_options(p, "--faces", 20, "faces", 256)
    add_budgets_option(p, DEFAULT_BUDGETS)
    p.add_argument("--seed", type=int, default=0, help="random seed of the synthetic faces (default 0)")
    p.add_argument("--photo-weight", type=float, default=None,
                   help="photometric weight of the fits (default: the fit's own, as in fit-face --help)")
    p.add_argument("--renderers", default="softras",
                   help="comma-separated renderers of the synthetic photos: softras (softras-cl, sharp, "
                        "the fit's own image formation), mitsuba (Mitsuba 3 path tracer: environment + "
                        "sun light, cast shadows, bounces; needs the validate extra); default softras")
    p.add_argument("--spp", type=int, default=DEFAULT_SPP,
                   help=f"Mitsuba samples per pixel (default {DEFAULT_SPP})")
    p.add_argument("--yaws", default=None,
                   help="comma-separated bins of |yaw| in degrees, e.g. 0-15,15-45,45-75: --faces faces "
                        "per bin, their hidden jaw landmarks on the silhouette as an annotator places them "
                        "(default: the standard faces at yaw +-30, jaw landmarks the model's points)")
    p.add_argument("--contour", default=None,
                   help="comma-separated ways the fits tie the jaw landmarks to the model, each fitted "
                        "to every face and compared per yaw bin: fixed (fixed model points), sliding (the "
                        "fitted mesh's occluding contour where the jaw is turned away); default: the fit's "
                        "own (FaceFitConfig.contour_landmarks)")
    p.add_argument("--landmarks", default=None,
                   help="comma-separated landmark sources, each fitted to every face: truth (the true 68 "
                        "with 1-2 px noise), detected (MediaPipe's 68 found on the photo; needs the detect "
                        "extra; faces it misses are left out of every run); default: truth")
    p.add_argument("--dense", default=None, metavar="W,...",
                   help="comma-separated dense landmark weights (fit-face --dense-landmarks), each fitted to "
                        "every face and compared with 0, e.g. 0,0.5; the dense points are MediaPipe's (needs "
                        "the detect extra); default: the fit's own (off)")
    add_model_option(p, "face")
    add_output_options(p, "directory for face.json, face.png (accuracy vs time), face_strip.png "
                          "(and face_mitsuba_strip.png)", run)
