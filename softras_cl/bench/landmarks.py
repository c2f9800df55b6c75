"""`softras-cl bench landmarks`: face detection and 68 landmarks on synthetic photos with known points.

Each frame (--frame W,H, default 1280x960) is a real photo without faces (skimage.data's
coffee, rocket, brick, grass or gravel, as in bench body-photo) with one or two faces
path-traced by Mitsuba 3 into it. A face is the demo face model (or --model) with a random
identity, expression and SH light (bench face's generator) and a detail texture read off a
real photo (the shipped astronaut or Grace Hopper, fitted from their shipped landmarks:
fitting.recipes.face_texture), lit by its light split into an environment and a sun
(validate.mitsuba_face), seen by one pinhole camera of 50 degrees across the frame. The faces
are spread evenly (stratified, shuffled) over yaw -80..80 degrees and over face widths 30-500
px on a log scale, pitch and roll +-20 degrees; a face's width is its jaw width (iBUG points 0
and 16 of its frontal face) in pixels at its distance. Every third frame holds a second face
45-75% as wide, |yaw| <= 45, beside the first: the intended face is the first (the larger),
which the detection layer's default choice (largest first) must take. Renders are cached
under --cache, so reruns only detect.

The true landmarks are the model's 68 landmark points of each face projected by the camera
(hidden ones included: the convention of Face Mesh's 3D points). Per backend (mediapipe, the
default detector, and dlib when installed), on each frame: every face found
(fitting.detection.find_faces, timed: the time per photo), the face the default rule chooses,
and which true face each candidate is (the true face whose landmark box, widened by MATCH_MARGIN
on each side, holds its landmarks' centroid). Reported: the detection rate of the intended faces,
how often the chosen face is the intended one (in the two-face frames), and NME, the mean point
distance over the true outer-eye-corner distance (iBUG 36-45), of the landmarks found on the
intended face (the 68 points, and the 51 without the jaw line), median and 90th percentile by
|yaw| bin and by width bin; the median seconds per photo. Targets: TARGETS.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import add_bench_parser, add_model_option, add_output_options, load_model, print_report
from softras_cl.errors import InputError
from softras_cl.fitting.keypoints import ibug68
from softras_cl.io.outputs import OutputFolder, write_figure, write_json
from softras_cl.provenance import provenance

FRAME = (1280, 960)                      # width, height
FOV_DEG = 50.0                           # across the frame's width
YAW_RANGE, WIDTH_RANGE = 80.0, (30.0, 500.0)
PITCH_ROLL_DEG = 20.0
YAW_BINS = ((0, 15), (15, 30), (30, 45), (45, 60), (60, 80))
WIDTH_BINS = ((30, 40), (40, 80), (80, 160), (160, 320), (320, 500))
SECOND_FACE_EVERY = 3                    # every third frame has a second, smaller face
SECOND_FACE_SCALE = (0.45, 0.75)         # its width over the first face's
SKINS = ("astronaut", "grace_hopper")    # examples/data photos whose detail texture dresses the faces
DEFAULT_SPP = 16
MATCH_MARGIN = 0.25                      # a candidate is a face's when inside its landmark box widened this much
CACHE_VERSION = 2
TARGETS = dict(detection_rate=0.99, found_min_width_px=40.0, found_max_yaw_deg=60.0, nme_median=0.05,
               seconds_per_photo=0.3)
EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "data"
QUICK = dict(frames=3, frame=(320, 240), spp=4, widths=(60.0, 110.0), yaw=30.0)


# ---------------------------------------------------------------------------------------------
# scoring
# ---------------------------------------------------------------------------------------------

def nme(points, truth, which=slice(None)) -> float:
    """Mean distance of points (68, 2) to truth (68, 2) over the points ``which`` (default all),
    divided by the truth's outer-eye-corner distance |truth[36] - truth[45]|."""
    points, truth = np.asarray(points, np.float64), np.asarray(truth, np.float64)
    error = np.linalg.norm(points[which] - truth[which], axis=1).mean()
    right, left = ibug68.OUTER_EYE_CORNERS
    return float(error / np.linalg.norm(truth[right] - truth[left]))


