"""Make examples/data/talking_head.mp4 (run once; the output is committed), and with --docs the
pictures of docs/face_tracking.md from a track-face run on it.

    .venv/bin/python scripts/make_track_example.py
    .venv/bin/softras-cl track-face examples/data/talking_head.mp4 --out out/talking_head
    .venv/bin/python scripts/make_track_example.py --docs out/talking_head

The video: a synthetic talking head of the shipped demo face (CC0), `softras-cl bench track`'s
generator (softras_cl.bench.track.make_sequence, seed 7: a random identity, smooth random head
pose, expression and light) over scikit-image's `coffee` photo (public domain), 96 frames at
24 fps (4 s), 192 x 192 pixels, H.264 through PyAV; no audio.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
VIDEO = ROOT / "examples" / "data" / "talking_head.mp4"
FRAMES, FPS, SIZE, SEED = 96, 24.0, 192, 7


def make_video() -> None:
    from softras_cl.bench.track import make_sequence
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    make_sequence(load_demo_face_model(), np.random.default_rng(SEED), FRAMES, SIZE, FPS, "coffee", VIDEO)
    print(VIDEO, VIDEO.stat().st_size, "bytes")


def make_docs(run: Path) -> None:
    """docs/face_tracking_strip.png (4 overlay frames of the run) and docs/face_tracking_plot.png
    (its track.png)."""
    import shutil

    from PIL import Image

    from softras_cl.io.video import open_video

    frames = list(open_video(run / "overlay.mp4").frames())
    picks = np.linspace(0, len(frames) - 1, 4).round().astype(int)
    strip = np.concatenate([frames[i].image for i in picks], axis=0)
    Image.fromarray(strip).quantize(128).save(ROOT / "docs" / "face_tracking_strip.png", optimize=True)
    shutil.copyfile(run / "track.png", ROOT / "docs" / "face_tracking_plot.png")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--docs", type=Path, default=None, help="a track-face output folder of the example video")
    args = parser.parse_args()
    make_docs(args.docs) if args.docs else make_video()
