"""`softras-cl bench track`: the face tracker (track-face) on synthetic talking heads with known truth.

Each sequence: one random identity and albedo of the demo face (bench face's generator) whose head
pose, expression and light follow smooth random trajectories (sums of slow sinusoids: yaw +-25,
pitch +-10, roll +-6 degrees, the head moving a few centimetres, 10 expression components, the
light's direction turning), rendered over a real photo (skimage.data) at --size pixels and --fps,
encoded to H.264 through PyAV and decoded again, so the decode path is part of it. --renderer
softras: softras-cl's sharp render of the face's albedo and SH light; --renderer mitsuba: Mitsuba
3's path tracer (bench landmarks' faces: a detail texture read off a shipped photo, the light
split into an environment and a sun that casts shadows, --spp rays per pixel), frames kept under
OUT/track_cache so reruns only track.
Landmarks: MediaPipe's (the tracker's own path, --landmarks detected), or the true ones with 1.5 px
noise (--landmarks noisy, no detector needed).

Each sequence is tracked (fitting.recipes.face_track: identity from keyframes, then per frame) and
the first --independent frames are also fitted one by one by fit-face (--budget, from the same
landmarks). Reported per sequence and over all: vertex error (mm; fitted minus true world vertices,
after one similarity per sequence), landmark error (px, against the true landmarks), jitter (RMS of
the second temporal difference of the fitted minus the true vertices, mm per frame^2), the
identity's shape error (neutral face RMSE over the mean face's, as bench face-views), frames per
second end to end (decode, detection, identity fit, per-frame fits) and of the per-frame stage alone
(each frame's fit, its light and the fixed-lag smoothing); the tracker's errors before its fixed-lag
smoothing (each frame's own fit); and the appearance error (the fitted face's colour, albedo times
SH shading, against the truth's, relative RMS over the vertices facing the camera) with each
frame's fitted light and with the identity's light held for the video (with --renderer mitsuba
the truth's colour is still the model's albedo, not the skin texture the frames show, so this
error then mostly measures the texture's difference).
Targets (never lowered): per-frame stage >= 10 frames/s; jitter <= 1/3 of the independent fits' with
vertex and landmark errors no worse; identity error no worse than the best single frame's and >= 30%
below the mean single frame's.
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import time
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import add_bench_parser, add_output_options, print_report
from softras_cl.errors import InputError
from softras_cl.fitting.keypoints import ibug68
from softras_cl.io.outputs import OutputFolder, write_figure, write_json
from softras_cl.provenance import provenance

BACKGROUNDS = ("coffee", "rocket", "chelsea", "immunohistochemistry")   # skimage.data photos without faces
TARGET_FPS = 10.0
TARGET_JITTER_RATIO = 1.0 / 3.0
TARGET_IDENTITY_REDUCTION = 0.30
LANDMARK_NOISE_PX = 1.5
N_EXP_MOVING = 10
RENDERERS = ("softras", "mitsuba")
DEFAULT_SPP = 16
MITSUBA_CACHE_VERSION = 1


def smooth_signal(rng: np.random.Generator, times: np.ndarray, amplitude, components: int = 3) -> np.ndarray:
    """(T, D) smooth random signals (D = len(amplitude)): each a sum of ``components`` sinusoids of
    0.1-0.7 Hz with random phases, scaled to peak at about ``amplitude``."""
    amplitude = np.atleast_1d(np.asarray(amplitude, np.float64))
    freq = rng.uniform(0.1, 0.7, (components, amplitude.size))
    phase = rng.uniform(0, 2 * np.pi, (components, amplitude.size))
    weight = rng.uniform(0.5, 1.0, (components, amplitude.size))
    signal = np.einsum("cd,tcd->td", weight, np.sin(2 * np.pi * freq * times[:, None, None] + phase))
    return signal / weight.sum(0) * amplitude


def sequence_truth(model, rng: np.random.Generator, frames: int, size: int, fps: float) -> list[dict]:
    """Per-frame truth (bench face's blocks: id, exp, albedo, sh, rotation, translation, focal)
    of one talking head: bench face's random_truth for the identity, albedo, camera and base
    position, a frontal base pose, and the smooth trajectories of the module docstring."""
    from softras_cl.bench.face import random_truth
    from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle

    base = random_truth(model, rng, size)
    times = np.arange(frames) / fps
    angles = np.radians(smooth_signal(rng, times, (25.0, 10.0, 6.0)))
    shift = smooth_signal(rng, times, (0.02, 0.015, 0.03))
    exp = np.zeros((frames, model.n_exp))
    k = min(N_EXP_MOVING, model.n_exp)
    exp[:, :k] = smooth_signal(rng, times, np.full(k, 1.2))
    light = smooth_signal(rng, times, np.full(3, 0.25 * base["sh"][0, 0]))
    lo, hi = model.mean_shape.min(0), model.mean_shape.max(0)
    centre = (lo + hi) / 2
    truth = []
    for t in range(frames):
        yaw, pitch, roll = angles[t]
        R = axis_angle_to_matrix([0, yaw, 0]) @ axis_angle_to_matrix([pitch, 0, 0]) @ axis_angle_to_matrix([0, 0, roll])
        # turn about the face's centre, which stays where random_truth put it (plus the shift)
        position = base["translation"] + centre + shift[t]
        sh = base["sh"].copy()
        sh[:, 1:4] += light[t]
        truth.append(dict(base, exp=exp[t], sh=sh, rotation=matrix_to_axis_angle(R), translation=position - R @ centre))
    return truth


def background(name: str, size: int) -> np.ndarray:
    """A (size, size, 3) linear-RGB crop of the skimage.data photo ``name`` (its centre square)."""
    import skimage.data
    from skimage.transform import resize

    from softras_cl.srgb import to_linear

    photo = getattr(skimage.data, name)()[..., :3]
    h, w = photo.shape[:2]
    side = min(h, w)
    square = photo[(h - side) // 2:(h - side) // 2 + side, (w - side) // 2:(w - side) // 2 + side]
    return to_linear(resize(square, (size, size), anti_aliasing=True))


def render_frames(model, truth: list[dict], back: np.ndarray):
    """(frames (H, W, 3) uint8 sRGB, true landmarks (T, 68, 2) px, true world vertices (T, V, 3))."""
    from softras_cl.fitting.recipes.face import FaceScene
    from softras_cl.scene.renderer import SHARP

    scene = FaceScene(model, back.shape[:2], alpha_agg="hard")
    images, landmarks, vertices = [], [], []
    for values in truth:
        scene.set_depth_range(values["translation"])
        out = scene.render(values, *SHARP)
        alpha = out.alpha[0][..., None]
        images.append(srgb8(alpha * out.rgb[0] + (1 - alpha) * back))
        world, _ = scene.geometry(values)
        landmarks.append(scene.camera(values["focal"][0]).project_pixels(model.landmarks(world)[0])[0])
        vertices.append(world)
    return images, np.array(landmarks), np.array(vertices)


def srgb8(linear: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear RGB clipped to [0, 1] -> uint8 sRGB."""
    from softras_cl.srgb import to_srgb

    return np.round(to_srgb(np.clip(linear, 0, 1)) * 255).astype(np.uint8)


def render_frames_mitsuba(model, truth: list[dict], back: np.ndarray, *, skin: dict, spp: int, cache: Path,
                          seed: int):
    """render_frames' answer with each face path-traced by Mitsuba (bench landmarks' paint_face:
    the skin's detail texture, sun and sky, only over the face's box); frame t's sampler seed is
    seed + t. Each frame is kept in ``cache`` as mitsuba_<key>.png, its key a digest of what
    makes it (truth, background, skin, spp, seed), and read back when there."""
    from softras_cl.bench.landmarks import paint_face, projected
    from softras_cl.io.images import read_rgb8, write_image

    cache.mkdir(parents=True, exist_ok=True)
    images, landmarks, vertices = [], [], []
    for t, values in enumerate(truth):
        face = projected(model, values, back.shape[1::-1])
        png = cache / f"mitsuba_{_frame_key(model, values, back, skin, spp, seed + t)}.png"
        if not png.is_file():
            image = back.copy()
            paint_face(image, model, face, skin, spp, seed + t)
            write_image(png, image)
        images.append(read_rgb8(png))
        landmarks.append(face["landmarks"])
        vertices.append(face["world"])
    return images, np.array(landmarks), np.array(vertices)


def _frame_key(model, values: dict, back: np.ndarray, skin: dict, spp: int, seed: int) -> str:
    """A hex digest of everything a Mitsuba frame depends on."""
    digest = hashlib.sha1(f"{MITSUBA_CACHE_VERSION} {model.name} {spp} {seed}".encode())
    for part in [*(np.asarray(values[k], np.float64) for k in sorted(values)), back, skin["albedo"], skin["uvs"]]:
        digest.update(np.ascontiguousarray(part).tobytes())
    return digest.hexdigest()[:20]


def write_sequence(path: Path, images, fps: float, crf: int = 18) -> None:
    """The frames as an H.264 mp4 (softras_cl.io.video)."""
    from softras_cl.io.video import VideoWriter

    with VideoWriter(path, fps, crf=crf) as writer:
        for k, image in enumerate(images):
            writer.write(image, k / fps)


def make_sequence(model, rng: np.random.Generator, frames: int, size: int, fps: float, back: str, path: Path,
                  renderer=render_frames) -> dict:
    """One synthetic talking head written to ``path`` (mp4): truth, true landmarks and vertices.
    renderer(model, truth, background): render_frames or a render_frames_mitsuba partial."""
    truth = sequence_truth(model, rng, frames, size, fps)
    images, landmarks, vertices = renderer(model, truth, background(back, size))
    write_sequence(path, images, fps)
    return dict(truth=truth, landmarks=landmarks, vertices=vertices, path=path)


# ---------------------------------------------------------------------------------------------
# measures
# ---------------------------------------------------------------------------------------------

def similarity_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (T, V, 3) moved by the one similarity (scale, rotation, translation) over all frames that
    brings it nearest to b (T, V, 3) (least squares over every vertex of every frame)."""
    pa, pb = a.reshape(-1, 3), b.reshape(-1, 3)
    ma, mb = pa.mean(0), pb.mean(0)
    ca, cb = pa - ma, pb - mb
    U, S, Vt = np.linalg.svd(ca.T @ cb)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    scale = float(np.sum(S * np.diag(d)) / np.sum(ca * ca))
    return (scale * ca @ (U @ d @ Vt) + mb).reshape(a.shape)


def sequence_errors(fitted_vertices: np.ndarray, true_vertices: np.ndarray, fitted_landmarks, true_landmarks) -> dict:
    """vertex error (mm, mean over frames of the per-frame RMS), landmark error (px, mean), jitter
    (mm/frame^2) of one sequence's fitted frames against the truth (module docstring)."""
    aligned = similarity_onto(fitted_vertices, true_vertices)
    diff = aligned - true_vertices
    per_frame = np.sqrt(np.mean(np.sum(diff ** 2, axis=2), axis=1))
    jitter = np.sqrt(np.mean(np.sum(np.diff(diff, n=2, axis=0) ** 2, axis=2))) if len(diff) > 2 else float("nan")
    return dict(vertex_error_mm=1e3 * float(per_frame.mean()), jitter_mm=1e3 * float(jitter),
                landmark_error_px=float(np.linalg.norm(fitted_landmarks - true_landmarks, axis=2).mean()))


def appearance_error(model, world: np.ndarray, albedo, sh, truth: dict, true_world: np.ndarray) -> float:
    """The face's colour (albedo (V, 3) x SH shading of sh (3, 9) at the normals of world (V, 3))
    against the truth's (its albedo and light at the true vertices), linear-RGB RMS over the
    vertices facing the camera in the truth, over the truth's mean colour there."""
    from softras_cl.scene.shading import SH_A, sh_basis, vertex_normals

    def colours(vertices, albedo, sh):
        normals = vertex_normals(vertices[None], model.faces)[0][0]
        return albedo * ((sh_basis(normals) * SH_A) @ np.asarray(sh).T), normals

    true, normals = colours(true_world, model.albedo(truth["albedo"])[0], truth["sh"])
    seen = np.einsum("vi,vi->v", normals, -true_world) / np.linalg.norm(true_world, axis=1) > 0.3
    fitted = colours(world, albedo, sh)[0]
    return float(np.sqrt(np.mean((fitted[seen] - true[seen]) ** 2)) / np.mean(true[seen]))


def light_errors(model, identity, results, sequence: dict, every: int = 4) -> dict:
    """Mean appearance_error over every ``every``-th frame with a face: with each frame's fitted
    light and with the identity's (the light held for the video)."""
    from softras_cl.fitting.recipes.face_track import world_vertices

    albedo = model.albedo(identity.albedo)[0]
    frames = [r for r in results[::every] if not r.held]
    errors = {name: [] for name in ("frame", "identity")}
    for r in frames:
        world = world_vertices(model, identity, r.values)
        args = (sequence["truth"][r.index], sequence["vertices"][r.index])
        errors["frame"].append(appearance_error(model, world, albedo, r.values["sh"], *args))
        errors["identity"].append(appearance_error(model, world, albedo, identity.sh, *args))
    return dict(light_error=float(np.mean(errors["frame"])), light_error_identity=float(np.mean(errors["identity"])))


# ---------------------------------------------------------------------------------------------
# runs
# ---------------------------------------------------------------------------------------------

class _GivenLandmarks:
    """A stand-in for the face follower: each frame's landmarks given (the truth plus noise)."""

    def __init__(self, landmarks):
        self.landmarks, self.next = landmarks, 0

    def find(self, image, previous=None):
        points = self.landmarks[self.next % len(self.landmarks)]
        self.next += 1
        return points


def follower_for(mode: str, sequence: dict, rng: np.random.Generator):
    """The tracker's landmark source: MediaPipe ("detected") or the true landmarks + noise."""
    from softras_cl.fitting.detection.follow import FaceFollower

    if mode == "detected":
        return FaceFollower()
    return _GivenLandmarks(sequence["landmarks"] + rng.normal(0, LANDMARK_NOISE_PX, sequence["landmarks"].shape))


def run_tracker(model, sequence: dict, config, follower_factory, scan: int) -> dict:
    """Track one sequence from its mp4 as track-face does (the per-frame fits, then the fixed-lag
    smoothing); its results, identity and timings (the per-frame stage: the frames' fits, light
    included, and the smoothing)."""
    from softras_cl.fitting.jobs.face_video import identity_from_video
    from softras_cl.fitting.recipes.face_track import FixedLagSmoother, FrameTracker
    from softras_cl.io.video import open_video

    start = time.perf_counter()
    source = open_video(sequence["path"])
    identity = identity_from_video(source, model, config, follower_factory(), scan)
    identity_seconds = time.perf_counter() - start
    follower, tracker, results, smoothing = follower_factory(), None, [], 0.0
    for frame in source.frames():
        if tracker is None:
            tracker = FrameTracker(model, identity, frame.image.shape, config)
            smoother = FixedLagSmoother(config.smooth_lag, tracker.fitted_landmarks)
        result = tracker.follow(follower, frame.image, frame.time, frame.index)
        begin = time.perf_counter()
        results += [done for done, _ in smoother.push(result)]
        smoothing += time.perf_counter() - begin
    results += [done for done, _ in smoother.flush()]
    total = time.perf_counter() - start
    frame_seconds = sum(r.seconds for r in results) + smoothing
    return dict(identity=identity, results=results, identity_seconds=identity_seconds, seconds=total,
                frame_fps=len(results) / frame_seconds if frame_seconds else None,
                end_to_end_fps=len(results) / total)


def run_independent(model, sequence: dict, landmarks: np.ndarray, config, frames: int,
                    face_mesh_landmarks: bool) -> list:
    """fit-face on each of the first ``frames`` frames alone, from the given landmarks (T, 68, 2)
    (Face Mesh's points when ``face_mesh_landmarks``: MediaPipe's; else the true ones, as fit_face
    takes it): (its FaceFit, or the ValueError that
    stopped it (a fit that put the face behind the camera), seconds) per frame."""
    from softras_cl.fitting.recipes.face import fit_face
    from softras_cl.srgb import to_linear
    from softras_cl.io.video import open_video

    fits = []
    for frame in open_video(sequence["path"]).frames():
        if frame.index >= frames:
            break
        start = time.perf_counter()
        try:
            fit = fit_face(to_linear(frame.image / 255.0), landmarks[frame.index], model, config, progress=False,
                           face_mesh_landmarks=face_mesh_landmarks)
        except ValueError as error:
            fit = error
        fits.append((fit, time.perf_counter() - start))
    return fits


def independent_measures(model, fits, sequence: dict) -> dict:
    """The independent fits' errors (their landmarks the model's own points: truth_kind_landmarks),
    jitter, identity ratios and seconds (module docstring). A
    frame whose fit failed is counted (``failed``, the first error) and takes the last fit before
    it (the first fit after it at the start), as the tracker holds a frame without a face."""
    from softras_cl.bench.face import truth_kind_landmarks
    from softras_cl.bench.face_views import identity_ratio

    n = len(fits)
    done = [f for f, _ in fits if not isinstance(f, Exception)]
    failures = [str(f) for f, _ in fits if isinstance(f, Exception)]
    if not done:
        raise ValueError(f"every independent fit failed (first: {failures[0]})")
    held, last = [], done[0]
    for f, _ in fits:
        last = last if isinstance(f, Exception) else f
        held.append(last)
    vertices = np.array([f.scene.geometry(f.values)[0] for f in held])
    landmarks = np.array([f.crop.to_full(truth_kind_landmarks(f, model)) for f in held])
    ratios = [identity_ratio(model, f.values["id"], sequence["truth"][0]["id"]) for f in done]
    seconds = [s for _, s in fits]
    return dict(sequence_errors(vertices, sequence["vertices"][:n], landmarks, sequence["landmarks"][:n]),
                best_single_ratio=float(min(ratios)), mean_single_ratio=float(np.mean(ratios)),
                seconds_per_frame=float(np.mean(seconds)), failed=len(failures),
                first_failure=failures[0] if failures else None)


def frame_renderer(model, args, index: int, folder: Path):
    """(the renderer make_sequence takes for sequence ``index`` under --renderer, the mp4's name)."""
    if args.renderer == "softras":
        return render_frames, f"sequence_{index}.mp4"
    from softras_cl.bench.face import LANDMARKS_ONLY
    from softras_cl.bench.landmarks import SKINS, skin_texture

    cache = folder / "track_cache"
    cache.mkdir(parents=True, exist_ok=True)
    skin = skin_texture(model, SKINS[index % len(SKINS)], LANDMARKS_ONLY if args.quick else "fast", cache)
    renderer = functools.partial(render_frames_mitsuba, skin=skin, spp=args.spp, cache=cache,
                                 seed=args.seed * 10**6 + index * 10**4)
    return renderer, f"sequence_{index}_mitsuba.mp4"


def run_sequence(model, rng, index: int, args, config, face_config, folder: Path) -> dict:
    """Make, track and independently fit one sequence; its row."""
    from softras_cl.bench.face_views import identity_ratio
    from softras_cl.fitting.recipes.face_track import FrameTracker, world_vertices

    renderer, name = frame_renderer(model, args, index, folder)
    sequence = make_sequence(model, rng, args.frames, args.size, args.fps, BACKGROUNDS[index % len(BACKGROUNDS)],
                             folder / name, renderer)
    noise_rng = np.random.default_rng(rng.integers(2**32))
    given = follower_for(args.landmarks, sequence, noise_rng)
    factory = (lambda: given) if args.landmarks == "noisy" else (lambda: follower_for("detected", sequence, noise_rng))
    tracked = run_tracker(model, sequence, config, factory, args.scan)
    results, identity = tracked["results"], tracked["identity"]
    tracker = FrameTracker(model, identity, (args.size, args.size), config)
    used = np.array([r.detected if r.detected is not None else np.full((ibug68.COUNT, 2), np.nan) for r in results])
    n = min(args.independent, len(results))
    on_mesh = args.landmarks == "detected"            # MediaPipe's: Face Mesh points
    independent = independent_measures(model, run_independent(model, sequence, _filled(used), face_config, n, on_mesh),
                                       sequence)
    fitted = np.array([r.fitted for r in results])
    vertices = np.array([world_vertices(model, identity, r.values) for r in results])
    own = [dataclasses.replace(r, values=r.own) for r in results]          # before the smoothing
    row = dict(sequence=index, background=BACKGROUNDS[index % len(BACKGROUNDS)], frames=len(results),
               held=int(sum(r.held for r in results)), keyframes=list(identity.keyframes),
               identity_ratio=identity_ratio(model, identity.id, sequence["truth"][0]["id"]),
               identity_seconds=tracked["identity_seconds"], frame_fps=tracked["frame_fps"],
               end_to_end_fps=tracked["end_to_end_fps"],
               tracker=sequence_errors(vertices, sequence["vertices"], fitted, sequence["landmarks"]),
               tracker_on_independent_frames=sequence_errors(vertices[:n], sequence["vertices"][:n], fitted[:n],
                                                             sequence["landmarks"][:n]),
               unsmoothed_on_independent_frames=sequence_errors(
                   np.array([world_vertices(model, identity, r.values) for r in own[:n]]), sequence["vertices"][:n],
                   np.array([tracker.fitted_landmarks(r.values) for r in own[:n]]), sequence["landmarks"][:n]),
               **light_errors(model, identity, results, sequence),
               independent=independent, independent_frames=n)
    row["identity_reduction_vs_mean"] = 1.0 - row["identity_ratio"] / independent["mean_single_ratio"]
    row["jitter_ratio"] = row["tracker_on_independent_frames"]["jitter_mm"] / independent["jitter_mm"]
    row["tracker_strip"] = _strip_frames(sequence, results, model, identity)
    return row


def _filled(landmarks: np.ndarray) -> np.ndarray:
    """Frames without landmarks take the last frame's that had them (the independent fits need some)."""
    out = landmarks.copy()
    for t in range(1, len(out)):
        if not np.all(np.isfinite(out[t])):
            out[t] = out[t - 1]
    return out


def _strip_frames(sequence, results, model, identity) -> list:
    """Four evenly spaced overlay frames (uint8) for the strip picture."""
    from softras_cl.fitting.reports.face_track import OverlayDrawer
    from softras_cl.io.video import open_video

    picks = set(np.linspace(0, len(results) - 1, 4).round().astype(int).tolist())
    drawer, strip = None, []
    for frame in open_video(sequence["path"]).frames():
        if frame.index in picks:
            drawer = drawer or OverlayDrawer(model, identity, frame.image.shape)
            strip.append(drawer.draw(frame.image, results[frame.index]))
    return strip


def summarise(rows: list[dict]) -> dict:
    def mean(fn):
        return float(np.mean([fn(r) for r in rows]))

    s = dict(sequences=len(rows),
             frame_fps=mean(lambda r: r["frame_fps"]), end_to_end_fps=mean(lambda r: r["end_to_end_fps"]),
             tracker_vertex_error_mm=mean(lambda r: r["tracker_on_independent_frames"]["vertex_error_mm"]),
             independent_vertex_error_mm=mean(lambda r: r["independent"]["vertex_error_mm"]),
             tracker_landmark_error_px=mean(lambda r: r["tracker_on_independent_frames"]["landmark_error_px"]),
             independent_landmark_error_px=mean(lambda r: r["independent"]["landmark_error_px"]),
             tracker_jitter_mm=mean(lambda r: r["tracker_on_independent_frames"]["jitter_mm"]),
             independent_jitter_mm=mean(lambda r: r["independent"]["jitter_mm"]),
             identity_ratio=mean(lambda r: r["identity_ratio"]),
             best_single_ratio=mean(lambda r: r["independent"]["best_single_ratio"]),
             mean_single_ratio=mean(lambda r: r["independent"]["mean_single_ratio"]),
             identity_seconds=mean(lambda r: r["identity_seconds"]),
             independent_seconds_per_frame=mean(lambda r: r["independent"]["seconds_per_frame"]),
             unsmoothed_vertex_error_mm=mean(lambda r: r["unsmoothed_on_independent_frames"]["vertex_error_mm"]),
             unsmoothed_landmark_error_px=mean(lambda r: r["unsmoothed_on_independent_frames"]["landmark_error_px"]),
             unsmoothed_jitter_mm=mean(lambda r: r["unsmoothed_on_independent_frames"]["jitter_mm"]),
             light_error=mean(lambda r: r["light_error"]),
             light_error_identity=mean(lambda r: r["light_error_identity"]),
             independent_failed=int(sum(r["independent"].get("failed", 0) for r in rows)))
    s["targets"] = dict(
        frame_fps=s["frame_fps"] >= TARGET_FPS,
        jitter=(s["tracker_jitter_mm"] <= TARGET_JITTER_RATIO * s["independent_jitter_mm"]
                and s["tracker_vertex_error_mm"] <= s["independent_vertex_error_mm"]
                and s["tracker_landmark_error_px"] <= s["independent_landmark_error_px"]),
        identity=(s["identity_ratio"] <= s["best_single_ratio"]
                  and s["identity_ratio"] <= (1 - TARGET_IDENTITY_REDUCTION) * s["mean_single_ratio"]))
    return s


def format_table(rows: list[dict], s: dict) -> str:
    from softras_cl.bench.tools import format_table as table

    flat = [dict(seq=r["sequence"], frames=r["frames"], held=r["held"], fps=r["frame_fps"], e2e=r["end_to_end_fps"],
                 v_t=r["tracker_on_independent_frames"]["vertex_error_mm"], v_i=r["independent"]["vertex_error_mm"],
                 l_t=r["tracker_on_independent_frames"]["landmark_error_px"], l_i=r["independent"]["landmark_error_px"],
                 j_t=r["tracker_on_independent_frames"]["jitter_mm"], j_i=r["independent"]["jitter_mm"],
                 id_t=r["identity_ratio"], id_b=r["independent"]["best_single_ratio"],
                 id_m=r["independent"]["mean_single_ratio"]) for r in rows]
    columns = [("seq", "seq", "d"), ("frames", "frames", "d"), ("held", "held", "d"), ("frame fps", "fps", ".1f"),
               ("e2e fps", "e2e", ".1f"), ("vertex mm track", "v_t", ".2f"), ("indep", "v_i", ".2f"),
               ("landmark px track", "l_t", ".2f"), ("indep", "l_i", ".2f"), ("jitter track", "j_t", ".3f"),
               ("indep", "j_i", ".3f"), ("identity track", "id_t", ".3f"), ("best single", "id_b", ".3f"),
               ("mean single", "id_m", ".3f")]

    def said(ok):
        return "reached" if ok else "NOT reached"

    t = s["targets"]
    return "\n".join([table(flat, columns),
                      f"per-frame stage {s['frame_fps']:.1f} frames/s (target >= {TARGET_FPS:g}: {said(t['frame_fps'])}); "
                      f"end to end {s['end_to_end_fps']:.1f} frames/s; identity fit {s['identity_seconds']:.1f} s",
                      f"jitter {s['tracker_jitter_mm']:.3f} against {s['independent_jitter_mm']:.3f} mm/frame^2 "
                      f"independent (target <= 1/3 with vertex and landmark errors no worse: {said(t['jitter'])})",
                      f"identity ratio {s['identity_ratio']:.3f}, best single frame {s['best_single_ratio']:.3f}, "
                      f"mean single {s['mean_single_ratio']:.3f} (target: no worse than the best and >= 30% below "
                      f"the mean: {said(t['identity'])})",
                      f"before the fixed-lag smoothing: jitter {s['unsmoothed_jitter_mm']:.3f} mm/frame^2, vertex "
                      f"{s['unsmoothed_vertex_error_mm']:.2f} mm, landmark {s['unsmoothed_landmark_error_px']:.2f} px",
                      f"appearance error {s['light_error']:.3f} with each frame's light, {s['light_error_identity']:.3f} "
                      "with the identity's light for every frame",
                      f"independent fits that failed (each held at the fit before it): {s['independent_failed']}"])


def save_pictures(rows: list[dict], folder: Path) -> None:
    """track_strip.png (overlay frames of the first sequence) and track_jitter.png (per
    sequence, the tracker's and the independent fits' jitter)."""
    from matplotlib.figure import Figure

    from softras_cl.io.images import write_image
    from softras_cl.srgb import to_linear

    if rows and rows[0]["tracker_strip"]:
        write_image(folder / "track_strip.png", to_linear(np.concatenate(rows[0]["tracker_strip"], axis=0) / 255.0))
    fig = Figure(figsize=(6, 3.4))
    ax = fig.subplots()
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["independent"]["jitter_mm"] for r in rows], 0.4, label="independent fit-face per frame")
    ax.bar(x + 0.2, [r["tracker_on_independent_frames"]["jitter_mm"] for r in rows], 0.4, label="track-face")
    ax.set(xlabel="sequence", ylabel="jitter, mm / frame^2", xticks=x)
    ax.legend(fontsize=8)
    fig.suptitle("bench track: jitter (RMS second difference of the vertex error)")
    fig.tight_layout()
    write_figure(fig, folder / "track_jitter.png", dpi=110)