def owner(candidate, faces: list[dict]) -> int | None:
    """The index of the true face (dicts with "landmarks" (68, 2)) a FaceCandidate is: the
    first whose landmark box, widened by MATCH_MARGIN of its size on each side, holds the
    centroid of the candidate's landmarks (of its box without landmarks); None for none."""
    if candidate.landmarks is not None:
        centre = candidate.landmarks.mean(0)
    else:
        centre = candidate.box[:2] + candidate.box[2:] / 2 - 0.5
    for i, face in enumerate(faces):
        lo, hi = face["landmarks"].min(0), face["landmarks"].max(0)
        pad = MATCH_MARGIN * (hi - lo)
        if np.all(centre >= lo - pad) and np.all(centre <= hi + pad):
            return i
    return None


def score_frame(candidates, faces: list[dict], seconds: float) -> dict:
    """One frame's row: faces found in the stated order (candidates), the truth (faces[0] the
    intended face); found (a candidate with landmarks is the intended face), chosen_right (the
    default choice, the first candidate, is it), second_found, false_faces (candidates that are
    no true face), and for the first candidate that is the intended face: nme, nme_51 (without
    the jaw) and its offsets (face_frame_offsets)."""
    from softras_cl.fitting.detection import choose_face

    owners = [owner(c, faces) for c in candidates]
    mine = [c for c, o in zip(candidates, owners) if o == 0 and c.landmarks is not None]
    chosen = choose_face(candidates)[0] if candidates else None
    row = dict(seconds=seconds, candidates=len(candidates), found=bool(mine),
               chosen_right=chosen is not None and owners[chosen] == 0,
               second_found=len(faces) > 1 and 1 in owners, false_faces=owners.count(None))
    if mine:
        truth = faces[0]["landmarks"]
        row.update(nme=nme(mine[0].landmarks, truth), nme_51=nme(mine[0].landmarks, truth, slice(ibug68.JAW.stop, ibug68.COUNT)),
                   offsets=face_frame_offsets(mine[0].landmarks, truth))
    return row


def face_frame_offsets(points, truth) -> np.ndarray:
    """(68, 2) offsets points - truth in the truth face's own frame: turned so that its eye
    line (iBUG 36 -> 45) runs along +x, over the outer-eye-corner distance."""
    right, left = ibug68.OUTER_EYE_CORNERS
    eyes = truth[left] - truth[right]
    c, s = eyes / np.linalg.norm(eyes) ** 2
    return (np.asarray(points) - truth) @ np.array([[c, -s], [s, c]])


def systematic_nme(rows: list[dict], max_yaw: float = 15.0) -> float | None:
    """The part of the NME that is the same on every face: the mean over the 68 points of the
    length of their median face-frame offset (face_frame_offsets; the median, so that one face
    meshed wrongly does not count) over the found faces with |yaw| <= max_yaw (None without
    any): a detector's points placed consistently elsewhere than the model's (the landmark
    definitions differ), as opposed to its scatter."""
    offsets = [r["offsets"] for r in rows if r["found"] and abs(r["yaw"]) <= max_yaw]
    return float(np.linalg.norm(np.median(offsets, axis=0), axis=1).mean()) if offsets else None


def in_bin(value: float, lo: float, hi: float, last: bool) -> bool:
    """lo <= value < hi (<= hi for the last bin)."""
    return lo <= value < hi or (last and value == hi)


def summarise(rows: list[dict]) -> dict:
    """Detection rate, right-face rate (frames with two faces), NME median / p90 (68 and 51
    points, found faces) and median seconds of a list of rows (score_frame + "yaw", "width_px",
    "two_faces"); None where there is nothing to count."""
    found = [r for r in rows if r["found"]]
    two = [r for r in rows if r["two_faces"]]

    def stat(key, q):
        return float(np.percentile([r[key] for r in found], q)) if found else None

    return dict(faces=len(rows), found=len(found), detection_rate=len(found) / len(rows) if rows else None,
                two_face_frames=len(two),
                right_face_rate=sum(r["chosen_right"] for r in two) / len(two) if two else None,
                nme_median=stat("nme", 50), nme_p90=stat("nme", 90),
                nme_51_median=stat("nme_51", 50), nme_51_p90=stat("nme_51", 90),
                median_seconds=float(np.median([r["seconds"] for r in rows])) if rows else None)


