"""`softras-cl bench body-photo`: body fitting to synthetic photos of people with known answers.

Each synthetic photo: the demo body (or --model) with a random shape and a random plausible pose
(softras_cl.bench.body.random_pose: joints within the pose prior, knees and elbows as hinges,
turned up to +-30 degrees about the vertical), dressed by part (skin on the head, forearms and
hands, a random shirt colour on the torso and upper arms, random trousers on the hips, thighs and
calves, dark shoes, hair, eyes and a mouth: paint_face) and drawn with Gouraud (Lambert) shading by softras-cl's hard render, from a
camera at a random distance (3.8-5.0 m) and height (0.6-1.2 m) with the fitting camera's field
of view, over a real photo (one of BACKGROUNDS from skimage.data, resized to the frame). With
--renderer mitsuba the same person (vertices, colours, camera, background) is path-traced by
Mitsuba 3 instead (mitsuba_photo: a sun and a sky, so shadows and shading the fit's renderer
does not make); the true mask stays the sharp softras-cl silhouette. The
person detector (fitting.detection.people) sees each photo as a user's would; the fit
(fitting.recipes.body_photo) runs on what it found, with the full objective and its ablations
(keypoints only, mask only: OBJECTIVES).

Reported per objective: detection rate; MPJPE (mm, after aligning the pelvis: one view leaves the
depth open) and PA-MPJPE (mm, after the similarity transform that best aligns the 24 joints);
the mask IoU of the fit's sharp silhouette against the true one; the median time per photo end to
end (detection and fit; detection timed once per photo and added to every objective).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import (add_bench_parser, add_model_option, add_output_options, add_samples_options,
                                    check_samples, load_model, print_report)
from softras_cl.errors import InputError
from softras_cl.io.outputs import OutputFolder, write_json
from softras_cl.provenance import provenance

BACKGROUNDS = ("coffee", "rocket", "brick", "grass", "gravel")
SKIN = ("head", "left_forearm", "right_forearm", "left_hand", "right_hand")
SHIRT = ("torso", "left_upper_arm", "right_upper_arm")
TROUSERS = ("hips", "left_thigh", "right_thigh", "left_calf", "right_calf")
SHOES = ("left_foot", "right_foot")
HAIR_COLORS = ((0.03, 0.02, 0.01), (0.15, 0.07, 0.03), (0.5, 0.35, 0.15))
SKIN_TONES = ((0.62, 0.42, 0.32), (0.45, 0.28, 0.18), (0.25, 0.14, 0.09), (0.75, 0.55, 0.45))
RENDERERS = ("softras", "mitsuba")
SKY_AMBIENT, SUN_DIRECTIONAL = 0.8, 0.4      # sun_light: shading albedo * (0.8 + 0.4 cos) before shadows
SUN_SHARE = 0.6                              # of it in the sun (sharp shadows), the rest the sky
MITSUBA_SPP = 64
CACHE_VERSION = 1


def clothing_colors(model, rng: np.random.Generator) -> np.ndarray:
    """(V, 3) linear RGB: skin, a shirt, trousers and shoes by the model's part names (a model
    without parts: skin everywhere)."""
    skin = np.array(SKIN_TONES[rng.integers(len(SKIN_TONES))])
    colors = np.tile(skin, (len(model.v_template), 1))
    if model.part_labels is None:
        return colors
    for parts, color in ((SHIRT, rng.uniform(0.05, 0.8, 3)), (TROUSERS, rng.uniform(0.03, 0.4, 3)),
                         (SHOES, np.full(3, 0.03))):
        for name in parts:
            if name in model.part_names:
                colors[model.part_labels == model.part_names.index(name)] = color
    paint_face(model, colors, np.array(HAIR_COLORS[rng.integers(len(HAIR_COLORS))]))
    return colors


def paint_face(model, colors: np.ndarray, hair: np.ndarray) -> None:
    """Hair (above the brows, and the back of the head), dark eyes and a mouth on the head's
    vertices of ``colors`` (V, 3), in place, placed from the nose vertex
    (fitting.keypoints.pose33.head_landmarks): without them a detector cannot tell the
    bald, blank demo head's front from its back."""
    from softras_cl.fitting.keypoints.pose33 import head_landmarks

    marks = head_landmarks(model)
    if not marks:
        return
    head = np.asarray(model.weights).argmax(1) == model.joint_names.index("head")
    v = model.v_template
    nose = v[marks["nose"]]
    centre_z = 0.5 * (v[marks["left_ear"], 2] + v[marks["right_ear"], 2])
    hair_mask = head & ((v[:, 1] > nose[1] + 0.07) | ((v[:, 2] < centre_z - 0.02) & (v[:, 1] > nose[1] - 0.03)))
    colors[hair_mask] = hair
    front = head & (v[:, 2] > nose[2] - 0.05)
    for centre, radius, color in (((0.032, 0.035), 0.012, (0.02, 0.02, 0.02)), ((-0.032, 0.035), 0.012, (0.02, 0.02, 0.02)),
                                  ((0.0, -0.04), 0.016, (0.35, 0.05, 0.05))):
        near = np.hypot(v[:, 0] - nose[0] - centre[0], (v[:, 1] - nose[1] - centre[1]) * 1.8) < radius
        colors[front & near] = color