def run(args: argparse.Namespace) -> int:
    from softras_cl.fitting.models.face_loaders import load_demo_face_model
    from softras_cl.fitting.recipes.face import FaceFitConfig
    from softras_cl.fitting.recipes.track_settings import TrackConfig

    from softras_cl.validate.mitsuba import mitsuba_available

    if args.quick:
        args.sequences, args.frames, args.independent, args.size = 1, 24, 12, min(args.size, 160)
        args.spp = min(args.spp, 4)
    for name in ("sequences", "frames", "independent", "scan"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.frames < 3:
        raise InputError(f"--frames must be >= 3 (jitter is a second difference), got {args.frames}")
    if args.spp < 2:
        raise InputError(f"--spp must be >= 2 (Mitsuba rays per pixel), got {args.spp}")
    if args.renderer == "mitsuba" and not mitsuba_available():
        raise InputError("--renderer mitsuba needs Mitsuba 3: pip install 'softras-cl[validate]'")
    config = TrackConfig(size=min(256, args.size), light_speed=args.light_speed, smooth_lag=args.smooth_lag)
    face_config = FaceFitConfig.from_budget(args.budget, size=min(256, args.size))
    with OutputFolder(args.out, "bench track", "--out") as folder:
        model = load_demo_face_model()
        rng = np.random.default_rng(args.seed)
        rows = []
        for i in range(args.sequences):
            rows.append(run_sequence(model, rng, i, args, config, face_config, folder.path))
            if not args.json:
                print(f"sequence {i}: {rows[-1]['frames']} frames tracked", flush=True)
        summary = summarise(rows)
        save_pictures(rows, folder.path)
        kept = [{k: v for k, v in r.items() if k != "tracker_strip"} for r in rows]
        doc = dict(frames=args.frames, fps=args.fps, size=args.size, seed=args.seed, landmarks=args.landmarks,
                   renderer=args.renderer, spp=args.spp if args.renderer == "mitsuba" else None,
                   independent_budget=args.budget, tracker=dataclasses.asdict(config),
                   summary=summary, sequences=kept, provenance=provenance(dict(options=args)))
        write_json(folder.path / "track.json", doc)
        print_report(doc, args.json, format_table(rows, summary))
    return 0


def register(which) -> None:
    """Add `track` to the `softras-cl bench` subparsers."""
    from softras_cl.fitting.recipes.track_settings import TrackConfig

    p = add_bench_parser(which, __doc__, "track", help="the face tracker on synthetic talking heads against per-frame fits")
    p.add_argument("--sequences", type=int, default=3, help="synthetic sequences, one identity each (default 3)")
    p.add_argument("--frames", type=int, default=240, help="frames per sequence (default 240)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    p.add_argument("--size", type=int, default=256, help="square frame size in pixels (default 256)")
    p.add_argument("--independent", type=int, default=240,
                   help="frames fitted one by one by fit-face, from the first (default 240: all)")
    p.add_argument("--budget", default="fast", help="schedule of the independent fits (default: fast)")
    p.add_argument("--scan", type=int, default=150, help="keyframes are chosen among the first FRAMES (default 150)")
    p.add_argument("--landmarks", choices=("detected", "noisy"), default="detected",
                   help=f"detected: MediaPipe's, as track-face (default); noisy: the true ones + {LANDMARK_NOISE_PX} px noise")
    p.add_argument("--light-speed", type=float, default=TrackConfig.light_speed,
                   help=f"the tracker's --light-speed (default {TrackConfig.light_speed:g}; 0: the identity's light)")
    p.add_argument("--smooth-lag", type=int, default=TrackConfig.smooth_lag,
                   help=f"the tracker's --smooth-lag (default {TrackConfig.smooth_lag}; 0: no smoothing)")
    p.add_argument("--renderer", choices=RENDERERS, default="softras",
                   help="who renders the faces: softras (default) or mitsuba (path traced, a detail texture and "
                        "shadows; needs softras-cl[validate])")
    p.add_argument("--spp", type=int, default=DEFAULT_SPP,
                   help=f"Mitsuba rays per pixel with --renderer mitsuba (default {DEFAULT_SPP})")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--quick", action="store_true",
                   help="1 sequence of 24 frames at 160 px, 12 fitted independently, at most 4 rays per pixel")
    add_output_options(p, "directory for track.json, track_strip.png, track_jitter.png, "
                          "the sequences' mp4 files and track_cache (Mitsuba's frames and skin textures)", run)