def by_bins(rows: list[dict], key: str, bins) -> list[dict]:
    """summarise() of the rows whose ``key`` (abs for yaw) falls in each (lo, hi) bin."""
    out = []
    for i, (lo, hi) in enumerate(bins):
        chosen = [r for r in rows if in_bin(abs(r[key]), lo, hi, i == len(bins) - 1)]
        out.append(dict(summarise(chosen), bin=f"{lo:g}-{hi:g}"))
    return out


def targets(rows: list[dict], summary: dict) -> dict:
    """The detection targets on one backend's rows: value and reached of each (a value None,
    nothing to measure, is not reached)."""
    t = TARGETS
    eligible = [r for r in rows if r["width_px"] >= t["found_min_width_px"] and abs(r["yaw"]) <= t["found_max_yaw_deg"]]
    rate = sum(r["found"] for r in eligible) / len(eligible) if eligible else None

    def target(value, ok, **extra):
        return dict(value=value, reached=value is not None and bool(ok(value)), **extra)

    return dict(detection_rate=target(rate, lambda v: v >= t["detection_rate"], faces=len(eligible)),
                right_face_every_frame=target(summary["right_face_rate"], lambda v: v == 1.0),
                nme_median=target(summary["nme_median"], lambda v: v <= t["nme_median"]),
                seconds_per_photo=target(summary["median_seconds"], lambda v: v < t["seconds_per_photo"]))


# ---------------------------------------------------------------------------------------------
# synthetic frames
# ---------------------------------------------------------------------------------------------