def background(name: str, size: int) -> np.ndarray:
    """(size, size, 3) linear RGB: a centre square of skimage.data's ``name`` resized."""
    import skimage.data
    from skimage.transform import resize

    from softras_cl.srgb import to_linear

    image = getattr(skimage.data, name)()
    image = np.repeat(image[..., None], 3, -1) if image.ndim == 2 else image[..., :3]
    h, w = image.shape[:2]
    side = min(h, w)
    square = image[(h - side) // 2:(h + side) // 2, (w - side) // 2:(w + side) // 2]
    return to_linear(resize(square / 255.0, (size, size), order=1, anti_aliasing=True))


def synthetic_photo(model, rng: np.random.Generator, size: int, fov_deg: float) -> dict:
    """One photo drawn by softras-cl: truth blocks, image (size, size, 3) uint8 sRGB, true 3D
    joints (J, 3) and vertices (V, 3), the camera, the true person mask (size, size) bool, the
    background's name, the clothing colours albedo (V, 3)."""
    from softras_cl.bench.body import random_pose
    from softras_cl.raster.settings import RasterSettings
    from softras_cl.scene.camera import Camera
    from softras_cl.scene.renderer import SHARP, Renderer
    from softras_cl.srgb import to_srgb

    truth = random_pose(model, rng)
    state, _ = model.forward(truth["betas"], truth["body_pose"], truth["global_rotation"], truth["translation"])
    distance, height = rng.uniform(3.8, 5.0), rng.uniform(0.6, 1.2)
    camera = Camera.look_at((0.0, height, distance), (0.0, 0.85, 0.0), fov_deg=fov_deg, image_size=(size, size))
    settings = RasterSettings(image_size=(size, size), outputs=("rgb", "alpha"), near=0.5, far=distance + 3.0,
                              double_sided=True, color_agg="hard", alpha_agg="hard")
    albedo = clothing_colors(model, rng)
    out = Renderer(settings, shading="vertex").forward(state.vertices, model.faces, camera,
                                                       albedo=albedo, sigma=SHARP[0],
                                                       gamma=SHARP[1])
    name = BACKGROUNDS[rng.integers(len(BACKGROUNDS))]
    alpha = out.alpha[0][..., None]
    image = alpha * out.rgb[0] + (1 - alpha) * background(name, size)
    return dict(truth=truth, image=np.round(255 * to_srgb(np.clip(image, 0, 1))).astype(np.uint8),
                joints_3d=state.joints, vertices=state.vertices, camera=camera, mask=out.alpha[0] > 0.5,
                background=name, albedo=albedo)


def sun_light(rng: np.random.Generator) -> np.ndarray:
    """(3, 9) SH light of a sunny day for mitsuba_photo: a constant SKY_AMBIENT plus a first-order
    term of SUN_DIRECTIONAL towards a sun 30-60 degrees high and up to 60 degrees to either side
    of the camera (which looks down -z)."""
    from softras_cl.scene.shading import SH_A, SH_Y1, sh_ambient

    elevation, azimuth = np.radians(rng.uniform(30, 60)), np.radians(rng.uniform(-60, 60))
    towards_sun = np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)])
    sh = sh_ambient(SKY_AMBIENT)
    sh[:, [3, 1, 2]] = SUN_DIRECTIONAL / (SH_A[1] * SH_Y1) * towards_sun     # the basis order is (1, y, z, x, ...)
    return sh


