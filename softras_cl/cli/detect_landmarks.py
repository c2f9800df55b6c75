"""`softras-cl detect-landmarks PHOTO --out FILE.pts`: the 68 iBUG points of the faces in a photo
(dlib by default, MediaPipe Face Mesh as the second backend; docs/landmarks.md)."""
from __future__ import annotations

import argparse
from pathlib import Path

from softras_cl.fitting.landmark_detect import BACKENDS


def face_out_path(out, index: int) -> Path:
    """Where --all-faces writes face `index` (0 = the largest): FILE.pts -> FILE_0.pts, FILE_1.pts..."""
    out = Path(out)
    return out.with_name(f"{out.stem}_{index}{out.suffix}")


def _run_detect(args: argparse.Namespace) -> int:
    import numpy as np

    from softras_cl.fitting.landmark_detect import (detect_faces, draw_landmarks, no_face_error,
                                                    read_photo_rgb8)
    from softras_cl.io.images import image_format
    from softras_cl.io.landmarks import write_pts
    from softras_cl.io.outputs import atomic_path

    image = read_photo_rgb8(args.photo)
    _check_output_files(args)
    options = {"upsample": args.upsample, "min_score": args.min_score}
    faces = detect_faces(image, args.backend, **options)
    if not faces:
        raise no_face_error(str(args.photo), args.backend, options)
    chosen = faces if args.all_faces else faces[:1]
    for i, face in enumerate(chosen):
        out = face_out_path(args.out, i) if args.all_faces else Path(args.out)
        write_pts(out, face.points)
        x0, y0, x1, y1 = face.box
        print(f"wrote {out} (68 iBUG points, 1-based .pts pixel coordinates; {face.backend} face "
              f"box x {x0:.0f}-{x1:.0f}, y {y0:.0f}-{y1:.0f}, score {face.score:.2f})")
    if len(faces) > 1 and not args.all_faces:
        print(f"{len(faces)} faces found; wrote the largest (--all-faces writes each)")
    if args.overlay:
        overlay = draw_landmarks(image, np.stack([f.points for f in chosen]), scale=args.overlay_scale)
        with atomic_path(args.overlay) as tmp:
            overlay.save(tmp, format=image_format(args.overlay))
        print(f"wrote {args.overlay}")
    return 0


def _check_output_files(args: argparse.Namespace) -> None:
    """--out (and --overlay) can be written, checked before detecting: OutputError (exit 3)
    naming the option, InputError for an --overlay that is no image file."""
    from softras_cl.io.images import image_format
    from softras_cl.io.outputs import check_output_file

    check_output_file(face_out_path(args.out, 0) if args.all_faces else args.out, "--out")
    if args.overlay:
        image_format(args.overlay, what="--overlay")
        check_output_file(args.overlay, "--overlay")


def register(sub) -> None:
    p = sub.add_parser(
        "detect-landmarks", help="detect 68 iBUG face landmarks in a photo and write a .pts file",
        description="Detect the 68 iBUG 300-W face landmarks and write them as an iBUG .pts file "
                    "(1-based pixel coordinates), the input of `softras-cl fit-face --landmarks`. "
                    "Backends: dlib (HOG face detector + the iBUG-trained 68-point predictor; the "
                    'default; pip install "softras-cl[landmarks]", installs beside numpy 2; the '
                    "68-point model is for non-commercial use) and mediapipe (Face Mesh, 468 points "
                    'mapped to 68, an approximation; pip install "softras-cl[landmarks-mediapipe]", '
                    "numpy<2: a separate environment). Several faces: the largest, or each with "
                    "--all-faces.")
    p.add_argument("photo", metavar="PHOTO", help="image file (PNG, JPEG, ...) with frontal faces")
    p.add_argument("--out", required=True, metavar="FILE.pts",
                   help="where to write the 68 landmarks (.pts); with --all-faces, FILE_0.pts for the "
                        "largest face, FILE_1.pts for the next, ...")
    p.add_argument("--overlay", metavar="FILE.png", default=None,
                   help="also write the photo with the 68 numbered points drawn on it (every written "
                        "face), to check them")
    p.add_argument("--overlay-scale", type=float, default=1.0, metavar="S",
                   help="scale of the overlay image relative to the photo (default 1)")
    p.add_argument("--backend", choices=BACKENDS, default=None,
                   help="detector: dlib or mediapipe (default: dlib when installed, else mediapipe)")
    p.add_argument("--all-faces", action="store_true",
                   help="write every face found (largest first) instead of only the largest")
    p.add_argument("--upsample", type=int, default=1, metavar="N",
                   help="dlib: double the image N times before detecting (default 1: faces down to "
                        "about 40 px; 0: about 80 px, 3x faster)")
    p.add_argument("--min-score", type=float, default=0.5, metavar="S",
                   help="dlib: drop detections scoring below S (default 0.5; dlib's own threshold is 0)")
    p.set_defaults(func=_run_detect)