def stratified(rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
    """n values, one uniform in each of n equal parts of [lo, hi], shuffled."""
    return rng.permutation((np.arange(n) + rng.uniform(size=n)) / n * (hi - lo) + lo)


def frame_plans(rng: np.random.Generator, n: int, frame, yaw_range: float = YAW_RANGE,
                widths=WIDTH_RANGE) -> list[dict]:
    """What each of n frames shows: faces (list of dict yaw, pitch, roll in degrees, width_px,
    seed), skin, background, seed. Yaws and widths (log scale) stratified over their ranges."""
    from softras_cl.bench.body_photo import BACKGROUNDS

    yaws = stratified(rng, n, -yaw_range, yaw_range)
    log_widths = stratified(rng, n, *np.log(widths))
    plans = []
    for i in range(n):
        pitch, roll = rng.uniform(-PITCH_ROLL_DEG, PITCH_ROLL_DEG, 2)
        faces = [dict(yaw=float(yaws[i]), pitch=float(pitch), roll=float(roll),
                      width_px=float(np.exp(log_widths[i])), seed=int(rng.integers(2**31)))]
        if i % SECOND_FACE_EVERY == SECOND_FACE_EVERY - 1:
            p2, r2 = rng.uniform(-PITCH_ROLL_DEG, PITCH_ROLL_DEG, 2)
            faces.append(dict(yaw=float(rng.uniform(-45, 45)), pitch=float(p2), roll=float(r2),
                              width_px=faces[0]["width_px"] * float(rng.uniform(*SECOND_FACE_SCALE)),
                              seed=int(rng.integers(2**31))))
        plans.append(dict(faces=faces, skin=SKINS[i % len(SKINS)], frame=list(frame),
                          background=BACKGROUNDS[int(rng.integers(len(BACKGROUNDS)))], seed=int(rng.integers(2**31))))
    return plans


def frame_camera(frame) -> tuple[float, tuple[float, float]]:
    """(focal px, principal point (cx, cy)) of a frame (width, height): FOV_DEG across it."""
    w, h = frame
    return 0.5 * w / math.tan(math.radians(FOV_DEG) / 2), ((w - 1) / 2, (h - 1) / 2)


def face_truth(model, face: dict, frame, centre_px) -> dict:
    """bench face's truth blocks (random identity, expression, albedo and SH light from the
    face's seed) posed by the face's yaw, pitch, roll, at the distance where its jaw is
    width_px wide, its landmarks' centre at pixel centre_px (x, y)."""
    from softras_cl.bench.face import random_truth
    from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle

    focal, (cx, cy) = frame_camera(frame)
    truth = random_truth(model, np.random.default_rng(face["seed"]), frame[1])
    yaw, pitch, roll = np.radians([face["yaw"], face["pitch"], face["roll"]])
    R = axis_angle_to_matrix([0, yaw, 0]) @ axis_angle_to_matrix([pitch, 0, 0]) @ axis_angle_to_matrix([0, 0, roll])
    shape, _ = model.shape(truth["id"], truth["exp"])
    marks = model.landmarks(shape)[0]
    depth = focal * np.linalg.norm(marks[0] - marks[16]) / face["width_px"]
    position = depth * np.array([(centre_px[0] - cx) / focal, -(centre_px[1] - cy) / focal, -1.0])
    return dict(truth, rotation=matrix_to_axis_angle(R), translation=position - R @ marks.mean(0),
                focal=np.array([focal]))


def place_faces(model, plan: dict, rng: np.random.Generator) -> list[dict]:
    """Each face of the plan placed in the frame: its truth (face_truth), its world vertices,
    camera, projected landmarks (68, 2) and vertex box (x0, y0, x1, y1) px. A face's box lies
    inside the frame, anywhere (uniform over the places it fits; the frame's centre when 100
    tries find none), a second face's box apart from the first's (left out when 100 tries find
    no such place)."""
    placed = []
    for face in plan["faces"]:
        centred = projected(model, face_truth(model, face, plan["frame"], np.asarray(plan["frame"]) / 2), plan["frame"])
        size = centred["box"][2:] - centred["box"][:2]
        for _ in range(100):
            corner = [rng.uniform(0, max(s - d, 0)) for s, d in zip(plan["frame"], size)]
            centre = np.asarray(plan["frame"]) / 2 + corner - centred["box"][:2]
            where = projected(model, face_truth(model, face, plan["frame"], centre), plan["frame"])
            inside = np.all(where["box"][:2] >= 0) and np.all(where["box"][2:] <= np.asarray(plan["frame"]) - 1)
            if inside and not (placed and boxes_meet(where["box"], placed[0]["box"])):
                placed.append(dict(face, **where))
                break
        else:
            if not placed:
                placed.append(dict(face, **centred))
    return placed


def projected(model, truth: dict, frame) -> dict:
    """truth, world vertices (V, 3), camera, landmarks (68, 2) and vertex box (x0, y0, x1, y1)
    of a face's truth seen in the frame (width, height)."""
    from softras_cl.fitting.recipes.face import FaceScene

    scene = FaceScene(model, tuple(frame)[::-1])
    world, _ = scene.geometry(truth)
    camera = scene.camera(truth["focal"][0])
    pixels, _ = camera.project_pixels(world)
    landmarks, _ = camera.project_pixels(model.landmarks(world)[0])
    return dict(truth=truth, world=world, camera=camera, landmarks=landmarks,
                box=np.concatenate([pixels.min(0), pixels.max(0)]))


def boxes_meet(a, b, gap: float = 4.0) -> bool:
    """Two (x0, y0, x1, y1) boxes overlap or come within ``gap`` px."""
    return not (a[2] + gap < b[0] or b[2] + gap < a[0] or a[3] + gap < b[1] or b[3] + gap < a[1])


def frame_background(name: str, frame) -> np.ndarray:
    """(height, width, 3) linear RGB: skimage.data's ``name`` (bench body-photo's square
    background at the frame's width), its middle rows."""
    from softras_cl.bench.body_photo import background

    w, h = frame
    square = background(name, max(w, h))
    top, left = (square.shape[0] - h) // 2, (square.shape[1] - w) // 2
    return square[top:top + h, left:left + w]


def textured_mesh(mi, world, faces, uvs, texture):
    """A Mitsuba mesh (smooth vertex normals) whose diffuse reflectance is ``texture`` (S, S, 3)
    linear RGB at ``uvs`` (V, 2) (bilinear; v up, flipped for Mitsuba)."""
    import drjit as dr

    from softras_cl.scene.shading import vertex_normals
    from softras_cl.validate.mitsuba_face import MAX_ALBEDO

    reflectance = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(np.clip(texture, 0, MAX_ALBEDO), np.float32)),
                   "filter_type": "bilinear", "wrap_mode": "clamp", "raw": True}
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": reflectance})
    mesh = mi.Mesh("face", vertex_count=len(world), face_count=len(faces), props=props,
                   has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.scalar.ArrayXf(np.asarray(world, np.float32).ravel())
    params["faces"] = dr.scalar.ArrayXu(np.asarray(faces, np.uint32).ravel())
    normals = vertex_normals(np.asarray(world, np.float64)[None], faces)[0][0]
    params["vertex_normals"] = dr.scalar.ArrayXf(normals.astype(np.float32).ravel())
    params["vertex_texcoords"] = dr.scalar.ArrayXf(np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], 1).astype(np.float32).ravel())
    params.update()
    return mesh


