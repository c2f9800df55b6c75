"""`softras-cl detect-landmarks PHOTO --out FILE.pts`: 68 iBUG points from MediaPipe Face Mesh."""
from __future__ import annotations

import argparse
import sys

import numpy as np

from softras_cl.fitting.landmark_detect import detect_landmarks, draw_landmarks


def _run_detect(args: argparse.Namespace) -> int:
    from PIL import Image

    try:
        image = np.asarray(Image.open(args.photo).convert("RGB"))
    except OSError as e:
        print(f"softras-cl: cannot read {args.photo}: {e}", file=sys.stderr)
        return 2
    try:
        points = detect_landmarks(image)
    except ImportError as e:
        print(f"softras-cl: {e}", file=sys.stderr)
        return 1
    except ValueError as e:
        print(f"softras-cl: {args.photo}: {e}", file=sys.stderr)
        return 1
    from softras_cl.io.landmarks import write_pts

    write_pts(args.out, points)
    print(f"wrote {args.out} (68 iBUG points, 1-based .pts pixel coordinates)")
    if args.overlay:
        draw_landmarks(image, points, scale=args.overlay_scale).save(args.overlay)
        print(f"wrote {args.overlay}")
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "detect-landmarks", help="detect 68 iBUG face landmarks in a photo and write a .pts file",
        description="Detect the 68 iBUG 300-W face landmarks with MediaPipe Face Mesh (468 points, "
                    "mapped to 68; an approximation) and write them as an iBUG .pts file (1-based "
                    "pixel coordinates), the input of `softras-cl fit-face --landmarks`. Needs the "
                    'optional extra: pip install "softras-cl[landmarks]" (mediapipe 0.10.21, '
                    "numpy<2: use a separate environment).")
    p.add_argument("photo", metavar="PHOTO", help="image file (PNG, JPEG, ...) with one frontal face")
    p.add_argument("--out", required=True, metavar="FILE.pts", help="where to write the 68 landmarks (.pts)")
    p.add_argument("--overlay", metavar="FILE.png", default=None,
                   help="also write the photo with the 68 numbered points drawn on it, to check them")
    p.add_argument("--overlay-scale", type=float, default=1.0, metavar="S",
                   help="scale of the overlay image relative to the photo (default 1)")
    p.set_defaults(func=_run_detect)