def mitsuba_photo(model, sample: dict, size: int, spp: int, seed: int) -> dict:
    """dict(image (size, size, 3) linear RGB in [0, 1], alpha (size, size) the person's pixel
    coverage): ``sample``'s person (synthetic_photo: same vertices, colours,
    camera and background) path-traced by Mitsuba 3 under sun_light(seed) with SUN_SHARE of it
    in a sun (sharp shadows: arms on the torso, one leg on the other) and the rest a sky
    (validate.mitsuba_face.face_scene_dict), only over the true mask's box, composited over the
    background. ``seed`` draws the sun and the sampler's noise."""
    from softras_cl.validate.mitsuba import _mitsuba, crop_film
    from softras_cl.validate.mitsuba_face import composite, face_scene_dict, path_trace

    mi = _mitsuba()
    rng = np.random.default_rng(seed)
    scene = face_scene_dict(mi, sample["vertices"], model.faces, sample["albedo"], sample["camera"],
                            sun_light(rng), spp, SUN_SHARE)
    rows, cols = np.nonzero(sample["mask"])
    x, y = crop_film(scene["sensor"], (cols.min(), rows.min(), cols.max() + 1, rows.max() + 1), (size, size))
    render = path_trace(mi, scene, spp, int(rng.integers(2 ** 31)))
    image, alpha = background(sample["background"], size), np.zeros((size, size))
    h, w = render["alpha"].shape
    image[y:y + h, x:x + w] = composite(render, image[y:y + h, x:x + w])
    alpha[y:y + h, x:x + w] = render["alpha"]
    return dict(image=image, alpha=alpha)


def cached_mitsuba_photo(model, sample: dict, size: int, spp: int, seed: int, cache: Path) -> np.ndarray:
    """mitsuba_photo() as (size, size, 3) uint8 sRGB, the PNG kept in ``cache`` (mitsuba_<seed>.png
    + .json): read back when the stored key (size, spp, CACHE_VERSION, the sample's background
    and a checksum of its vertices, colours and camera centre) matches, else rendered and stored."""
    from softras_cl.io.images import read_rgb8, write_image

    person = hashlib.sha256()
    for block in (sample["vertices"], sample["albedo"], sample["camera"].center()):
        person.update(np.ascontiguousarray(block, np.float64).tobytes())
    key = dict(size=size, spp=spp, version=CACHE_VERSION, background=sample["background"], person=person.hexdigest())
    png, meta = cache / f"mitsuba_{seed}.png", cache / f"mitsuba_{seed}.json"
    if png.is_file() and meta.is_file() and json.loads(meta.read_text()) == key:
        return read_rgb8(png)
    write_image(png, mitsuba_photo(model, sample, size, spp, seed)["image"])
    write_json(meta, key)
    return read_rgb8(png)


def procrustes_error(pred: np.ndarray, true: np.ndarray) -> float:
    """Mean joint distance after the similarity transform (rotation, uniform scale, translation)
    that best maps pred (J, 3) onto true (J, 3) (Umeyama)."""
    p, t = pred - pred.mean(0), true - true.mean(0)
    u, s, vt = np.linalg.svd(p.T @ t)
    d = np.sign(np.linalg.det(u @ vt))
    s[-1] *= d
    u[:, -1] *= d
    rotation = u @ vt
    scale = s.sum() / (p ** 2).sum()
    return float(np.linalg.norm(scale * p @ rotation - t, axis=1).mean())