def render_face(model, face: dict, skin: dict, frame, spp: int, seed: int) -> tuple[dict, tuple[int, int]]:
    """Mitsuba's path-traced render of one placed face (place_faces) with the skin's texture,
    only over its box (a film crop): (dict rgb (h, w, 3) premultiplied, alpha (h, w)), the
    crop's top-left pixel (x, y))."""
    from softras_cl.validate.mitsuba import _mitsuba, crop_film
    from softras_cl.validate.mitsuba_face import face_scene_dict, path_trace

    mi = _mitsuba()
    world, truth = face["world"], face["truth"]
    scene = face_scene_dict(mi, world, model.faces, model.albedo(truth["albedo"])[0], face["camera"], truth["sh"], spp)
    scene["mesh"] = textured_mesh(mi, world, model.faces, skin["uvs"], skin["albedo"])
    corner = crop_film(scene["sensor"], face["box"], frame)
    return path_trace(mi, scene, spp, seed), corner


def make_frame(model, plan: dict, skins: dict, spp: int) -> dict:
    """The frame of a plan: image (H, W, 3) linear RGB and its faces (place_faces; the first the
    intended one) with their landmarks; faces drawn smallest first."""
    rng = np.random.default_rng(plan["seed"])
    faces = place_faces(model, plan, rng)
    image = frame_background(plan["background"], plan["frame"])
    for k, face in reversed(list(enumerate(faces))):
        paint_face(image, model, face, skins[plan["skin"]], spp, plan["seed"] % 10**6 + k)
    return dict(image=image, faces=faces)


def paint_face(image: np.ndarray, model, face: dict, skin: dict, spp: int, seed: int) -> None:
    """Composite render_face's render of ``face`` (projected) over ``image`` (H, W, 3) linear
    RGB, in place, inside the face's box only."""
    from softras_cl.validate.mitsuba_face import composite

    render, (x, y) = render_face(model, face, skin, image.shape[1::-1], spp, seed)
    h, w = render["alpha"].shape
    image[y:y + h, x:x + w] = composite(render, image[y:y + h, x:x + w])


