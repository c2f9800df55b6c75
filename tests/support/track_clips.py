"""What the track-face command tests share: a tiny identity budget and tracker options (seconds,
not a real fit), and a 9-frame, 128 px synthetic talking head at 10 fps (bench track's generator)."""
from __future__ import annotations

import numpy as np

TINY = dict(landmark_iters=10, photo_stages=((1e-4, 3e-3, 4), (1e-5, 1e-3, 4)))
FAST = ["--size", "64", "--budget", "fast", "--keyframes", "2", "--chunk", "4", "--no-progress"]
FRAMES, FPS, SIZE = 9, 10.0, 128


def talking_head(model, path) -> dict:
    """The 9-frame talking head of ``model`` written to ``path`` (mp4), and its truth
    (softras_cl.bench.track.make_sequence's dict)."""
    from softras_cl.bench.track import make_sequence

    return make_sequence(model, np.random.default_rng(3), FRAMES, SIZE, FPS, "coffee", path)
