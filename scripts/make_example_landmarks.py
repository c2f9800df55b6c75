"""Make examples/data/*.pts and *_landmarks.png with MediaPipe Face Mesh (run once; outputs are committed).

Run it with a Python that has mediapipe (the `landmarks-mediapipe` extra, numpy<2), e.g.

    python3.11 -m venv /tmp/lmkvenv && /tmp/lmkvenv/bin/pip install "mediapipe==0.10.21" pillow
    /tmp/lmkvenv/bin/python scripts/make_example_landmarks.py

fitting/landmark_detect.py is loaded by file path, so that environment needs neither pyopencl
nor the rest of softras-cl.
"""
import importlib.util
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "examples" / "data"
spec = importlib.util.spec_from_file_location("landmark_detect", ROOT / "fitting" / "landmark_detect.py")
ld = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ld)

for photo in ["astronaut.png", "grace_hopper.jpg"]:
    stem = photo.rsplit(".", 1)[0]
    image = np.asarray(Image.open(DATA / photo).convert("RGB"))
    points = ld.detect_landmarks(image, backend="mediapipe")
    (DATA / f"{stem}.pts").write_text(ld.format_pts(points))
    # overlay: the face region (landmark box + 25 % margin), scaled to 640 px wide
    lo, hi = points.min(0), points.max(0)
    m = 0.25 * (hi - lo)
    x0, y0 = np.maximum(np.floor(lo - m), 0).astype(int)
    x1, y1 = np.minimum(np.ceil(hi + m), [image.shape[1] - 1, image.shape[0] - 1]).astype(int)
    crop = image[y0:y1 + 1, x0:x1 + 1]
    overlay = ld.draw_landmarks(crop, points - [x0, y0], scale=640 / crop.shape[1])
    overlay.quantize(128).save(DATA / f"{stem}_landmarks.png", optimize=True)  # 128 colours: small file
    print(stem, image.shape, "x", points[:, 0].min().round(1), points[:, 0].max().round(1),
          "y", points[:, 1].min().round(1), points[:, 1].max().round(1), "crop", (x0, y0, x1, y1))