def skin_texture(model, name: str, budget: str, cache: Path) -> dict:
    """The detail texture of examples/data/<name> (its shipped landmarks, a fit at ``budget``,
    fitting.recipes.face_texture.estimate_texture): dict albedo (S, S, 3) linear RGB, uvs
    (V, 2); kept in ``cache`` (skin_<name>_<budget>.npz)."""
    path = cache / f"skin_{name}_{budget}_{model.name}.npz"
    if path.is_file():
        with np.load(path) as stored:
            return dict(albedo=stored["albedo"], uvs=stored["uvs"])
    from softras_cl.bench.face import budget_config
    from softras_cl.fitting.recipes.face import fit_face
    from softras_cl.fitting.recipes.face_texture import estimate_texture
    from softras_cl.io.images import read_image
    from softras_cl.io.landmarks import read_landmarks

    photo_path = next(EXAMPLES.glob(f"{name}.*"))
    photo = read_image(photo_path)
    fit = fit_face(photo, read_landmarks(EXAMPLES / "landmarks" / f"{name}.pts"), model,
                   budget_config(budget, 256), progress=False)
    texture = estimate_texture(fit, photo)
    skin = dict(albedo=texture.albedo, uvs=texture.layout.uvs)
    np.savez_compressed(path, **skin)
    return skin


def cached_frame(model, plan: dict, skins: dict, spp: int, cache: Path, index: int) -> dict:
    """make_frame(plan), read from ``cache`` (frame_<index>.png + .json) when the stored plan,
    spp and CACHE_VERSION match, else rendered and stored: image (H, W, 3) uint8 sRGB, as the
    PNG holds it, faces (each with yaw, pitch, roll, width_px, landmarks (68, 2)), skin."""
    from softras_cl.io.images import read_rgb8, write_image

    key = dict(plan=plan, spp=spp, version=CACHE_VERSION, model=model.name)
    png, meta = cache / f"frame_{index:04d}.png", cache / f"frame_{index:04d}.json"
    if png.is_file() and meta.is_file():
        stored = json.loads(meta.read_text())
        if stored["key"] == json.loads(json.dumps(key)):
            faces = [dict(f, landmarks=np.array(f["landmarks"])) for f in stored["faces"]]
            return dict(image=read_rgb8(png), faces=faces, skin=plan["skin"])
    frame = make_frame(model, plan, skins, spp)
    faces = [{k: face[k] for k in ("yaw", "pitch", "roll", "width_px", "landmarks")} for face in frame["faces"]]
    write_image(png, frame["image"])
    write_json(meta, dict(key=key, faces=[dict(f, landmarks=f["landmarks"].tolist()) for f in faces]))
    return dict(image=read_rgb8(png), faces=faces, skin=plan["skin"])


# ---------------------------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------------------------

def detect_rows(frames: list[dict], backend: str, progress: bool) -> list[dict]:
    """score_frame() of every frame by one backend (find_faces timed per frame, after one
    untimed call that loads the models), with the intended face's yaw, width_px, two_faces."""
    from tqdm import tqdm

    from softras_cl.fitting.detection import find_faces

    find_faces(frames[0]["image"], backend)
    rows = []
    for i, frame in enumerate(tqdm(frames, desc=f"bench landmarks [{backend}]", disable=not progress)):
        start = time.perf_counter()
        candidates = find_faces(frame["image"], backend)
        row = score_frame(candidates, frame["faces"], time.perf_counter() - start)
        first = frame["faces"][0]
        rows.append(dict(row, frame=i, skin=frame["skin"], yaw=first["yaw"], pitch=first["pitch"], roll=first["roll"],
                         width_px=first["width_px"], two_faces=len(frame["faces"]) > 1))
    return rows


def parse_frame(text: str) -> tuple[int, int]:
    """'1280,960' -> (1280, 960); InputError naming --frame unless two integers >= 64."""
    try:
        w, h = (int(v) for v in text.split(","))
    except ValueError:
        w = h = 0
    if min(w, h) < 64:
        raise InputError(f"--frame must be WIDTH,HEIGHT in pixels, each >= 64, e.g. 1280,960; got {text!r}")
    return w, h


def parse_backends(text: str | None) -> list[str]:
    """--backends: the named backends (InputError naming it for an unknown or missing one);
    None: every installed one (mediapipe first)."""
    from softras_cl.fitting.detection.find import BACKENDS, available_backends, check_backend

    if text is None:
        found = available_backends()
        if not found:
            check_backend(None)             # raises the default backend's install hint
        return found
    names = [b.strip() for b in text.split(",") if b.strip()]
    if not names or any(b not in BACKENDS for b in names) or len(set(names)) != len(names):
        raise InputError(f"--backends must name some of {', '.join(BACKENDS)} once each, got {text!r}")
    for name in names:
        check_backend(name)
    return names