def evaluate(fit, sample: dict) -> dict:
    """MPJPE (pelvis-aligned) and PA-MPJPE in mm and the fit's silhouette IoU against the true
    mask (at the working size)."""
    from skimage.transform import resize

    from softras_cl.scene.renderer import SHARP

    state, _ = fit.scene.pose(fit.values)
    joints, true = state.joints, sample["joints_3d"]
    mine = fit.scene.render(state.vertices, *SHARP).alpha[0] > 0.5
    theirs = resize(sample["mask"].astype(float), mine.shape, order=1, anti_aliasing=True) > 0.5
    return dict(mpjpe_mm=1e3 * float(np.linalg.norm((joints - joints[0]) - (true - true[0]), axis=1).mean()),
                pa_mpjpe_mm=1e3 * procrustes_error(joints, true),
                mask_iou=float((mine & theirs).sum() / max((mine | theirs).sum(), 1)))


def run_photo(model, sample: dict, objectives, config, budget: str) -> dict:
    """Detection and one fit per objective of one photo: {objective: row} (a row without
    numbers when no person was found)."""
    from softras_cl.fitting.detection import NoPersonError, detect_person
    from softras_cl.fitting.recipes.body_photo import fit_body_photo

    start = time.perf_counter()
    try:
        detection = detect_person(sample["image"])
    except NoPersonError:
        return {o: dict(detected=False, background=sample["background"]) for o in objectives}
    detect_seconds = time.perf_counter() - start
    rows = {}
    for objective in objectives:
        start = time.perf_counter()
        fit = fit_body_photo(sample["image"].shape[:2], detection, model, config, budget, objective=objective,
                             progress=False)
        rows[objective] = dict(detected=True, background=sample["background"],
                               seconds=detect_seconds + time.perf_counter() - start, **evaluate(fit, sample))
    return rows


def summarise(rows: list[dict]) -> dict:
    """Detection rate and, over the detected photos, mean errors and IoU, the median PA-MPJPE
    (a few photos whose detection went wrong weigh heavily on the mean) and the median time."""
    found = [r for r in rows if r["detected"]]

    def mean(key):
        return float(np.mean([r[key] for r in found])) if found else float("nan")

    return dict(photos=len(rows), detection_rate=len(found) / len(rows), mpjpe_mm=mean("mpjpe_mm"),
                pa_mpjpe_mm=mean("pa_mpjpe_mm"), mask_iou=mean("mask_iou"),
                pa_mpjpe_median_mm=float(np.median([r["pa_mpjpe_mm"] for r in found])) if found else float("nan"),
                median_seconds=float(statistics.median(r["seconds"] for r in found)) if found else float("nan"))


TARGETS = dict(pa_mpjpe_mm=60.0, median_seconds=5.0)


def targets_reached(summary: dict) -> dict:
    """The targets: full PA-MPJPE <= 60 mm and below keypoints-only's, median <= 5 s per photo."""
    full, keypoints = summary.get("full"), summary.get("keypoints")
    if full is None:
        return {}
    doc = dict(pa_mpjpe_le_60mm=full["pa_mpjpe_mm"] <= TARGETS["pa_mpjpe_mm"],
               median_le_5s=full["median_seconds"] <= TARGETS["median_seconds"])
    if keypoints is not None:
        doc["better_than_keypoints_only_mm"] = keypoints["pa_mpjpe_mm"] - full["pa_mpjpe_mm"]
    return doc


