"""Inputs and stand-ins for scripts/gpu_check.sh's product jobs (docs/gpu_check.md): a synthetic
talking-head clip for `softras-cl track-face`, photos for a `softras-cl fit-face` batch, and
track-face run where the GPU machines' image lacks MediaPipe and PyAV.

    python3 scripts/gpu_check_jobs.py clip DIR [--frames 90 --width 640 --height 480 --fps 30]
    python3 scripts/gpu_check_jobs.py photos DIR [--count 32]
    python3 scripts/gpu_check_jobs.py track DIR OUT [--report FILE] [TRACK-FACE OPTIONS]

`clip`: bench track's talking head (softras_cl.bench.track: a random identity of the demo face
with smooth random head pose, expression and light, drawn by softras-cl's sharp render) over
scikit-image's `coffee` photo, WIDTH x HEIGHT, as a folder of PNG frames (DIR/frames/, so that
no video decoder is needed), with DIR/landmarks.npy (the true 68 landmarks of every frame plus
1.5 px noise, as bench track --landmarks noisy) and DIR/clip.json (frames, size, fps, seconds).

`photos`: COUNT photos in DIR, each a crop of a shipped photo (examples/data: astronaut.png,
grace_hopper.jpg) with its landmark file beside it (NAME.pts, the shipped landmarks moved with
the crop), so that `fit-face DIR` fits them all without a detector.

`track`: `softras-cl track-face DIR/frames --fps FPS --out OUT OPTIONS` in this process, the
face's landmarks in each frame taken from DIR/landmarks.npy (MediaPipe, track-face's detector,
is too large to carry to the GPU machine: 67 MB installed), and, when PyAV is not installed
(72 MB of FFmpeg libraries), the overlay video's frames still drawn but not encoded (overlay.mp4
and its chunks hold a line saying so). Writes --report (JSON: the exit code, what stood in) and
exits with track-face's exit code.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHIPPED = (("astronaut.png", "astronaut.pts"), ("grace_hopper.jpg", "grace_hopper.pts"))
NOISE_PX = 1.5


# ---- the talking-head clip ------------------------------------------------------------------
def background(width: int, height: int) -> np.ndarray:
    """(height, width, 3) linear RGB: the centre of skimage.data.coffee() cut to the clip's aspect
    and resized."""
    import skimage.data
    from skimage.transform import resize

    from softras_cl.srgb import to_linear

    photo = skimage.data.coffee()[..., :3]
    h, w = photo.shape[:2]
    ch, cw = (h, round(h * width / height)) if w * height >= h * width else (round(w * height / width), w)
    crop = photo[(h - ch) // 2:(h - ch) // 2 + ch, (w - cw) // 2:(w - cw) // 2 + cw]
    return to_linear(resize(crop, (height, width), anti_aliasing=True))


def make_clip(folder: Path, frames: int, width: int, height: int, fps: float, seed: int) -> dict:
    """The clip of the module docstring in ``folder``; returns what clip.json holds."""
    from softras_cl.bench.track import render_frames, sequence_truth
    from softras_cl.fitting.models.face_loaders import load_demo_face_model
    from PIL import Image

    start = time.perf_counter()
    model = load_demo_face_model()
    rng = np.random.default_rng(seed)
    truth = sequence_truth(model, rng, frames, height, fps)      # the face fills ~60% of the height
    images, landmarks, _ = render_frames(model, truth, background(width, height))
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    for k, image in enumerate(images):
        Image.fromarray(image).save(folder / "frames" / f"{k:06d}.png", compress_level=1)
    np.save(folder / "landmarks.npy", landmarks + rng.normal(0, NOISE_PX, landmarks.shape))
    info = dict(frames=frames, width=width, height=height, fps=fps, seed=seed, landmark_noise_px=NOISE_PX,
                seconds=time.perf_counter() - start)
    (folder / "clip.json").write_text(json.dumps(info, indent=2) + "\n")
    return info


# ---- the batch's photos ---------------------------------------------------------------------
def make_photos(folder: Path, count: int, seed: int = 0) -> list[Path]:
    """``count`` crops of the shipped photos in ``folder``, each with NAME.pts beside it: a random
    margin of 0-15% of the side cut from each edge, never into the landmarks' box."""
    from PIL import Image

    from softras_cl.io.landmarks import read_landmarks, write_pts

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    sources = [(Image.open(REPO / "examples/data" / photo).convert("RGB"),
                read_landmarks(REPO / "examples/data/landmarks" / pts)) for photo, pts in SHIPPED]
    written = []
    for i in range(count):
        image, points = sources[i % len(sources)]
        w, h = image.size
        lo, hi = points.min(0), points.max(0)
        x0, y0 = (np.minimum(rng.uniform(0, 0.15, 2) * (w, h), lo - 8)).clip(0).astype(int)
        x1, y1 = (np.maximum((w, h) - rng.uniform(0, 0.15, 2) * (w, h), hi + 8)).clip(0, (w, h)).astype(int)
        path = folder / f"photo_{i:03d}.png"
        image.crop((int(x0), int(y0), int(x1), int(y1))).save(path)
        write_pts(path.with_suffix(".pts"), points - (x0, y0))
        written.append(path)
    return written