def backend_report(rows: list[dict]) -> dict:
    """One backend's summary: over all frames, by |yaw| bin, by width bin, and its targets."""
    summary = dict(summarise(rows), nme_systematic_frontal=systematic_nme(rows),
                   right_face_rate_when_found=summarise([r for r in rows if r["found"]])["right_face_rate"])
    return dict(summary=summary, by_yaw=by_bins(rows, "yaw", YAW_BINS), by_width=by_bins(rows, "width_px", WIDTH_BINS),
                by_skin=[dict(summarise([r for r in rows if r["skin"] == k]), bin=k) for k in SKINS],
                targets=targets(rows, summary), frames=[{k: v for k, v in r.items() if k != "offsets"} for r in rows])


def format_report(reports: dict) -> str:
    """The text tables: per backend, by yaw and by width, then the targets."""
    from softras_cl.bench.tools import format_table

    columns = [("faces", "faces", "d"), ("found", "detection_rate", ".0%"), ("right face", "right_face_rate", ".0%"),
               ("NME med", "nme_median", ".3f"), ("NME p90", "nme_p90", ".3f"), ("NME51 med", "nme_51_median", ".3f"),
               ("NME51 p90", "nme_51_p90", ".3f"), ("median s", "median_seconds", ".2f")]
    blocks = []
    for backend, r in reports.items():
        for title, rows in (("|yaw| deg", r["by_yaw"]), ("width px", r["by_width"]), ("skin", r["by_skin"])):
            blocks.append(f"{backend}, by {title}:\n" + format_table(rows + [dict(r["summary"], bin="all")],
                                                                     [(title, "bin", "s")] + columns))
        s = r["summary"]
        blocks.append(f"{backend}: the face chosen is the intended one in {_percent(s['right_face_rate_when_found'])} "
                      "of the two-face frames where the intended face was found; the systematic part of the "
                      f"frontal NME (|yaw| <= 15) is {_number(s['nme_systematic_frontal'])}")
        t = r["targets"]
        blocks.append(f"{backend} targets: " + "; ".join(
            f"{name} {_number(v['value'])} "
            f"({'reached' if v['reached'] else 'NOT reached'})" for name, v in t.items()))
    return "\n\n".join(blocks)


def _number(v) -> str:
    return "-" if v is None else format(v, ".3g")


def _percent(v) -> str:
    return "-" if v is None else format(v, ".0%")