def format_table(summary: dict) -> str:
    head = ("objective", "photos", "detected", "MPJPE mm", "PA-MPJPE mm", "median PA mm", "mask IoU", "median s")
    lines = ["  ".join(f"{h:>12}" for h in head)]
    for name, s in summary.items():
        cells = (name, s["photos"], f"{s['detection_rate']:.0%}", f"{s['mpjpe_mm']:.1f}", f"{s['pa_mpjpe_mm']:.1f}",
                 f"{s['pa_mpjpe_median_mm']:.1f}", f"{s['mask_iou']:.3f}", f"{s['median_seconds']:.2f}")
        lines.append("  ".join(f"{c:>12}" for c in cells))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from softras_cl.fitting.recipes.body_settings import OBJECTIVES, PHOTO_BUDGETS, BodyFitConfig
    from softras_cl.validate.mitsuba import mitsuba_available

    if args.quick:
        args.photos, args.size, args.budget = 1, 192, "fast"
    objectives = [o.strip() for o in args.objectives.split(",") if o.strip()]
    unknown = sorted(set(objectives) - set(OBJECTIVES))
    if unknown or not objectives:
        raise InputError(f"--objectives must name some of {', '.join(OBJECTIVES)}, got {args.objectives!r}")
    if args.budget not in PHOTO_BUDGETS:
        raise InputError(f"--budget must be one of {', '.join(PHOTO_BUDGETS)}, got {args.budget!r}")
    check_samples(args, "--photos", min_size=64)
    if args.renderer not in RENDERERS:
        raise InputError(f"--renderer must be one of {', '.join(RENDERERS)}, got {args.renderer!r}")
    if args.renderer == "mitsuba" and not mitsuba_available():
        raise InputError("--renderer mitsuba needs Mitsuba 3: pip install 'softras-cl[validate]'")
    with OutputFolder(args.out, "bench body-photo", "--out") as folder:
        model = load_model("body", args.model)
        config = BodyFitConfig.from_budget(args.budget)
        rng = np.random.default_rng(args.seed)
        load_start = os.getloadavg()
        cache = folder.path / "body_photo_cache"
        per_photo = []
        for index in tqdm(range(args.photos), desc="bench body-photo", disable=args.json):
            sample = synthetic_photo(model, rng, args.size, config.fov_deg)
            if args.renderer == "mitsuba":
                cache.mkdir(exist_ok=True)
                image = cached_mitsuba_photo(model, sample, args.size, MITSUBA_SPP, 1000 * args.seed + index, cache)
                sample = dict(sample, image=image)
            per_photo.append(run_photo(model, sample, objectives, config, args.budget))
        summary = {o: summarise([p[o] for p in per_photo]) for o in objectives}
        doc = dict(photos=args.photos, size=args.size, seed=args.seed, budget=args.budget, renderer=args.renderer,
                   backgrounds=list(BACKGROUNDS), camera=f"distance 3.8-5.0 m, height 0.6-1.2 m, "
                   f"{config.fov_deg} deg across the shorter side (the fit's default --fov)",
                   summary=summary, targets=targets_reached(summary),
                   load_average=dict(start=load_start, end=os.getloadavg()),
                   per_photo={o: [p[o] for p in per_photo] for o in objectives},
                   provenance=provenance(dict(options=args)))
        write_json(folder.path / "body_photo.json", doc)
        print_report(doc, args.json, format_table(summary))
    return 0


def register(which) -> None:
    """Add `body-photo` to the `softras-cl bench` subparsers."""
    p = add_bench_parser(which, __doc__, "body-photo", help="body fitting to synthetic photos of people with known answers")
    add_samples_options(p, "--photos", 20, "photos", 256)
    p.add_argument("--budget", default="default", help="fit-body's schedule budget (default: default)")
    p.add_argument("--objectives", default="full,keypoints,mask",
                   help="comma-separated objectives: full, keypoints (keypoints only), mask (mask only)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the photos (default 0)")
    add_model_option(p, "body")
    p.add_argument("--renderer", default="softras",
                   help="who draws the people: softras (softras-cl, Gouraud shading, no shadows; the default) or "
                   f"mitsuba (Mitsuba 3's path tracer, {MITSUBA_SPP} rays per pixel, a sun and a sky: shadows; "
                   "renders cached in OUT/body_photo_cache)")
    p.add_argument("--quick", action="store_true", help="tiny run for tests: 1 photo at 192 px, fast budget")
    add_output_options(p, "directory for body_photo.json", run)