# ---- track-face with stand-ins --------------------------------------------------------------
def frame_key(image: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()


class GivenLandmarks:
    """A stand-in for track-face's FaceFollower: the landmarks of each frame, looked up by the
    frame's pixels (the frames of a folder of PNGs come back exactly as written)."""

    def __init__(self, by_frame: dict, *args, **kwargs):
        self.by_frame, self.started = by_frame, False

    def find(self, image: np.ndarray, previous=None):
        points = self.by_frame.get(frame_key(image))
        self.started = self.started or points is not None
        return points


class DroppedVideo:
    """A stand-in for softras_cl.io.video.VideoWriter without PyAV: takes the frames (drawn by
    the caller as usual) and writes one line saying how many it dropped."""

    def __init__(self, path, fps, crf=None):
        self.path, self.frames = Path(path), 0

    def __enter__(self):
        return self

    def __exit__(self, *error):
        self.path.write_text(f"not encoded (no PyAV): {self.frames} frames\n")
        return False

    def write(self, image, time_s):
        self.frames += 1


def importable(name: str) -> bool:
    try:
        __import__(name)
    except ImportError:
        return False
    return True


def track(clip: Path, out: Path, options: list[str]) -> tuple[int, dict]:
    """track-face on the clip (module docstring); (exit code, what stood in). The stand-ins are
    put back as they were on the way out."""
    from softras_cl.cli import main
    from softras_cl.fitting.jobs import face_video
    from softras_cl.fitting.reports import face_track
    from softras_cl.io import video
    from softras_cl.io.images import read_rgb8

    info = json.loads((clip / "clip.json").read_text())
    landmarks = np.load(clip / "landmarks.npy")
    frames = sorted((clip / "frames").glob("*.png"))
    by_frame = {frame_key(read_rgb8(path)): points for path, points in zip(frames, landmarks)}
    patches = [(face_video, "FaceFollower", lambda *a, **k: GivenLandmarks(by_frame)),
               (face_video, "_check_detector", lambda: None)]
    stand_ins = dict(landmarks=f"given: the true landmarks + {info['landmark_noise_px']} px noise (no MediaPipe)",
                     overlay_video="encoded (PyAV)")
    if not importable("av"):
        patches += [(video, "VideoWriter", DroppedVideo),
                    (face_track, "concatenate_overlays", lambda folder, chunks, fps: (
                        folder / "overlay.mp4").write_text("not encoded (no PyAV)\n"))]
        stand_ins["overlay_video"] = "drawn, not encoded (no PyAV)"
    saved = [(module, name, getattr(module, name)) for module, name, _ in patches]
    try:
        for module, name, value in patches:
            setattr(module, name, value)
        rc = main(["track-face", str(clip / "frames"), "--fps", str(info["fps"]), "--out", str(out), *options])
    finally:
        for module, name, value in saved:
            setattr(module, name, value)
    return rc, stand_ins


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("clip", help="write the talking-head clip")
    c.add_argument("folder", type=Path)
    c.add_argument("--frames", type=int, default=90)
    c.add_argument("--width", type=int, default=640)
    c.add_argument("--height", type=int, default=480)
    c.add_argument("--fps", type=float, default=30.0)
    c.add_argument("--seed", type=int, default=7)
    ph = sub.add_parser("photos", help="write the batch's photos with their landmark files")
    ph.add_argument("folder", type=Path)
    ph.add_argument("--count", type=int, default=32)
    t = sub.add_parser("track", help="track-face on a clip, with stand-ins for MediaPipe (and PyAV)")
    t.add_argument("clip", type=Path)
    t.add_argument("out", type=Path)
    t.add_argument("--report", type=Path, default=None, help="JSON file: exit code and stand-ins")
    args, rest = p.parse_known_args(argv)
    if args.command != "track" and rest:
        p.error(f"unrecognized arguments: {' '.join(rest)}")
    if args.command == "clip":
        print(json.dumps(make_clip(args.folder, args.frames, args.width, args.height, args.fps, args.seed)))
        return 0
    if args.command == "photos":
        print(f"{len(make_photos(args.folder, args.count))} photos in {args.folder}")
        return 0
    rc = 1
    stand_ins = None
    try:
        rc, stand_ins = track(args.clip, args.out, rest)
    finally:
        if args.report is not None:
            args.report.write_text(json.dumps(dict(rc=rc, stand_ins=stand_ins), indent=2) + "\n")
    return rc


if __name__ == "__main__":
    sys.exit(main())