def save_chart(reports: dict, frame, path: Path) -> None:
    """NME (median, p90 dashed) and detection rate per backend, by |yaw| bin and by width bin;
    frame (width, height) for the title."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 6))
    axes = fig.subplots(2, 2)
    for col, (key, label) in enumerate((("by_yaw", "|yaw| (degrees)"), ("by_width", "face width (px)"))):
        for backend, r in reports.items():
            bins = [b["bin"] for b in r[key]]

            def values(name):
                return [np.nan if b[name] is None else b[name] for b in r[key]]

            line, = axes[0, col].plot(bins, values("nme_median"), "o-", label=f"{backend} median")
            axes[0, col].plot(bins, values("nme_p90"), "o--", color=line.get_color(), label=f"{backend} p90")
            axes[1, col].plot(bins, values("detection_rate"), "o-", color=line.get_color(), label=backend)
        axes[0, col].axhline(TARGETS["nme_median"], color="grey", lw=0.8, ls=":", label="target (median)")
        axes[1, col].axhline(TARGETS["detection_rate"], color="grey", lw=0.8, ls=":", label="target")
        axes[0, col].set(ylabel="NME (eye corners)", yscale="log")
        axes[1, col].set(ylabel="intended face found", xlabel=label, ylim=(-0.02, 1.02))
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    fig.suptitle(f"bench landmarks: Mitsuba renders of the textured demo face in {frame[0]}x{frame[1]} photos",
                 fontsize=10)
    fig.tight_layout()
    write_figure(fig, path, dpi=100)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from softras_cl.bench.face import LANDMARKS_ONLY
    from softras_cl.validate.mitsuba import mitsuba_available

    backends = parse_backends(args.backends)
    frame, spp, widths, yaw_range, n = parse_frame(args.frame), args.spp, WIDTH_RANGE, YAW_RANGE, args.frames
    if args.quick:
        frame, spp, widths, yaw_range, n = QUICK["frame"], QUICK["spp"], QUICK["widths"], QUICK["yaw"], QUICK["frames"]
    if n < 1 or spp < 2:
        raise InputError(f"--frames must be >= 1 and --spp >= 2, got {n} and {spp}")
    if not mitsuba_available():
        raise InputError("bench landmarks renders its photos with Mitsuba 3: pip install 'softras-cl[validate]'")
    with OutputFolder(args.out, "bench landmarks", "--out") as folder:
        cache = Path(args.cache) if args.cache else folder.path / "landmarks_cache"
        cache.mkdir(parents=True, exist_ok=True)
        model = load_model("face", args.model)
        budget = LANDMARKS_ONLY if args.quick else "fast"
        skins = {name: skin_texture(model, name, budget, cache) for name in SKINS}
        plans = frame_plans(np.random.default_rng(args.seed), n, frame, yaw_range, widths)
        load_start, start = os.getloadavg(), time.perf_counter()
        frames = [cached_frame(model, p, skins, spp, cache, i)
                  for i, p in enumerate(tqdm(plans, desc="bench landmarks [frames]", disable=args.json))]
        frames_seconds = time.perf_counter() - start
        reports = {b: backend_report(detect_rows(frames, b, not args.json)) for b in backends}
        doc = dict(frames=n, frame=list(frame), spp=spp, seed=args.seed, model=model.name, skins=list(SKINS),
                   frames_seconds=frames_seconds, load_average=dict(start=load_start, end=os.getloadavg()),
                   skin_fit_budget=budget, fov_deg=FOV_DEG, yaw_range=yaw_range, widths_px=list(widths),
                   second_face_every=SECOND_FACE_EVERY, targets=TARGETS, backends=reports,
                   provenance=provenance(dict(options=args)))
        write_json(folder.path / "landmarks.json", doc)
        save_chart(reports, frame, folder.path / "landmarks.png")
        print_report(doc, args.json, format_report(reports))
    return 0


def register(which) -> None:
    """Add `landmarks` to the `softras-cl bench` subparsers."""
    p = add_bench_parser(which, __doc__, "landmarks", help="face detection and 68 landmarks on Mitsuba photos with known points")
    p.add_argument("--frames", type=int, default=90, help="synthetic frames (default 90)")
    p.add_argument("--frame", default=",".join(map(str, FRAME)),
                   help=f"frame WIDTH,HEIGHT in pixels (default {FRAME[0]},{FRAME[1]})")
    p.add_argument("--spp", type=int, default=DEFAULT_SPP, help=f"Mitsuba rays per pixel (default {DEFAULT_SPP})")
    p.add_argument("--backends", default=None,
                   help="comma-separated face detector backends: mediapipe, dlib (default: every installed one)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the frames (default 0)")
    add_model_option(p, "face")
    p.add_argument("--cache", default=None,
                   help="folder of the rendered frames and skin textures, reused when the frames match "
                        "(default: OUT/landmarks_cache)")
    p.add_argument("--quick", action="store_true",
                   help=f"tiny run for tests: {QUICK['frames']} frames of {QUICK['frame'][0]}x{QUICK['frame'][1]}, "
                        f"{QUICK['spp']} rays per pixel, widths {QUICK['widths'][0]:g}-{QUICK['widths'][1]:g} px, "
                        f"|yaw| <= {QUICK['yaw']:g}")
    add_output_options(p, "directory for landmarks.json and landmarks.png", run, shown="tables")
